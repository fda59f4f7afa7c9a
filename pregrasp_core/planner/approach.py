"""Step 1 for one pre-grasp: the open hand's approach along its +z axis until a link box comes
within ``approach_clearance`` of the cloud or of the support plane, then the finger slices at
the pose where it stopped (:func:`prepare`)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from ..tolerances import GEOM_EPS
from .context import Context, View
from .kernels import kernels
from .slicing import Slice, finger_slices
from .types import Grasp

if TYPE_CHECKING:
    from ..pregrasps import PreGraspPool

APPROACH_WINDOW: float = 0.03
"""First approach window (metres): pairs are first gathered for this much travel only."""


def _approach(
    ctx: Context, T0: np.ndarray, q: np.ndarray, cm: np.ndarray, cp: np.ndarray
) -> tuple[float, str]:
    """Travel along hand +z until a box is ``approach_clearance`` from the cloud/support.

    ``cm``, ``cp`` (C, 3): the bounds of the cloud's cells' balls in the frame of the hand at
    the pre-grasp pose (``kernels.cells_in_frame``). The
    candidate (point, link) pairs are the points in each link's swept window: the hand-frame
    AABB of its box grown by the clearance and stretched ahead by the travel window. The cells
    whose balls meet a window give the candidates; the exact window test and the exact slab
    sweep run on those only."""
    prm = ctx.params
    c = prm.approach_clearance
    S = prm.max_approach
    Tb, lo, hi = ctx.boxes(q)
    s_sup = np.inf
    if ctx.support is not None:
        n = np.asarray(ctx.support.normal, dtype=np.float64)
        corners = ctx.corners(q) @ T0[:3, :3].T + T0[:3, 3]  # (8L, 3) world
        heights = corners @ n - (ctx.support.height + c)
        rate = float(n @ T0[:3, 2])  # height change per metre of approach
        s_sup = max(float(heights.min()), 0.0) / -rate if rate < -GEOM_EPS else np.inf
    s_obj = np.inf
    S_eff = min(S, s_sup)  # the hand cannot travel past the support plane
    wlo, whi = lo - c, hi + c  # (L, 3) each link's window across the approach
    # two passes: a short first window (most approaches end within a few centimetres); a hit
    # beyond it may hide an earlier one by a point it did not gather, so then the full window
    cells, half = ctx.cells, ctx.half + c
    for window in (min(APPROACH_WINDOW, S_eff), S_eff):
        top = whi[:, 2] + window
        s_obj = kernels().approach(
            ctx.xyz, cells.order, cells.start, cells.count, cm, cp, T0, wlo, whi, top, Tb, half
        )  # the cells' balls that meet a link's window, then the exact window test and sweep
        if s_obj <= window or window >= S_eff:
            break
    s = min(s_obj, s_sup)
    if not np.isfinite(s) or s > S:
        return np.inf, ""
    if s <= 0.0:
        return 0.0, "start"
    return float(s), "object" if s_obj <= s_sup else "support"


@dataclass
class Prepared:
    """A pre-grasp after its approach, with its finger slices (see :func:`prepare`)."""

    i: int
    """Index of the pre-grasp in the pool."""
    gt: str
    """Its grasp type."""
    T0: np.ndarray
    """(4, 4) the pre-grasp pose (T_world_hand)."""
    q0: np.ndarray
    """(J,) its preshape joints."""
    spread: float
    """Its finger spread (radians)."""
    T: np.ndarray
    """(4, 4) the hand pose after the approach."""
    s: float
    """Metres travelled along the approach."""
    stop: str
    """What ended the approach (:data:`~pregrasp_core.planner.types.APPROACH_STOPS`)."""
    view: View
    """The cloud in the frame of ``T``."""
    slices: list[Slice]
    """One slice per finger of the grasp type, at ``T``."""


def prepare(ctx: Context, pool: PreGraspPool, i: int) -> Prepared | Grasp:
    """Approach and slicing of pre-grasp ``i``; a rejected ``Grasp`` when nothing is ahead."""
    prm = ctx.params
    gt = str(pool.grasp_type[i])
    T0 = np.asarray(pool.T_world_hand[i], dtype=np.float64)
    q0 = np.asarray(pool.q[i], dtype=np.float64)
    spread = float(pool.spread[i])

    # 1. approach, with the cloud (its cells) in the frame of the hand at the pre-grasp pose
    # (the cell centres as geometry.to_frame gives them, and their balls' bounds)
    c0, cm, cp = kernels().cells_in_frame(ctx.cells.centre, ctx.cells.radius, T0)  # (C, 3)
    s, stop = _approach(ctx, T0, q0, cm, cp)
    limit = float(pool.approach_limit[i]) if pool.approach_limit is not None else np.inf
    if s > limit:  # a pinch across a thin part: the fingertips stay on it
        s, stop = max(limit, 0.0), "limit"
    if not np.isfinite(s):
        detail = f"no cloud point within {prm.max_approach:.3f} m ahead"
        return Grasp.from_rejection(i, gt, T0, q0, "nothing_ahead", detail)
    T = T0.copy()
    T[:3, 3] += s * T0[:3, 2]
    # the cloud points the hand can reach after the approach (a box about the hand, r on every
    # side; below the palm also from up to max_lift higher up), in the frame of the hand
    # there: every point a link can touch or hold, for the slices and the 3D checks (r = the
    # hand's reach + the largest contact or penetration distance)
    r = ctx.reach + max(prm.contact_distance, prm.penetration_tol)
    lift = prm.max_lift if ctx.support is not None else 0.0
    view = View(T0, c0, r, max(-r, s - r - lift), r + s, (-s,))
    # 2. the slices (closed for many pre-grasps at once by the caller)
    slices = finger_slices(ctx, T, view, q0, gt, spread)
    return Prepared(i, gt, T0, q0, spread, T, s, stop, view, slices)
