"""Compiled loops of the decomposition and of its MVBB fits (numba, issue 15).

Each kernel does, in one pass over its arrays, exactly what a short chain of numpy calls did
before (the chains are quoted in the docstrings): only comparisons, minima and maxima, integer
arithmetic and single IEEE operations in the same order, never a reordered sum or a fused
multiply-add, so the results are the same to the bit (``docs/decomposition.md``, "Compiled
loops"). The floating-point products that decide the search (matrix products on BLAS,
``arctan2``, ``cos``) stay in numpy.

numba is imported and the kernels are compiled (or loaded from numba's on-disk cache,
``cache=True``) on first use, never when this module is imported; :func:`warm_up` does it on
purpose, e.g. at the start of a server, so that the first decomposition does not pay for it.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import NamedTuple

import numpy as np

from .jit import Lazy, inline_helpers, njit


def _fma(a, b, c):  # pragma: no cover - replaced by the llvm.fma intrinsic in kernels()
    raise RuntimeError("_fma is only defined inside the compiled kernels")


def _kernel_mask(q, lo, ext, grid):  # pragma: no cover - compiled by numba
    # numpy: cells = minimum(((q - lo) / ext * grid).astype(int64), grid - 1); per axis a the
    # column cell = cells[b] * grid + cells[c]; maximum.at / minimum.at per column; the first
    # (lowest index) point of each column equal to its top and to its bottom is kept. (Values
    # are finite: a column's first value always beats the -inf / inf start.)
    n = q.shape[1]
    keep = np.zeros(n, dtype=np.bool_)
    cells = np.empty((3, n), dtype=np.int64)
    for a in range(3):
        la, ea = lo[a], ext[a]
        for i in range(n):
            cell = np.int64((q[a, i] - la) / ea * grid)
            cells[a, i] = cell if cell < grid - 1 else grid - 1
    g2 = grid * grid
    top = np.empty(g2)
    bottom = np.empty(g2)
    first_top = np.empty(g2, dtype=np.int64)
    first_bottom = np.empty(g2, dtype=np.int64)
    for a in range(3):
        b, c = (a + 1) % 3, (a + 2) % 3
        top[:] = -np.inf
        bottom[:] = np.inf
        first_top[:] = n
        first_bottom[:] = n
        # One pass: the index moves only on a strictly larger (smaller) value, so it ends at the
        # first point equal to the column's maximum (minimum), as numpy's hit test found it.
        for i in range(n):
            k = cells[b, i] * grid + cells[c, i]
            v = q[a, i]
            if v > top[k]:
                top[k] = v
                first_top[k] = i
            if v < bottom[k]:
                bottom[k] = v
                first_bottom[k] = i
        for k in range(g2):
            if first_top[k] < n:
                keep[first_top[k]] = True
            if first_bottom[k] < n:
                keep[first_bottom[k]] = True
    return keep


def _widen(v, mx, mn):  # pragma: no cover - compiled by numba, inline (see kernels())
    # a running extent [mn, mx] with the value v added: the comparisons of numpy's running
    # maximum and minimum
    if v > mx:
        mx = v
    if v < mn:
        mn = v
    return mx, mn


def _cut_scan(pT, order, a, lo, hi):  # pragma: no cover - compiled by numba
    # numpy (best_cut, one axis): s = pT[:, order]; x = s[a]; pre/suf = running max - running
    # min of the two other rows from the front / the back; for every cut i in [lo, hi]:
    # total = (x[i] - x[0]) * pre0[i] * pre1[i] + (x[-1] - x[i + 1]) * suf0[i + 1] * suf1[i + 1],
    # inf where x[i + 1] <= x[i]; argmin (the first minimum).
    n = order.shape[0]
    b0 = 1 if a == 0 else 0
    b1 = 1 if a == 2 else 2
    m = hi - lo + 1
    pre0 = np.empty(m)
    pre1 = np.empty(m)
    mx0 = -np.inf
    mn0 = np.inf
    mx1 = -np.inf
    mn1 = np.inf
    for i in range(hi + 1):
        j = order[i]
        mx0, mn0 = _widen(pT[b0, j], mx0, mn0)
        mx1, mn1 = _widen(pT[b1, j], mx1, mn1)
        if i >= lo:
            pre0[i - lo] = mx0 - mn0
            pre1[i - lo] = mx1 - mn1
    x0 = pT[a, order[0]]
    xn = pT[a, order[n - 1]]
    mx0 = -np.inf
    mn0 = np.inf
    mx1 = -np.inf
    mn1 = np.inf
    best_j = 0
    best = np.inf
    for i in range(n - 1, lo, -1):  # i = the first point of the right child
        j = order[i]
        mx0, mn0 = _widen(pT[b0, j], mx0, mn0)
        mx1, mn1 = _widen(pT[b1, j], mx1, mn1)
        if i <= hi + 1:
            t = i - 1 - lo  # the cut between sorted positions i - 1 and i
            xl, xr = pT[a, order[i - 1]], pT[a, j]
            if xr <= xl:
                total = np.inf
            else:
                total = xl - x0
                total *= pre0[t]
                total *= pre1[t]
                v_right = xn - xr
                v_right *= mx0 - mn0
                v_right *= mx1 - mn1
                total += v_right
            # argmin's first minimum: scanning backwards, a tie moves to the smaller index (and
            # when every cut is inf, argmin's 0 is the last one visited)
            if total <= best:
                best, best_j = total, t
    return best_j, best


def _outside(eq, F, thr):  # pragma: no cover - compiled by numba
    # numpy: signed = eq[:, :3] @ F (BLAS: the fma chain, see _pattern_search); signed +=
    # eq[:, 3:]; signed.max(axis=0) > thr. Faces outer, points inner (vectorised); a point is
    # outside as soon as one face gives more than thr (the maximum does, exactly).
    n_faces = eq.shape[0]
    m = F.shape[1]
    best = np.empty(m)
    for j in range(m):
        best[j] = -np.inf
    x, y, z = F[0], F[1], F[2]
    for k in range(n_faces):
        n0, n1, n2, off = eq[k, 0], eq[k, 1], eq[k, 2], eq[k, 3]
        for j in range(m):
            v = _fma(n2, z[j], _fma(n1, y[j], n0 * x[j])) + off
            best[j] = v if v > best[j] else best[j]
    out = np.empty(m, dtype=np.bool_)
    for j in range(m):
        out[j] = best[j] > thr
    return out


def _sweep(frames, V, rot2):  # pragma: no cover - compiled by numba
    # numpy (mvbb._sweep): proj = frames.T @ V per frame (BLAS: the fma chain); height = extent
    # of proj[:, 2]; xy = rot2 @ proj[:, :2] (the fma chain of two terms); ext = extents of xy;
    # volumes = ext[:, :M] * ext[:, M:] * height. Points outer, the 2M rows inner (vectorised).
    K = frames.shape[0]
    h = V.shape[1]
    M2 = rot2.shape[0]
    M = M2 // 2
    out = np.empty((K, M))
    mx = np.empty(M2)
    mn = np.empty(M2)
    r0 = np.ascontiguousarray(rot2[:, 0])
    r1 = np.ascontiguousarray(rot2[:, 1])
    for k in range(K):
        a0, a1, a2 = frames[k, 0, 0], frames[k, 1, 0], frames[k, 2, 0]
        b0, b1, b2 = frames[k, 0, 1], frames[k, 1, 1], frames[k, 2, 1]
        c0, c1, c2 = frames[k, 0, 2], frames[k, 1, 2], frames[k, 2, 2]
        hmx = -np.inf
        hmn = np.inf
        for j in range(h):
            x, y, z = V[0, j], V[1, j], V[2, j]
            u = _fma(a2, z, _fma(a1, y, a0 * x))
            w = _fma(b2, z, _fma(b1, y, b0 * x))
            t = _fma(c2, z, _fma(c1, y, c0 * x))
            hmx = t if t > hmx else hmx
            hmn = t if t < hmn else hmn
            if j == 0:
                for m in range(M2):
                    v = _fma(r1[m], w, r0[m] * u)
                    mx[m] = v
                    mn[m] = v
            else:
                for m in range(M2):
                    v = _fma(r1[m], w, r0[m] * u)
                    mx[m] = v if v > mx[m] else mx[m]
                    mn[m] = v if v < mn[m] else mn[m]
        height = hmx - hmn
        for m in range(M):
            area = (mx[m] - mn[m]) * (mx[M + m] - mn[M + m])
            out[k, m] = area * height
    return out


def _frames(n):  # pragma: no cover - compiled by numba
    # numpy (mvbb._frames_from_normals): helper = the world axis of the smallest |n_i| (the first
    # on a tie); u = helper x n; u /= sqrt((u0 u0 + u1 u1) + u2 u2); v = n x u; frames[k] = the
    # columns (u, v, n). The cross products are written out in full, as numpy computes them.
    K = n.shape[0]
    out = np.empty((K, 3, 3))
    for k in range(K):
        n0, n1, n2 = n[k, 0], n[k, 1], n[k, 2]
        i = 0
        if abs(n1) < abs(n0):
            i = 1
        if abs(n2) < abs(n[k, i]):
            i = 2
        h0 = 1.0 if i == 0 else 0.0
        h1 = 1.0 if i == 1 else 0.0
        h2 = 1.0 if i == 2 else 0.0
        u0 = h1 * n2 - h2 * n1
        u1 = h2 * n0 - h0 * n2
        u2 = h0 * n1 - h1 * n0
        norm = np.sqrt(u0 * u0 + u1 * u1 + u2 * u2)
        u0 /= norm
        u1 /= norm
        u2 /= norm
        out[k, 0, 0], out[k, 1, 0], out[k, 2, 0] = u0, u1, u2
        out[k, 0, 1] = n1 * u2 - n2 * u1
        out[k, 1, 1] = n2 * u0 - n0 * u2
        out[k, 2, 1] = n0 * u1 - n1 * u0
        out[k, 0, 2], out[k, 1, 2], out[k, 2, 2] = n0, n1, n2
    return out


def _near_faces(proj, lo, hi, margin):  # pragma: no cover - compiled by numba
    # numpy: flatnonzero(any((proj >= hi[:, None] - margin) | (proj <= lo[:, None] + margin),
    # axis=0)) for proj (3, N): the points within margin of a face of the box [lo, hi].
    n = proj.shape[1]
    top = np.empty(3)
    bottom = np.empty(3)
    for a in range(3):
        top[a] = hi[a] - margin
        bottom[a] = lo[a] + margin
    keep = np.empty(n, dtype=np.int64)
    m = 0
    for j in range(n):
        hit = False
        for a in range(3):
            v = proj[a, j]
            if v >= top[a] or v <= bottom[a]:
                hit = True
        if hit:
            keep[m] = j
            m += 1
    return keep[:m].copy()


def _pattern_search(  # pragma: no cover - compiled by numba
    cur_t, cur_vol, Vf, stencils_t, steps, level, radius, reach, max_iter, shrink
):
    # The loop of mvbb._pattern_search, to the bit (see there for the method). cur_t (T, 3, 3)
    # float64 rows = box axes, updated in place; cur_vol (T,) and Vf (3, f) in the precision of
    # the volumes (float32 or float64); stencils_t (L, 26, 3, 3) float64; steps (L,); level (T,)
    # int64, updated in place; shrink (1,) = 1 - 1e-12 in the precision of the volumes.
    # Every matrix product is the fused multiply-add chain c0 * x0 -> fma(c1, x1, .) ->
    # fma(c2, x2, .) in the precision of its operands, which is what BLAS (and numpy's stacked
    # 3 x 3 products) compute on this machine for matrices of at least 2 rows and 2 columns;
    # with a single active point the extent is 0 whatever the product gives. The loops over
    # points are outside and the loops over trials (or box axes) inside, so that the compiler
    # vectorises the running maxima and minima across trials.
    T = cur_t.shape[0]
    f = Vf.shape[1]
    n_levels = steps.shape[0]
    n_trial = 26 * T
    tmp = np.empty(1, dtype=Vf.dtype)
    near = np.zeros((3, f), dtype=np.bool_)
    proj = np.empty((f, 3 * T), dtype=Vf.dtype)  # box-frame coordinates, live box axes inner
    act = np.empty((3, 3, f), dtype=Vf.dtype)  # act[k] = the active points of axis k
    n_act = np.full(3, f, dtype=np.int64)
    for k in range(3):
        act[k, :, :] = Vf
    trial = np.empty((T, 26, 3, 3))
    coef = np.empty((3, 3, n_trial), dtype=Vf.dtype)  # coef[k, c, r]: trial axis k of trial r
    mx = np.empty(max(n_trial, 3 * T), dtype=Vf.dtype)
    mn = np.empty(max(n_trial, 3 * T), dtype=Vf.dtype)
    tv = np.empty(n_trial, dtype=Vf.dtype)
    c3 = np.empty((3, 3 * T), dtype=Vf.dtype)
    live = np.empty(T, dtype=np.int64)
    better = np.empty(T, dtype=np.int64)
    spent = 0.0
    budget = -1.0
    for _ in range(max_iter):
        n_live = 0
        for t in range(T):
            if level[t] < n_levels:
                live[n_live] = t
                n_live += 1
        if n_live == 0:
            break
        step = -np.inf
        for u in range(n_live):
            if steps[level[live[u]]] > step:
                step = steps[level[live[u]]]
        if spent + step > budget:
            budget = reach * step
            spent = 0.0
            margin = 2.0 * radius * budget * (1.0 + 1e-9)
            tmp[0] = margin
            mg = tmp[0]
            nr = 3 * n_live
            for u in range(n_live):
                for i in range(3):
                    for c in range(3):
                        tmp[0] = cur_t[live[u], i, c]
                        c3[c, 3 * u + i] = tmp[0]
            for j in range(f):
                x, y, z = Vf[0, j], Vf[1, j], Vf[2, j]
                for r in range(nr):
                    proj[j, r] = _fma(c3[2, r], z, _fma(c3[1, r], y, c3[0, r] * x))
            for r in range(nr):
                mx[r] = proj[0, r]
                mn[r] = proj[0, r]
            for j in range(1, f):
                for r in range(nr):
                    v = proj[j, r]
                    mx[r] = v if v > mx[r] else mx[r]
                    mn[r] = v if v < mn[r] else mn[r]
            for r in range(nr):
                mx[r] = mx[r] - mg  # the thresholds, in the precision of the volumes
                mn[r] = mn[r] + mg
            for j in range(f):
                for i in range(3):
                    hit = False
                    for u in range(n_live):
                        v = proj[j, 3 * u + i]
                        if v >= mx[3 * u + i] or v <= mn[3 * u + i]:
                            hit = True
                    near[i, j] = hit
            for k in range(3):
                m = 0
                for j in range(f):
                    if near[k, j]:
                        act[k, 0, m] = Vf[0, j]
                        act[k, 1, m] = Vf[1, j]
                        act[k, 2, m] = Vf[2, j]
                        m += 1
                n_act[k] = m
        for u in range(n_live):
            t = live[u]
            lv = level[t]
            for s in range(26):
                for i in range(3):
                    for j in range(3):
                        x = stencils_t[lv, s, i, 0] * cur_t[t, 0, j]
                        x = _fma(stencils_t[lv, s, i, 1], cur_t[t, 1, j], x)
                        x = _fma(stencils_t[lv, s, i, 2], cur_t[t, 2, j], x)
                        trial[u, s, i, j] = x
                        tmp[0] = x
                        coef[i, j, 26 * u + s] = tmp[0]
        nt = 26 * n_live
        for r in range(nt):
            tv[r] = 1.0
        for k in range(3):
            a = n_act[k]
            x, y, z = act[k, 0, 0], act[k, 1, 0], act[k, 2, 0]
            for r in range(nt):
                v = _fma(coef[k, 2, r], z, _fma(coef[k, 1, r], y, coef[k, 0, r] * x))
                mx[r] = v
                mn[r] = v
            for j in range(1, a):
                x, y, z = act[k, 0, j], act[k, 1, j], act[k, 2, j]
                for r in range(nt):
                    v = _fma(coef[k, 2, r], z, _fma(coef[k, 1, r], y, coef[k, 0, r] * x))
                    mx[r] = v if v > mx[r] else mx[r]
                    mn[r] = v if v < mn[r] else mn[r]
            for r in range(nt):
                tv[r] *= mx[r] - mn[r]
        n_better = 0
        for u in range(n_live):
            jb = 0
            for s in range(1, 26):
                if tv[26 * u + s] < tv[26 * u + jb]:
                    jb = s
            better[u] = -1
            if tv[26 * u + jb] < cur_vol[live[u]] * shrink[0]:
                better[u] = jb
                n_better += 1
        if n_better > 0:
            spent += step
        for u in range(n_live):
            t = live[u]
            if better[u] >= 0:
                cur_t[t] = trial[u, better[u]]
                cur_vol[t] = tv[26 * u + better[u]]
            else:
                level[t] += 1


MINMAX_FLAGS = frozenset({"nnan", "nsz"})
"""The only fast-math flags any kernel gets: no NaN (the clouds are checked finite) and no
signed zeros, which lets the compiler vectorise the running maxima and minima (exact in any
order). No reassociation and no contraction into fused multiply-adds: every sum and product
stays in its order, so the results do not change."""


class Kernels(NamedTuple):
    """The compiled kernels (see the module docstring)."""

    pattern_search: Callable[..., object]
    frames: Callable[[np.ndarray], np.ndarray]
    near_faces: Callable[[np.ndarray, np.ndarray, np.ndarray, float], np.ndarray]
    sweep: Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]
    outside: Callable[[np.ndarray, np.ndarray, float], np.ndarray]
    kernel_mask: Callable[[np.ndarray, np.ndarray, np.ndarray, int], np.ndarray]
    cut_scan: Callable[[np.ndarray, np.ndarray, int, int, int], tuple[int, float]]


def kernels() -> Kernels:
    """The compiled kernels; the first call imports numba and compiles them (or loads them from
    numba's cache), once per process even when several threads ask at the same time."""
    return _KERNELS.get()


def _build() -> Kernels:
    """Import numba and wrap the kernels (compiled lazily, on their first call)."""
    from .jit import import_numba

    import_numba()
    from numba.core.extending import intrinsic

    @intrinsic
    def fma(typingctx: object, a: object, b: object, c: object) -> object:
        """fma(a, b, c) = a * b + c rounded once (llvm.fma), for float32 or float64."""

        def codegen(
            context: object, builder: object, sig: object, args: tuple[object, ...]
        ) -> object:
            return builder.fma(*args)  # type: ignore[attr-defined]

        return a(a, b, c), codegen  # type: ignore[operator]

    globals()["_fma"] = fma  # the compiled kernels resolve _fma here
    inline_helpers(globals(), "_widen")  # compiled into cut_scan (no call in its loops)

    return Kernels(
        pattern_search=njit(_pattern_search, fastmath=set(MINMAX_FLAGS)),
        outside=njit(_outside, fastmath=set(MINMAX_FLAGS)),
        sweep=njit(_sweep, fastmath=set(MINMAX_FLAGS)),
        frames=njit(_frames),
        near_faces=njit(_near_faces),
        kernel_mask=njit(_kernel_mask),
        cut_scan=njit(_cut_scan),
    )


_KERNELS = Lazy(_build)


def warm_up() -> float:
    """Import numba and compile (or load from its cache) every kernel for the argument types the
    decomposition and its MVBB fits use, by decomposing a small fixed cloud (an L of 600 points).
    Returns the seconds it took (about 1 s on this machine with a warm cache, mostly importing
    numba; a first compile takes several seconds)."""
    from .decomposition import DecompositionParams, decompose

    t0 = time.perf_counter()
    kernels()
    rng = np.random.default_rng(0)
    bar = rng.uniform((0.0, 0.0, 0.0), (0.10, 0.02, 0.02), (400, 3))
    leg = rng.uniform((0.0, 0.0, 0.0), (0.02, 0.08, 0.02), (200, 3))
    decompose(np.concatenate([bar, leg]), DecompositionParams(volume_ratio=0.95, min_points=50))
    return time.perf_counter() - t0
