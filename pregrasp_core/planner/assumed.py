"""How the planner treats the points a single view's completion assumed (``docs/partial-views.md``).

The completion (``pregrasp_core.sensor.complete_view``) copies the visible points by a symmetry
to stand for the unseen back and closes the holes between far-apart points with midpoints;
those points are guesses. Measured against the true meshes of the generated views, the copies
lay 1-3 mm inside the true surface (median per view) until session 6, when the completion took
the smallest object the view allowed; since it takes the copy the view's evidence fits best
(``docs/partial-views.md``, session 7) the median per view is within about 1.5 mm either way
without noise, and scatters by about 2 mm either way at 2 mm of noise. A hand closed on them
sits inside the true object by as much when they lie inside.

So the planner keeps its hand ``PlannerParams.assumed_clearance`` away from assumed points: for
the approach, the closing and the 3D checks each assumed point is moved that far outward along
its normal (:func:`obstacle_points`), while a contact on it keeps the assumed point itself (its
position and normal: the best guess of the surface) and is flagged ``Contact.assumed``. Visible
points are used as they are. Grasps are ranked as before (by quality): on the generated views no
force-closure grasp among the 20 best of any view had all its contacts on visible points (a
wrapping grasp of a single view needs the back), and preferring grasps with fewer assumed
contacts changed the true-mesh figures by one or two views either way (measured, see the page).
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial import cKDTree

from ..limits import MAX_ASSUMED_CLEARANCE
from .boxes import box_signed_distance

if TYPE_CHECKING:
    from ..hand import Hand
    from .types import GraspSet, PlannerParams

__all__ = ["MAX_ASSUMED_CLEARANCE", "obstacle_points", "point_mask", "without_occupied"]


def point_mask(mask: np.ndarray | None, n_points: int, name: str = "assumed") -> np.ndarray | None:
    """``mask`` (the points a view's completion assumed, or those of another per-point flag
    called ``name``) as an (N,) bool array checked against the cloud's ``n_points``, or None
    when it is None or flags no point."""
    if mask is None:
        return None
    out = np.asarray(mask, dtype=bool)
    if out.shape != (n_points,):
        raise ValueError(
            f"{name} must be a bool mask of shape ({n_points},), got shape {out.shape}"
        )
    return out if np.any(out) else None


def obstacle_points(
    points: np.ndarray, normals: np.ndarray, assumed: np.ndarray | None, clearance: float
) -> np.ndarray:
    """(N, 3) the cloud as the hand must clear it: ``points`` (N, 3) with the ``assumed`` (N,)
    ones moved ``clearance`` metres along their outward unit ``normals`` (N, 3); ``points``
    itself when nothing is assumed or the clearance is 0."""
    if assumed is None or clearance <= 0.0:
        return points
    out = points.copy()
    out[assumed] += clearance * normals[assumed]
    return out


def without_occupied(
    gs: GraspSet,
    points: np.ndarray,
    normals: np.ndarray,
    assumed: np.ndarray | None,
    hand: Hand,
    params: PlannerParams,
    n_pool: int,
    crest: np.ndarray | None = None,
) -> GraspSet:
    """``gs``, planned on the cloud ``points`` (N, 3) followed by obstacle points (a single
    view's hidden space, ``sensor/occluded.py``), with contacts only on the cloud's points: a
    link whose contact is an obstacle point (index >= N) takes the cloud point nearest its box
    within ``contact_distance`` instead (as the planner picks contacts; none: the contact is
    dropped); a grasp left without contacts is rejected as ``no_contact``; every kept grasp is
    rescored (torques about the cloud's own frame, not the obstacles') and ranked again.
    ``crest``: (N,) bool or None, the cloud's crest-rule points (as :func:`plan_grasps` takes
    them)."""
    from .plan import rank_grasps
    from .rank import first_level, quality_frame, score_grasp, settle_exact
    from .types import Contact, Grasp, GraspSet
    from .verify import crest_contact_normals

    n = len(points)
    am = point_mask(assumed, n)
    geom = obstacle_points(points, normals, am, params.assumed_clearance)
    tree = cKDTree(geom)
    half = np.asarray(hand.link_box_half, dtype=np.float64)
    names = tuple(hand.link_names)
    reach = float(np.max(np.linalg.norm(half, axis=1))) + params.contact_distance
    frame = quality_frame(params.quality, points)
    level = first_level(params.quality, n_pool)
    out: list[Grasp] = []
    for g in gs.grasps:  # loop over the pool's grasps
        if not g.kept:
            out.append(g)
            continue
        contacts = list(g.contacts)
        if any(c.point_index >= n for c in contacts):
            Tb = g.T_world_hand @ hand.box_poses(g.q)  # (L, 4, 4) link boxes, world
            kept = []
            for c in contacts:  # loop over <= L contacts
                if c.point_index < n:
                    kept.append(c)
                    continue
                j = names.index(c.link)
                near = np.asarray(tree.query_ball_point(Tb[j, :3, 3], reach), dtype=np.int64)
                if not len(near):
                    continue
                d = box_signed_distance(geom[near], Tb[j][None], half[j][None])[:, 0]
                k = int(np.argmin(d))
                if d[k] > params.contact_distance:
                    continue
                p = int(near[k])
                n_in = -normals[p]
                at_crest = crest is not None and bool(crest[p])
                if at_crest:
                    n_in = crest_contact_normals(n_in[None], points[p][None], Tb[j][None],
                                                 half[j][None])[0]  # fmt: skip
                kept.append(Contact(
                    points[p].copy(), n_in, c.link, p, float(d[k]), Tb[j, :3, 1].copy(),
                    bool(am[p]) if am is not None else False, at_crest,
                ))  # fmt: skip
            if not kept:
                out.append(Grasp.from_rejection(
                    g.pregrasp, g.grasp_type, g.T_world_hand, g.q, "no_contact",
                    "every contact on the occupied (unseen) space", g.approach_distance,
                    g.approach_stop, g.fingers,
                ))  # fmt: skip
                continue
            g = dataclasses.replace(g, contacts=tuple(kept))
        out.append(score_grasp(params.quality, frame, level, g))
    out, _ = settle_exact(out, params.quality, frame)
    order = rank_grasps(out)
    for r, k in enumerate(order.tolist()):
        out[k] = dataclasses.replace(out[k], rank=r)
    rejected = {key: 0 for key in gs.rejected}
    for g in out:
        if g.rejection is not None:
            rejected[g.rejection] = rejected.get(g.rejection, 0) + 1
    return GraspSet(tuple(out), order, gs.joint_names, rejected, dict(gs.phase_seconds))
