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

import numpy as np

from ..limits import MAX_ASSUMED_CLEARANCE

__all__ = ["MAX_ASSUMED_CLEARANCE", "assumed_mask", "obstacle_points"]


def assumed_mask(assumed: np.ndarray | None, n_points: int) -> np.ndarray | None:
    """``assumed`` as an (N,) bool array checked against the cloud's ``n_points``, or None when
    it is None or flags no point."""
    if assumed is None:
        return None
    mask = np.asarray(assumed, dtype=bool)
    if mask.shape != (n_points,):
        raise ValueError(
            f"assumed must be a bool mask of shape ({n_points},), got shape {mask.shape}"
        )
    return mask if np.any(mask) else None


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
