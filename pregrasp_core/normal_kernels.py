"""Compiled kernels of :mod:`pregrasp_core.normals` (numba, ``cache=True``, ``nogil=True``).

Imported only when a cloud without normals is oriented (numba's import costs a few tenths of a
second); each kernel is compiled on its first call, or by :func:`warm_up`, and cached on disk.
Every loop is over points (or views, then points); no kernel allocates per point. The kernels
release Python's lock: :mod:`pregrasp_core.normals` runs them on a few threads, each on its own
rows (or its own group of views), so that the results do not depend on the threads.

* :func:`grid_build`, :func:`knn_rows`: exact k nearest neighbours on a uniform grid of cells
  (a ring of cells around the query's cell grows until the k-th distance is inside it; columns
  of cells along z read as one run, cut to what the current k-th distance allows); rows sorted
  by distance (ties by index), the point itself first.
* :func:`pca_rows`: the covariance of the first ``s`` neighbours for a few scales ``s`` from
  one prefix sum, closed-form 3x3 eigenvalues (trigonometric solution), the normal of the
  smallest scale whose surface variation is below a bound.
* :func:`visibility_votes`: orthographic depth buffers, one per view direction; a point is
  hidden when it lies behind the tangent plane of its pixel's front-most point.
* :func:`same_side_weights`, :func:`fill_signs`: growth of the decided signs over the
  neighbour graph.
"""

from __future__ import annotations

import math

import numpy as np

from .jit import import_numba

nb = import_numba()


@nb.njit(cache=True, nogil=True, inline="always")
def _insert(bd: np.ndarray, bi: np.ndarray, count: int, k: int, d2: float, j: int) -> int:
    """Insert (d2, j) into the top-k lists ``bd``/``bi`` holding ``count`` entries, slot 0 the
    query itself, the others ordered by (distance, index); the caller has checked that (d2, j)
    comes before the k-th entry when the lists are full."""
    pos = count if count < k else k - 1
    while pos > 1 and (bd[pos - 1] > d2 or (bd[pos - 1] == d2 and bi[pos - 1] > j)):
        if pos < k:
            bd[pos] = bd[pos - 1]
            bi[pos] = bi[pos - 1]
        pos -= 1
    bd[pos] = d2
    bi[pos] = j
    return count + 1 if count < k else count


@nb.njit(cache=True, nogil=True)
def occupied_cells(p: np.ndarray, lo: np.ndarray, h: float) -> int:
    """Number of distinct cubes of side ``h`` from ``lo`` that hold a point of ``p``."""
    n = p.shape[0]
    c = np.empty((n, 3), np.int64)
    dims = np.zeros(3, np.int64)
    for i in range(n):
        for a in range(3):
            c[i, a] = int(math.floor((p[i, a] - lo[a]) / h))
            dims[a] = max(dims[a], c[i, a] + 1)
    seen = np.zeros(dims[0] * dims[1] * dims[2], np.bool_)
    count = 0
    for i in range(n):
        key = (c[i, 0] * dims[1] + c[i, 1]) * dims[2] + c[i, 2]
        if not seen[key]:
            seen[key] = True
            count += 1
    return count


@nb.njit(cache=True, nogil=True)
def grid_dims(p: np.ndarray, lo: np.ndarray, h: float) -> tuple[np.ndarray, int]:
    """(3,) cells per axis of the grid of cubes of side ``h`` from ``lo`` over ``p``, and the
    largest number of points in one cell."""
    n = p.shape[0]
    c = np.empty((n, 3), np.int64)
    dims = np.zeros(3, np.int64)
    for i in range(n):
        for a in range(3):
            c[i, a] = int(math.floor((p[i, a] - lo[a]) / h))
            dims[a] = max(dims[a], c[i, a] + 1)
    counts = np.zeros(dims[0] * dims[1] * dims[2], np.int32)
    most = 0
    for i in range(n):
        key = (c[i, 0] * dims[1] + c[i, 1]) * dims[2] + c[i, 2]
        counts[key] += 1
        most = max(most, counts[key])
    return dims, most


@nb.njit(cache=True, nogil=True)
def grid_build(
    p: np.ndarray, h: float, lo: np.ndarray, dims: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The grid of cubes of side ``h`` from ``lo``, ``dims`` (3,) per axis: (N, 3) cell of each
    point, (N,) point ids in cell order (cells by x, then y, then z: the cells of a column along
    z are adjacent), (cells + 1,) start of each cell in that order, (N, 3) the points in that
    order (contiguous reads)."""
    n = p.shape[0]
    gx, gy, gz = dims[0], dims[1], dims[2]
    cell = np.empty((n, 3), np.int64)
    key = np.empty(n, np.int64)
    for i in range(n):
        ix = min(max(int((p[i, 0] - lo[0]) / h), 0), gx - 1)
        iy = min(max(int((p[i, 1] - lo[1]) / h), 0), gy - 1)
        iz = min(max(int((p[i, 2] - lo[2]) / h), 0), gz - 1)
        cell[i, 0] = ix
        cell[i, 1] = iy
        cell[i, 2] = iz
        key[i] = (ix * gy + iy) * gz + iz
    n_cells = gx * gy * gz
    start = np.zeros(n_cells + 1, np.int64)
    for i in range(n):
        start[key[i] + 1] += 1
    for c in range(n_cells):
        start[c + 1] += start[c]
    fill = start[:-1].copy()
    order = np.empty(n, np.int64)
    for i in range(n):  # counting sort (stable)
        order[fill[key[i]]] = i
        fill[key[i]] += 1
    ps = np.empty((n, 3))
    for t in range(n):
        ps[t, 0] = p[order[t], 0]
        ps[t, 1] = p[order[t], 1]
        ps[t, 2] = p[order[t], 2]
    return cell, order, start, ps


@nb.njit(cache=True, nogil=True)
def query_order(cell: np.ndarray, dims: np.ndarray, queries: np.ndarray) -> np.ndarray:
    """Rows of ``queries`` in cell order (neighbouring queries read the same cells)."""
    n_q = queries.shape[0]
    qkey = np.empty(n_q, np.int64)
    for r in range(n_q):
        i = queries[r]
        qkey[r] = (cell[i, 0] * dims[1] + cell[i, 1]) * dims[2] + cell[i, 2]
    return np.argsort(qkey, kind="mergesort")


@nb.njit(cache=True, nogil=True)
def _scan(
    ps: np.ndarray,
    order: np.ndarray,
    t0: int,
    t1: int,
    i: int,
    px: float,
    py: float,
    pz: float,
    bd: np.ndarray,
    bi: np.ndarray,
    count: int,
    k: int,
) -> int:
    """Offer the points ``t0 .. t1 - 1`` (cell order) to the top-k lists of point ``i``."""
    for t in range(t0, t1):
        dx = ps[t, 0] - px
        dy = ps[t, 1] - py
        dz = ps[t, 2] - pz
        d2 = dx * dx + dy * dy + dz * dz
        if count < k or d2 <= bd[k - 1]:
            j = order[t]
            if j == i:
                continue
            if count == k and d2 == bd[k - 1] and j > bi[k - 1]:
                continue
            count = _insert(bd, bi, count, k, d2, j)
    return count


@nb.njit(cache=True, nogil=True)
def knn_rows(
    p: np.ndarray,
    cell: np.ndarray,
    order: np.ndarray,
    start: np.ndarray,
    ps: np.ndarray,
    queries: np.ndarray,
    qorder: np.ndarray,
    a0: int,
    a1: int,
    k: int,
    h: float,
    lo: np.ndarray,
    dims: np.ndarray,
    max_ring: int,
    dist: np.ndarray,
    idx: np.ndarray,
    unresolved: np.ndarray,
) -> None:
    """Exact k nearest neighbours of the queries ``qorder[a0:a1]`` (rows of ``queries``, point
    ids) on a grid from :func:`grid_build`, written into row ``r`` of ``dist`` / ``idx`` (Q, k):
    the point itself first, then by distance (ties by index), and ``unresolved[r]`` when the
    k-th neighbour lies beyond ``max_ring`` rings of cells (the caller asks a k-d tree). Rings
    of cells grow around the query's cell until the k-th distance is inside the scanned block;
    a column of cells along z is read as one run, cut to the z range the current k-th distance
    allows, and columns and cells farther than it are skipped (their bounds widened by 1e-9
    cells: the skipping never drops a point the full scan would keep)."""
    gx, gy, gz = dims[0], dims[1], dims[2]
    bd = np.empty(k)
    bi = np.empty(k, np.int64)
    eps = 1e-9 * h
    for qq in range(a0, a1):
        row = qorder[qq]
        i = queries[row]
        px, py, pz = p[i, 0], p[i, 1], p[i, 2]
        bd[0] = 0.0
        bi[0] = i
        count = 1
        ci, cj, ck = cell[i, 0], cell[i, 1], cell[i, 2]
        r = 0
        done = False
        while not done:
            r += 1
            for ix in range(max(ci - r, 0), min(ci + r, gx - 1) + 1):
                bx0 = lo[0] + ix * h - eps
                bx1 = lo[0] + (ix + 1) * h + eps
                ddx = bx0 - px if px < bx0 else (px - bx1 if px > bx1 else 0.0)
                ddx2 = ddx * ddx
                if count == k and ddx2 > bd[k - 1]:
                    continue
                for iy in range(max(cj - r, 0), min(cj + r, gy - 1) + 1):
                    by0 = lo[1] + iy * h - eps
                    by1 = lo[1] + (iy + 1) * h + eps
                    ddy = by0 - py if py < by0 else (py - by1 if py > by1 else 0.0)
                    dxy2 = ddx2 + ddy * ddy
                    if count == k and dxy2 > bd[k - 1]:
                        continue
                    base = (ix * gy + iy) * gz
                    if r == 1 or abs(ix - ci) == r or abs(iy - cj) == r:
                        z0 = max(ck - r, 0)
                        z1 = min(ck + r, gz - 1)
                        if count == k:  # the z range within the k-th distance
                            s = math.sqrt(bd[k - 1] - dxy2) * (1.0 + 1e-9) + eps
                            if pz - s > lo[2]:
                                z0 = max(z0, int((pz - s - lo[2]) / h))
                            z1 = min(z1, int((pz + s - lo[2]) / h))
                        if z0 <= z1:
                            count = _scan(
                                ps, order, start[base + z0], start[base + z1 + 1],
                                i, px, py, pz, bd, bi, count, k,
                            )  # fmt: skip
                    else:  # inside the previous block: only the two cells at +-r along z
                        for iz in (ck - r, ck + r):
                            if iz < 0 or iz >= gz:
                                continue
                            bz0 = lo[2] + iz * h - eps
                            bz1 = lo[2] + (iz + 1) * h + eps
                            ddz = bz0 - pz if pz < bz0 else (pz - bz1 if pz > bz1 else 0.0)
                            if count == k and dxy2 + ddz * ddz > bd[k - 1]:
                                continue
                            c = base + iz
                            count = _scan(
                                ps, order, start[c], start[c + 1],
                                i, px, py, pz, bd, bi, count, k,
                            )  # fmt: skip
            # distance from the point to the outside of the scanned block of cells
            m = np.inf
            for a in range(3):
                ca, g = cell[i, a], dims[a]
                if ca - r > 0:
                    m = min(m, p[i, a] - (lo[a] + (ca - r) * h))
                if ca + r < g - 1:
                    m = min(m, lo[a] + (ca + r + 1) * h - p[i, a])
            if count == k and bd[k - 1] < m * m:  # (a tie at m could lie outside)
                done = True
            elif m == np.inf:  # the block covers the whole grid
                done = True
            elif r >= max_ring:
                unresolved[row] = True
                done = True
        for t in range(k):
            dist[row, t] = math.sqrt(bd[t]) if t < count else np.inf
            idx[row, t] = bi[t] if t < count else i


@nb.njit(cache=True, nogil=True)
def _smallest_eig(
    a00: float, a01: float, a02: float, a11: float, a12: float, a22: float
) -> tuple[float, float, float, float, float, float]:
    """(l_min, l_mid, l_max) of a symmetric 3x3 matrix and the unit eigenvector of l_min."""
    q = (a00 + a11 + a22) / 3.0
    p1 = a01 * a01 + a02 * a02 + a12 * a12
    b00, b11, b22 = a00 - q, a11 - q, a22 - q
    p2 = b00 * b00 + b11 * b11 + b22 * b22 + 2.0 * p1
    if p2 <= 1e-300:
        return q, q, q, 0.0, 0.0, 1.0
    pp = math.sqrt(p2 / 6.0)
    det = (
        b00 * (b11 * b22 - a12 * a12)
        - a01 * (a01 * b22 - a12 * a02)
        + a02 * (a01 * a12 - b11 * a02)
    )
    r = det / (2.0 * pp * pp * pp)
    r = min(max(r, -1.0), 1.0)
    phi = math.acos(r) / 3.0
    e1 = q + 2.0 * pp * math.cos(phi)
    e3 = q + 2.0 * pp * math.cos(phi + 2.0 * math.pi / 3.0)
    e2 = 3.0 * q - e1 - e3
    # eigenvector of e3: the largest cross product of two rows of (A - e3 I)
    r0x, r0y, r0z = a00 - e3, a01, a02
    r1x, r1y, r1z = a01, a11 - e3, a12
    r2x, r2y, r2z = a02, a12, a22 - e3
    c0x, c0y, c0z = r0y * r1z - r0z * r1y, r0z * r1x - r0x * r1z, r0x * r1y - r0y * r1x
    c1x, c1y, c1z = r0y * r2z - r0z * r2y, r0z * r2x - r0x * r2z, r0x * r2y - r0y * r2x
    c2x, c2y, c2z = r1y * r2z - r1z * r2y, r1z * r2x - r1x * r2z, r1x * r2y - r1y * r2x
    n0 = c0x * c0x + c0y * c0y + c0z * c0z
    n1 = c1x * c1x + c1y * c1y + c1z * c1z
    n2 = c2x * c2x + c2y * c2y + c2z * c2z
    if n0 >= n1 and n0 >= n2:
        vx, vy, vz, nn = c0x, c0y, c0z, n0
    elif n1 >= n2:
        vx, vy, vz, nn = c1x, c1y, c1z, n1
    else:
        vx, vy, vz, nn = c2x, c2y, c2z, n2
    if nn <= 1e-300:
        return e3, e2, e1, 0.0, 0.0, 1.0
    s = 1.0 / math.sqrt(nn)
    return e3, e2, e1, vx * s, vy * s, vz * s


@nb.njit(cache=True, nogil=True)
def pca_rows(
    p: np.ndarray,
    idx: np.ndarray,
    scales: np.ndarray,
    flat: float,
    a0: int,
    a1: int,
    normals: np.ndarray,
    variation: np.ndarray,
) -> None:
    """Rows ``a0 .. a1 - 1`` of :func:`pca_scales`, written into ``normals`` and ``variation``."""
    n_s = scales.shape[0]
    for i in range(a0, a1):
        sx = sy = sz = 0.0
        sxx = sxy = sxz = syy = syz = szz = 0.0
        t = 0
        c = idx[i, 0]  # the point itself: coordinates relative to it
        for si in range(n_s):
            m = scales[si]
            while t < m:
                j = idx[i, t]
                x = p[j, 0] - p[c, 0]
                y = p[j, 1] - p[c, 1]
                z = p[j, 2] - p[c, 2]
                sx += x
                sy += y
                sz += z
                sxx += x * x
                sxy += x * y
                sxz += x * z
                syy += y * y
                syz += y * z
                szz += z * z
                t += 1
            mx, my, mz = sx / m, sy / m, sz / m
            l3, l2, l1, vx, vy, vz = _smallest_eig(
                sxx / m - mx * mx,
                sxy / m - mx * my,
                sxz / m - mx * mz,
                syy / m - my * my,
                syz / m - my * mz,
                szz / m - mz * mz,
            )
            total = l1 + l2 + l3
            var = max(l3, 0.0) / total if total > 1e-300 else 0.0
            if var < flat or si == n_s - 1:
                normals[i, 0] = vx
                normals[i, 1] = vy
                normals[i, 2] = vz
                variation[i] = min(var, 1.0 / 3.0)
                break


@nb.njit(cache=True, nogil=True)
def pca_scales(
    p: np.ndarray, idx: np.ndarray, scales: np.ndarray, flat: float
) -> tuple[np.ndarray, np.ndarray]:
    """(R, 3) unit normals and (R,) surface variation l3 / (l1 + l2 + l3): per row of ``idx``
    (a point's neighbours, itself first, then by distance), the covariance of its first
    ``scales[s]`` entries (ascending ``scales``); the smallest scale whose variation is below
    ``flat`` is kept, else the largest."""
    n = idx.shape[0]
    normals = np.empty((n, 3))
    variation = np.empty(n)
    pca_rows(p, idx, scales, flat, 0, n, normals, variation)
    return normals, variation


@nb.njit(cache=True, nogil=True)
def visibility_votes(
    p: np.ndarray,
    n: np.ndarray,
    m: np.ndarray,
    dirs: np.ndarray,
    u: np.ndarray,
    w: np.ndarray,
    radius: float,
    pix: float,
    g: int,
    tol: float,
    curv_radius: float,
    rank: np.ndarray,
    v0: int,
    v1: int,
    net: np.ndarray,
    tot: np.ndarray,
    net_m: np.ndarray,
) -> None:
    """Add to net (N,) and total (N,) votes, and to the net votes (N,) of the second directions
    ``m`` (same sightings), those of the views ``v0 .. v1 - 1``: for each view ``dirs[v]``
    (towards the viewer; ``u[v]``, ``w[v]`` span its image plane), the front-most point of
    every pixel of side ``pix`` (``g`` x ``g`` pixels over [-radius, radius]^2); a point is
    seen unless it lies more than ``tol + l^2 / (2 curv_radius)`` behind the tangent plane of
    its pixel's front point (``l`` the image distance between the two, the allowance for a
    convex surface curving away); a sighting votes ``sign(n . d) |n . d|``. ``p`` centred on
    the cloud. Of equally deep points the one of lowest ``rank`` (N,) is a pixel's front point
    (the caller's order of the points: the votes do not depend on the order of ``p``)."""
    n_pts = p.shape[0]
    front = np.empty(g * g)
    front_id = np.empty(g * g, np.int64)
    cell = np.empty(n_pts, np.int64)
    depth = np.empty(n_pts)
    lx = np.empty(n_pts)
    ly = np.empty(n_pts)
    for v in range(v0, v1):
        dx, dy, dz = dirs[v, 0], dirs[v, 1], dirs[v, 2]
        ux, uy, uz = u[v, 0], u[v, 1], u[v, 2]
        wx, wy, wz = w[v, 0], w[v, 1], w[v, 2]
        front[:] = -np.inf
        front_id[:] = -1
        for i in range(n_pts):
            x = p[i, 0] * ux + p[i, 1] * uy + p[i, 2] * uz
            y = p[i, 0] * wx + p[i, 1] * wy + p[i, 2] * wz
            d = p[i, 0] * dx + p[i, 1] * dy + p[i, 2] * dz
            ix = min(max(int((x + radius) / pix), 0), g - 1)
            iy = min(max(int((y + radius) / pix), 0), g - 1)
            c = iy * g + ix
            cell[i] = c
            depth[i] = d
            lx[i] = x
            ly[i] = y
            if d > front[c] or (d == front[c] and rank[i] < rank[front_id[c]]):
                front[c] = d
                front_id[c] = i
        for i in range(n_pts):
            f = front_id[cell[i]]
            if f != i:
                fnd = n[f, 0] * dx + n[f, 1] * dy + n[f, 2] * dz
                hgt = (
                    (p[i, 0] - p[f, 0]) * n[f, 0]
                    + (p[i, 1] - p[f, 1]) * n[f, 1]
                    + (p[i, 2] - p[f, 2]) * n[f, 2]
                )
                if fnd < 0.0:
                    hgt = -hgt  # the front point's normal turned towards the viewer
                l2 = (lx[i] - lx[f]) ** 2 + (ly[i] - ly[f]) ** 2
                if hgt < -(tol + 0.5 * l2 / curv_radius):
                    continue  # behind the front surface of its pixel
            nd = n[i, 0] * dx + n[i, 1] * dy + n[i, 2] * dz
            a = abs(nd)
            tot[i] += a
            net[i] += a if nd > 0.0 else -a
            net_m[i] += m[i, 0] * dx + m[i, 1] * dy + m[i, 2] * dz


@nb.njit(cache=True, nogil=True)
def same_side_weights(
    p: np.ndarray, n: np.ndarray, idx: np.ndarray, sigma: float, skip: np.ndarray
) -> np.ndarray:
    """(N, k) signed weights ``(n_i . n_j) exp(-(h / sigma)^2)`` of each point's neighbours,
    ``h`` the larger of the neighbour's offset along ``n_i`` and the point's along ``n_j``
    (a neighbour across a thin wall sits along the normal: no say); 0 for the point itself and
    for the rows ``skip`` (N,) bool (the decided points, whose weights no one reads)."""
    n_pts, k = idx.shape
    out = np.zeros((n_pts, k))
    for i in range(n_pts):
        if skip[i]:
            continue
        for t in range(k):
            j = idx[i, t]
            if j == i:
                continue
            ox = p[j, 0] - p[i, 0]
            oy = p[j, 1] - p[i, 1]
            oz = p[j, 2] - p[i, 2]
            h1 = abs(ox * n[i, 0] + oy * n[i, 1] + oz * n[i, 2])
            h2 = abs(ox * n[j, 0] + oy * n[j, 1] + oz * n[j, 2])
            h = max(h1, h2) / sigma
            nn = n[i, 0] * n[j, 0] + n[i, 1] * n[j, 1] + n[i, 2] * n[j, 2]
            out[i, t] = nn * math.exp(-h * h)
    return out


@nb.njit(cache=True, nogil=True)
def fill_signs(
    sign: np.ndarray, decided: np.ndarray, idx: np.ndarray, wts: np.ndarray, rounds: int
) -> np.ndarray:
    """Signs (N,) grown from the decided points: each round, every undecided point takes the
    sign of the weighted sum of its neighbours' signs (0 while none has a say)."""
    n_pts, k = idx.shape
    cur = sign.copy()
    nxt = sign.copy()
    for _ in range(rounds):
        changed = False
        for i in range(n_pts):
            if decided[i]:
                continue
            acc = 0.0
            for t in range(k):
                acc += cur[idx[i, t]] * wts[i, t]
            s = 1.0 if acc > 0.0 else (-1.0 if acc < 0.0 else 0.0)
            if s != cur[i]:
                changed = True
            nxt[i] = s
        cur, nxt = nxt, cur
        nxt[:] = cur
        if not changed:
            break
    return cur


def warm_up() -> None:
    """Compile (or load from the cache) every kernel on a tiny cloud."""
    rng = np.random.default_rng(0)
    p = rng.normal(size=(64, 3))
    lo = p.min(axis=0)
    occupied_cells(p, lo, 0.5)
    dims, _ = grid_dims(p, lo, 0.5)
    cell, order, start, ps = grid_build(p, 0.5, lo, dims)
    q = np.arange(64)
    qorder = query_order(cell, dims, q)
    dist, idx = np.empty((64, 8)), np.empty((64, 8), np.int64)
    knn_rows(p, cell, order, start, ps, q, qorder, 0, 64, 8, 0.5, lo, dims, 3, dist, idx,
             np.zeros(64, np.bool_))  # fmt: skip
    normals, _ = pca_scales(p, idx, np.array([4, 8], np.int64), 0.02)
    d = np.array([[0.0, 0.0, 1.0]])
    u, w = np.array([[1.0, 0, 0]]), np.array([[0, 1.0, 0]])
    net, tot, net_m = np.zeros(64), np.zeros(64), np.zeros(64)
    visibility_votes(
        p, normals, normals, d, u, w, 4.0, 1.0, 8, 0.1, 1.0, np.arange(64), 0, 1, net, tot, net_m
    )
    wts = same_side_weights(p, normals, idx, 0.1, np.zeros(64, np.bool_))
    fill_signs(np.zeros(64), np.zeros(64, np.bool_), idx, wts, 2)
