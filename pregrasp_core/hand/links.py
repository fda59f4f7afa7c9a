"""Points in the hand's links: exact point-in-box tests of one configuration, and counts per
link for thousands of hands at once, culled by a voxel occupancy grid of the hand (see
``docs/hand.md``, "Collision geometry and queries")."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geometry import as_points
from .kinematics import box_poses
from .model import HandModel


def _all3(b: np.ndarray) -> np.ndarray:
    """``np.all(b, axis=-1)`` for a last axis of 3, several times faster."""
    return b[..., 0] & b[..., 1] & b[..., 2]


_PAIR_CHUNK: int = 1_000_000
"""Batched point-in-link counts move at most this many (point, hand) pairs at once (memory)."""

_VOXEL: float = 0.004
"""Voxel size (metres) of the hand occupancy grid that culls points before exact box tests."""

_GRID_MAX_CONFIGS: int = 8
"""Batched counts build an occupancy grid per distinct configuration only up to this many
distinct configurations (a pre-grasp pool has one per grasp type); beyond it they cull by each
hand's bounding box."""


def points_in_links(
    model: HandModel, p_hand: np.ndarray, q: np.ndarray, margin: float = 0.0
) -> np.ndarray:
    """(N, L) bool: point n lies inside link l's collision box grown by ``margin`` on every
    side, for one configuration ``q`` (J,). Columns in ``link_names`` order."""
    p = as_points(p_hand, "p_hand")
    Tb = box_poses(model, model.one_q(q))  # (L, 4, 4)
    R = Tb[:, :3, :3]  # (L, 3, 3) box axes as columns
    L = R.shape[0]
    # box-frame coordinates of every point in every box with one matrix product:
    # local[n, l, k] = p[n] . R[l][:, k] - t[l] . R[l][:, k]
    Rcat = R.transpose(1, 0, 2).reshape(3, 3 * L)  # (3, 3L)
    off = np.einsum("lj,ljk->lk", Tb[:, :3, 3], R).reshape(3 * L)
    local = (p @ Rcat - off).reshape(-1, L, 3)  # (N, L, 3)
    return _all3(np.abs(local) <= model.link_box_half + margin)


def points_in_hand(
    model: HandModel, p_hand: np.ndarray, q: np.ndarray, margin: float = 0.0
) -> np.ndarray:
    """(N,) bool: point inside any link (grown by ``margin``) at configuration ``q`` (J,)."""
    return np.any(points_in_links(model, p_hand, q, margin), axis=1)


def link_point_counts(
    model: HandModel,
    points: np.ndarray,
    T_world_hand: np.ndarray,
    q: np.ndarray,
    margin: float = 0.0,
) -> np.ndarray:
    """(G, L) int64: how many of ``points`` (N, 3, world) lie in each link's box (grown by
    ``margin``) for G hands at poses ``T_world_hand`` (G, 4, 4) and configurations ``q``
    ((J,) shared by all hands, or (G, J)).

    Made for thousands of hands against a 20k-point cloud: the points are moved into the
    frames of a chunk of hands with one matrix product, tested against each hand's
    axis-aligned bounding box (hand frame, at its configuration), and only the points inside
    it get the exact tests against the link boxes, grouped by distinct configuration (a
    pool has one preshape per grasp type)."""
    pts = as_points(points, "points")
    T = np.asarray(T_world_hand, dtype=np.float64)
    if T.ndim != 3 or T.shape[1:] != (4, 4):
        raise ValueError(f"T_world_hand must have shape (G, 4, 4), got {T.shape}")
    G, L, N = T.shape[0], len(model.link_names), pts.shape[0]
    Q = np.asarray(q, dtype=np.float64)
    if Q.ndim == 1:
        Qb, _ = model.as_q(Q)
        inverse = np.zeros(G, dtype=np.int64)
    else:
        Qall, _ = model.as_q(Q)
        if Qall.shape[0] != G:
            raise ValueError(
                f"q must have shape ({model.n_joints},) or ({G}, {model.n_joints}), got {Q.shape}"
            )
        Qb, inverse = np.unique(Qall, axis=0, return_inverse=True)
        inverse = inverse.reshape(-1)
    counts = np.zeros((G, L), dtype=np.int64)
    if G == 0 or N == 0:
        return counts
    # per distinct configuration: box-frame transform as one (3, 3L) product
    Tb = box_poses(model, Qb)  # (U, L, 4, 4)
    Rb = Tb[:, :, :3, :3]
    Rcat = Rb.transpose(0, 2, 1, 3).reshape(-1, 3, 3 * L)  # (U, 3, 3L)
    off = np.einsum("ulj,uljk->ulk", Tb[:, :, :3, 3], Rb).reshape(-1, 3 * L)  # (U, 3L)
    half = model.link_box_half + margin  # (L, 3)
    if Qb.shape[0] <= _GRID_MAX_CONFIGS:
        grid = _OccupancyGrid.build(Rcat, off, half, Tb[:, :, :3, 3], Rb)
    else:  # many distinct configurations: cull by each hand's bounding box only
        reach = np.einsum("ulij,lj->uli", np.abs(Rb), half)  # (U, L, 3)
        box_lo = (Tb[:, :, :3, 3] - reach).min(axis=1)  # (U, 3) hand frame
        box_hi = (Tb[:, :, :3, 3] + reach).max(axis=1)
    R = T[:, :3, :3]
    t_off = np.einsum("gj,gjk->gk", T[:, :3, 3], R)  # (G, 3): R^T t
    chunk = max(1, _PAIR_CHUNK // max(N, 1))
    flat_counts = np.zeros(G * L, dtype=np.int64)
    for g0 in range(0, G, chunk):
        g1 = min(G, g0 + chunk)
        Rc = R[g0:g1].transpose(1, 0, 2).reshape(3, -1)  # (3, 3Gc)
        p_hand = (pts @ Rc).reshape(N, g1 - g0, 3) - t_off[g0:g1]  # (N, Gc, 3)
        if Qb.shape[0] <= _GRID_MAX_CONFIGS:
            code = grid.lookup(p_hand, inverse[g0:g1])  # (N, Gc) conservative cull
        else:
            uc = inverse[g0:g1]  # (Gc,) configuration of each hand of the chunk
            inb = (p_hand >= box_lo[uc]) & (p_hand <= box_hi[uc])  # (N, Gc, 3)
            code = np.where(_all3(inb), L, -1)  # test every link of the hand
        n_idx, g_idx = np.nonzero(code >= 0)
        if n_idx.size == 0:
            continue
        cand = p_hand[n_idx, g_idx]  # (P, 3) candidate points in their hand's frame
        g_abs = g_idx + g0
        # group the candidates by (configuration, link code) with one radix sort; each group
        # is one matrix product: a single link's box, or all L boxes (code L)
        key = (inverse[g_abs] * (L + 1) + code[n_idx, g_idx]).astype(np.int16)
        order = np.argsort(key, kind="stable")
        ks = key[order]
        cuts = np.flatnonzero(np.diff(ks)) + 1
        for seg in np.split(order, cuts):  # at most (L + 1) x distinct configurations
            u, lk = divmod(int(key[seg[0]]), L + 1)
            if lk < L:
                local = cand[seg] @ Rb[u, lk] - off[u, 3 * lk : 3 * lk + 3]  # (P_s, 3)
                inside = _all3(np.abs(local) <= half[lk])
                flat_counts += np.bincount(g_abs[seg[inside]] * L + lk, minlength=G * L)
            else:
                local = (cand[seg] @ Rcat[u] - off[u]).reshape(-1, L, 3)  # (P_s, L, 3)
                pi, li = np.nonzero(_all3(np.abs(local) <= half))
                flat_counts += np.bincount(g_abs[seg[pi]] * L + li, minlength=G * L)
    counts += flat_counts.reshape(G, L)
    return counts


def hands_hit_points(
    model: HandModel,
    points: np.ndarray,
    T_world_hand: np.ndarray,
    q: np.ndarray,
    margin: float = 0.0,
) -> np.ndarray:
    """(G,) bool: any of ``points`` (N, 3, world) inside any link of hand g (see
    :func:`link_point_counts`)."""
    return link_point_counts(model, points, T_world_hand, q, margin).sum(axis=1) > 0


@dataclass(frozen=True)
class _OccupancyGrid:
    """Voxels of the hand frame that may hold a point of a (grown) link box, per distinct
    configuration, with the link when only one can be there. Conservative: a voxel is marked
    for a box when its centre lies in the box grown by the voxel's circumradius, so every point
    inside a box falls in a voxel marked for that box."""

    lo: np.ndarray
    """(3,) corner of the grid, hand frame."""
    dims: np.ndarray
    """(3,) int64 number of voxels per axis."""
    link: np.ndarray
    """(U, C) int8 per voxel: -1 no link, l in [0, L) only link l, L several links."""

    @classmethod
    def build(
        cls,
        Rcat: np.ndarray,
        off: np.ndarray,
        half: np.ndarray,
        centers: np.ndarray,
        Rb: np.ndarray,
    ) -> _OccupancyGrid:
        """The grid of U configurations from their box-frame transforms (``Rcat`` (U, 3, 3L),
        ``off`` (U, 3L), as in :func:`link_point_counts`), the grown half sides ``half`` (L, 3)
        and the box centres (U, L, 3) and rotations ``Rb`` (U, L, 3, 3) in the hand frame."""
        h = _VOXEL
        reach = np.einsum("ulij,lj->uli", np.abs(Rb), half)  # (U, L, 3) AABB half sizes
        lo = (centers - reach).min(axis=(0, 1)) - 2.0 * h  # two empty voxels all round
        hi = (centers + reach).max(axis=(0, 1)) + 2.0 * h
        dims = np.ceil((hi - lo) / h).astype(np.int64)
        axes = [lo[k] + (np.arange(dims[k]) + 0.5) * h for k in range(3)]
        c = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)  # (C, 3)
        L = half.shape[0]
        grow = half + 0.5 * np.sqrt(3.0) * h
        link = np.empty((Rcat.shape[0], c.shape[0]), dtype=np.int8)
        for u in range(Rcat.shape[0]):  # distinct configurations (a handful)
            local = (c @ Rcat[u] - off[u]).reshape(-1, L, 3)
            hit = _all3(np.abs(local) <= grow)  # (C, L)
            n = hit.sum(axis=1)
            link[u] = np.where(n == 0, -1, np.where(n == 1, np.argmax(hit, axis=1), L))
        return cls(lo=lo, dims=dims, link=link)

    def lookup(self, p_hand: np.ndarray, u_of_hand: np.ndarray) -> np.ndarray:
        """(N, G) voxel link codes (see ``link``) for points (N, G, 3) in the frames of G hands
        with configuration ids ``u_of_hand`` (G,). Points outside the grid are clipped onto its
        border voxels, which are always empty (the grid has a margin of two voxels)."""
        x = (p_hand - self.lo) * (1.0 / _VOXEL)
        np.clip(x, 0.0, self.dims - 1.0, out=x)
        cell = x.astype(np.int32)  # (N, G, 3) voxel indices (truncation = floor here)
        d1, d2 = int(self.dims[1]), int(self.dims[2])
        flat = (cell[..., 0] * d1 + cell[..., 1]) * d2 + cell[..., 2]  # (N, G)
        flat += (u_of_hand * self.link.shape[1]).astype(np.int32)[None, :]
        return np.take(self.link.reshape(-1), flat)
