"""The slicing contact planner: pre-grasp -> approach -> per-finger slicing and closing -> 3D
verification -> contacts -> quality, with a trace for every pre-grasp (see ``docs/planner.md``).

For each pre-grasp of the pool (DESIGN section 8, after arXiv 1907.09142):

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
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import os
import threading
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any

import fcl
import numpy as np

from .geometry import box_corners
from .normals import NormalParams, estimate_normals
from .quality import GraspQuality, QualityParams, grasp_quality
from .tolerances import CONTACT_DISTANCE, GEOM_EPS, PENETRATION_TOL

logger = logging.getLogger(__name__)

REJECTION_REASONS: dict[str, str] = {
    "nothing_ahead": "the hand meets no cloud point within max_approach along its approach",
    "no_contact": "after closing, no link is within contact_distance of the cloud",
    "penetration": "a link holds cloud points deeper than penetration_tol and opening its "
    "finger does not clear them (or the palm/knuckle does)",
    "self_collision": "two links of the closed hand intersect (python-fcl)",
    "support_collision": "a link of the closed hand goes below the support plane (python-fcl)",
}
"""Why a pre-grasp can be rejected (keys used in ``Grasp.rejection`` and the result file)."""

APPROACH_WINDOW: float = 0.03
"""First approach window (metres): pairs are first gathered for this much travel only."""

APPROACH_STOPS: tuple[str, ...] = ("object", "support", "start", "support_lifted")
"""What ended the approach: a cloud point, the support plane, already close at the start, or
the support followed by a retreat so that the fingers close on the object (``max_lift``)."""

LIFT_STEP: float = 0.005
"""Retreat step (metres) when the support plane stops the fingers (see ``max_lift``)."""

_CHUNK: int = 64
"""Pre-grasps whose fingers are closed together in one call of the batched closing model."""

CELL_SIZE: float = 0.01
"""Side (metres) of the cubic cells that group the cloud for the planner's candidate searches
(see :class:`_Cells`). Only the speed depends on it, never a result."""

CELL_MARGIN: float = 1e-9
"""Added to every cell's bounding-ball radius (metres): far above the rounding of a frame
change, so that a cell test never drops a point the exact test would keep."""

CONTACT_TIE: float = 1e-12
"""Metres: cloud points this close to a link's least distance tie for its contact."""


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
    threads: int = 0
    """Threads for the per-pre-grasp phases (approach and slicing, verification, quality: numpy,
    and qhull release Python's global lock for most of their work); 0 = one per
    CPU this process may use (at most 64), 1 = none. Only the speed depends on it, never a
    result."""

    def __post_init__(self) -> None:
        if int(self.threads) != self.threads or self.threads < 0:
            raise ValueError(f"threads must be an integer >= 0, got {self.threads}")
        for name in ("approach_clearance", "closing_margin", "penetration_tol"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v >= 0.0):
                raise ValueError(f"{name} must be a finite length >= 0, got {v}")
        if not self.max_approach > 0.0:
            raise ValueError(f"max_approach must be > 0, got {self.max_approach}")
        if not self.contact_distance >= self.closing_margin:
            raise ValueError(
                f"contact_distance ({self.contact_distance}) must be >= closing_margin "
                f"({self.closing_margin}) so that a finger stopped by a point touches it"
            )
        if not (np.isfinite(self.slice_resolution) and self.slice_resolution >= 0.0):
            raise ValueError(f"slice_resolution must be >= 0, got {self.slice_resolution}")
        if self.slice_resolution * np.sqrt(2.0) > self.closing_margin:
            raise ValueError(
                f"slice_resolution ({self.slice_resolution}) times sqrt(2) must not exceed "
                f"closing_margin ({self.closing_margin}): a link could touch a dropped point"
            )
        if int(self.closing_steps) != self.closing_steps or self.closing_steps < 2:
            raise ValueError(f"closing_steps must be an integer >= 2, got {self.closing_steps}")


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

    def __iter__(self):
        return iter(self.grasps)

    def __getitem__(self, i: int) -> Grasp:
        return self.grasps[i]

    @property
    def ranked(self) -> list[Grasp]:
        """The kept grasps, best first."""
        return [self.grasps[i] for i in self.ranking]

    @property
    def best(self) -> int | None:
        """Index into ``grasps`` of the best grasp, or None when every pre-grasp was rejected."""
        return int(self.ranking[0]) if len(self.ranking) else None

    def top(self, k: int) -> list[Grasp]:
        """The ``k`` best kept grasps."""
        return [self.grasps[i] for i in self.ranking[: max(int(k), 0)]]

    @property
    def n_force_closure(self) -> int:
        """Number of kept grasps with epsilon > 0."""
        return int(sum(g.epsilon > 0.0 for g in self.grasps))


# ------------------------------------------------------------------------------ geometry


def _to_frame(p: np.ndarray, T: np.ndarray) -> np.ndarray:
    """(M, 3) points ``p`` in the frame of the pose ``T`` (4, 4): ``(p - t) R``, element by element
    (not a BLAS product), so that a row's result never depends on the other rows."""
    d = p - T[:3, 3]
    R = T[:3, :3]
    return d[:, 0:1] * R[0] + d[:, 1:2] * R[1] + d[:, 2:3] * R[2]


def _to_frame_t(xyz: np.ndarray, T: np.ndarray) -> np.ndarray:
    """:func:`_to_frame` for points stored by coordinate: ``xyz`` (3, M) -> (3, M), with the
    same operations in the same order (so the same numbers), on contiguous rows."""
    R = T[:3, :3]
    d0, d1, d2 = xyz[0] - T[0, 3], xyz[1] - T[1, 3], xyz[2] - T[2, 3]
    out = np.empty_like(d0, shape=(3, len(d0)))
    for j in range(3):  # the three output coordinates
        out[j] = d0 * R[0, j] + d1 * R[1, j] + d2 * R[2, j]
    return out


def box_signed_distance(p: np.ndarray, T_boxes: np.ndarray, half: np.ndarray) -> np.ndarray:
    """(M, L) exact signed distance from points ``p`` (M, 3) to boxes with poses ``T_boxes``
    (L, 4, 4) (same frame as ``p``) and half extents ``half`` (L, 3); negative inside (minus the
    depth to the nearest face)."""
    R = T_boxes[:, :3, :3]  # (L, 3, 3)
    L = R.shape[0]
    local = (p @ R.transpose(1, 0, 2).reshape(3, 3 * L)).reshape(-1, L, 3)
    local -= np.einsum("li,lij->lj", T_boxes[:, :3, 3], R)[None]
    q = np.abs(local) - half[None]  # (M, L, 3)
    outside = np.linalg.norm(np.maximum(q, 0.0), axis=2)
    inside = np.minimum(q.max(axis=2), 0.0)
    return outside + inside


def sweep_hit(
    p: np.ndarray, T_boxes: np.ndarray, half: np.ndarray, direction: np.ndarray
) -> tuple[float, int]:
    """First travel ``s >= 0`` at which boxes moving by ``s * direction`` touch a point.

    p: (M, 3) points, T_boxes: (L, 4, 4) box poses, half: (L, 3) half extents (already grown by
    any clearance), direction: (3,) unit, all in one frame. Returns ``(s, box index)``, or
    ``(inf, -1)`` when no point is ever touched. Exact slab intersection per (point, box).
    """
    p = np.asarray(p, dtype=np.float64)
    T = np.asarray(T_boxes, dtype=np.float64)
    if len(p) == 0 or len(T) == 0:
        return np.inf, -1
    # rotate everything so that the motion is along +z, then test every (point, box) pair
    z = np.asarray(direction, dtype=np.float64) / np.linalg.norm(direction)
    helper = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    F = np.stack([x, np.cross(z, x), z])  # rows: the new frame's axes
    Tz = T.copy()
    Tz[:, :3, :3] = F @ T[:, :3, :3]
    Tz[:, :3, 3] = T[:, :3, 3] @ F.T
    ip, il = np.divmod(np.arange(len(p) * len(T)), len(T))
    pz = p @ F.T  # (M, 3) in the frame whose z is the motion
    hw = np.asarray(half, dtype=np.float64)
    s, k = _sweep_pairs(pz[ip, 0], pz[ip, 1], pz[ip, 2], il, Tz, hw)
    return (s, int(il[k])) if np.isfinite(s) else (np.inf, -1)


def _sweep_pairs(
    px: np.ndarray, py: np.ndarray, pz: np.ndarray, il: np.ndarray, T: np.ndarray, half: np.ndarray
) -> tuple[float, int]:
    """First travel along +z (the frame's z axis) at which box ``il[k]`` (pose ``T[il[k]]``,
    half extents ``half[il[k]]``; T (L, 4, 4), half (L, 3)) touches point k (coordinates ``px,
    py, pz`` (K,)), minimised over the K pairs: ``(s, k)``, or ``(inf, -1)`` if never. Exact
    slab intersection in each box's frame, one axis at a time."""
    R, t = T[:, :3, :3], T[:, :3, 3]
    v0, v1, v2 = px - t[il, 0], py - t[il, 1], pz - t[il, 2]
    s_in = np.full(len(il), -np.inf)
    s_out = np.full(len(il), np.inf)
    for j in range(3):  # the box's three axes
        a = v0 * R[il, 0, j] + v1 * R[il, 1, j] + v2 * R[il, 2, j]  # box coordinate j
        d = R[il, 2, j]  # the motion (+z) in box coordinate j
        h = half[il, j]
        small = np.abs(d) < 1e-12
        d_safe = np.where(small, 1.0, d)
        t1 = (a - h) / d_safe
        t2 = (a + h) / d_safe
        inside = np.abs(a) <= h
        s_in = np.maximum(
            s_in, np.where(small, np.where(inside, -np.inf, np.inf), np.minimum(t1, t2))
        )
        s_out = np.minimum(
            s_out, np.where(small, np.where(inside, np.inf, -np.inf), np.maximum(t1, t2))
        )
    hit = (s_in <= s_out) & (s_out >= 0.0)
    if not hit.any():
        return np.inf, -1
    s = np.where(hit, np.maximum(s_in, 0.0), np.inf)
    k = int(np.argmin(s))
    return float(s[k]), k


# ------------------------------------------------------------------------------ planner


class _Cells:
    """The cloud grouped into cubic cells for candidate searches. A search tests every cell's
    bounding ball (a few thousand cells instead of tens of thousands of points) and expands the
    cells that pass into their points: a superset of what it looks for, on which the exact test
    then runs. So the cells change only the speed, never which points pass."""

    def __init__(self, points: np.ndarray, size: float) -> None:
        n = len(points)
        key = np.floor(points / size).astype(np.int64)
        cell = np.unique(key, axis=0, return_inverse=True)[1].ravel() if n else np.zeros(0, int)
        self.order = np.argsort(cell, kind="stable")
        """(N,) cloud indices grouped by cell, ascending within a cell."""
        sc = cell[self.order]
        self.start = np.flatnonzero(np.r_[True, sc[1:] != sc[:-1]]) if n else np.zeros(0, int)
        """(C,) where each cell's points begin in ``order``."""
        self.count = np.diff(np.r_[self.start, n])
        """(C,) points per cell."""
        if n:
            ps = points[self.order]
            lo = np.minimum.reduceat(ps, self.start, axis=0)
            hi = np.maximum.reduceat(ps, self.start, axis=0)
            self.centre = 0.5 * (lo + hi)
            """(C, 3) cell ball centres, world."""
            d = np.linalg.norm(ps - np.repeat(self.centre, self.count, axis=0), axis=1)
            self.radius = np.maximum.reduceat(d, self.start) + CELL_MARGIN
            """(C,) radii of balls about ``centre`` that hold every point of the cell."""
        else:
            self.centre, self.radius = np.zeros((0, 3)), np.zeros(0)

    def points_of(self, cells: np.ndarray) -> np.ndarray:
        """The cloud indices of the points of ``cells`` (distinct cells), ascending."""
        seen = np.zeros(len(self.order), dtype=bool)
        seen[self.expand(cells)[0]] = True
        return np.flatnonzero(seen)

    def expand(self, cells: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The cloud indices (K,) of the points of ``cells`` (a list that may repeat cells) and,
        for each point, its row in ``cells``."""
        n = self.count[cells]
        k = np.repeat(np.arange(len(cells)), n)
        first = np.cumsum(n) - n
        return self.order[np.arange(len(k)) - first[k] + self.start[cells][k]], k


@dataclass(frozen=True)
class _View:
    """The cloud as the hand sees it: in the frame of the pre-grasp pose ``T0``, then moved
    along the approach by the shifts ``dz`` (hand z), added one after the other as the planner
    moved the hand (so that every coordinate is rounded exactly as when the planner worked on
    one array of all the points). Only the points in the keep box (``T0`` frame: ``|x|, |y| <=
    r``, ``z_lo <= z <= z_hi``) are ever seen: every point a link can touch or hold."""

    T0: np.ndarray  # (4, 4) the pre-grasp pose
    centres: np.ndarray  # (C, 3) the cell centres in the frame of T0
    r: float
    z_lo: float
    z_hi: float
    dz: tuple[float, ...] = ()

    def moved(self, dz: float) -> _View:
        """The view after the hand moved by ``dz`` along hand z (a retreat: positive)."""
        return dataclasses.replace(self, dz=(*self.dz, dz))

    def cells(self, ctx: _Context) -> tuple[np.ndarray, np.ndarray]:
        """``(centres (C, 3), ok (C,))``: the cell centres in the hand frame (the shifts summed:
        the cell tests need no exact rounding, their radii cover it) and which cells' balls
        meet the keep box."""
        rad = ctx.cells.radius
        c = self.centres
        ok = (np.abs(c[:, 0]) <= self.r + rad) & (np.abs(c[:, 1]) <= self.r + rad)
        ok &= (c[:, 2] >= self.z_lo - rad) & (c[:, 2] <= self.z_hi + rad)
        c = c.copy()
        c[:, 2] += sum(self.dz)
        return c, ok

    def points(self, ctx: _Context, pid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(ok (K,), p (3, K'))``: which of the cloud points ``pid`` are in the keep box, and
        their coordinates in the hand frame (by coordinate: x, y, z rows)."""
        p0 = _to_frame_t(ctx.xyz[:, pid], self.T0)
        x, y, z = p0
        ok = (np.abs(x) <= self.r) & (np.abs(y) <= self.r) & (z >= self.z_lo) & (z <= self.z_hi)
        p = p0[:, ok]
        for d in self.dz:  # loop over <= 2 moves
            p[2] += d
        return ok, p

    def near(self, ctx: _Context, centre: np.ndarray, radius: float) -> np.ndarray:
        """(M, 3) the seen points within ``radius`` of ``centre`` (hand frame), in ascending
        cloud order."""
        c, ok = self.cells(ctx)
        ok &= np.sum((c - centre) ** 2, axis=1) <= (radius + ctx.cells.radius) ** 2
        _, p = self.points(ctx, ctx.cells.points_of(np.flatnonzero(ok)))
        d2 = (p[0] - centre[0]) ** 2 + (p[1] - centre[1]) ** 2 + (p[2] - centre[2]) ** 2
        return np.ascontiguousarray(p[:, d2 <= radius**2].T)


class _Context:
    """Per-call data shared by every pre-grasp (cloud, hand geometry caches)."""

    def __init__(self, points, normals, hand, params: PlannerParams, support) -> None:
        self.points = points
        self.normals = normals
        self.hand = hand
        self.params = params
        self.support = support
        self.cells = _Cells(points, CELL_SIZE)
        self.xyz = np.ascontiguousarray(points.T)  # (3, N) the cloud by coordinate
        self.link_names = tuple(hand.link_names)
        self.half = np.asarray(hand.link_box_half, dtype=np.float64)
        self.link_index = {n: i for i, n in enumerate(self.link_names)}
        self.clock = dict.fromkeys(("approach_slicing", "closing", "verification", "quality"), 0.0)
        self._planes: dict[tuple[str, float], Any] = {}
        self._boxes: dict[bytes, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
        self._pairs: dict[bytes, list[tuple[str, str]]] = {}
        self._lock = threading.Lock()
        # reach: half side of a cube about the palm origin that holds every link box at any
        # configuration (palm half diagonal, or first joint + middle + distal at any flexion)
        reach = np.linalg.norm(self.half[self.link_index["palm"]])
        for f in hand.fingers:
            base = np.linalg.norm(hand.flexion_plane(f, 0.0).origin)
            tip = f.middle_length + f.distal_length + np.hypot(0.5 * f.thickness, 0.5 * f.width)
            reach = max(reach, base + tip)
        self.reach = float(reach)

    def plane(self, finger, spread: float):
        key = (finger.name, round(float(spread), 12))
        hit = self._planes.get(key)
        if hit is None:  # (threads: a plane computed twice is the same plane)
            hit = self._planes.setdefault(key, self.hand.flexion_plane(finger, spread))
        return hit

    def prefetch_boxes(self, Q: np.ndarray) -> None:
        """Compute and cache the box poses and the self-collisions (:meth:`self_pairs`) of many
        configurations ``Q`` (B, J) at once."""
        Q = np.ascontiguousarray(Q, dtype=np.float64)
        new = [b for b in range(len(Q)) if Q[b].tobytes() not in self._pairs]
        if not new:
            return
        Tb_all = self.hand.box_poses(Q[new])  # (B', L, 4, 4)
        corners = box_corners(Tb_all.reshape(-1, 4, 4), np.tile(self.half, (len(new), 1)))
        corners = corners.reshape(len(new), -1, 8, 3)
        lo, hi = corners.min(axis=2), corners.max(axis=2)
        pairs = self.hand.self_collisions_many(Q[new], Tb_all)
        for k, b in enumerate(new):  # loop over the configurations: fill the caches
            key = Q[b].tobytes()
            self._store(self._boxes, key, (Tb_all[k], lo[k], hi[k]))
            self._store(self._pairs, key, pairs[k])

    def _store(self, cache: dict, key: bytes, value: Any) -> None:
        with self._lock:  # the planner's threads share the caches; every change goes here
            cache[key] = value
            while len(cache) > 4096:  # a bound for pools of arbitrary preshapes
                cache.pop(next(iter(cache)))

    def self_pairs(self, q: np.ndarray) -> list[tuple[str, str]]:
        """:meth:`Hand.self_collisions` at ``q`` (cached)."""
        key = q.tobytes()
        hit = self._pairs.get(key)
        if hit is None:
            hit = self.hand.self_collisions(q, self.boxes(q)[0])
            self._store(self._pairs, key, hit)
        return hit

    def boxes(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Box poses (L, 4, 4) and their hand-frame AABBs lo, hi (L, 3) at ``q`` (cached)."""
        key = q.tobytes()
        hit = self._boxes.get(key)
        if hit is None:
            Tb = self.hand.box_poses(q)
            corners = box_corners(Tb, self.half).reshape(-1, 8, 3)
            hit = (Tb, corners.min(axis=1), corners.max(axis=1))
            self._store(self._boxes, key, hit)
        return hit


def _approach(ctx: _Context, T0: np.ndarray, q: np.ndarray, c0: np.ndarray) -> tuple[float, str]:
    """Travel along hand +z until a box is ``approach_clearance`` from the cloud/support.

    ``c0`` (C, 3): the cloud's cell centres in the frame of the hand at the pre-grasp pose. The
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
        corners = box_corners(Tb, ctx.half) @ T0[:3, :3].T + T0[:3, 3]  # (8L, 3) world
        heights = corners @ n - (ctx.support.height + c)
        rate = float(n @ T0[:3, 2])  # height change per metre of approach
        s_sup = max(float(heights.min()), 0.0) / -rate if rate < -GEOM_EPS else np.inf
    s_obj = np.inf
    S_eff = min(S, s_sup)  # the hand cannot travel past the support plane
    wlo, whi = lo - c, hi + c  # (L, 3) each link's window across the approach
    rad = ctx.cells.radius[:, None]
    cm, cp = c0 - rad, c0 + rad  # (C, 3) the cells' balls' bounds
    # two passes: a short first window (most approaches end within a few centimetres); a hit
    # beyond it may hide an earlier one by a point it did not gather, so then the full window
    for window in (min(APPROACH_WINDOW, S_eff), S_eff):
        top = whi[:, 2] + window
        ci, il = np.nonzero(
            (cp[:, 2:3] >= wlo[:, 2])
            & (cm[:, 2:3] <= top)
            & (cp[:, 0:1] >= wlo[:, 0])
            & (cm[:, 0:1] <= whi[:, 0])
            & (cp[:, 1:2] >= wlo[:, 1])
            & (cm[:, 1:2] <= whi[:, 1])
        )  # (cell, link) pairs: the cell's ball meets the link's window
        pid, k = ctx.cells.expand(ci)
        il = il[k]
        ps = _to_frame_t(ctx.xyz[:, pid], T0)
        px, py, pz = ps
        hit = np.flatnonzero(
            (pz >= wlo[il, 2])
            & (pz <= top[il])
            & (px >= wlo[il, 0])
            & (px <= whi[il, 0])
            & (py >= wlo[il, 1])
            & (py <= whi[il, 1])
        )  # (K,) the candidate pairs: the point is in the link's window
        if len(hit):
            s_obj = _sweep_pairs(px[hit], py[hit], pz[hit], il[hit], Tb, ctx.half + c)[0]
        if s_obj <= window or window >= S_eff:
            break
    s = min(s_obj, s_sup)
    if not np.isfinite(s) or s > S:
        return np.inf, ""
    if s <= 0.0:
        return 0.0, "start"
    return float(s), "object" if s_obj <= s_sup else "support"


def _support_collision(ctx: _Context, T: np.ndarray, q: np.ndarray) -> str | None:
    """The first link whose box reaches below the support plane by > penetration_tol (fcl)."""
    if ctx.support is None:
        return None
    n = np.asarray(ctx.support.normal, dtype=np.float64)
    table = fcl.CollisionObject(
        fcl.Halfspace(n, float(ctx.support.height) - ctx.params.penetration_tol), fcl.Transform()
    )
    Tb = T @ ctx.boxes(q)[0]  # (L, 4, 4) world
    req = fcl.CollisionRequest()
    for i, name in enumerate(ctx.link_names):  # loop over the ~10 links
        obj = fcl.CollisionObject(
            fcl.Box(*(2.0 * ctx.half[i])), fcl.Transform(Tb[i, :3, :3], Tb[i, :3, 3])
        )
        if fcl.collide(obj, table, req, fcl.CollisionResult()) > 0:
            return name
    return None


def _link_distances(
    ctx: _Context, view: _View, q: np.ndarray, reach: float
) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Per link of the hand at configuration ``q``: cloud indices of the points within
    ``reach`` of its box and their exact signed distances to it (< 0 inside), in ascending
    cloud order (``view``: the cloud in the hand's frame). Candidates: the points in the AABB
    of a box grown by ``reach`` (found through the cells); all pairs' distances at once."""
    Tb, lo, hi = ctx.boxes(q)  # hand frame
    blo, bhi = lo - reach, hi + reach  # (L, 3)
    c, ok = view.cells(ctx)
    rad = ctx.cells.radius[:, None]
    cm, cp = c - rad, c + rad
    ci, il = np.nonzero(
        ok[:, None]
        & (cp[:, 0:1] >= blo[:, 0])
        & (cm[:, 0:1] <= bhi[:, 0])
        & (cp[:, 1:2] >= blo[:, 1])
        & (cm[:, 1:2] <= bhi[:, 1])
        & (cp[:, 2:3] >= blo[:, 2])
        & (cm[:, 2:3] <= bhi[:, 2])
    )  # (cell, link) pairs: the cell's ball meets the link's grown AABB
    pid, k = ctx.cells.expand(ci)
    seen, p = view.points(ctx, pid)
    pid, il = pid[seen], il[k[seen]]
    x, y, z = p
    inside = np.flatnonzero(
        (x >= blo[il, 0])
        & (x <= bhi[il, 0])
        & (y >= blo[il, 1])
        & (y <= bhi[il, 1])
        & (z >= blo[il, 2])
        & (z <= bhi[il, 2])
    )
    il, pid = il[inside], pid[inside]
    # the exact distance to each pair's box, in its frame
    Tl = Tb[il]  # (K, 4, 4)
    v0, v1, v2 = x[inside] - Tl[:, 0, 3], y[inside] - Tl[:, 1, 3], z[inside] - Tl[:, 2, 3]
    half = ctx.half[il]
    qd = [
        np.abs(v0 * Tl[:, 0, j] + v1 * Tl[:, 1, j] + v2 * Tl[:, 2, j]) - half[:, j]
        for j in range(3)  # the box's three axes
    ]
    out = [np.maximum(qj, 0.0) for qj in qd]
    d = np.sqrt(out[0] ** 2 + out[1] ** 2 + out[2] ** 2) + np.minimum(
        np.maximum(np.maximum(qd[0], qd[1]), qd[2]), 0.0
    )
    near = np.flatnonzero(d <= reach)
    near = near[np.lexsort((pid[near], il[near]))]  # by link, then ascending cloud index
    il, d, cloud = il[near], d[near], pid[near]
    cuts = np.searchsorted(il, np.arange(1, len(Tb)))
    return np.split(cloud, cuts), np.split(d, cuts)


def _support_line_2d(
    ctx: _Context, T: np.ndarray, plane: Any, half_width: float, reach: float
) -> np.ndarray:
    """(S, 2) points along the support plane's trace in a finger's flexion plane, spaced by
    ``closing_margin`` within ``reach`` of the finger's first joint (the 2D origin; the moving
    links never get farther), so that the closing model stops a link on the
    table as on the object. The trace is raised by ``half_width |n . plane normal|``: the link
    box is that much lower at its side edges when the plane is tilted. Empty without a support
    plane or when the flexion plane is parallel to it."""
    if ctx.support is None:
        return np.zeros((0, 2))
    n_h = T[:3, :3].T @ np.asarray(ctx.support.normal, dtype=np.float64)  # hand frame
    h_h = float(ctx.support.height) - float(np.asarray(ctx.support.normal) @ T[:3, 3])
    a, b = float(n_h @ plane.u), float(n_h @ plane.v)
    ab = np.hypot(a, b)
    if ab < 1e-6:
        return np.zeros((0, 2))
    target = h_h + half_width * abs(float(n_h @ plane.normal)) - float(n_h @ plane.origin)
    foot = target * np.array([a, b]) / ab**2  # nearest point of the line to the 2D origin
    along = np.array([-b, a]) / ab
    d_foot = float(np.linalg.norm(foot))
    if d_foot > reach:
        return np.zeros((0, 2))
    half_len = np.sqrt(reach**2 - d_foot**2)  # the chord of the line inside the reach
    step = max(ctx.params.closing_margin, 1e-4)
    t = np.arange(-half_len, half_len + step, step)
    return foot + t[:, None] * along


def _thin_2d(p2: np.ndarray, cell: float) -> np.ndarray:
    """One point of ``p2`` (M, 2) per occupied square cell of side ``cell`` (0: all points):
    the first in the given order.

    A slice projects a 3D band of the surface (one finger width thick) onto its plane, where
    many points fall within a fraction of a millimetre of each other."""
    if cell <= 0.0 or len(p2) < 2:
        return p2
    c = np.floor(p2 / cell).astype(np.int64)
    c -= c.min(axis=0)
    key = c[:, 0] * (int(c[:, 1].max()) + 1) + c[:, 1]
    m = len(p2)
    n_cells = int(key.max()) + 1
    if n_cells > 16 * m + 65536:  # a sparse spread of points: sort instead of a dense grid
        _, first = np.unique(key, return_index=True)
        return p2[np.sort(first)]
    # the lowest row of every cell, on a dense grid; a row is kept when it is its cell's lowest
    rows = np.arange(m)
    lowest = np.full(n_cells, m, dtype=np.int64)
    np.minimum.at(lowest, key, rows)
    return p2[lowest[key] == rows]


@dataclass
class _Slice:
    """One finger's slice, ready for the closing model."""

    finger: Any
    points_2d: np.ndarray  # (M + S, 2) the thinned slice points, then the support trace
    q_start: np.ndarray  # (2,) the finger's preshape flexion
    n_obj: int  # rows of points_2d that are cloud points (the rest: the support plane)
    has_table: bool  # the support plane crosses the finger's reach
    n_slice: int  # cloud points in the slice before thinning


def _slices(
    ctx: _Context, T: np.ndarray, view: _View, q0: np.ndarray, gt: str, spread: float
) -> list[_Slice]:
    """The slice of every finger of the grasp type for the hand at pose ``T`` (``view``: the
    cloud in that hand frame)."""
    prm = ctx.params
    out = []
    fingers = ctx.hand.fingers_for(gt)
    planes = [ctx.plane(f, spread) for f in fingers]
    nrm = np.array([pl.normal for pl in planes]).T  # (3, F)
    shift = np.array([pl.origin @ pl.normal for pl in planes])  # (F,)
    half_w = np.array([0.5 * f.width for f in fingers])
    # the moving links never get farther than Lm + hypot(Ld, h) from the first joint
    reach = [f.middle_length + np.hypot(f.distal_length, 0.5 * f.thickness) for f in fingers]
    r_all = np.array(reach) + prm.closing_margin  # (F,)
    # candidates: the cells whose balls meet a finger's band (within half a finger width of
    # its plane, and within its reach in the plane: in 3D within hypot(reach, half width) of
    # its first joint)
    c, ok = view.cells(ctx)
    rad = ctx.cells.radius[:, None]
    origins = np.array([pl.origin for pl in planes])  # (F, 3)
    d2 = (
        (c[:, 0:1] - origins[:, 0]) ** 2
        + (c[:, 1:2] - origins[:, 1]) ** 2
        + (c[:, 2:3] - origins[:, 2]) ** 2
    )  # (C, F)
    cand = (
        ok[:, None]
        & (np.abs(c @ nrm - shift) <= half_w + 1e-9 + rad)
        & (d2 <= (np.hypot(r_all, half_w) + 1e-9 + rad) ** 2)
    )  # (C, F)
    _, p = view.points(ctx, ctx.cells.points_of(np.flatnonzero(cand.any(axis=1))))
    # the band test (the offsets along the flexion planes' normals, with a margin far above
    # their rounding; the exact slice test follows)
    along = p[0, :, None] * nrm[0] + p[1, :, None] * nrm[1] + p[2, :, None] * nrm[2]  # (M, F)
    near_band = np.abs(along - shift) <= half_w + 1e-9
    for j, (f, plane) in enumerate(zip(fingers, planes, strict=True)):  # <= 3 fingers
        band = near_band[:, j]
        # the 2D coordinates and offsets (FlexionPlane.to_plane) of the points in the band
        uvn = _to_frame_t(p[:, band], plane.T_hand_plane)
        p2, off = uvn[:2].T, uvn[2]
        r_f = r_all[j]
        in_slice = (np.abs(off) <= 0.5 * f.width) & (
            p2[:, 0] ** 2 + p2[:, 1] ** 2 <= (r_f + 1e-9) ** 2
        )
        p_slice = _thin_2d(p2[in_slice], prm.slice_resolution)
        table = _support_line_2d(ctx, T, plane, 0.5 * f.width, r_f)
        out.append(
            _Slice(
                f,
                np.concatenate([p_slice, table]),
                q0[list(f.flex_index)],
                len(p_slice),
                len(table) > 0,
                int(np.count_nonzero(in_slice)),
            )
        )
    return out


def _close_slices(ctx: _Context, slices: list[_Slice]) -> list:
    """Close the fingers of many slices with one call of the hand's batched closing model."""
    prm = ctx.params
    return ctx.hand.close_fingers(
        [(sl.finger, sl.points_2d, sl.q_start) for sl in slices],
        n_steps=prm.closing_steps,
        margin=prm.closing_margin,
    )


def _closing_records(q0: np.ndarray, slices: list[_Slice], cls: list) -> tuple[np.ndarray, list]:
    """The joint vector after closing and, per finger, ``(finger, FingerClosing, n_slice, links
    touched on cloud points, stopped by the support)``."""
    q = q0.copy()
    closings = []
    for sl, cl in zip(slices, cls, strict=True):  # loop over <= 3 fingers
        f = sl.finger
        q[list(f.flex_index)] = cl.q
        touched = tuple(c.link for c in cl.contacts if c.index < sl.n_obj)
        on_table = any(c.index >= sl.n_obj for c in cl.contacts) or (
            cl.start_in_contact and not touched and sl.has_table
        )
        closings.append((f, cl, sl.n_slice, touched, on_table))
    return q, closings


def _open_self_collisions(
    ctx: _Context, q: np.ndarray, closings: list, corrected: dict
) -> tuple[np.ndarray, bool]:
    """Undo finger-finger collisions of the closed hand (python-fcl): for a colliding pair, each
    finger owning one of the two links is opened back along its closing path (bisection over
    the path samples) to the last sample where the pair is apart; the finger that keeps the
    most of its closing is used. At most ``len(closings)`` pairs are resolved; what remains is
    rejected later as ``self_collision``. Returns ``(q, clean)``; ``clean`` says that python-fcl
    found no pair at the returned ``q``."""
    hand = ctx.hand
    q = q.copy()
    for _ in range(len(closings)):  # loop over <= 3 fingers
        pairs = ctx.self_pairs(q)
        if not pairs:
            return q, True
        a, b = pairs[0]
        best = None  # (kept path index, finger, q_flex)
        for f, cl, *_ in closings:  # loop over <= 3 fingers
            if not {a, b} & {f.links[1], f.links[2]} or len(cl.path) == 0:
                continue

            def apart(i: int, f=f, cl=cl, pair=(a, b)) -> bool:
                qq = q.copy()
                qq[list(f.flex_index)] = cl.path[i]
                return pair not in hand.self_collisions(qq)

            if not apart(0):
                continue
            lo, hi = 0, len(cl.path) - 1  # apart(lo) holds; find the last apart sample
            while hi - lo > 1:  # bisection over the path samples
                mid = (lo + hi) // 2
                if apart(mid):
                    lo = mid
                else:
                    hi = mid
            i = hi if apart(hi) else lo
            if best is None or i > best[0]:
                best = (i, f, cl.path[i])
        if best is None:
            break
        _, f, q_flex = best
        q[list(f.flex_index)] = q_flex
        corrected[f.name] = True
    return q, not ctx.self_pairs(q)


@dataclass
class _Prepared:
    """A pre-grasp after its approach, with its finger slices (see :func:`_prepare`)."""

    i: int
    gt: str
    T0: np.ndarray
    q0: np.ndarray
    spread: float
    T: np.ndarray  # hand pose after the approach
    s: float
    stop: str
    view: _View  # the cloud in the frame of T
    slices: list[_Slice]


def _rejected(
    i: int, gt: str, T: np.ndarray, q: np.ndarray, reason: str, detail: str, s: float = 0.0,
    stop: str = "", fingers: tuple = (),
) -> Grasp:  # fmt: skip
    return Grasp(i, gt, T, s, stop, q, tuple(fingers), (), 0.0, 0.0, None, reason, detail)


def _prepare(ctx: _Context, pool: Any, i: int) -> _Prepared | Grasp:
    """Approach and slicing of pre-grasp ``i``; a rejected ``Grasp`` when nothing is ahead."""
    prm = ctx.params
    gt = str(pool.grasp_type[i])
    T0 = np.asarray(pool.T_world_hand[i], dtype=np.float64)
    q0 = np.asarray(pool.q[i], dtype=np.float64)
    spread = float(pool.spread[i])

    # 1. approach, with the cloud (its cells) in the frame of the hand at the pre-grasp pose
    c0 = _to_frame(ctx.cells.centre, T0)  # (C, 3)
    s, stop = _approach(ctx, T0, q0, c0)
    if not np.isfinite(s):
        detail = f"no cloud point within {prm.max_approach:.3f} m ahead"
        return _rejected(i, gt, T0, q0, "nothing_ahead", detail)
    T = T0.copy()
    T[:3, 3] += s * T0[:3, 2]
    # the cloud points the hand can reach after the approach (a box about the hand, r on every
    # side; below the palm also from up to max_lift higher up), in the frame of the hand
    # there: every point a link can touch or hold, for the slices and the 3D checks (r = the
    # hand's reach + the largest contact or penetration distance)
    r = ctx.reach + max(prm.contact_distance, prm.penetration_tol)
    lift = prm.max_lift if ctx.support is not None else 0.0
    view = _View(T0, c0, r, max(-r, s - r - lift), r + s, (-s,))
    # 2. the slices (closed for many pre-grasps at once by the caller)
    slices = _slices(ctx, T, view, q0, gt, spread)
    return _Prepared(i, gt, T0, q0, spread, T, s, stop, view, slices)


def _finish(ctx: _Context, pre: _Prepared, q: np.ndarray, closings: list, lift: float) -> Grasp:
    """After the closing (``q`` and ``closings`` from :func:`_closing_records`, at the height
    ``lift`` that :func:`_lift_retries` chose): 3D verification and contacts."""
    hand, prm = ctx.hand, ctx.params
    i, gt, T0, q0, spread = pre.i, pre.gt, pre.T0, pre.q0, pre.spread
    T, s, stop, view = pre.T.copy(), pre.s, pre.stop, pre.view

    def rejected(reason: str, detail: str, T=T0, s=0.0, stop="", q=q0, fingers=()) -> Grasp:
        return _rejected(i, gt, T, q, reason, detail, s, stop, fingers)

    if lift > 0.0:  # the hand closed from higher up (see _lift_retries)
        T[:3, 3] -= lift * T0[:3, 2]
        view = view.moved(lift)
        s -= lift
        stop = "support_lifted"

    # 3. verification in 3D. Fingers that closed into each other (python-fcl) stop where they
    # meet: the finger that needs the least opening goes back along its closing path.
    corrected = {f.name: False for f, *_ in closings}
    q, clean = _open_self_collisions(ctx, q, closings, corrected)
    q_checked = q.copy()
    # depth of the nearby cloud points in every link
    reach = max(prm.contact_distance, prm.penetration_tol)
    ids, dists = _link_distances(ctx, view, q, reach)
    bad = {ctx.link_names[j] for j, d in enumerate(dists) if np.any(d < -prm.penetration_tol)}
    if bad:
        for f, cl, *_ in closings:
            cols = [ctx.link_index[n] for n in (f.links[1], f.links[2])]
            if not bad & {f.links[1], f.links[2]}:
                continue
            # open the finger back along its closing path (bisection over the path samples)
            # to the last sample where its links hold no point deeper than the tolerance
            origin = ctx.plane(f, spread).origin
            near = view.near(ctx, origin, ctx.reach + reach)

            def clear(k: int, f=f, cl=cl, cols=cols, near=near) -> bool:
                qq = q.copy()
                qq[list(f.flex_index)] = cl.path[k]
                d = box_signed_distance(near, hand.box_poses(qq)[cols], ctx.half[cols])
                return not np.any(d < -prm.penetration_tol)

            if len(cl.path) and clear(0):
                lo, hi = 0, len(cl.path) - 1
                while hi - lo > 1:  # bisection over the closing steps
                    mid = (lo + hi) // 2
                    lo, hi = (mid, hi) if clear(mid) else (lo, mid)
                q[list(f.flex_index)] = cl.path[hi if clear(hi) else lo]
                corrected[f.name] = True
        ids, dists = _link_distances(ctx, view, q, reach)
    fingers = tuple(
        FingerTrace(
            f.name,
            n,
            q[list(f.flex_index)].copy(),
            touched,
            bool(cl.palm_stop),
            on_table,
            bool(cl.at_limits),
            corrected[f.name],
        )
        for f, cl, n, touched, on_table in closings
    )
    depth = np.array([-d.min() if len(d) else -np.inf for d in dists])
    if depth.max() > prm.penetration_tol:
        j = int(np.argmax(depth))
        return rejected(
            "penetration",
            f"{ctx.link_names[j]} holds a point {depth[j] * 1e3:.1f} mm deep",
            T, s, stop, q, fingers,
        )  # fmt: skip
    pairs = [] if clean and np.array_equal(q, q_checked) else ctx.self_pairs(q)
    if pairs:
        detail = f"{pairs[0][0]} and {pairs[0][1]}"
        return rejected("self_collision", detail, T, s, stop, q, fingers)
    below = _support_collision(ctx, T, q)
    if below is not None:
        detail = f"{below} below the support plane"
        return rejected("support_collision", detail, T, s, stop, q, fingers)

    # 4. contacts: one per link, the nearest cloud point within contact_distance. Points as
    # near as it (within CONTACT_TIE: a face of the object parallel to the link's face) form a
    # patch; the contact is its point nearest the link box's centre (then the lowest cloud
    # index), so the choice never depends on rounding or on the candidates' order
    centres = (T @ ctx.boxes(q)[0])[:, :3, 3]  # (L, 3) link box centres, world
    links, local, dist = [], [], []
    for j, (sel, d) in enumerate(zip(ids, dists, strict=True)):  # loop over the ~10 links
        if len(d) and d.min() <= prm.contact_distance:
            tie = np.flatnonzero(d <= d.min() + CONTACT_TIE)
            if len(tie) > 1:
                off = np.sum((ctx.points[sel[tie]] - centres[j]) ** 2, axis=1)
                k = int(tie[np.lexsort((sel[tie], off))[0]])
            else:
                k = int(tie[0])
            links.append(j)
            local.append(sel[k])
            dist.append(float(d[k]))
    if not links:
        return rejected("no_contact", "", T, s, stop, q, fingers)
    pid = np.asarray(local, dtype=np.int64)
    Tb = ctx.boxes(q)[0]
    tangents = Tb[links, :3, 1] @ T[:3, :3].T  # link box y axes in the world
    normals_in = -ctx.normals[pid]
    contacts = tuple(
        Contact(
            ctx.points[p].copy(), normals_in[k].copy(), ctx.link_names[j], int(p), dist[k],
            tangents[k].copy(),
        )
        for k, (j, p) in enumerate(zip(links, pid, strict=True))
    )  # fmt: skip
    # 5. quality: by the caller (see _score)
    return Grasp(i, gt, T, s, stop, q, fingers, contacts, 0.0, 0.0, None, None, "")


def _score(prm: PlannerParams, g: Grasp) -> Grasp:
    """``g`` with the epsilon, volume and quality detail of its contacts."""
    pts = np.array([c.point for c in g.contacts])
    nrm = np.array([c.normal for c in g.contacts])
    tng = np.array([c.tangent for c in g.contacts])
    qual: GraspQuality = grasp_quality(pts, nrm, prm.quality, tangents=tng)
    return dataclasses.replace(g, epsilon=qual.epsilon, volume=qual.volume, detail=qual.reason)


def _n_threads(threads: int) -> int:
    """Threads of the planner (``PlannerParams.threads``; 0 = the usable CPUs)."""
    if threads:
        return int(threads)
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # not on Linux
        return os.cpu_count() or 1


def _lift_retries(ctx: _Context, todo: list[_Prepared], records: dict, each: Callable) -> None:
    """Retreats from the support (``PlannerParams.max_lift``) for the pre-grasps of a chunk:
    when the table, not the object, ended the approach and some finger closed on the table (or
    could not move), the hand closes again from ``k * LIFT_STEP`` higher up (back along the
    approach), k = 1, 2, ..., and keeps the height where the most fingers touch the object. It
    stops when every finger touches the object or when no finger is held by the table any more
    (going higher cannot help). Round k closes the fingers of every pre-grasp still retreating
    in one call of the batched closing model. ``records`` (pre-grasp -> (q, closings, lift)) is
    updated in place."""
    prm = ctx.params
    if ctx.support is None or prm.max_lift <= 0.0:
        return
    active = [p for p in todo if p.stop in ("support", "start")]
    best = {p.i: sum(bool(c[3]) for c in records[p.i][1]) for p in active}  # fingers on object
    for k in range(1, int(round(prm.max_lift / LIFT_STEP)) + 1):  # <= ~8 retreats
        active = [p for p in active if best[p.i] != len(records[p.i][1])]
        if not active:
            break
        up = k * LIFT_STEP

        def slices_up(p: _Prepared, up: float = up) -> list[_Slice]:
            T_up = p.T.copy()
            T_up[:3, 3] -= up * p.T0[:3, 2]
            return _slices(ctx, T_up, p.view.moved(up), p.q0, p.gt, p.spread)

        sls = each(slices_up, active)
        cls = _close_slices(ctx, [sl for ss in sls for sl in ss])
        going, j = [], 0
        for p, ss in zip(active, sls, strict=True):  # loop over the retreating pre-grasps
            q_up, cl_up = _closing_records(p.q0, ss, cls[j : j + len(ss)])
            j += len(ss)
            n_up = sum(bool(c[3]) for c in cl_up)
            if n_up > best[p.i]:
                best[p.i] = n_up
                records[p.i] = (q_up, cl_up, up)
            if any(c[4] and not c[3] for c in cl_up):  # a finger is still held by the table
                going.append(p)
        active = going


def _finish_or_keep(ctx: _Context, records: dict, p: _Prepared | Grasp) -> Grasp:
    """:func:`_finish` for a prepared pre-grasp (its closing in ``records``); a rejection as
    it is."""
    return _finish(ctx, p, *records[p.i]) if isinstance(p, _Prepared) else p


def _plan_chunks(
    ctx: _Context,
    pool: Any,
    P: int,
    ex: ThreadPoolExecutor | None,
    grasps: list[Grasp],
    progress: Callable[[int, int], None] | None,
) -> None:
    """Plan the pre-grasps of ``pool`` chunk by chunk into ``grasps`` (see :func:`plan_grasps`).
    The per-pre-grasp phases run on the thread pool ``ex`` when there is one (numpy and qhull
    release Python's global lock for most of their work); every pre-grasp is planned
    independently, so the results never depend on the threads."""

    def each(fn: Callable[[Any], Any], items: list) -> list:
        return (
            list(ex.map(fn, items)) if ex is not None and len(items) > 1 else list(map(fn, items))
        )

    prm, clock, done = ctx.params, ctx.clock, 0
    for c0 in range(0, P, _CHUNK):  # loop over chunks of pre-grasps
        t0 = time.perf_counter()
        preps = each(functools.partial(_prepare, ctx, pool), list(range(c0, min(P, c0 + _CHUNK))))
        todo = [p for p in preps if isinstance(p, _Prepared)]
        t1 = time.perf_counter()
        cls = _close_slices(ctx, [sl for p in todo for sl in p.slices])
        records, k = {}, 0
        for p in todo:  # loop over the chunk's pre-grasps
            records[p.i] = (*_closing_records(p.q0, p.slices, cls[k : k + len(p.slices)]), 0.0)
            k += len(p.slices)
        _lift_retries(ctx, todo, records, each)
        t2 = time.perf_counter()
        if records:  # the link boxes of every closed hand of the chunk: one batched FK
            ctx.prefetch_boxes(np.array([r[0] for r in records.values()]))
        chunk = each(functools.partial(_finish_or_keep, ctx, records), preps)
        t3 = time.perf_counter()
        # 5. quality of the kept grasps: one 6D hull each
        kept = [k for k, g in enumerate(chunk) if g.kept]
        scored = each(functools.partial(_score, prm), [chunk[k] for k in kept])
        for k, g in zip(kept, scored, strict=True):
            chunk[k] = g
        t4 = time.perf_counter()
        clock["approach_slicing"] += t1 - t0
        clock["closing"] += t2 - t1
        clock["verification"] += t3 - t2
        clock["quality"] += t4 - t3
        grasps.extend(chunk)
        done += len(chunk)
        if progress is not None:
            progress(done, P)


def rank_grasps(grasps: list[Grasp] | tuple[Grasp, ...]) -> np.ndarray:
    """(K,) indices of the kept grasps, best first: epsilon, then volume, then contacts (all
    descending), ties by pre-grasp index."""
    kept = [k for k, g in enumerate(grasps) if g.kept]
    if not kept:
        return np.zeros(0, dtype=np.int64)
    eps = np.array([grasps[k].epsilon for k in kept])
    vol = np.array([grasps[k].volume for k in kept])
    nc = np.array([grasps[k].n_contacts for k in kept])
    order = np.lexsort((np.array(kept), -nc, -vol, -eps))
    return np.asarray(kept, dtype=np.int64)[order]


def plan_grasps(
    points: np.ndarray,
    normals: np.ndarray,
    pool: Any,
    hand: Any,
    params: PlannerParams | None = None,
    support: Any = None,
    progress: Callable[[int, int], None] | None = None,
) -> GraspSet:
    """Plan every pre-grasp of ``pool`` against the cloud.

    points: (N, 3) metres, world; normals: (N, 3) unit outward normals of the cloud (see
    :func:`cloud_normals`); pool: a ``PreGraspPool`` (``T_world_hand`` (P, 4, 4), ``q`` (P, J),
    ``spread`` (P,), ``grasp_type`` (P,)); hand: ``pregrasp_core.hand.Hand``; support: the
    ``SupportPlane`` (normal, height) or None; progress: called as ``progress(done, total)``.
    """
    prm = PlannerParams() if params is None else params
    pts = np.asarray(points, dtype=np.float64)
    nrm = np.asarray(normals, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points must have shape (N, 3), got {pts.shape}")
    if nrm.shape != pts.shape:
        raise ValueError(f"normals must have shape {pts.shape}, got {nrm.shape}")
    P = len(pool)
    joint_names = tuple(hand.joint_names)
    if P and np.shape(pool.q)[1] != len(joint_names):
        raise ValueError(
            f"pool.q has {np.shape(pool.q)[1]} joints, the hand has {len(joint_names)}"
        )
    ctx = _Context(pts, nrm, hand, prm, support)
    grasps: list[Grasp] = []
    # chunks of pre-grasps: approach and slicing per pre-grasp, the closing of every finger of
    # the chunk in one call of the batched closing model, verification and quality per
    # pre-grasp; the per-pre-grasp phases on a thread pool when prm.threads allows one
    n_threads = min(_n_threads(prm.threads), _CHUNK)
    ex = ThreadPoolExecutor(n_threads) if n_threads > 1 and P > 1 else None
    try:
        _plan_chunks(ctx, pool, P, ex, grasps, progress)
    finally:
        if ex is not None:
            ex.shutdown()
    order = rank_grasps(grasps)
    ranked = list(grasps)
    for r, k in enumerate(order):
        g = ranked[k]
        ranked[k] = dataclasses.replace(g, rank=r)
    rejected = {key: 0 for key in REJECTION_REASONS}
    for g in ranked:
        if g.rejection is not None:
            rejected[g.rejection] += 1
    logger.info(
        "planned %d pre-grasps: %d kept, %d force closure, rejected %s",
        P,
        len(order),
        sum(g.epsilon > 0 for g in ranked),
        rejected,
    )
    return GraspSet(tuple(ranked), order, joint_names, rejected, dict(ctx.clock))


def cloud_normals(cloud: Any, params: NormalParams | None = None) -> np.ndarray:
    """(N, 3) outward unit normals of a ``PointCloud`` by local PCA, oriented by its own normals
    when it has them (mesh-sampled clouds), else by propagation (:mod:`pregrasp_core.normals`)."""
    prm = NormalParams() if params is None else params
    return estimate_normals(cloud.points, prm, reference=cloud.normals).normals


# ------------------------------------------------------------------------------ result file


def grasp_to_dict(g: Grasp, hand: Any) -> dict[str, Any]:
    """One grasp as a JSON-ready dict (see ``docs/result-schema.md``, "grasps")."""
    return {
        "pregrasp": g.pregrasp,
        "grasp_type": g.grasp_type,
        "status": "kept" if g.kept else "rejected",
        "rejection": g.rejection,
        "detail": g.detail,
        "rank": g.rank,
        "epsilon": g.epsilon,
        "volume": g.volume,
        "n_contacts": g.n_contacts,
        "T_world_hand": g.T_world_hand.tolist(),
        "approach_distance": g.approach_distance,
        "approach_stop": g.approach_stop,
        "joints": hand.full_cfg(g.q),
        "fingers": [
            {
                "finger": f.finger,
                "n_slice": f.n_slice,
                "q": f.q.tolist(),
                "links_touched": list(f.links_touched),
                "palm_stop": f.palm_stop,
                "support_stop": f.support_stop,
                "at_limits": f.at_limits,
                "corrected": f.corrected,
            }
            for f in g.fingers
        ],
        "contacts": [
            {
                "link": c.link,
                "point": c.point.tolist(),
                "normal": c.normal.tolist(),
                "point_index": c.point_index,
                "distance": c.distance,
            }
            for c in g.contacts
        ],
    }


def grasps_sections(gs: GraspSet, hand: Any, params: PlannerParams | None = None) -> dict:
    """The ``grasps`` and ``best`` top-level sections of the result file."""
    prm = PlannerParams() if params is None else params
    best = gs.best
    return {
        "grasps": {
            "n_pregrasps": len(gs),
            "n_kept": int(len(gs.ranking)),
            "n_force_closure": gs.n_force_closure,
            "rejected": dict(gs.rejected),
            "ranking": gs.ranking.tolist(),
            "quality": {
                "mu": prm.quality.mu,
                "n_edges": prm.quality.n_edges,
                "torque_scale": prm.quality.torque_scale,
            },
            "items": [grasp_to_dict(g, hand) for g in gs.grasps],
        },
        "best": best,
    }


def grasps_to_dict(gs: GraspSet, hand: Any, params: PlannerParams | None = None) -> dict:
    """Same as :func:`grasps_sections`: ``{"grasps": {...}, "best": index | None}``."""
    return grasps_sections(gs, hand, params)
