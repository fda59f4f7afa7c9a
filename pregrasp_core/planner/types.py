"""The planner's parameters and results: :class:`PlannerParams`, and per pre-grasp one
:class:`Grasp` (kept or rejected, with its :class:`FingerTrace` and :class:`Contact` records),
gathered with the ranking in a :class:`GraspSet`."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np

from ..limits import (
    MAX_CLOSING_STEPS,
    MAX_CONTACT_LENGTH,
    MAX_LENGTH,
    MAX_RETREAT,
    MAX_THREADS,
    check_int,
    check_real,
    moved_field,
)
from ..normals import NormalParams
from ..quality import QualityParams
from ..tolerances import CONTACT_DISTANCE, PENETRATION_TOL
from .assumed import MAX_ASSUMED_CLEARANCE

REJECTION_REASONS: dict[str, str] = {
    "nothing_ahead": "the hand meets no cloud point within max_approach along its approach",
    "no_contact": "after closing, no link is within contact_distance of the cloud",
    "penetration": "a link holds cloud points deeper than penetration_tol and opening its "
    "finger does not clear them (or the palm/knuckle does)",
    "self_collision": "two links of the closed hand intersect (python-fcl)",
    "support_collision": "a link of the closed hand goes below the support plane (python-fcl)",
}
"""Why a pre-grasp can be rejected (keys used in ``Grasp.rejection`` and the result file)."""

APPROACH_STOPS: tuple[str, ...] = ("object", "support", "start", "support_lifted", "limit")
"""What ended the approach: a cloud point, the support plane, already close at the start, the
support followed by a retreat so that the fingers close on the object (``max_lift``), or the
pre-grasp's own approach limit (``PreGraspPool.approach_limit``: pinches across thin parts)."""


@dataclass(frozen=True)
class PlannerParams:
    """Parameters of the slicing contact planner (lengths in metres)."""

    approach_clearance: float = 0.002
    """The approach stops when a hand box is this close to a cloud point (or the support)."""
    max_approach: float = 0.15
    """Farthest the hand travels along its approach from the pre-grasp pose."""
    max_lift: float = 0.04
    """When the support plane ended the approach and a finger closes on the table instead of the
    object, retreat along the approach in 5 mm steps up to this far and keep the pose where the
    most fingers touch the object (0: never)."""
    closing_margin: float = 0.001
    """A finger link touches a slice point when within this distance (planar closing model)."""
    closing_steps: int = 48
    """Samples per closing phase of the closing model (refined by bisection)."""
    slice_resolution: float = 0.0007
    """A slice keeps one point per square cell of this side in its plane (0: every point). A
    dropped point lies within the cell diagonal (side x sqrt(2) = 0.99 mm) of a kept one, so
    with the diagonal below ``closing_margin`` no link ever touches a dropped point either."""
    contact_distance: float = CONTACT_DISTANCE
    """A link makes a contact when a cloud point lies within this distance of its box."""
    penetration_tol: float = PENETRATION_TOL
    """Largest depth a cloud point may have inside a link of the final hand."""
    quality: QualityParams = field(default_factory=QualityParams)
    """Friction coefficient, cone edges and torque scale of the quality measure."""
    normals: NormalParams = field(default_factory=NormalParams)
    """Normal estimation (computed once per cloud)."""
    assumed_clearance: float = 0.002
    """The hand keeps this far from points a single view's completion assumed (moved out along
    their normals for the approach, the closing and the checks; contacts keep the assumed point
    itself): the copies lie within about 1.5 mm of the true surface either way, up to 2 mm at
    2 mm of sensor noise (``planner/assumed.py``)."""
    threads: int = 0
    """Parallel workers of the planner; 0 = one per CPU this process may use (at most 64), 1 =
    none. From a process running one thread, the chunks of pre-grasps are planned in forked
    copies of the process (``plan._plan_forked``); with other threads alive (the viewer), threads
    run the per-pre-grasp phases (approach and slicing, verification, quality). Only the speed
    depends on it, never a result."""

    def __post_init__(self) -> None:
        # bounds: pregrasp_core.limits and docs/limits.md ("Planner"); each field is named
        def length(name: str, hi: float, *, lo_open: bool = False) -> float:
            v = check_real(name, getattr(self, name), 0.0, hi, lo_open=lo_open, **_METRES)
            object.__setattr__(self, name, v)
            return v

        for name in ("approach_clearance", "penetration_tol"):
            length(name, MAX_CONTACT_LENGTH)
        margin = length("closing_margin", MAX_CONTACT_LENGTH)
        length("assumed_clearance", MAX_ASSUMED_CLEARANCE)
        length("max_approach", MAX_LENGTH, lo_open=True)
        length("max_lift", MAX_RETREAT)
        if length("contact_distance", MAX_CONTACT_LENGTH) < margin:
            if moved_field(self, "closing_margin", "contact_distance") == "contact_distance":
                raise ValueError(
                    f"contact_distance must be at least closing_margin ({margin:g} m) so that a "
                    f"finger stopped by a point touches it, got {self.contact_distance!r}"
                )
            raise ValueError(
                f"closing_margin must be at most contact_distance ({self.contact_distance:g} m) "
                f"so that a finger stopped by a point touches it, got {margin!r}"
            )
        if length("slice_resolution", MAX_CONTACT_LENGTH) * np.sqrt(2.0) > margin:
            if moved_field(self, "closing_margin", "slice_resolution") == "slice_resolution":
                raise ValueError(
                    f"slice_resolution must be at most closing_margin / sqrt(2) "
                    f"({margin / np.sqrt(2.0):.3g} m): a link could touch a dropped point, got "
                    f"{self.slice_resolution!r}"
                )
            raise ValueError(
                f"closing_margin must be at least slice_resolution x sqrt(2) "
                f"({self.slice_resolution * np.sqrt(2.0):.3g} m): a link could touch a dropped "
                f"point, got {margin!r}"
            )
        steps = check_int("closing_steps", self.closing_steps, 2, MAX_CLOSING_STEPS)
        object.__setattr__(self, "closing_steps", steps)
        object.__setattr__(self, "threads", check_int("threads", self.threads, 0, MAX_THREADS))
        for name, kind in (("quality", QualityParams), ("normals", NormalParams)):
            if not isinstance(getattr(self, name), kind):
                raise ValueError(
                    f"{name} must be a {kind.__name__}, got {type(getattr(self, name)).__name__}"
                )


_METRES = {"what": "a length", "unit": " m"}


@dataclass(frozen=True)
class Contact:
    """One hand-object contact of a planned grasp."""

    point: np.ndarray
    """(3,) float64, metres, world frame: the touched cloud point."""
    normal: np.ndarray
    """(3,) float64 unit, world: the surface normal pointing INTO the object (force direction)."""
    link: str
    """The touching hand link (e.g. ``f1_distal``, ``palm``)."""
    point_index: int
    """Index of the touched point in the cloud."""
    distance: float
    """Signed distance (metres) from the link's box to the point (< 0: inside by that much)."""
    tangent: np.ndarray
    """(3,) float64 unit, world: first friction-cone edge direction (the link box's y axis)."""
    assumed: bool = False
    """The touched point was assumed by a single view's completion (``planner/assumed.py``)."""
    crest: bool = False
    """The touched point's normal is the crest rule's (a cloud without normals: an edge, a rim,
    a notch), so :attr:`normal` is the mean of it and the link's push
    (:func:`~pregrasp_core.planner.verify.crest_contact_normals`)."""


@dataclass(frozen=True)
class FingerTrace:
    """What the closing model did with one finger."""

    finger: str
    """Finger name."""
    n_slice: int
    """Cloud points in the finger's slice."""
    q: np.ndarray
    """(2,) final flexion angles (radians) after any correction."""
    links_touched: tuple[str, ...]
    """Links the planar closing model stopped on cloud points (middle first, then distal)."""
    palm_stop: bool
    """A link reached the palm and stopped there."""
    support_stop: bool
    """A link reached the support plane and stopped there."""
    at_limits: bool
    """The finger closed to its limits without touching anything."""
    corrected: bool
    """The finger was opened back along its path to clear a 3D penetration."""


@dataclass(frozen=True)
class Grasp:
    """The planner's outcome for one pre-grasp: a scored grasp or a rejection, with its trace."""

    pregrasp: int
    """Index of the pre-grasp in the pool."""
    grasp_type: str
    """The pre-grasp's grasp type."""
    T_world_hand: np.ndarray
    """(4, 4) float64: the hand pose at the end of the approach (pose of the grasp)."""
    approach_distance: float
    """Metres travelled along the approach from the pre-grasp pose (negative when the hand
    backed off from the table, ``approach_stop == "support_lifted"``)."""
    approach_stop: str
    """What ended the approach (:data:`APPROACH_STOPS`; '' when nothing did)."""
    q: np.ndarray
    """(J,) float64, radians: final joint positions (``Hand.joint_names`` order)."""
    fingers: tuple[FingerTrace, ...]
    """Per closed finger, what the closing model did."""
    contacts: tuple[Contact, ...]
    """The contacts (empty for most rejections)."""
    epsilon: float
    """Ferrari-Canny epsilon L1 (0: not force closure or rejected)."""
    volume: float
    """Wrench-hull volume (0 when degenerate or rejected)."""
    rank: int | None
    """0 = best among the kept grasps; None when rejected."""
    rejection: str | None
    """None when kept, else a key of :data:`REJECTION_REASONS`."""
    detail: str = ""
    """Human-readable detail of the rejection or of the quality ('' if nothing to say)."""
    epsilon_exact: bool = True
    """False when ``epsilon`` is an upper bound of the exact value (a grasp that cannot reach
    the best ``QualityParams.exact_top``; docs/quality.md). Force closure (epsilon > 0) is
    always exact."""
    volume_exact: bool = True
    """False when ``volume`` is an upper bound of the exact value."""
    quality_bound: str = ""
    """'' when both scores are exact, else the bound that gave them
    (:data:`pregrasp_core.quality.QUALITY_BOUNDS`)."""

    @classmethod
    def from_rejection(
        cls,
        pregrasp: int,
        grasp_type: str,
        T_world_hand: np.ndarray,
        q: np.ndarray,
        rejection: str,
        detail: str,
        approach_distance: float = 0.0,
        approach_stop: str = "",
        fingers: tuple[FingerTrace, ...] = (),
    ) -> Grasp:
        """A rejected pre-grasp (``rejection``: a key of :data:`REJECTION_REASONS`): no
        contacts, no scores, no rank."""
        return cls(
            pregrasp, grasp_type, T_world_hand, approach_distance, approach_stop, q,
            tuple(fingers), (), 0.0, 0.0, None, rejection, detail,
        )  # fmt: skip

    @property
    def n_contacts(self) -> int:
        """Number of contacts."""
        return len(self.contacts)

    @property
    def kept(self) -> bool:
        """True when the grasp was not rejected."""
        return self.rejection is None


@dataclass(frozen=True)
class GraspSet:
    """Every pre-grasp's outcome, in pool order, and the ranking of the kept ones."""

    grasps: tuple[Grasp, ...]
    """One per pre-grasp of the pool (``grasps[i].pregrasp == i``)."""
    ranking: np.ndarray
    """(K,) int64: indices into ``grasps`` of the kept grasps, best first."""
    joint_names: tuple[str, ...]
    """Names of the joints of ``Grasp.q``."""
    rejected: dict[str, int]
    """Number of rejected pre-grasps per reason (every key of :data:`REJECTION_REASONS`)."""
    phase_seconds: dict[str, float] = field(default_factory=dict)
    """Wall time per planner phase over the whole pool: ``approach_slicing``, ``closing``,
    ``verification`` (retreat from the support, 3D checks, contacts) and ``quality``."""

    def __len__(self) -> int:
        return len(self.grasps)

    def __iter__(self) -> Iterator[Grasp]:
        return iter(self.grasps)

    def __getitem__(self, i: int) -> Grasp:
        return self.grasps[i]

    @property
    def ranked(self) -> list[Grasp]:
        """The kept grasps, best first."""
        return [self.grasps[i] for i in self.ranking]

    @property
    def best(self) -> int | None:
        """Index into ``grasps`` of the best force-closure grasp (the first of the ranking, when
        its epsilon is > 0), or None when no grasp is force closure (see :attr:`best_reason`)."""
        if len(self.ranking) and self.grasps[int(self.ranking[0])].epsilon > 0.0:
            return int(self.ranking[0])
        return None

    @property
    def best_reason(self) -> str:
        """Why :attr:`best` is what it is, in one sentence for a user: the best grasp's epsilon,
        or why there is no force-closure grasp (empty pool, every pre-grasp rejected, or the
        kept grasps all score epsilon 0 and how many of them have fewer than 3 contacts)."""
        best = self.best
        if best is not None:
            g = self.grasps[best]
            return (
                f"force closure: the best of {self.n_force_closure} force-closure grasps has "
                f"epsilon {g.epsilon:.4f} with {g.n_contacts} contacts"
            )
        if len(self.grasps) == 0:
            return "no force-closure grasp: the pre-grasp pool is empty"
        if len(self.ranking) == 0:
            why = ", ".join(f"{k} {v}" for k, v in self.rejected.items() if v)
            return f"no force-closure grasp: every pre-grasp was rejected ({why})"
        kept = self.ranked
        few = sum(g.n_contacts < 3 for g in kept)
        return (
            f"no force-closure grasp: all {len(kept)} kept grasps have epsilon 0 "
            f"({few} with fewer than 3 contacts)"
        )

    def top(self, k: int) -> list[Grasp]:
        """The ``k`` best kept grasps."""
        return [self.grasps[i] for i in self.ranking[: max(int(k), 0)]]

    @property
    def n_force_closure(self) -> int:
        """Number of kept grasps with epsilon > 0."""
        return int(sum(g.epsilon > 0.0 for g in self.grasps))
