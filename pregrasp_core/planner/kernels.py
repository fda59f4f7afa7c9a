"""Compiled loops of the planner's per-pre-grasp searches (numba), each doing, point by point,
the same floating-point operations in the same order as the numpy code it replaced, so that
every coordinate, distance and selection is equal to the bit (``docs/planner.md``, "Speed notes").

numba is imported and the kernels compiled (or loaded from numba's on-disk cache, ``cache=True``)
on the first plan of a process (:func:`kernels`), never when the package is imported; the
kernels release Python's global lock (``nogil=True``), so the planner's threads run them side by
side.
"""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np

from ..jit import Lazy, inline_helpers, njit

APPROACH_CELL_MARGIN: float = 1e-6
"""Metres added to a link box's half extents in :func:`approach_sweep`'s sweep of a cell's
ball (its centre's slabs grown by its radius): far above the rounding of the coordinates, so
that sweep only prunes cells none of whose points could meet the box earlier."""

LINK_CELL_MARGIN: float = 1e-6
"""Metres added to the reach of :func:`link_distances`' test of a cell's ball against a link
box: far above the rounding of the box-frame coordinates (about 1e-16 m), so the test only
prunes cells without a point within reach."""


def kernels() -> SimpleNamespace:
    """The compiled kernels (``slices``, ...); the first call imports numba and compiles them
    (a few seconds the very first time, then loaded from numba's cache)."""
    return _KERNELS.get()


def _build() -> SimpleNamespace:
    """The kernels wrapped by numba (each compiled, or loaded, on its first call)."""
    inline_helpers(globals(), "_ball_meets_keep", "_to_view", "_in_keep", "_moved")
    return SimpleNamespace(
        slices=njit(slice_points),
        approach=njit(approach_sweep),
        link_distances=njit(link_distances),
        link_contacts=njit(link_contacts),
        cells_in_frame=njit(cells_in_frame),
    )


_KERNELS = Lazy(_build)


def _ball_meets_keep(cx, cy, cz, rc, r, z_lo, z_hi):  # pragma: no cover - numba, inline
    # the ball (centre cx, cy, cz, radius rc) meets the view's keep box |x|, |y| <= r,
    # z_lo <= z <= z_hi
    return abs(cx) <= r + rc and abs(cy) <= r + rc and cz >= z_lo - rc and cz <= z_hi + rc


def _to_view(xyz, i, T0):  # pragma: no cover - numba, inline
    # cloud point i in the frame of T0 (to_frame_t: R^T (p - t), each sum left to right)
    d0, d1, d2 = xyz[0, i] - T0[0, 3], xyz[1, i] - T0[1, 3], xyz[2, i] - T0[2, 3]
    x = d0 * T0[0, 0] + d1 * T0[1, 0] + d2 * T0[2, 0]
    y = d0 * T0[0, 1] + d1 * T0[1, 1] + d2 * T0[2, 1]
    z = d0 * T0[0, 2] + d1 * T0[1, 2] + d2 * T0[2, 2]
    return x, y, z


def _in_keep(x, y, z, r, z_lo, z_hi):  # pragma: no cover - numba, inline
    return abs(x) <= r and abs(y) <= r and z >= z_lo and z <= z_hi


def _moved(z, dz):  # pragma: no cover - numba, inline
    # z after the view's moves, one after the other
    for s in range(dz.shape[0]):
        z += dz[s]
    return z


def cells_in_frame(
    centre: np.ndarray, rad: np.ndarray, T: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(c (C, 3), lo (C, 3), hi (C, 3))``: the cell centres ``centre`` (C, 3) in the frame of
    the pose ``T`` (4, 4) and their balls' bounds ``c -/+ rad`` (``rad`` (C,)): the operations of
    :func:`~pregrasp_core.geometry.to_frame` (``(p - t) R``, each sum left to right) and of
    ``c - rad[:, None]``, ``c + rad[:, None]``, value by value (equal to the bit), in one pass
    instead of a dozen numpy temporaries per pre-grasp."""
    n = centre.shape[0]
    c = np.empty((n, 3))
    lo = np.empty((n, 3))
    hi = np.empty((n, 3))
    tx, ty, tz = T[0, 3], T[1, 3], T[2, 3]
    for i in range(n):
        d0, d1, d2 = centre[i, 0] - tx, centre[i, 1] - ty, centre[i, 2] - tz
        rc = rad[i]
        for j in range(3):
            v = d0 * T[0, j] + d1 * T[1, j] + d2 * T[2, j]
            c[i, j] = v
            lo[i, j] = v - rc
            hi[i, j] = v + rc
    return c, lo, hi


def slice_points(
    xyz: np.ndarray,
    order: np.ndarray,
    start: np.ndarray,
    count: np.ndarray,
    centres: np.ndarray,
    rad: np.ndarray,
    dz_sum: float,
    origins: np.ndarray,
    ball2: np.ndarray,
    T0: np.ndarray,
    r: float,
    z_lo: float,
    z_hi: float,
    dz: np.ndarray,
    nrm: np.ndarray,
    shift: np.ndarray,
    band: np.ndarray,
    T_planes: np.ndarray,
    half_width: np.ndarray,
    reach2: np.ndarray,
    cell: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The thinned slices of F fingers for one hand pose (the loop form of
    :func:`~pregrasp_core.planner.slicing.finger_slices`).

    xyz (3, N): the cloud by coordinate; order, start, count: the cells (:class:`Cells`);
    centres (C, 3), rad (C,): their balls in the frame of T0, the view's moves ``dz_sum`` not yet
    added (the cells searched: those whose balls meet the keep box and a finger's band and
    reach, ``origins`` (F, 3) its first joint, ``ball2`` (F,) its 3D reach + margin, the
    exact tests follow); T0 (4, 4): the view's pose; r, z_lo, z_hi: its keep box;
    dz (D,): its shifts along hand z; nrm (3, F), shift (F,), band (F,): the flexion planes'
    normals, offsets and band half widths (+ margin); T_planes (F, 4, 4): the planes' frames
    in the hand; half_width (F,): half finger widths; reach2 (F,): squared 2D reach limits;
    cell: the thinning cell side. Returns ``(uv (M, 2), first (F + 1,), n_slice (F,))``: finger
    j's thinned points are ``uv[first[j]:first[j + 1]]``, in ascending cloud order."""
    n = xyz.shape[1]
    F = nrm.shape[1]
    cand = np.empty(n, dtype=np.int64)
    m0 = 0
    for c in range(centres.shape[0]):  # the points of the candidate cells
        rc = rad[c]
        cx, cy, cz = centres[c, 0], centres[c, 1], centres[c, 2]
        if not _ball_meets_keep(cx, cy, cz, rc, r, z_lo, z_hi):
            continue  # the cell's ball misses the keep box
        cz = cz + dz_sum
        near = False
        for j in range(F):  # the ball meets finger j's band and reach
            along = cx * nrm[0, j] + cy * nrm[1, j] + cz * nrm[2, j]
            e0, e1, e2 = cx - origins[j, 0], cy - origins[j, 1], cz - origins[j, 2]
            lim = ball2[j] + rc
            if abs(along - shift[j]) <= band[j] + rc and e0 * e0 + e1 * e1 + e2 * e2 <= lim * lim:
                near = True
                break
        if near:
            for k in range(start[c], start[c] + count[c]):
                cand[m0] = order[k]
                m0 += 1
    # in ascending cloud order (each index once: the cells are disjoint): a radix sort of
    # the indices, 8 bits a pass, instead of passes over a mark per cloud point
    tmp = np.empty(m0, dtype=np.int64)
    srt = cand[:m0]
    bit = 0
    hist = np.zeros(257, dtype=np.int64)
    while (n - 1) >> bit > 0:
        hist[:] = 0
        for a in range(m0):
            hist[((srt[a] >> bit) & 255) + 1] += 1
        for b in range(256):
            hist[b + 1] += hist[b]
        for a in range(m0):
            d = (srt[a] >> bit) & 255
            tmp[hist[d]] = srt[a]
            hist[d] += 1
        srt, tmp = tmp, srt
        bit += 8
    px = np.empty(m0)
    py = np.empty(m0)
    pz = np.empty(m0)
    k = 0
    tx, ty, tz = T0[0, 3], T0[1, 3], T0[2, 3]
    r00, r01, r02 = T0[0, 0], T0[0, 1], T0[0, 2]
    r10, r11, r12 = T0[1, 0], T0[1, 1], T0[1, 2]
    r20, r21, r22 = T0[2, 0], T0[2, 1], T0[2, 2]
    for a in range(m0):  # ascending cloud order
        i = srt[a]
        d0, d1, d2 = xyz[0, i] - tx, xyz[1, i] - ty, xyz[2, i] - tz
        x = d0 * r00 + d1 * r10 + d2 * r20
        y = d0 * r01 + d1 * r11 + d2 * r21
        z = d0 * r02 + d1 * r12 + d2 * r22
        if _in_keep(x, y, z, r, z_lo, z_hi):
            px[k], py[k], pz[k] = x, y, _moved(z, dz)
            k += 1
    m = k
    uv = np.empty((m * F, 2))
    first = np.zeros(F + 1, dtype=np.int64)
    n_slice = np.zeros(F, dtype=np.int64)
    out = 0
    ku = np.empty(m, dtype=np.int64)
    kv = np.empty(m, dtype=np.int64)
    su = np.empty(m)
    sv = np.empty(m)
    pu = np.empty(m)  # per point: its plane coordinates and whether it is in the slice
    pv = np.empty(m)
    ins = np.empty(m, dtype=np.bool_)
    for j in range(F):  # <= 3 fingers
        Tp = T_planes[j]
        ox, oy, oz = Tp[0, 3], Tp[1, 3], Tp[2, 3]
        a00, a01, a02 = Tp[0, 0], Tp[0, 1], Tp[0, 2]
        a10, a11, a12 = Tp[1, 0], Tp[1, 1], Tp[1, 2]
        a20, a21, a22 = Tp[2, 0], Tp[2, 1], Tp[2, 2]
        n0, n1, n2, sh, bd = nrm[0, j], nrm[1, j], nrm[2, j], shift[j], band[j]
        hw, lim = half_width[j], reach2[j]
        ns = 0
        for i in range(m):  # every point's exact tests without a branch (so vectorised)
            along = px[i] * n0 + py[i] * n1 + pz[i] * n2
            d0, d1, d2 = px[i] - ox, py[i] - oy, pz[i] - oz
            u = d0 * a00 + d1 * a10 + d2 * a20
            v = d0 * a01 + d1 * a11 + d2 * a21
            off = d0 * a02 + d1 * a12 + d2 * a22
            pu[i], pv[i] = u, v
            ins[i] = (abs(along - sh) <= bd) & (abs(off) <= hw) & (u * u + v * v <= lim)
        for i in range(m):  # the slice's points, in ascending cloud order
            if ins[i]:
                su[ns], sv[ns] = pu[i], pv[i]
                ns += 1
        n_slice[j] = ns
        if cell <= 0.0 or ns < 2:  # thin_2d keeps every point
            for i in range(ns):
                uv[out, 0], uv[out, 1] = su[i], sv[i]
                out += 1
        else:  # the first point of every occupied square cell (thin_2d)
            for i in range(ns):
                ku[i] = np.int64(math.floor(su[i] / cell))
                kv[i] = np.int64(math.floor(sv[i] / cell))
            u0, v0, v1 = ku[0], kv[0], kv[0]
            for i in range(ns):
                u0 = min(u0, ku[i])
                v0 = min(v0, kv[i])
                v1 = max(v1, kv[i])
            width = v1 - v0 + 1
            u1 = u0
            for i in range(ns):
                u1 = max(u1, ku[i])
            n_cells = (u1 - u0 + 1) * width
            keep = np.zeros(ns, dtype=np.bool_)
            if n_cells <= 16 * ns + 65536:  # a dense grid: the first row seen in each cell
                taken = np.zeros(n_cells, dtype=np.bool_)
                for i in range(ns):  # ascending rows
                    key = (ku[i] - u0) * width + (kv[i] - v0)
                    if not taken[key]:
                        taken[key] = True
                        keep[i] = True
            else:  # a sparse spread: a stable sort of the cell keys
                keys = (ku[:ns] - u0) * width + (kv[:ns] - v0)
                rows = np.argsort(keys, kind="mergesort")  # stable: the lowest row first
                for a in range(ns):
                    if a == 0 or keys[rows[a]] != keys[rows[a - 1]]:
                        keep[rows[a]] = True
            for i in range(ns):
                if keep[i]:
                    uv[out, 0], uv[out, 1] = su[i], sv[i]
                    out += 1
        first[j + 1] = out
    return uv[:out], first, n_slice


def approach_sweep(
    xyz: np.ndarray,
    order: np.ndarray,
    start: np.ndarray,
    count: np.ndarray,
    cm: np.ndarray,
    cp: np.ndarray,
    T0: np.ndarray,
    wlo: np.ndarray,
    whi: np.ndarray,
    top: np.ndarray,
    Tb: np.ndarray,
    half: np.ndarray,
) -> float:
    """The first travel along hand +z at which a link box (poses ``Tb`` (L, 4, 4), half extents
    ``half`` (L, 3), grown by the clearance) touches a cloud point of its travel window (hand
    frame at ``T0``: ``wlo <= p <= whi`` across, ``wlo z <= p z <= top``), inf if none (the loop
    form of the window test and :func:`~pregrasp_core.planner.boxes.sweep_pairs` in
    :func:`~pregrasp_core.planner.approach.prepare`). cm, cp (C, 3): the cells' balls' bounds in
    that frame; xyz, order, start, count: the cloud and its cells. A cell whose ball meets a
    link's window is searched only when the ball itself, swept, can meet the box before the
    least travel found so far (its centre's slab interval with the half extents grown by its
    radius: a superset of every point's of the ball)."""
    best = np.inf
    L = Tb.shape[0]
    for c in range(cm.shape[0]):
        for il in range(L):
            if not (
                cp[c, 2] >= wlo[il, 2]
                and cm[c, 2] <= top[il]
                and cp[c, 0] >= wlo[il, 0]
                and cm[c, 0] <= whi[il, 0]
                and cp[c, 1] >= wlo[il, 1]
                and cm[c, 1] <= whi[il, 1]
            ):
                continue
            R = Tb[il]
            # the ball's own sweep: the slabs of its centre, each grown by its radius (a point
            # of the ball meets the box only within them); none ahead, or none before the
            # least travel found so far: no point of the cell can lower it
            rc = 0.5 * max(cp[c, 0] - cm[c, 0], cp[c, 1] - cm[c, 1], cp[c, 2] - cm[c, 2])
            v0 = 0.5 * (cm[c, 0] + cp[c, 0]) - R[0, 3]
            v1 = 0.5 * (cm[c, 1] + cp[c, 1]) - R[1, 3]
            v2 = 0.5 * (cm[c, 2] + cp[c, 2]) - R[2, 3]
            c_in, c_out = -np.inf, np.inf
            for j in range(3):
                a = v0 * R[0, j] + v1 * R[1, j] + v2 * R[2, j]
                d = R[2, j]
                h = half[il, j] + rc + APPROACH_CELL_MARGIN
                if abs(d) < 1e-12:
                    if abs(a) > h:
                        c_in = np.inf
                else:
                    t1 = (a - h) / d
                    t2 = (a + h) / d
                    c_in = max(c_in, min(t1, t2))
                    c_out = min(c_out, max(t1, t2))
            if not (c_in <= c_out and c_out >= 0.0 and c_in <= best):
                continue
            for k in range(start[c], start[c] + count[c]):
                px, py, pz = _to_view(xyz, order[k], T0)
                if not (
                    pz >= wlo[il, 2]
                    and pz <= top[il]
                    and px >= wlo[il, 0]
                    and px <= whi[il, 0]
                    and py >= wlo[il, 1]
                    and py <= whi[il, 1]
                ):
                    continue
                v0, v1, v2 = px - R[0, 3], py - R[1, 3], pz - R[2, 3]
                s_in, s_out = -np.inf, np.inf
                for j in range(3):  # the box's three axes (slab intersection)
                    a = v0 * R[0, j] + v1 * R[1, j] + v2 * R[2, j]
                    d = R[2, j]
                    h = half[il, j]
                    if abs(d) < 1e-12:
                        inside = abs(a) <= h
                        lo_j = -np.inf if inside else np.inf
                        hi_j = np.inf if inside else -np.inf
                    else:
                        t1 = (a - h) / d
                        t2 = (a + h) / d
                        lo_j = min(t1, t2)
                        hi_j = max(t1, t2)
                    s_in = max(s_in, lo_j)
                    s_out = min(s_out, hi_j)
                if s_in <= s_out and s_out >= 0.0:
                    best = min(best, max(s_in, 0.0))
    return best


def link_distances(
    xyz: np.ndarray,
    order: np.ndarray,
    start: np.ndarray,
    count: np.ndarray,
    centres: np.ndarray,
    rad: np.ndarray,
    dz_sum: float,
    T0: np.ndarray,
    r: float,
    z_lo: float,
    z_hi: float,
    dz: np.ndarray,
    blo: np.ndarray,
    bhi: np.ndarray,
    Tb: np.ndarray,
    half: np.ndarray,
    reach: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per link (poses ``Tb`` (L, 4, 4), half extents ``half``): the cloud points of the view
    (pose ``T0``, keep box r, z_lo, z_hi, shifts dz) within ``reach`` of its box and their exact
    signed distances (the loop form of ``verify._link_distances``). Candidates: the points in
    the link's AABB grown by ``reach`` (``blo``, ``bhi`` (L, 3)), from the cells whose balls
    (``centres`` (C, 3) in the frame of T0, radii ``rad``, moved by ``dz_sum``) meet it and the
    keep box. Returns
    ``(ids (K,), d (K,), first (L + 1,))``: link l's points ``ids[first[l]:first[l + 1]]`` in
    ascending cloud order. A cell whose ball meets the AABB is searched only when the ball
    also comes within ``reach`` of the box itself (the distance from its centre to the box
    in the box's frame)."""
    L = Tb.shape[0]
    cap = 1024
    ids = np.empty(cap, dtype=np.int64)
    dist = np.empty(cap)
    first = np.zeros(L + 1, dtype=np.int64)
    n = 0
    C = centres.shape[0]
    ok = np.zeros(C, dtype=np.bool_)
    cm = np.empty((C, 3))
    cp = np.empty((C, 3))
    cc = np.empty((C, 3))
    for c in range(C):  # the cells whose balls meet the keep box; their bounds, moved
        rc = rad[c]
        cx, cy, cz = centres[c, 0], centres[c, 1], centres[c, 2]
        ok[c] = _ball_meets_keep(cx, cy, cz, rc, r, z_lo, z_hi)
        cz = cz + dz_sum
        cc[c, 0], cc[c, 1], cc[c, 2] = cx, cy, cz
        cm[c, 0], cm[c, 1], cm[c, 2] = cx - rc, cy - rc, cz - rc
        cp[c, 0], cp[c, 1], cp[c, 2] = cx + rc, cy + rc, cz + rc
    for il in range(L):
        R = Tb[il]
        g = n
        for c in range(C):
            if not (
                ok[c]
                and cp[c, 0] >= blo[il, 0]
                and cm[c, 0] <= bhi[il, 0]
                and cp[c, 1] >= blo[il, 1]
                and cm[c, 1] <= bhi[il, 1]
                and cp[c, 2] >= blo[il, 2]
                and cm[c, 2] <= bhi[il, 2]
            ):
                continue
            # and the ball within reach of the box itself, not only of its bounding box: the
            # distance from the ball's centre to the box at most reach + its radius (a point
            # within reach of the box lies in such a ball; LINK_CELL_MARGIN covers rounding)
            w0, w1, w2 = cc[c, 0] - R[0, 3], cc[c, 1] - R[1, 3], cc[c, 2] - R[2, 3]
            e0 = max(abs(w0 * R[0, 0] + w1 * R[1, 0] + w2 * R[2, 0]) - half[il, 0], 0.0)
            e1 = max(abs(w0 * R[0, 1] + w1 * R[1, 1] + w2 * R[2, 1]) - half[il, 1], 0.0)
            e2 = max(abs(w0 * R[0, 2] + w1 * R[1, 2] + w2 * R[2, 2]) - half[il, 2], 0.0)
            lim = reach + rad[c] + LINK_CELL_MARGIN
            if e0 * e0 + e1 * e1 + e2 * e2 > lim * lim:
                continue
            for k in range(start[c], start[c] + count[c]):
                i = order[k]
                x, y, z = _to_view(xyz, i, T0)
                if not _in_keep(x, y, z, r, z_lo, z_hi):
                    continue
                z = _moved(z, dz)
                if not (
                    x >= blo[il, 0]
                    and x <= bhi[il, 0]
                    and y >= blo[il, 1]
                    and y <= bhi[il, 1]
                    and z >= blo[il, 2]
                    and z <= bhi[il, 2]
                ):
                    continue
                v0, v1, v2 = x - R[0, 3], y - R[1, 3], z - R[2, 3]
                q0 = abs(v0 * R[0, 0] + v1 * R[1, 0] + v2 * R[2, 0]) - half[il, 0]
                q1 = abs(v0 * R[0, 1] + v1 * R[1, 1] + v2 * R[2, 1]) - half[il, 1]
                q2 = abs(v0 * R[0, 2] + v1 * R[1, 2] + v2 * R[2, 2]) - half[il, 2]
                o0, o1, o2 = max(q0, 0.0), max(q1, 0.0), max(q2, 0.0)
                d = math.sqrt(o0 * o0 + o1 * o1 + o2 * o2) + min(max(max(q0, q1), q2), 0.0)
                if d <= reach:
                    if n == cap:  # grow the outputs
                        cap *= 2
                        ids2 = np.empty(cap, dtype=np.int64)
                        dist2 = np.empty(cap)
                        ids2[:n] = ids[:n]
                        dist2[:n] = dist[:n]
                        ids, dist = ids2, dist2
                    ids[n] = i
                    dist[n] = d
                    n += 1
        if n - g > 1:  # ascending cloud order within the link
            o = np.argsort(ids[g:n])
            ids[g:n] = ids[g:n][o]
            dist[g:n] = dist[g:n][o]
        first[il + 1] = n
    return ids[:n], dist[:n], first


def link_contacts(
    ids: np.ndarray,
    d: np.ndarray,
    first: np.ndarray,
    xyz: np.ndarray,
    centres: np.ndarray,
    contact_distance: float,
    tie: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Per link (the output of :func:`link_distances`: link l's points ``ids[first[l]:first[l +
    1]]``, distances ``d``): ``(least (L,), pick (L,))``, the least distance (inf without
    points) and the position in ``ids`` of the link's contact point, -1 for none (the loop
    form of ``verify._contacts``' choice): a link whose least distance is at most
    ``contact_distance`` touches; of its points within ``tie`` of that distance, the one
    nearest to its box centre (``centres`` (L, 3), world; squared distance summed x, y, z in
    that order, as numpy sums a row), then the lowest cloud index. ``centres`` empty: only the
    least distances. xyz (3, N): the cloud by coordinate."""
    L = first.shape[0] - 1
    least = np.full(L, np.inf)
    pick = np.full(L, -1, dtype=np.int64)
    for j in range(L):
        a, b = first[j], first[j + 1]
        if b == a:
            continue
        m = d[a]
        for k in range(a + 1, b):
            if d[k] < m:
                m = d[k]
        least[j] = m
        if centres.shape[0] == 0 or not m <= contact_distance:
            continue
        thr = m + tie
        best, best_off, best_id = -1, np.inf, 0
        for k in range(a, b):
            if not d[k] <= thr:
                continue
            i = ids[k]
            e0 = xyz[0, i] - centres[j, 0]
            e1 = xyz[1, i] - centres[j, 1]
            e2 = xyz[2, i] - centres[j, 2]
            off = (e0 * e0 + e1 * e1) + e2 * e2
            if best < 0 or off < best_off or (off == best_off and i < best_id):
                best, best_off, best_id = k, off, i
        pick[j] = best
    return least, pick
