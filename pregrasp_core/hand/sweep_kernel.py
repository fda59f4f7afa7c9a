"""The closing model's coarse sweep as one compiled loop (numba; see
:func:`~pregrasp_core.hand.batch_events.coarse_sweep`): the same tests of the same (sample,
point) pairs with the same arithmetic as the numpy sweep it replaced, so every result is
equal to the bit. numba is imported and the loop compiled (or loaded from numba's on-disk
cache) on the first closing of a process (:func:`sweep_kernel`), never at import; it releases
Python's global lock."""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from ..jit import Lazy, inline_helpers, njit

_KERNEL = Lazy(lambda: _build_sweep())


def _build_sweep() -> Callable[..., tuple[np.ndarray, np.ndarray]]:
    # (the speeds divided by are > 0: lengths and half thicknesses plus |margin|)
    inline_helpers(globals(), "first_tests")
    return njit(coarse_sweep_loop, error_model="numpy")


def sweep_kernel() -> Callable[..., tuple[np.ndarray, np.ndarray]]:
    """The compiled :func:`coarse_sweep_loop` (numba imported on the first call)."""
    return _KERNEL.get()


def coarse_sweep_loop(
    flat: np.ndarray,
    t_flat: np.ndarray,
    inv_step: np.ndarray,
    n_t: np.ndarray,
    best: np.ndarray,
    px: np.ndarray,
    py: np.ndarray,
    rows: np.ndarray,
    C1: int,
    m: float,
    mid: bool,
    dis: bool,
) -> tuple[np.ndarray, np.ndarray]:
    """The first touching coarse sample of R slices and the certified-free parameter of every
    point (``batch_events.coarse_sweep``'s loop).

    flat (11, R * C1): per configuration d1x, d1y, d2x, d2y, cs, cr, hm, top0, top1, sp0, sp1
    (the sweep's per-configuration arrays, in this order); t_flat (R * C1,): the parameters;
    inv_step (R,); n_t (R,); best (R,): the first palm touch (C1 if none), updated; px, py,
    rows (P,): the points and their slices' rows; C1: samples per slice; m: the margin; mid,
    dis: which links are tested. Returns ``(best (R,), free (P,))``."""
    P = px.shape[0]
    R = n_t.shape[0]
    lim = np.minimum(n_t, best)
    free = np.zeros(P)
    # buckets as linked lists: head[k] -> first point, nxt_in[p] -> the next point
    head = np.full(C1 + 1, -1, dtype=np.int64)
    link = np.full(P, -1, dtype=np.int64)
    hit_row = np.zeros(R, dtype=np.bool_)
    # sample 0, where every point is tested (most of the sweep's tests): the pair tests of
    # every point in one branch-free pass (vectorised by the compiler), then the points that
    # are not touched go to the next sample they may touch at (in the bucket order below)
    clear0 = np.empty(P)
    hit0 = np.empty(P, dtype=np.bool_)
    first_tests(flat, px, py, rows, C1, m, mid, dis, clear0, hit0)
    t_next0 = np.empty(P, dtype=np.int64)
    for p in range(P):
        rw = rows[p]
        t_next0[p] = -1  # not tested (its slice ended before sample 0) or touched
        if lim[rw] > 0:
            ci = rw * C1
            clear = clear0[p]
            tk = t_flat[ci]
            f = free[p]
            if tk - clear < f:
                free[p] = max(f, tk + clear)
            if hit0[p]:
                hit_row[rw] = True
            else:
                y = (tk + clear) * inv_step[rw]
                nxt = np.int64(min(np.floor(y), C1)) if math.isfinite(y) else np.int64(C1)
                t_next0[p] = nxt if nxt > 1 else 1
    for rw in range(R):  # the first touch of the slices hit at sample 0
        if hit_row[rw]:
            best[rw] = 0
            lim[rw] = min(n_t[rw], 0)
            hit_row[rw] = False
    for p in range(P):  # (head insertion: each bucket's points in decreasing order)
        nk = t_next0[p]
        if nk >= 0 and nk < lim[rows[p]]:
            link[p] = head[nk]
            head[nk] = p
    tested = np.empty(P, dtype=np.int64)
    t_next = np.empty(P, dtype=np.int64)
    t_hit = np.zeros(P, dtype=np.bool_)
    for k in range(1, C1):  # the samples in order: a slice stops at its first touch
        n = 0
        p = head[k]
        head[k] = -1
        while p >= 0:
            nx = link[p]
            rw = rows[p]
            if lim[rw] > k:
                ci = rw * C1 + k
                # the pair's test (the arithmetic of the numpy sweep's pair test): hit = a link
                # within the margin; clear = the path parameter over which the point surely
                # stays off both links (its distance to each grown rectangle over the
                # rectangle's largest speed; 0 when it touches)
                hit = False
                clear = np.inf
                hm = flat[6, ci]
                for lk in range(2):  # middle, distal
                    if (lk == 0 and not mid) or (lk == 1 and not dis):
                        continue
                    dx = flat[0, ci] if lk == 0 else flat[2, ci]
                    dy = flat[1, ci] if lk == 0 else flat[3, ci]
                    s = dx * px[p]
                    s += dy * py[p]
                    r = dx * py[p]
                    r -= dy * px[p]
                    if lk == 1:
                        s -= flat[4, ci]
                        r -= flat[5, ci]
                    top = flat[7, ci] if lk == 0 else flat[8, ci]
                    r = abs(r)
                    top = s - top
                    s = -s
                    s -= m
                    s = max(s, top)
                    s = max(s, 0.0)
                    r -= hm
                    r = max(r, 0.0)
                    if max(s, r) == 0.0:
                        hit = True
                    s *= s
                    r *= r
                    s += r
                    s = math.sqrt(s)
                    s -= 1e-9
                    s = max(s, 0.0)
                    s /= flat[9, ci] if lk == 0 else flat[10, ci]
                    clear = min(clear, s)
                if hit:
                    clear = 0.0
                tk = t_flat[ci]
                f = free[p]
                if tk - clear < f:
                    free[p] = max(f, tk + clear)
                if hit:
                    hit_row[rw] = True
                y = (tk + clear) * inv_step[rw]
                nxt = np.int64(min(np.floor(y), C1)) if math.isfinite(y) else np.int64(C1)
                tested[n] = p
                t_next[n] = nxt if nxt > k + 1 else k + 1
                t_hit[n] = hit
                n += 1
            p = nx
        for rw in range(R):  # the first touch of the slices hit at this sample
            if hit_row[rw]:
                best[rw] = k
                lim[rw] = min(n_t[rw], k)
                hit_row[rw] = False
        for a in range(n):  # the untouched points move on to the next sample they may touch at
            p = tested[a]
            nk = t_next[a]
            if not t_hit[a] and nk < lim[rows[p]]:
                link[p] = head[nk]
                head[nk] = p
    return best, free


def first_tests(
    flat: np.ndarray,
    px: np.ndarray,
    py: np.ndarray,
    rows: np.ndarray,
    C1: int,
    m: float,
    mid: bool,
    dis: bool,
    clear: np.ndarray,
    hit: np.ndarray,
) -> None:
    """:func:`coarse_sweep_loop`'s pair test of every point at the first sample of its row,
    into ``clear`` and ``hit`` (P,): the same arithmetic in the same order (so the same
    values), without a branch on the point: the points go run by run of the same row (the
    points of a slice are consecutive), each run's configuration read once, so that numba
    vectorises the loop over the run's points."""
    P = px.shape[0]
    p0 = 0
    while p0 < P:
        rw = rows[p0]
        p1 = p0 + 1
        while p1 < P and rows[p1] == rw:
            p1 += 1
        ci = rw * C1
        hm = flat[6, ci]
        d1x, d1y, d2x, d2y = flat[0, ci], flat[1, ci], flat[2, ci], flat[3, ci]
        cs, cr, top0, top1, sp0, sp1 = (
            flat[4, ci],
            flat[5, ci],
            flat[7, ci],
            flat[8, ci],
            flat[9, ci],
            flat[10, ci],
        )
        xs, ys, cl, ht = px[p0:p1], py[p0:p1], clear[p0:p1], hit[p0:p1]
        for i in range(p1 - p0):  # (views from 0: numba vectorises the loop)
            x, y = xs[i], ys[i]
            h = False
            c = np.inf
            if mid:
                s = d1x * x
                s += d1y * y
                r = d1x * y
                r -= d1y * x
                r = abs(r)
                top = s - top0
                s = -s
                s -= m
                s = max(s, top)
                s = max(s, 0.0)
                r -= hm
                r = max(r, 0.0)
                h = h | (max(s, r) == 0.0)
                s *= s
                r *= r
                s += r
                s = math.sqrt(s)
                s -= 1e-9
                s = max(s, 0.0)
                s /= sp0
                c = min(c, s)
            if dis:
                s = d2x * x
                s += d2y * y
                r = d2x * y
                r -= d2y * x
                s -= cs
                r -= cr
                r = abs(r)
                top = s - top1
                s = -s
                s -= m
                s = max(s, top)
                s = max(s, 0.0)
                r -= hm
                r = max(r, 0.0)
                h = h | (max(s, r) == 0.0)
                s *= s
                r *= r
                s += r
                s = math.sqrt(s)
                s -= 1e-9
                s = max(s, 0.0)
                s /= sp1
                c = min(c, s)
            cl[i] = 0.0 if h else c
            ht[i] = h
        p0 = p1


_HITS = Lazy(lambda: njit(ragged_hits_loop))


def hits_kernel() -> Callable[..., np.ndarray]:
    """The compiled :func:`ragged_hits_loop` (numba imported on the first call)."""
    return _HITS.get()


def ragged_hits_loop(
    d1x: np.ndarray,
    d1y: np.ndarray,
    d2x: np.ndarray,
    d2y: np.ndarray,
    cs: np.ndarray,
    cr: np.ndarray,
    out: np.ndarray,
    px: np.ndarray,
    py: np.ndarray,
    seg: np.ndarray,
    h: np.ndarray,
    Lm: np.ndarray,
    Ld: np.ndarray,
    margin: float,
    pts: np.ndarray,
    rows: np.ndarray,
    n_row: np.ndarray,
    mid_on: bool,
    dis_on: bool,
) -> np.ndarray:
    """The loop form of :func:`~pregrasp_core.hand.batch_hits.any_hit_ragged`: ``out`` (R, C)
    bool, holding the palm's hits of the samples in use, gets True where point ``pts[i]``
    (coordinates ``px``, ``py``, slice ``seg``) touches a link at one of the first
    ``n_row[rows[i]]`` configurations (``d1x`` ... ``cr`` (R, C), as ``Configs``) of its row.
    Each test is :func:`~pregrasp_core.hand.batch_hits.pair_hits`' arithmetic, value by value
    (2-term dot products written out, the same bounds), so the result is the same. A sample
    already touched is not tested again (the result is an "any")."""
    m = margin
    for i in range(pts.shape[0]):
        p = pts[i]
        row = rows[i]
        x, y = px[p], py[p]
        s_ = seg[p]
        hm = h[s_] + m
        top_m = Lm[s_] + m
        top_d = Ld[s_] + m
        for j in range(n_row[row]):
            if out[row, j]:
                continue
            if mid_on:
                dx, dy = d1x[row, j], d1y[row, j]
                s = dx * x + dy * y
                r = -dy * x + dx * y
                if s >= -m and s <= top_m and abs(r) <= hm:
                    out[row, j] = True
                    continue
            if dis_on:
                dx, dy = d2x[row, j], d2y[row, j]
                s = dx * x + dy * y
                s -= cs[row, j]
                r = -dy * x + dx * y
                r -= cr[row, j]
                if s >= -m and s <= top_d and abs(r) <= hm:
                    out[row, j] = True
    return out


_REFINE = Lazy(lambda: (njit(refine_samples_loop), njit(refine_hits_loop)))


def refine_kernels() -> tuple[Callable[..., tuple[np.ndarray, ...]], Callable[..., None]]:
    """The compiled ``(refine_samples_loop, refine_hits_loop)`` (numba imported on the first
    call): one level of the refinement of the closing's brackets in two compiled passes
    around numpy's cosines and sines (``batch_events.batch_first_events``)."""
    return _REFINE.get()


def refine_samples_loop(
    f_lo: np.ndarray,
    f_hi: np.ndarray,
    n_ref: np.ndarray,
    live: np.ndarray,
    n_max: int,
    qb: np.ndarray,
    A0: float,
    A1: float,
    upper: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The samples of one refinement level of the live brackets ``live`` (L,) (indices into
    ``f_lo``, ``f_hi``, ``n_ref`` (E,) and the path rows ``qb``, ``upper`` (E, 2)):
    ``np.linspace(lo, hi, n_ref + 2)[1:-1]`` per bracket, padded with ``hi`` to ``n_max``
    samples, as ``(ts (L, n_max), a1, a2)`` with ``a1``, ``a2`` the middle and distal link
    angles of the configurations ``min(qb + A t, upper)`` there (``batch_hits.paths``; a1 =
    q1, a2 = q1 + q2). The same operations as the numpy code they replace, value by value."""
    L = live.shape[0]
    ts = np.empty((L, n_max))
    a1 = np.empty((L, n_max))
    a2 = np.empty((L, n_max))
    for i in range(L):
        e = live[i]
        lo, hi, n = f_lo[e], f_hi[e], n_ref[e]
        stp = (hi - lo) / np.float64(n + 1)
        u0, u1 = upper[e, 0], upper[e, 1]
        for j in range(n_max):
            t = np.float64(j + 1) * stp
            t += lo
            if not j + 1 <= n:
                t = hi
            ts[i, j] = t
            q1 = qb[e, 0] + A0 * t
            q2 = qb[e, 1] + A1 * t
            q1 = q1 if (q1 < u0 or q1 != q1) else u0  # np.minimum (NaN propagated)
            q2 = q2 if (q2 < u1 or q2 != q2) else u1
            a1[i, j] = q1
            a2[i, j] = q1 + q2
    return ts, a1, a2


def refine_hits_loop(
    ts: np.ndarray,
    d1x: np.ndarray,
    d1y: np.ndarray,
    d2x: np.ndarray,
    d2y: np.ndarray,
    live: np.ndarray,
    n_ref: np.ndarray,
    f_lo: np.ndarray,
    f_hi: np.ndarray,
    sl_of: np.ndarray,
    Lk: np.ndarray,
    Lm: np.ndarray,
    Ld: np.ndarray,
    h: np.ndarray,
    margin: float,
    palm_on: bool,
    px: np.ndarray,
    py: np.ndarray,
    seg: np.ndarray,
    pts: np.ndarray,
    rows: np.ndarray,
    mid_on: bool,
    dis_on: bool,
) -> None:
    """One refinement level of the live brackets (``live``, as :func:`refine_samples_loop`),
    given the cosines and sines of its link angles (``d1x = cos a1`` ... (L, n_max)): the
    configurations' distal joint terms and palm tests (``batch_hits.Configs.of``), the points'
    hits (``pts`` (Np,) with their brackets ``rows``, only those of live brackets are tested:
    :func:`ragged_hits_loop`'s tests), then each live bracket narrowed to the first touching
    sample (``f_lo`` = the sample before it, ``f_hi`` = it) or, when none touches, to
    ``[last sample, f_hi]``; in place. ``sl_of`` (E,): the slice of each bracket. Every value
    by the operations of the numpy code it replaces, so the same brackets."""
    L, C = d1x.shape
    m = margin
    row_of = np.full(f_lo.shape[0], -1, dtype=np.int64)
    for i in range(L):
        row_of[live[i]] = i
    cs = np.empty((L, C))
    cr = np.empty((L, C))
    out = np.zeros((L, C), dtype=np.bool_)
    for i in range(L):
        e = live[i]
        s_ = sl_of[e]
        lm, ld, hh = Lm[s_], Ld[s_], h[s_]
        floor = -Lk[s_] + m
        for j in range(C):
            o2x = lm * d1x[i, j]
            o2y = lm * d1y[i, j]
            cs[i, j] = d2x[i, j] * o2x + d2y[i, j] * o2y
            cr[i, j] = -d2y[i, j] * o2x + d2x[i, j] * o2y
            pm = False
            pd = False
            if palm_on:
                if mid_on:
                    v = lm * d1x[i, j]
                    v = 0.0 if 0.0 < v else v  # np.minimum(0.0, v) (NaN propagated)
                    pm = v - hh * abs(d1y[i, j]) < floor
                if dis_on:
                    v = ld * d2x[i, j]
                    v = 0.0 if 0.0 < v else v
                    pd = o2x + v - hh * abs(d2y[i, j]) < floor
            out[i, j] = (pm | pd) & (j < n_ref[e])
    for k in range(pts.shape[0]):  # ragged_hits_loop's tests, on the live brackets' points
        row = row_of[rows[k]]
        if row < 0:
            continue
        p = pts[k]
        x, y = px[p], py[p]
        s_ = seg[p]
        hm = h[s_] + m
        top_m = Lm[s_] + m
        top_d = Ld[s_] + m
        for j in range(n_ref[live[row]]):
            if out[row, j]:
                continue
            if mid_on:
                dx, dy = d1x[row, j], d1y[row, j]
                s = dx * x + dy * y
                r = -dy * x + dx * y
                if s >= -m and s <= top_m and abs(r) <= hm:
                    out[row, j] = True
                    continue
            if dis_on:
                dx, dy = d2x[row, j], d2y[row, j]
                s = dx * x + dy * y
                s -= cs[row, j]
                r = -dy * x + dx * y
                r -= cr[row, j]
                if s >= -m and s <= top_d and abs(r) <= hm:
                    out[row, j] = True
    for i in range(L):  # the first touching sample of each live bracket
        e = live[i]
        jj = -1
        for j in range(C):
            if out[i, j]:
                jj = j
                break
        if jj >= 0:
            f_lo[e] = ts[i, jj - 1] if jj > 0 else f_lo[e]
            f_hi[e] = ts[i, jj]
        else:
            f_lo[e] = ts[i, n_ref[e] - 1]


def _build_candidates() -> tuple[Callable[..., tuple[np.ndarray, np.ndarray]], ...]:
    inline_helpers(globals(), "_link_distance")
    return njit(near_candidates_loop), njit(distal_candidates_loop)


_CANDIDATES = Lazy(_build_candidates)


def candidate_kernels() -> tuple[Callable[..., tuple[np.ndarray, np.ndarray]], ...]:
    """The compiled ``(near_candidates_loop, distal_candidates_loop)`` (numba imported on the
    first call)."""
    return _CANDIDATES.get()


def _link_distance(x: float, y: float, dx: float, dy: float, length: float, h: float) -> float:
    """``batch_hits.batch_distance`` of one point (``x``, ``y``, from the link's joint) to a
    link of ``length`` and half thickness ``h`` along ``(dx, dy)``: the same operations,
    ``np.maximum``'s NaN included."""
    s = x * dx + y * dy
    r = x * -dy + y * dx
    a = abs(s - 0.5 * length) - 0.5 * length
    b = abs(r) - h
    return a if (a >= b or a != a) else b


def near_candidates_loop(
    has: np.ndarray,
    hi: np.ndarray,
    free: np.ndarray,
    pts: np.ndarray,
    rows: np.ndarray,
    qa0: np.ndarray,
    qa1: np.ndarray,
    qz0: np.ndarray,
    qz1: np.ndarray,
    c0: np.ndarray,
    s0: np.ndarray,
    c1: np.ndarray,
    s1: np.ndarray,
    px: np.ndarray,
    py: np.ndarray,
    seg: np.ndarray,
    Lm: np.ndarray,
    Ld: np.ndarray,
    h: np.ndarray,
    m: float,
    mid: bool,
    dis: bool,
) -> tuple[np.ndarray, np.ndarray]:
    """The points ``pts`` (with their rows ``rows``, the sweep's ``free`` of each) that may
    touch a link inside their row's bracket ``[lo, hi]`` (``batch_events.batch_first_events``):
    those of rows with a touch (``has``) that the sweep did not certify off the links over
    ``[0, hi]``, and whose distance to a link at ``hi`` is within what the link can move over
    the bracket (``closing.may_touch``). ``qa*``, ``qz*`` (R,): the joints at the brackets'
    ends; ``c0, s0, c1, s1`` (R,): numpy's cos and sin of ``qz0`` and of ``qz0 + qz1``. The
    same operations as the numpy code, so the same points, in the same order: ``(pts, rows)``."""
    n_in = pts.shape[0]
    keep = np.zeros(n_in, dtype=np.bool_)
    n = 0
    for i in range(n_in):
        r = rows[i]
        if not has[r] or hi[r] < free[i]:
            continue
        p = pts[i]
        x, y = px[p], py[p]
        s_ = seg[p]
        d1 = abs(qz0[r] - qa0[r])
        d2 = abs((qz0[r] + qz1[r]) - (qa0[r] + qa1[r]))
        rho = math.sqrt(x * x + y * y)
        lm = Lm[s_]
        k = False
        if mid:
            k = _link_distance(x, y, c0[r], s0[r], lm, h[s_]) <= m + rho * d1 + 1e-9
        if dis:
            x2 = x - lm * c0[r]
            y2 = y - lm * s0[r]
            lim = m + (rho + lm) * d2 + lm * d1 + 1e-9
            k = k | (_link_distance(x2, y2, c1[r], s1[r], Ld[s_], h[s_]) <= lim)
        keep[i] = k
        n += k
    out_p = np.empty(n, dtype=np.int64)
    out_r = np.empty(n, dtype=np.int64)
    j = 0
    for i in range(n_in):
        if keep[i]:
            out_p[j] = pts[i]
            out_r[j] = rows[i]
            j += 1
    return out_p, out_r


def distal_candidates_loop(
    start: np.ndarray,
    two: np.ndarray,
    px: np.ndarray,
    py: np.ndarray,
    o2x: np.ndarray,
    o2y: np.ndarray,
    r2sq: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """The points of the slices ``two`` (increasing; slice ``s`` holds the points
    ``start[s]:start[s + 1]``) within ``sqrt(r2sq)`` of their slice's distal joint
    ``(o2x, o2y)``, as ``(pts, rows)`` (rows: the index in ``two``), in point order: the
    candidates of the closing's phase 2 (``closing_batch.close_fingers``), by the numpy code's
    operations (``dx * dx + dy * dy <= r2 * r2``)."""
    n = 0
    for k in range(two.shape[0]):  # count them
        s = two[k]
        ox, oy, lim = o2x[s], o2y[s], r2sq[s]
        for p in range(start[s], start[s + 1]):
            dx = px[p] - ox
            dy = py[p] - oy
            n += dx * dx + dy * dy <= lim
    out_p = np.empty(n, dtype=np.int64)
    out_r = np.empty(n, dtype=np.int64)
    n = 0
    for k in range(two.shape[0]):  # then list them
        s = two[k]
        ox, oy, lim = o2x[s], o2y[s], r2sq[s]
        for p in range(start[s], start[s + 1]):
            dx = px[p] - ox
            dy = py[p] - oy
            if dx * dx + dy * dy <= lim:
                out_p[n] = p
                out_r[n] = k
                n += 1
    return out_p, out_r


_REACH = Lazy(lambda: njit(reach_loop))


def reach_kernel() -> Callable[..., tuple[np.ndarray, np.ndarray, np.ndarray, int]]:
    """The compiled :func:`reach_loop` (numba imported on the first call)."""
    return _REACH.get()


def reach_loop(
    P: np.ndarray, sizes: np.ndarray, reach2: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """The columns and the reach test of the points of many slices in one branch-free pass:
    ``P`` (N, 2) the slices' points one slice after the other (``sizes`` (S,) each),
    ``reach2`` (S,) each slice's squared reach. Returns ``(x (N,), y (N,), keep (N,), n)``:
    ``P``'s columns, whether ``x * x + y * y <= reach2`` of the point's slice (the value of
    ``np.einsum("ij,ij->i", P, P)``: each product rounded, then their sum), and how many are
    kept (``closing_batch.close_fingers``)."""
    N = P.shape[0]
    xs = np.empty(N)
    ys = np.empty(N)
    keep = np.empty(N, dtype=np.bool_)
    n = 0
    i0 = 0
    for s in range(sizes.shape[0]):
        i1 = i0 + sizes[s]
        lim = reach2[s]
        Ps, xv, yv, kv = P[i0:i1], xs[i0:i1], ys[i0:i1], keep[i0:i1]
        for i in range(i1 - i0):  # (views from 0: numba vectorises the loop)
            x, y = Ps[i, 0], Ps[i, 1]
            xv[i] = x
            yv[i] = y
            k = x * x + y * y <= lim
            kv[i] = k
            n += k
        i0 = i1
    return xs, ys, keep, n
