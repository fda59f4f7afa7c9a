"""Compiled loops of the pool's collision test (numba, issue 15).

:func:`hand_hits_points` of :mod:`.collision` asks, for every open hand of a batch, whether a
cloud point lies inside one of the cells its link boxes are cut into (``link_cells``). The
numpy version (``_batch_hits``) decided most (hand, cell) rows by a k-d tree nearest-point
query and the rest by an exact point-in-box test; the kernel here does the exact test only,
on the points of a uniform voxel grid of the cloud that can lie in the cell, and stops at a
hand's first hit. Its floating-point operations are those of the numpy expressions, in their
order (no fused multiply-add, no reassociation):

- the cell's world centre ``einsum("gij,cj->gci", R_hand, t_cell) + t_hand``: per axis i
  ``((0 + R[i,0] t[0]) + R[i,1] t[1]) + R[i,2] t[2]``, then ``+ t_hand[i]``;
- its world rotation ``einsum("gij,cjk->gcik", R_hand, R_cell)``, the same sum over j;
- a point's cell coordinates ``einsum("mj,mjk->mk", p - centre, R)``, the same sum over j;
- the decision ``abs(local) <= half + CELL_SEAM`` on the three axes.

(The einsums sum over j in the order 0, 1, 2 for these layouts on this machine; a test checks
the kernel's values against them to the bit.) The grid only chooses which points are tested:
every point that can pass the test is among them (the cell's world bounding box, padded), so
the answers do not depend on the voxel size.

numba is imported and the kernels are compiled (or loaded from numba's on-disk cache,
``cache=True``) on first use, never when this module is imported; :func:`warm_up` does it on
purpose.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import NamedTuple

import numpy as np

from ..jit import Lazy, inline_helpers, njit

PAD: float = 1e-9
"""Metres added to a cell's world bounding box when choosing the voxels to visit (with
``1e-12`` of the coordinates' size): round-off of the centre, the rotation and the box is far
below it, so no point that passes the exact test is left out (a larger pad only visits more
points; the answers are the same)."""

MAX_VOXELS: int = 1 << 21
"""At most this many voxels in a cloud's grid, and at most 8 per point (or 4,096): the voxel
grows for a large or sparse cloud (the grid takes 32 bytes a point and 16 a voxel while it is
built)."""


def _bounds(pts):  # pragma: no cover - compiled by numba
    # (3,) minimum and (3,) maximum of the points (N, 3), N >= 1 (numpy's min(axis=0) and
    # max(axis=0), which are slow on this layout)
    lo = pts[0].copy()
    hi = pts[0].copy()
    for i in range(1, pts.shape[0]):
        for a in range(3):
            v = pts[i, a]
            if v < lo[a]:
                lo[a] = v
            if v > hi[a]:
                hi[a] = v
    return lo, hi


def _grid(pts, lo, h, dims):  # pragma: no cover - compiled by numba
    # counting sort of the points by voxel (x-major, then y, then z); the points keep their
    # order inside a voxel and their bits (copied)
    n = pts.shape[0]
    ny, nz = dims[1], dims[2]
    nvox = dims[0] * ny * nz
    vox = np.empty(n, dtype=np.int64)
    start = np.zeros(nvox + 1, dtype=np.int64)
    for i in range(n):
        k = 0
        for a in range(3):
            c = np.int64((pts[i, a] - lo[a]) / h)
            k = k * dims[a] + min(max(c, 0), dims[a] - 1)
        vox[i] = k
        start[k + 1] += 1
    for k in range(nvox):
        start[k + 1] += start[k]
    fill = start[:-1].copy()
    sorted_pts = np.empty((n, 3))
    for i in range(n):
        j = fill[vox[i]]
        fill[vox[i]] = j + 1
        sorted_pts[j, 0] = pts[i, 0]
        sorted_pts[j, 1] = pts[i, 1]
        sorted_pts[j, 2] = pts[i, 2]
    return start, sorted_pts


def _frame(T, Tc, c, centre, R):  # pragma: no cover - compiled by numba
    # world centre and rotation of cell c of hand T, in the einsums' order (module docstring)
    for i in range(3):
        s = 0.0
        s = s + T[i, 0] * Tc[c, 0, 3]
        s = s + T[i, 1] * Tc[c, 1, 3]
        s = s + T[i, 2] * Tc[c, 2, 3]
        centre[i] = s + T[i, 3]
    for i in range(3):
        for k in range(3):
            s = 0.0
            s = s + T[i, 0] * Tc[c, 0, k]
            s = s + T[i, 1] * Tc[c, 1, k]
            s = s + T[i, 2] * Tc[c, 2, k]
            R[i, k] = s


def _frames(T, Tc):  # pragma: no cover - compiled by numba
    # (G, C, 3) centres and (G, C, 3, 3) rotations of every cell of every hand (for tests)
    G, C = T.shape[0], Tc.shape[0]
    centres = np.empty((G, C, 3))
    Rs = np.empty((G, C, 3, 3))
    for g in range(G):
        for c in range(C):
            _frame(T[g], Tc, c, centres[g, c], Rs[g, c])
    return centres, Rs


def _coord(d0, d1, d2, R, k):  # pragma: no cover - compiled by numba, inline
    # coordinate k of the offset d in the cell frame R: ((0 + d0 R[0,k]) + d1 R[1,k]) + d2 R[2,k]
    s = 0.0
    s = s + d0 * R[0, k]
    s = s + d1 * R[1, k]
    s = s + d2 * R[2, k]
    return s


def _local(p, centre, R):  # pragma: no cover - compiled by numba
    # (M, 3) cell coordinates of the points p (M, 3): (p - centre) @ R in the einsum's order,
    # with the helper the kernel uses (for tests)
    M = p.shape[0]
    out = np.empty((M, 3))
    for m in range(M):
        d0 = p[m, 0] - centre[0]
        d1 = p[m, 1] - centre[1]
        d2 = p[m, 2] - centre[2]
        for k in range(3):
            out[m, k] = _coord(d0, d1, d2, R, k)
    return out


def _range(x, e, lo, h, n):  # pragma: no cover - compiled by numba
    # voxels [i0, i1] (clamped to [0, n - 1]; i0 > i1: none) that hold the points of [x - e,
    # x + e] along one axis (the voxel of a point is monotone in its coordinate)
    a = np.floor((x - e - lo) / h)
    b = np.floor((x + e - lo) / h)
    if not (a <= n - 1.0 and b >= 0.0):  # outside the grid, or NaN
        return 1, 0
    i0 = 0 if a < 0.0 else np.int64(a)
    i1 = n - 1 if b > n - 1.0 else np.int64(b)
    return i0, i1


def _hits(
    Tw, part, cell_lo, Tc, half, r_out, seam, lo, h, dims, start, spts
):  # pragma: no cover - compiled by numba
    # (G,) bool: hand g (Tw[g], cells cell_lo[part[g]] .. cell_lo[part[g] + 1] - 1) holds a
    # point inside a cell (|local| <= half + seam on the three axes); first hit ends the hand
    G = Tw.shape[0]
    out = np.zeros(G, dtype=np.bool_)
    nx, ny, nz = dims[0], dims[1], dims[2]
    centre = np.empty(3)
    R = np.empty((3, 3))
    ext = np.empty(3)
    grown = np.empty(3)
    for g in range(G):
        T = Tw[g]
        hit = False
        for c in range(cell_lo[part[g]], cell_lo[part[g] + 1]):
            _frame(T, Tc, c, centre, R)
            # quick look with the bounding sphere: any voxel at all?
            r = r_out[c]
            pad = PAD + 1e-12 * (abs(centre[0]) + abs(centre[1]) + abs(centre[2]) + r)
            x0, x1 = _range(centre[0], r + pad, lo[0], h, nx)
            if x0 > x1:
                continue
            y0, y1 = _range(centre[1], r + pad, lo[1], h, ny)
            if y0 > y1:
                continue
            z0, z1 = _range(centre[2], r + pad, lo[2], h, nz)
            if z0 > z1:
                continue
            # the cell's world bounding box (never larger than the sphere's)
            for i in range(3):
                grown[i] = half[c, i] + seam
            for i in range(3):
                ext[i] = (
                    abs(R[i, 0]) * grown[0] + abs(R[i, 1]) * grown[1] + abs(R[i, 2]) * grown[2]
                ) + pad
            x0, x1 = _range(centre[0], ext[0], lo[0], h, nx)
            y0, y1 = _range(centre[1], ext[1], lo[1], h, ny)
            z0, z1 = _range(centre[2], ext[2], lo[2], h, nz)
            if x0 > x1 or y0 > y1 or z0 > z1:
                continue
            for ix in range(x0, x1 + 1):
                for iy in range(y0, y1 + 1):
                    base = (ix * ny + iy) * nz
                    for j in range(start[base + z0], start[base + z1 + 1]):
                        d0 = spts[j, 0] - centre[0]
                        d1 = spts[j, 1] - centre[1]
                        d2 = spts[j, 2] - centre[2]
                        # the axes one by one, the first one out ends the point
                        if not (abs(_coord(d0, d1, d2, R, 0)) <= grown[0]):
                            continue
                        if not (abs(_coord(d0, d1, d2, R, 1)) <= grown[1]):
                            continue
                        if abs(_coord(d0, d1, d2, R, 2)) <= grown[2]:
                            hit = True
                            break
                    if hit:
                        break
                if hit:
                    break
            if hit:
                break
        out[g] = hit
    return out


class Kernels(NamedTuple):
    """The compiled kernels (see the module docstring)."""

    bounds: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]
    grid: Callable[..., tuple[np.ndarray, np.ndarray]]
    hits: Callable[..., np.ndarray]
    frames: Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]
    local: Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]


def kernels() -> Kernels:
    """The compiled kernels; the first call imports numba and compiles them (or loads them from
    numba's cache), once per process even when several threads ask at the same time."""
    return _KERNELS.get()


def _build() -> Kernels:
    """Import numba and wrap the kernels (compiled lazily, on their first call)."""
    inline_helpers(globals(), "_frame", "_coord", "_range")  # copied into the kernels
    return Kernels(
        bounds=njit(_bounds),
        grid=njit(_grid),
        hits=njit(_hits),
        frames=njit(_frames),
        local=njit(_local),
    )


_KERNELS = Lazy(_build)


def _writable(a: np.ndarray, dtype: type = np.float64) -> np.ndarray:
    """``a`` as a C-contiguous writable array of ``dtype`` (a copy only when it is not one
    already): numba compiles a kernel once per array type, and a read-only array (the
    pipeline's clouds are) is another type, which :func:`warm_up` would not have loaded."""
    a = np.ascontiguousarray(a, dtype=dtype)
    return a if a.flags.writeable else a.copy()


class PointGrid(NamedTuple):
    """A cloud's points sorted by voxel of a uniform grid (see :func:`point_grid`)."""

    lo: np.ndarray
    """(3,) lowest corner, the points' minimum."""
    h: float
    """Metres: side of a voxel."""
    dims: np.ndarray
    """(3,) int64 voxels per axis."""
    start: np.ndarray
    """(V + 1,) int64: the points of voxel v (x-major) are ``pts[start[v]:start[v + 1]]``."""
    pts: np.ndarray
    """(N, 3) the points, by voxel."""


def point_grid(pts: np.ndarray, h: float) -> PointGrid:
    """The points (N, 3), N >= 1, in a uniform grid of voxels of side ``h`` (larger when the grid
    would have more than :data:`MAX_VOXELS`) over their bounding box."""
    k = kernels()
    pts = _writable(pts)
    lo, hi = k.bounds(pts)
    size = hi - lo
    h = float(h)
    limit = min(MAX_VOXELS, max(4096, 8 * len(pts)))
    while True:
        cells = np.floor(size / h) + 1.0  # (3,) float: a far outlier's counts overflow int64
        if float(np.prod(cells)) <= limit:
            dims = cells.astype(np.int64)
            break
        h *= 1.25
    start, spts = k.grid(pts, lo, h, dims)
    return PointGrid(lo=lo, h=h, dims=dims, start=start, pts=spts)


def hits(
    T_world_hand: np.ndarray,
    part: np.ndarray,
    cell_lo: np.ndarray,
    T_cell: np.ndarray,
    half: np.ndarray,
    seam: float,
    grid: PointGrid,
) -> np.ndarray:
    """(G,) bool: hand g at ``T_world_hand[g]`` (G, 4, 4) holds a grid point inside one of the
    cells ``cell_lo[part[g]]`` to ``cell_lo[part[g] + 1] - 1`` of ``T_cell`` (C, 4, 4) and
    ``half`` (C, 3) (each half side grown by ``seam``)."""
    T, Tc, hf = _writable(T_world_hand), _writable(T_cell), _writable(half)
    r_out = np.sqrt((hf + seam) ** 2 @ np.ones(3))  # bounding spheres (only prune)
    return kernels().hits(
        T,
        _writable(part, np.int64),
        _writable(cell_lo, np.int64),
        Tc,
        hf,
        r_out,
        float(seam),
        grid.lo,
        grid.h,
        grid.dims,
        grid.start,
        grid.pts,
    )


def warm_up() -> float:
    """Import numba and compile (or load from its cache) the kernels for the argument types the
    pool uses, on a small fixed case. Returns the seconds it took."""
    t0 = time.perf_counter()
    k = kernels()
    pts = np.random.default_rng(0).uniform(-0.05, 0.05, (200, 3))
    grid = point_grid(pts, 0.01)
    T = np.tile(np.eye(4), (2, 1, 1))
    T[1, :3, 3] = 1.0
    Tc = np.eye(4)[None]
    half = np.full((1, 3), 0.01)
    hits(T, np.zeros(2, dtype=np.int64), np.array([0, 1]), Tc, half, 1e-12, grid)
    c, R = k.frames(T, Tc)
    k.local(pts, c[0, 0], R[0, 0])
    return time.perf_counter() - t0
