"""The slicing contact planner: pre-grasp -> approach -> per-finger slicing and closing -> 3D
verification -> contacts -> quality, with a trace for every pre-grasp (see ``docs/planner.md``).

For each pre-grasp of the pool (after arXiv 1907.09142):

1. **Approach.** The open hand moves along its approach (hand +z) until one of its collision
   boxes (palm, knuckles or a finger link, at the preshape) comes within
   ``PlannerParams.approach_clearance`` of a cloud point: an exact ray/slab computation for every
   (point, box) pair near the sweep. The support plane, when given, also stops the hand (its
   boxes stay ``approach_clearance`` above it). Nothing ahead within ``max_approach``: rejected.
2. **Slicing and closing.** For each finger the grasp type uses, the cloud points within half a
   finger width of the finger's flexion plane and within the finger's reach, in that plane's 2D
   frame and thinned to one per 0.7 mm cell, plus the support plane's trace, go to the hand's
   planar closing model (:meth:`pregrasp_core.hand.Hand.close_finger`, vectorised over points
   and closing steps), which returns the flexion angles and the touching links. When the table
   rather than the object stopped the approach and a finger closed on the table, the hand backs
   off along its approach in 5 mm steps (``max_lift``) and closes again.
3. **3D verification.** Fingers closed into each other (python-fcl) are opened back along their
   closing paths. Then, at the final pose and joint angles: every nearby cloud point's depth
   inside every link box (exact box distance); a finger that holds a point deeper than
   ``penetration_tol`` is opened back along its closing path until it holds none (corrected),
   else the pre-grasp is rejected; then python-fcl checks the links against each other
   (:meth:`Hand.self_collisions`) and against the support half-space.
4. **Contacts.** Every link with a cloud point within ``contact_distance`` of its box makes one
   contact: the nearest such cloud point, its normal (from :mod:`pregrasp_core.normals`,
   negated so that it points **into the object**), and the link. The first friction-cone edge
   is the link box's y axis (the finger's flexion-plane normal), fixed to the hand, so the
   scores do not depend on the world frame.
5. **Quality.** :func:`pregrasp_core.quality.grasp_quality` (Ferrari-Canny epsilon L1 and
   wrench-hull volume). Kept grasps are ranked by epsilon, then volume, then number of contacts.

Every pre-grasp yields one :class:`Grasp` (kept, with scores and rank, or rejected with a
reason from :data:`REJECTION_REASONS`), so the whole trace is in the result file.

Modules: ``types`` (parameters and results), ``cells`` (the spatial index), ``context`` (what
the pre-grasps of one plan share, the cloud as a hand pose sees it), ``boxes`` (exact
point-box geometry), ``approach`` (step 1), ``slicing`` (step 2), ``verify`` (steps 3 and 4),
``plan`` (the pool in chunks, threads, quality, ranking), ``serialize`` (the result file).
"""

from .boxes import box_signed_distance, sweep_hit
from .plan import LIFT_STEP, cloud_normals, plan_grasps, rank_grasps
from .serialize import grasp_to_dict, grasps_sections
from .types import (
    APPROACH_STOPS,
    REJECTION_REASONS,
    Contact,
    FingerTrace,
    Grasp,
    GraspSet,
    PlannerParams,
)

__all__ = [
    "APPROACH_STOPS",
    "LIFT_STEP",
    "REJECTION_REASONS",
    "Contact",
    "FingerTrace",
    "Grasp",
    "GraspSet",
    "PlannerParams",
    "box_signed_distance",
    "cloud_normals",
    "grasp_to_dict",
    "grasps_sections",
    "plan_grasps",
    "rank_grasps",
    "sweep_hit",
]
