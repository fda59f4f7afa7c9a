"""The open hand against the cloud and the support plane, for whole batches of hands.

:func:`hand_hits_points` (any cloud point inside a link's collision box) and
:func:`hand_min_height` (lowest link corner above the support plane) are the two tests of the
pool's filters; :func:`hand_corners` and :func:`link_cells` give the links' boxes they use.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial import cKDTree

from ..facemask import SupportPlane
from ..geometry import as_points, box_corners
from ..tolerances import GEOM_EPS

if TYPE_CHECKING:
    from ..hand import Hand

CELL_SEAM: float = 1e-12
"""Metres: cells of a link box are grown by this so that round-off at their shared seams
cannot let a point slip between two cells (:func:`hand_hits_points`)."""

CellCache = dict[tuple[bytes, float], tuple[np.ndarray, np.ndarray]]
""":func:`link_cells` per (preshape bytes, margin), shared by calls of :func:`hand_hits_points`."""


def hand_corners(hand: Hand, q: np.ndarray) -> np.ndarray:
    """(8 L, 3) corners of all the links' collision boxes at configuration ``q`` (J,), hand
    frame."""
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
    per value of ``grasp_type`` (P,) (negative: the hand reaches below the plane)."""
    out = np.zeros(len(T_world_hand))
    for gt in np.unique(grasp_type):  # loop over the (at most 4) preshapes
        sel = np.flatnonzero(grasp_type == gt)
        corners = hand_corners(hand, q[sel[0]])  # (C, 3) hand frame
        T = T_world_hand[sel]  # (m, 4, 4)
        up_hand = np.einsum("mji,j->mi", T[:, :3, :3], support.normal)  # (m, 3) up in hand frames
        h = corners @ up_hand.T + (T[:, :3, 3] @ support.normal)[None, :]  # (C, m) heights
        out[sel] = h.min(axis=0) - support.height
    return out


def link_cells(hand: Hand, q: np.ndarray, margin: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """The links' collision boxes at ``q`` (J,), grown by ``margin`` and cut into near-cubic
    cells (a box's side / its shortest side cells per axis, rounded up).

    Returns ``(T_hand_cell (C, 4, 4), half (C, 3))``: the cells tile the boxes exactly, so a point
    lies in a link box iff it lies in one of its cells."""
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


def hand_hits_points(
    hand: Hand,
    T_world_hand: np.ndarray,
    grasp_type: np.ndarray,
    q: np.ndarray,
    points: np.ndarray,
    kd: cKDTree | None = None,
    margin: float = 0.0,
    cells: CellCache | None = None,
) -> np.ndarray:
    """(P,) bool: the open hand at ``T_world_hand`` (P, 4, 4) with preshape ``q`` (P, J) holds
    at least one of ``points`` (N, 3) inside a link's collision box grown by ``margin``: the
    same answer as ``Hand.hands_hit_points`` (a test checks it), faster for a pool.

    Each link box is cut into near-cubic cells (:func:`link_cells`); one nearest-point query
    per cell decides most cells (no point within its circumscribed sphere: free; a point within
    its inscribed sphere: hit); the undecided cells get the exact point-in-box test on the points
    of their circumscribed sphere. Hands already hit skip their remaining cells. ``cells``: an
    optional dict caching :func:`link_cells` per preshape across calls."""
    pts = as_points(points)
    P = len(T_world_hand)
    out = np.zeros(P, dtype=bool)
    if P == 0 or len(pts) == 0:
        return out
    kd = cKDTree(pts) if kd is None else kd
    for gt in np.unique(grasp_type):  # loop over the (at most 4) preshapes
        sel = np.flatnonzero(grasp_type == gt)
        key = (q[sel[0]].tobytes(), float(margin))
        if cells is None or key not in cells:
            cell = link_cells(hand, q[sel[0]], margin)
            if cells is not None:
                cells[key] = cell
        else:
            cell = cells[key]
        T_cell, half = cell  # (C, 4, 4), (C, 3)
        r_out = np.linalg.norm(half, axis=1)  # (C,)
        r_in = half.min(axis=1)
        R = np.einsum("gij,cjk->gcik", T_world_hand[sel, :3, :3], T_cell[:, :3, :3])  # (G,C,3,3)
        centres = np.einsum("gij,cj->gci", T_world_hand[sel, :3, :3], T_cell[:, :3, 3])
        centres += T_world_hand[sel, None, :3, 3]  # (G, C, 3) world cell centres
        d, _ = kd.query(centres.reshape(-1, 3), k=1, distance_upper_bound=float(r_out.max()))
        d = d.reshape(len(sel), -1)  # (G, C); inf when nothing within the largest radius
        hit = np.any(d < r_in, axis=1)  # (G,)
        g, c = np.nonzero((d <= r_out) & ~(d < r_in) & ~hit[:, None])  # undecided cells
        if len(g):
            lists = kd.query_ball_point(centres[g, c], r_out[c], return_sorted=False)
            lens = np.fromiter((len(x) for x in lists), dtype=np.int64, count=len(g))
            if lens.sum():
                ip = np.concatenate([np.asarray(x, dtype=np.int64) for x in lists if len(x)])
                k = np.repeat(np.arange(len(g)), lens)  # (M,) undecided cell of each pair
                local = np.einsum("mj,mjk->mk", pts[ip] - centres[g[k], c[k]], R[g[k], c[k]])
                # + CELL_SEAM: a point on the seam of two cells may miss both by round-off
                inside = np.all(np.abs(local) <= half[c[k]] + CELL_SEAM, axis=1)
                hit[np.unique(g[k[inside]])] = True
        out[sel] = hit
    return out
