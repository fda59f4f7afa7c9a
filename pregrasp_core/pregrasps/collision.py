"""The open hand against the cloud and the support plane, for whole batches of hands.

:func:`hand_hits_points` (any cloud point inside a link's collision box) and
:func:`hand_min_height` (lowest link corner above the support plane) are the two tests of the
pool's filters; :func:`hand_corners` and :func:`link_cells` give the links' boxes they use.
"""

from __future__ import annotations

import weakref
from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial import cKDTree

from ..facemask import SupportPlane
from ..geometry import as_points, box_corners
from ..tolerances import GEOM_EPS

if TYPE_CHECKING:
    from ..hand import Hand
    from .collision_kernels import PointGrid

CELL_SEAM: float = 1e-12
"""Metres: cells of a link box are grown by this so that round-off at their shared seams
cannot let a point slip between two cells (:func:`hand_hits_points`)."""

HAND_BATCH: int = 4096
"""Hands tested at once by :func:`hand_hits_points`."""

PAIR_BATCH: int = 1 << 18
"""(cell, point) pairs of the exact point-in-box test handled at once by
:func:`hand_hits_points`."""

BYTES_PER_HAND: int = 10_000
"""Peak bytes of :func:`hand_hits_points` per hand of a batch: the link cells' frames, centres
and distances with their temporaries (measured 4,500 to 6,300 for the 37 cells of the default
hand)."""

BYTES_PER_PAIR: int = 400
"""Peak bytes per (cell, point) pair of the exact test (the index lists and the pair arrays,
about 300)."""


def collision_batch_bytes() -> int:
    """Bytes: bound on the peak memory of :func:`hand_hits_points` whatever the number of hands
    and points (one full batch of each kind: 4096 hands and 262,144 pairs take about 140 MB)."""
    return HAND_BATCH * BYTES_PER_HAND + PAIR_BATCH * BYTES_PER_PAIR


CellCache = dict[tuple[bytes, float], tuple[np.ndarray, np.ndarray]]
""":func:`link_cells` per (preshape bytes, margin), shared by calls of :func:`hand_hits_points`."""

_HAND_CELLS: weakref.WeakKeyDictionary[Hand, CellCache] = weakref.WeakKeyDictionary()

HAND_CELLS_KEPT: int = 256
"""Preshapes whose link cells :func:`hand_cell_cache` keeps per hand (then it starts again)."""


def hand_cell_cache(hand: Hand) -> CellCache:
    """The :data:`CellCache` of ``hand``, shared by every pool built for it (the cells are a
    function of the hand, the preshape and the margin only: a new threshold or cloud in the
    viewer reuses them)."""
    cache = _HAND_CELLS.get(hand)
    if cache is None or len(cache) > HAND_CELLS_KEPT:
        cache = {}
        _HAND_CELLS[hand] = cache
    return cache


def _by_preshape(q: np.ndarray) -> list[np.ndarray]:
    """Indices of the rows of ``q`` (P, J) grouped by distinct preshape, in order of first
    appearance (the paper's types have one preshape each, the pinches adapt theirs)."""
    Q = np.asarray(q, dtype=np.float64)
    if len(Q) == 0:
        return []
    _, first, inv = np.unique(Q, axis=0, return_index=True, return_inverse=True)
    inv = inv.reshape(-1)
    return [np.flatnonzero(inv == g) for g in np.argsort(first)]


_HAND_POSES: weakref.WeakKeyDictionary[Hand, dict[bytes, tuple[np.ndarray, np.ndarray]]] = (
    weakref.WeakKeyDictionary()
)

HAND_POSES_KEPT: int = 256
"""Preshapes whose link box poses and corners :func:`preshape_box_poses` keeps per hand (then it
starts again)."""


def _pose_entry(hand: Hand, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(box poses (L, 4, 4), corners (8 L, 3))`` of the preshape ``q`` (J,), both read-only,
    computed once per hand and preshape (by its bytes)."""
    Q = np.asarray(q, dtype=np.float64)
    cache = _HAND_POSES.setdefault(hand, {})
    key = Q.tobytes()
    got = cache.get(key)
    if got is None:
        if len(cache) >= HAND_POSES_KEPT:  # full: start again (a kept preshape stays kept)
            cache.clear()
        Tb = hand.box_poses(Q)  # (L, 4, 4)
        corners = box_corners(Tb, hand.link_box_half)
        Tb.setflags(write=False)
        corners.setflags(write=False)
        got = cache[key] = (Tb, corners)
    return got


def preshape_box_poses_many(hand: Hand, Q: np.ndarray) -> np.ndarray:
    """(B, L, 4, 4): :func:`preshape_box_poses` of each row of ``Q`` (B, J), B >= 1, the rows
    not kept yet by one batched forward kinematics (``hand.box_poses`` of them together, which
    gives each row the bits of its own call: tests check it on random preshapes and every call
    of the demo objects' pools), then kept like those of :func:`preshape_box_poses`."""
    Qa = np.asarray(Q, dtype=np.float64)
    cache = _HAND_POSES.setdefault(hand, {})
    keys = [row.tobytes() for row in Qa]
    new = [i for i, k in enumerate(keys) if k not in cache]
    if new and len(cache) + len(new) > HAND_POSES_KEPT:  # full: start again
        cache.clear()
        new = list(range(len(keys)))
    if new:
        Tb_new = hand.box_poses(Qa[new])  # (n, L, 4, 4)
        for i, Tb in zip(new, Tb_new, strict=True):  # loop over the new preshapes
            Tb = Tb.copy()
            corners = box_corners(Tb, hand.link_box_half)
            Tb.setflags(write=False)
            corners.setflags(write=False)
            cache[keys[i]] = (Tb, corners)
    return np.stack([cache[k][0] for k in keys])


def preshape_box_poses(hand: Hand, q: np.ndarray) -> np.ndarray:
    """``hand.box_poses(q)`` (L, 4, 4) of one preshape ``q`` (J,), read-only: computed once per
    hand and preshape (kept per hand, by the preshape's bytes), the same array for the pinch's
    self-collision check, :func:`hand_corners` and :func:`link_cells` (the pinches adapt their
    preshape to the part: one forward kinematics per preshape instead of three)."""
    return _pose_entry(hand, q)[0]


def hand_corners(hand: Hand, q: np.ndarray) -> np.ndarray:
    """(8 L, 3) corners of all the links' collision boxes at configuration ``q`` (J,), hand
    frame (a fresh copy of the corners kept per preshape, :func:`preshape_box_poses`)."""
    return _pose_entry(hand, q)[1].copy()


def _hand_corners_reference(hand: Hand, q: np.ndarray) -> np.ndarray:
    """:func:`hand_corners` without the cache (the version before it, kept for its tests)."""
    Tb = hand.box_poses(np.asarray(q, dtype=np.float64))  # (L, 4, 4)
    return box_corners(Tb, hand.link_box_half)


def hand_min_height(
    hand: Hand,
    T_world_hand: np.ndarray,
    grasp_type: np.ndarray,
    q: np.ndarray,
    support: SupportPlane,
) -> np.ndarray:
    """(P,) metres: height above ``support`` of the lowest corner of the links' collision boxes
    of each open hand at ``T_world_hand`` (P, 4, 4) with preshape ``q`` (P, J), one preshape
    per row (negative: the hand reaches below the plane). ``grasp_type`` (P,) is not used: the
    hands are grouped by preshape (the pinches adapt theirs to the part)."""
    return _min_height(T_world_hand, q, support, lambda qi: _pose_entry(hand, qi)[1])


def _hand_min_height_reference(
    hand: Hand, T_world_hand: np.ndarray, q: np.ndarray, support: SupportPlane
) -> np.ndarray:
    """:func:`hand_min_height` with each preshape's corners computed afresh (the version before
    the kept corners, the reference of its tests and benchmark)."""
    return _min_height(T_world_hand, q, support, lambda qi: _hand_corners_reference(hand, qi))


def _min_height(
    T_world_hand: np.ndarray,
    q: np.ndarray,
    support: SupportPlane,
    corners_of: Callable[[np.ndarray], np.ndarray],
) -> np.ndarray:
    """:func:`hand_min_height` with the corners (8 L, 3) of a preshape from ``corners_of``."""
    out = np.zeros(len(T_world_hand))
    for sel in _by_preshape(q):  # loop over the distinct preshapes (a few)
        corners = corners_of(q[sel[0]])  # (C, 3) hand frame
        T = T_world_hand[sel]  # (m, 4, 4)
        up_hand = np.einsum("mji,j->mi", T[:, :3, :3], support.normal)  # (m, 3) up in hand frames
        h = corners @ up_hand.T + (T[:, :3, 3] @ support.normal)[None, :]  # (C, m) heights
        out[sel] = h.min(axis=0) - support.height
    return out


_LINK_GRIDS: weakref.WeakKeyDictionary[Hand, dict[float, list[tuple[np.ndarray, np.ndarray]]]] = (
    weakref.WeakKeyDictionary()
)


def _link_grids(hand: Hand, margin: float) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per link of ``hand``, ``(offs (c, 3), half (c, 3))``: the centres of its box's cells in
    the box frame and their half sides, for ``margin`` (a function of the hand and the margin
    only, not of the preshape: built once per hand and margin, read-only)."""
    per_hand = _grids_of(hand)
    got = per_hand.get(float(margin))
    if got is None:
        half = np.asarray(hand.link_box_half, dtype=np.float64) + margin  # (L, 3)
        got = []
        for l in range(len(half)):  # loop over the ~10 links
            n = np.maximum(np.ceil(half[l] / max(half[l].min(), GEOM_EPS) - 1e-9), 1).astype(int)
            h = half[l] / n  # (3,) half sides of the cells
            grids = [(np.arange(k) + 0.5) * 2 * hh - k * hh for k, hh in zip(n, h, strict=True)]
            offs = np.stack(np.meshgrid(*grids, indexing="ij"), axis=-1).reshape(-1, 3)  # (c, 3)
            hs = np.tile(h, (len(offs), 1))
            offs.setflags(write=False)
            hs.setflags(write=False)
            got.append((offs, hs))
        if len(per_hand) > HAND_CELLS_KEPT:
            per_hand.clear()
        per_hand[float(margin)] = got
    return got


def _grids_of(hand: Hand) -> dict[float, list[tuple[np.ndarray, np.ndarray]]]:
    """The hand's :func:`_link_grids` per margin."""
    got = _LINK_GRIDS.get(hand)
    if got is None:
        got = _LINK_GRIDS[hand] = {}
    return got


def link_cells(hand: Hand, q: np.ndarray, margin: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """The links' collision boxes at ``q`` (J,), grown by ``margin`` and cut into near-cubic
    cells (a box's side / its shortest side cells per axis, rounded up).

    Returns ``(T_hand_cell (C, 4, 4), half (C, 3))``: the cells tile the boxes exactly, so a point
    lies in a link box iff it lies in one of its cells. The box poses come from
    :func:`preshape_box_poses` and the cells' layout in each box (a function of the hand and
    the margin only) is kept per hand: per preshape only the cells' poses are computed, with
    the operations of :func:`_link_cells_reference` (the same numbers, a test checks it)."""
    Tb = preshape_box_poses(hand, q)  # (L, 4, 4)
    Ts, hs = [], []
    for l, (offs, h) in enumerate(_link_grids(hand, margin)):  # loop over the ~10 links
        T = np.tile(Tb[l], (len(offs), 1, 1))
        T[:, :3, 3] += offs @ Tb[l, :3, :3].T
        Ts.append(T)
        hs.append(h)
    return np.concatenate(Ts), np.concatenate(hs)


def _link_cells_reference(
    hand: Hand, q: np.ndarray, margin: float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`link_cells` as it was before its caches (kept as the reference of its tests)."""
    Tb = hand.box_poses(np.asarray(q, dtype=np.float64))  # (L, 4, 4)
    half = np.asarray(hand.link_box_half, dtype=np.float64) + margin  # (L, 3)
    Ts, hs = [], []
    for l in range(len(half)):  # loop over the ~10 links
        n = np.maximum(np.ceil(half[l] / max(half[l].min(), GEOM_EPS) - 1e-9), 1).astype(int)
        h = half[l] / n  # (3,) half sides of the cells
        grids = [(np.arange(k) + 0.5) * 2 * hh - k * hh for k, hh in zip(n, h, strict=True)]
        offs = np.stack(np.meshgrid(*grids, indexing="ij"), axis=-1).reshape(-1, 3)  # (c, 3)
        T = np.tile(Tb[l], (len(offs), 1, 1))
        T[:, :3, 3] += offs @ Tb[l, :3, :3].T
        Ts.append(T)
        hs.append(np.tile(h, (len(offs), 1)))
    return np.concatenate(Ts), np.concatenate(hs)


VOXEL: float = 0.005
"""Metres: side of the voxels of the cloud's grid in :func:`hand_hits_points` (only a matter of
speed: the answers do not depend on it)."""


def _preshape_cells(
    hand: Hand, q: np.ndarray, margin: float, cells: CellCache | None
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`link_cells` of the preshape ``q`` (J,) with ``margin``, from ``cells`` when it has
    them (and put there when not)."""
    key = (q.tobytes(), float(margin))
    if cells is None or key not in cells:
        cell = link_cells(hand, q, margin)
        if cells is not None:
            cells[key] = cell
        return cell
    return cells[key]


def _preshape_parts(q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(part (P,), first (K,))``: the rows of ``q`` (P, J), P >= 1, grouped by their bytes
    (one preshape per group, every row of a group equal to its ``first`` row to the bit);
    ``part[i]`` is the group of row i. (Faster than :func:`_by_preshape`'s
    ``unique(axis=0)``: one look when every row is the first, as for the paper's types.)"""
    Q = np.ascontiguousarray(q, dtype=np.float64).reshape(len(q), -1)
    b = Q.view(np.int64)
    if (b == b[0]).all():
        return np.zeros(len(Q), dtype=np.int64), np.zeros(1, dtype=np.int64)
    rows = Q.view(np.dtype((np.void, Q.shape[1] * 8))).reshape(-1)
    _, first, inv = np.unique(rows, return_index=True, return_inverse=True)
    return inv.reshape(-1).astype(np.int64), first


def cloud_grid(points: np.ndarray) -> PointGrid:
    """The voxel grid :func:`hand_hits_points` tests ``points`` (N, 3), N >= 1, in (voxel
    :data:`VOXEL`), for a caller that makes many calls on one cloud (the pool: built once per
    pool, with no k-d tree)."""
    from . import collision_kernels as ck

    return ck.point_grid(as_points(points), VOXEL)


def hand_hits_points(
    hand: Hand,
    T_world_hand: np.ndarray,
    grasp_type: np.ndarray,
    q: np.ndarray,
    points: np.ndarray,
    margin: float = 0.0,
    cells: CellCache | None = None,
    grid: PointGrid | None = None,
) -> np.ndarray:
    """(P,) bool: the open hand at ``T_world_hand`` (P, 4, 4) with preshape ``q`` (P, J) holds
    at least one of ``points`` (N, 3) inside a link's collision box grown by ``margin``: the
    same answer as ``Hand.hands_hit_points`` (a test checks it), faster for a pool.

    Each link box is cut into near-cubic cells (:func:`link_cells`); a compiled kernel
    (:mod:`.collision_kernels`) puts the points in a uniform grid of voxels of side
    :data:`VOXEL` and, per hand and cell, tests exactly (``abs(local) <= half + CELL_SEAM``, the
    operations of :func:`hand_hits_points_numpy` in their order) the points of the voxels that
    meet the cell's world bounding box; a hand's first hit ends it. The answers are those of
    :func:`hand_hits_points_numpy` (tests check it). ``cells``: an optional dict caching
    :func:`link_cells` per preshape across calls. ``grid``: :func:`cloud_grid` of ``points``,
    for a caller that makes many calls on one cloud (the pool builds it once); built here when
    None. Memory is O(P + N + cells + voxels),
    whatever P and N (at most 8 voxels a point)."""
    from . import collision_kernels as ck

    pts = as_points(points)
    P = len(T_world_hand)
    if P == 0 or len(pts) == 0:
        return np.zeros(P, dtype=bool)
    part, first = _preshape_parts(q)
    Ts, hs = [], []
    for i in first:  # loop over the distinct preshapes
        cell = _preshape_cells(hand, q[i], margin, cells)
        Ts.append(cell[0])
        hs.append(cell[1])
    cell_lo = np.concatenate([[0], np.cumsum([len(t) for t in Ts])])
    return ck.hits(
        T_world_hand,
        part,
        cell_lo,
        np.concatenate(Ts),
        np.concatenate(hs),
        CELL_SEAM,
        grid if grid is not None else cloud_grid(pts),
    )


def hand_hits_points_numpy(
    hand: Hand,
    T_world_hand: np.ndarray,
    grasp_type: np.ndarray,
    q: np.ndarray,
    points: np.ndarray,
    margin: float = 0.0,
    cells: CellCache | None = None,
    grid: PointGrid | None = None,
    kd: cKDTree | None = None,
) -> np.ndarray:
    """:func:`hand_hits_points` in numpy (the version before the compiled kernel, kept as the
    reference of its tests and benchmark, called with the same arguments: ``grid`` is not
    used; ``kd``, the k-d tree of ``points``, is built when None).

    Each link box is cut into near-cubic cells (:func:`link_cells`); one nearest-point query
    per cell decides most cells (no point within its circumscribed sphere: free; a point within
    its inscribed sphere: hit); the undecided cells get the exact point-in-box test on the points
    of their circumscribed sphere. Hands already hit skip their remaining cells.

    Memory is bounded whatever P and N: the hands go in batches of :data:`HAND_BATCH` and the
    exact test in batches of about :data:`PAIR_BATCH` (cell, point) pairs."""
    pts = as_points(points)
    P = len(T_world_hand)
    out = np.zeros(P, dtype=bool)
    if P == 0 or len(pts) == 0:
        return out
    kd = cKDTree(pts) if kd is None else kd
    parts: list[tuple[np.ndarray, tuple[np.ndarray, np.ndarray]]] = []  # (hands, their cells)
    for every in _by_preshape(q):  # loop over the distinct preshapes (a few)
        cell = _preshape_cells(hand, q[every[0]], margin, cells)
        parts += [(every[s : s + HAND_BATCH], cell) for s in range(0, len(every), HAND_BATCH)]
    # consecutive parts in batches of at most HAND_BATCH hands (the pinches adapt their
    # preshape to the part: many preshapes of a few hands each, tested together)
    batch: list[tuple[np.ndarray, tuple[np.ndarray, np.ndarray]]] = []
    n = 0
    for k, (sel, cell) in enumerate(parts):  # loop over the parts
        batch.append((sel, cell))
        n += len(sel)
        if k + 1 == len(parts) or n + len(parts[k + 1][0]) > HAND_BATCH:
            idx = np.concatenate([b[0] for b in batch])
            out[idx] = _batch_hits([(T_world_hand[b[0]], b[1]) for b in batch], pts, kd)
            batch, n = [], 0
    return out


def _batch_hits(
    parts: list[tuple[np.ndarray, tuple[np.ndarray, np.ndarray]]], pts: np.ndarray, kd: cKDTree
) -> np.ndarray:
    """(G,) bool: :func:`hand_hits_points_numpy` for the hands of ``parts`` one after the
    other, each part ``(T_world_hand (G_p, 4, 4), the cells of their preshape)``. Every (hand,
    cell) row gets the operations it got when each preshape was tested on its own (the same
    einsums per part, then row by row): the same answers."""
    rows_c, rows_out, rows_in, rows_hand, rows_cell = [], [], [], [], []
    G = 0
    for T, (T_cell, half) in parts:  # loop over the parts (a few preshapes)
        centres = np.einsum("gij,cj->gci", T[:, :3, :3], T_cell[:, :3, 3])
        centres += T[:, None, :3, 3]  # (G_p, C, 3) world cell centres
        g_p, c_p = len(T), len(T_cell)
        rows_c.append(centres.reshape(-1, 3))
        rows_out.append(np.tile(np.linalg.norm(half, axis=1), g_p))
        rows_in.append(np.tile(half.min(axis=1), g_p))
        rows_hand.append(np.repeat(np.arange(G, G + g_p), c_p))
        rows_cell.append(np.tile(np.arange(c_p), g_p))
        G += g_p
    centres, r_out, r_in = np.concatenate(rows_c), np.concatenate(rows_out), np.concatenate(rows_in)
    hand_of, cell_of = np.concatenate(rows_hand), np.concatenate(rows_cell)
    # one nearest-point query per row; the bound only prunes (a row's own radius decides it)
    d, _ = kd.query(centres, k=1, distance_upper_bound=float(r_out.max()))
    inner = d < r_in
    hit = np.zeros(G, dtype=bool)
    hit[hand_of[inner]] = True
    und = np.flatnonzero((d <= r_out) & ~inner & ~hit[hand_of])  # (U,) undecided rows
    if len(und) == 0:
        return hit
    # the cells' rotations only for the hands with an undecided cell: per part the same einsum
    # over those hands (same layout per hand), so each rotation has the bits of the full one
    R = np.empty((len(und), 3, 3))
    halves = np.empty((len(und), 3))
    start = 0
    for T, (T_cell, half) in parts:  # loop over the parts
        stop = start + len(T)
        mine = np.flatnonzero((hand_of[und] >= start) & (hand_of[und] < stop))
        if len(mine):
            g = hand_of[und[mine]] - start
            c = cell_of[und[mine]]
            ug, g_row = np.unique(g, return_inverse=True)
            Rp = np.einsum("gij,cjk->gcik", T[ug][:, :3, :3], T_cell[:, :3, :3])  # (H, C, 3, 3)
            R[mine] = Rp[g_row, c]
            halves[mine] = half[c]
        start = stop
    cu_c, cu_r, gu_all = centres[und], r_out[und], hand_of[und]
    n_in = kd.query_ball_point(cu_c, cu_r, return_length=True)  # (U,) points
    group = (np.cumsum(n_in) - n_in) // PAIR_BATCH  # (U,) batch of each cell, by its pairs
    for j in np.unique(group[n_in > 0]):  # loop over the batches of pairs (one when few)
        u = np.flatnonzero((group == j) & (n_in > 0))
        u = u[~hit[gu_all[u]]]  # hands hit by an earlier batch are done
        if len(u) == 0:
            continue
        lists = kd.query_ball_point(cu_c[u], cu_r[u], return_sorted=False)
        lens = np.fromiter((len(x) for x in lists), dtype=np.int64, count=len(u))
        ip = np.concatenate([np.asarray(x, dtype=np.int64) for x in lists if len(x)])
        k = u[np.repeat(np.arange(len(u)), lens)]  # (M,) undecided row of each pair
        local = np.einsum("mj,mjk->mk", pts[ip] - cu_c[k], R[k])
        # + CELL_SEAM: a point on the seam of two cells may miss both by round-off
        inside = np.all(np.abs(local) <= halves[k] + CELL_SEAM, axis=1)
        hit[np.unique(gu_all[k[inside]])] = True
    return hit
