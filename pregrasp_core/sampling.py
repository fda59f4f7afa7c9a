"""Tree traversal and the pre-grasp pool (Sainul, Deb & Deb 2019, section III.D).

1. :func:`traverse` decides which nodes of the decomposition tree get pre-grasps (the paper's two
   conditions by default, see :class:`TraversalPolicy`).
2. :func:`sample_node` samples the enclosing surface of a candidate's box for its grasp type
   (sphere for spherical and two-finger tip, cylinder for cylindrical, circle for three-finger
   tip) on the usable sub-faces at a fixed interval; each sample aims the hand's approach
   (+z of the hand frame) at the box (its centre, or its axis for radial cylinder samples) and
   rolls the hand so that it closes across the part as its grasp type needs.
3. :func:`build_pool` stacks the samples of all candidates, drops those whose open hand (in its
   preshape) holds a cloud point or reaches below the support plane, and counts every drop.

Everything is deterministic: no random numbers are drawn. Frames and conventions are in
``docs/conventions.md`` and ``docs/pregrasps.md``.
"""

from __future__ import annotations

import enum
import logging
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from .box import OrientedBox
from .decomposition import BoxTree
from .facemask import (
    FACE_AXIS,
    FACE_NORMAL,
    FACE_RIGHT,
    FACE_UP,
    FaceMasks,
    SupportPlane,
    subface_scheme,
    usable_subfaces,
)
from .geometry import as_points
from .shape import GRASP_TYPES, NodeShape, ShapeParams, is_small
from .tolerances import GEOM_EPS

logger = logging.getLogger(__name__)

FALLBACK_ORDER: tuple[str, ...] = ("cylindrical", "spherical", "three_finger_tip", "two_finger_tip")
"""Order in which other grasp types are tried when a candidate's own type gives nothing."""

CELL_SEAM: float = 1e-12
"""Metres: cells of a link box are grown by this so that round-off at their shared seams
cannot let a point slip between two cells (:func:`hand_hits_points`)."""

SURFACES: tuple[str, ...] = ("sphere", "cylinder_side", "cylinder_cap", "circle")
"""Names of the enclosing-surface patches a pre-grasp can come from."""

DROP_REASONS: tuple[str, ...] = ("blocked_subface", "support", "object_collision")
"""Reasons a sample is dropped, in the order the filters run: its sub-face is not usable (its
face or an adjacent face it borders is blocked); the open hand reaches below the support plane;
the open hand holds a cloud point."""


class TraversalPolicy(str, enum.Enum):
    """Which nodes of the tree get pre-grasps."""

    PAPER = "paper"
    """The paper's rule: every node is visited from the root down; a node is a candidate when
    (a) it is a leaf or one of its children is small, and (b) it fits the hand's aperture for its
    grasp type. A node failing (b) passes its children on (they are visited anyway)."""
    LEAVES = "leaves"
    """Only the leaves that fit the hand."""
    ALL = "all"
    """Every node, whatever its size (for exploration)."""

    def __str__(self) -> str:
        return self.value


@dataclass(frozen=True)
class SamplingParams:
    """Parameters of the traversal and of the pre-grasp sampling."""

    interval: float = 0.02
    """Metres: distance between neighbouring samples on the enclosing surface (> 0)."""
    policy: TraversalPolicy = TraversalPolicy.PAPER
    """Which nodes get pre-grasps (:class:`TraversalPolicy` or its string value)."""
    aperture_scale: float = 1.0
    """Multiplies the hand's aperture in the fit test of the traversal (> 0)."""
    standoff: float = 0.01
    """Metres: the palm origin sits this far outside the enclosing surface (>= 0)."""
    collision_margin: float = 0.0
    """Metres: the hand's links are grown by this in the object-collision test (>= 0)."""
    support_margin: float = 0.0
    """Metres: the hand's geometry must stay at least this far above the support plane
    (may be negative to tolerate touching it)."""
    max_backoff: float = 0.06
    """Metres: how far a pre-grasp may be moved back along its approach line (away from the
    part) to clear the support plane and the cloud; beyond it the pre-grasp is dropped."""
    backoff_step: float = 0.01
    """Metres: the back-offs tried are the multiples of this up to ``max_backoff`` (> 0)."""
    fallback: bool = True
    """When a candidate's own grasp type leaves no pre-grasp (every sample blocked or colliding),
    try the other types whose grip width fits the hand, in :data:`FALLBACK_ORDER`, and keep the
    first that gives any (recorded in ``PreGraspPool.fallback``). ``False`` = the paper's fixed
    mapping only."""

    def __post_init__(self) -> None:
        checks = (
            ("interval", lambda v: v > 0, "> 0"),
            ("aperture_scale", lambda v: v > 0, "> 0"),
            ("standoff", lambda v: v >= 0, ">= 0"),
            ("collision_margin", lambda v: v >= 0, ">= 0"),
            ("support_margin", lambda v: True, "finite"),
            ("max_backoff", lambda v: v >= 0, ">= 0"),
            ("backoff_step", lambda v: v > 0, "> 0"),
        )
        for name, ok, what in checks:
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float, np.floating, np.integer)):
                raise ValueError(f"{name} must be a number {what}, got {v!r}")
            if not (np.isfinite(v) and ok(v)):
                raise ValueError(f"{name} must be {what}, got {v!r}")
            object.__setattr__(self, name, float(v))
        object.__setattr__(self, "fallback", bool(self.fallback))
        try:
            object.__setattr__(self, "policy", TraversalPolicy(self.policy))
        except ValueError:
            raise ValueError(
                f"policy must be one of {[p.value for p in TraversalPolicy]}, got {self.policy!r}"
            ) from None


# ----------------------------------------------------------------------------- traversal


def _type_str(grasp_type: Any) -> str:
    """The string value of a grasp type given as ``GraspType`` or str."""
    s = str(getattr(grasp_type, "value", grasp_type))
    if s not in GRASP_TYPES:
        raise ValueError(f"unknown grasp type {grasp_type!r}; expected one of {GRASP_TYPES}")
    return s


def grip_width(box: OrientedBox, grasp_type: Any) -> float:
    """Metres: the width of the part the open hand must span for this grasp type.

    cylindrical: the larger side of the cross-section (the fingers close across axis 0);
    spherical and two-finger tip: the longest side (sampled from every direction);
    three-finger tip: the thickness (the fingertips close across axis 2).
    """
    gt = _type_str(grasp_type)
    e = box.extents
    return float({"cylindrical": e[1], "three_finger_tip": e[2]}.get(gt, e[0]))


@dataclass(frozen=True)
class Traversal:
    """Which nodes get pre-grasps, and why each node does or does not."""

    candidates: tuple[int, ...]
    """Ids of the candidate nodes, in traversal order (breadth-first from the root)."""
    reasons: tuple[str, ...]
    """Per node id: ``"candidate"`` or why not (``"no small child"``, ``"too big: ..."``)."""
    policy: TraversalPolicy
    """The policy used."""

    def to_dict(self) -> dict:
        """JSON-ready dict."""
        return {
            "policy": self.policy.value,
            "candidates": list(self.candidates),
            "reasons": list(self.reasons),
        }


def traverse(
    tree: BoxTree,
    shapes: Sequence[NodeShape],
    hand: Any,
    params: SamplingParams | None = None,
    shape_params: ShapeParams | None = None,
) -> Traversal:
    """Visit the tree from the root down and pick the candidate nodes (see
    :class:`TraversalPolicy`). ``hand`` provides ``aperture(grasp_type) -> metres``;
    ``shape_params.small_size`` decides which children are small."""
    params = SamplingParams() if params is None else params
    if len(shapes) != len(tree.nodes):
        raise ValueError(
            f"shapes must have one entry per node ({len(tree.nodes)}), got {len(shapes)}"
        )
    order: list[int] = []
    queue = [tree.root.id]
    while queue:  # breadth-first over nodes (small set)
        i = queue.pop(0)
        order.append(i)
        queue.extend(tree.nodes[i].children)
    reasons = [""] * len(tree.nodes)
    candidates: list[int] = []
    for i in order:
        nd = tree.nodes[i]
        gt = shapes[i].grasp_type
        if params.policy is TraversalPolicy.ALL:
            ok, why = True, "candidate"
        else:
            width = grip_width(nd.box, gt)
            aperture = float(hand.aperture(gt)) * params.aperture_scale
            fits = width <= aperture
            if params.policy is TraversalPolicy.LEAVES:
                structural = nd.is_leaf
                no_why = "not a leaf"
            else:
                structural = nd.is_leaf or any(
                    is_small(tree.nodes[c].box, shape_params) for c in nd.children
                )
                no_why = "no small child"
            if not structural:
                ok, why = False, no_why
            elif not fits:
                ok, why = (
                    False,
                    f"too big: {_type_str(gt)} width {width:.3f} m > aperture {aperture:.3f} m",
                )
            else:
                ok, why = True, "candidate"
        reasons[i] = why
        if ok:
            candidates.append(i)
    logger.info("traversal (%s): candidates %s", params.policy.value, candidates)
    return Traversal(candidates=tuple(candidates), reasons=tuple(reasons), policy=params.policy)


# ----------------------------------------------------------------------------- sampling


@dataclass(frozen=True)
class NodeSamples:
    """Pre-grasp samples of one box in its box frame (before any filter)."""

    T_box_grasp: np.ndarray
    """(M, 4, 4) float64: grasp frames in the box frame: origin = the sample (where the hand's
    grasp centre goes), axes = the hand's axes (+z = approach)."""
    face: np.ndarray
    """(M,) int64: the face the sample projects onto."""
    subface: np.ndarray
    """(M,) int64: the sub-face of that face."""
    surface: np.ndarray
    """(M,) int64: index into :data:`SURFACES`."""
    aim: np.ndarray
    """(M, 3) float64, box frame: the point the approach is aimed at (box centre or axis)."""


def _grid(half_range: float, step: float) -> np.ndarray:
    """Centres of 2 m + 1 equal cells tiling [-half_range, half_range] with width ~``step``:
    symmetric about 0 and always containing 0 (the face's centre line)."""
    m = int(round(half_range / step - 0.5)) if step > 0 else 0
    m = max(m, 0)
    return np.arange(-m, m + 1) * (2.0 * half_range / (2 * m + 1))


def _frames(approach: np.ndarray, closing: np.ndarray, closing_is_x: bool) -> np.ndarray:
    """(M, 3, 3) rotations R_box_hand with z = approach and y (or x) = closing made orthogonal."""
    z = approach / np.linalg.norm(approach, axis=1, keepdims=True)
    c = closing - np.sum(closing * z, axis=1, keepdims=True) * z
    c = c / np.linalg.norm(c, axis=1, keepdims=True)
    if closing_is_x:
        x = c
        y = np.cross(z, x)
    else:
        y = c
        x = np.cross(y, z)
    return np.stack([x, y, z], axis=2)


def _with_both_signs(*arrays: np.ndarray) -> tuple[np.ndarray, ...]:
    """Repeat every row twice; the last array (the closing axis) gets + then - sign."""
    out = [np.repeat(a, 2, axis=0) for a in arrays]
    sign = np.tile([1.0, -1.0], len(arrays[-1]))
    out[-1] = out[-1] * sign[:, None]
    return tuple(out)


def sample_node(
    box: OrientedBox,
    grasp_type: Any,
    params: SamplingParams | None = None,
    usable: Sequence[np.ndarray] | None = None,
) -> NodeSamples:
    """Samples of the enclosing surface of ``box`` for ``grasp_type``, in the box frame.

    usable: the usable sub-faces (list of 6 bool arrays, see
    :func:`~pregrasp_core.facemask.usable_subfaces`); ``None`` = every sub-face. Every sample
    comes twice, with the hand rolled by 180 degrees about its approach (the closing axis with
    both signs), so that the set does not depend on the sign convention of the box axes.
    """
    params = SamplingParams() if params is None else params
    gt = _type_str(grasp_type)
    scheme = subface_scheme(gt)
    h = box.half_extents
    step = params.interval
    pos, app, clo, face, sub, surf, aim = [], [], [], [], [], [], []

    def _keep(f: int, s: np.ndarray) -> np.ndarray:
        return np.ones(len(s), bool) if usable is None else np.asarray(usable[f], bool)[s]

    if gt in ("spherical", "two_finger_tip"):
        radius = float(np.linalg.norm(h))
        for f in range(6):
            a = FACE_AXIS[f]
            r_ax, u_ax, n_ax = FACE_RIGHT[f], FACE_UP[f], FACE_NORMAL[f]
            hr, hu = float(np.abs(r_ax) @ h), float(np.abs(u_ax) @ h)
            tr = _grid(np.arctan2(hr, h[a]), step / max(radius, GEOM_EPS))
            tu = _grid(np.arctan2(hu, h[a]), step / max(radius, GEOM_EPS))
            TR, TU = np.meshgrid(tr, tu, indexing="ij")
            tan_r, tan_u = np.tan(TR.ravel()), np.tan(TU.ravel())
            d = n_ax + tan_r[:, None] * r_ax + tan_u[:, None] * u_ax  # (m, 3) unnormalised
            d = d / np.linalg.norm(d, axis=1, keepdims=True)
            # exit point of the ray from the centre through face f: n . p = h_a
            s = scheme.cell(f, tan_r * h[a], tan_u * h[a], hr, hu)
            keep = _keep(f, s)
            d, s = d[keep], s[keep]
            # closing axis: spherical -> hand y along the face's longer in-plane box axis;
            # two-finger tip -> the pinch (hand x) across the face's shorter in-plane axis
            inplane = np.sort([int(np.argmax(np.abs(r_ax))), int(np.argmax(np.abs(u_ax)))])
            ref_axis = inplane[0] if gt == "spherical" else inplane[1]
            ref = np.tile(np.eye(3)[ref_axis], (len(d), 1))
            pos.append(d * (radius + params.standoff))
            app.append(-d)
            clo.append(ref)
            face.append(np.full(len(d), f))
            sub.append(s)
            surf.append(np.zeros(len(d), int))
            aim.append(np.zeros((len(d), 3)))
    elif gt == "cylindrical":
        radius = float(np.hypot(h[1], h[2]))
        xs = _grid(h[0], step)
        for f in range(2, 6):  # side faces: radial approach towards the axis
            a = FACE_AXIS[f]
            u_ax, n_ax = FACE_UP[f], FACE_NORMAL[f]
            hu = float(np.abs(u_ax) @ h)
            tu = _grid(np.arctan2(hu, h[a]), step / max(radius, GEOM_EPS))
            X, TU = np.meshgrid(xs, tu, indexing="ij")
            x, tan_u = X.ravel(), np.tan(TU.ravel())
            d = n_ax + tan_u[:, None] * u_ax
            d = d / np.linalg.norm(d, axis=1, keepdims=True)
            right = x * FACE_RIGHT[f][0]  # 'right' of a side face is +-axis 0
            s = scheme.cell(f, right, tan_u * h[a], h[0], hu)
            keep = _keep(f, s)
            d, s, x = d[keep], s[keep], x[keep]
            on_axis = np.zeros((len(d), 3))
            on_axis[:, 0] = x
            pos.append(on_axis + d * (radius + params.standoff))
            app.append(-d)
            clo.append(np.cross(d, np.eye(3)[0]))  # hand x along the cylinder axis
            face.append(np.full(len(d), f))
            sub.append(s)
            surf.append(np.full(len(d), 1))
            aim.append(on_axis)
        for f in (0, 1):  # caps: axial approach through the centre, closing along axes 1 and 2
            s = np.zeros(2, dtype=np.int64)
            keep = _keep(f, s)
            n_ax = FACE_NORMAL[f]
            p = np.tile(n_ax * (h[0] + params.standoff), (2, 1))[keep]
            pos.append(p)
            app.append(np.tile(-n_ax, (len(p), 1)))
            clo.append(np.eye(3)[1:3][keep])
            face.append(np.full(len(p), f))
            sub.append(s[keep])
            surf.append(np.full(len(p), 2))
            aim.append(np.zeros((len(p), 3)))
    else:  # three_finger_tip: circle in the plane of axes 0 and 1
        radius = float(np.hypot(h[0], h[1]))
        for f in range(4):
            a = FACE_AXIS[f]
            r_ax, n_ax = FACE_RIGHT[f], FACE_NORMAL[f]
            hr = float(np.abs(r_ax) @ h)
            tr = _grid(np.arctan2(hr, h[a]), step / max(radius, GEOM_EPS))
            tan_r = np.tan(tr)
            d = n_ax + tan_r[:, None] * r_ax
            d = d / np.linalg.norm(d, axis=1, keepdims=True)
            s = scheme.cell(f, tan_r * h[a], np.zeros_like(tan_r), hr, h[2])
            keep = _keep(f, s)
            d, s = d[keep], s[keep]
            pos.append(d * (radius + params.standoff))
            app.append(-d)
            clo.append(np.tile(np.eye(3)[2], (len(d), 1)))  # fingertips close across axis 2
            face.append(np.full(len(d), f))
            sub.append(s)
            surf.append(np.full(len(d), 3))
            aim.append(np.zeros((len(d), 3)))

    cat = [np.concatenate(v, axis=0) for v in (pos, app, face, sub, surf, aim, clo)]
    P, A, F, S, U, M, C = _with_both_signs(*cat)
    T = np.tile(np.eye(4), (len(P), 1, 1))
    if len(P):
        T[:, :3, :3] = _frames(A, C, closing_is_x=(gt == "two_finger_tip"))
        T[:, :3, 3] = P
    return NodeSamples(
        T_box_grasp=T,
        face=F.astype(np.int64),
        subface=S.astype(np.int64),
        surface=U.astype(np.int64),
        aim=M,
    )


# ----------------------------------------------------------------------------- the pool


@dataclass(frozen=True)
class PreGrasp:
    """One pre-grasp: where the open hand starts and how it is shaped."""

    T_world_hand: np.ndarray
    """(4, 4) float64: pose of the hand's root link (palm) in the world."""
    approach: np.ndarray
    """(3,) float64, unit, world: the approach direction (the hand's +z axis)."""
    grasp_type: str
    """The grasp type (a :class:`~pregrasp_core.shape.GraspType` value)."""
    spread: float
    """Radians: the spread of the two spreading fingers in the preshape."""
    q: np.ndarray
    """(J,) float64, radians: preshape joint positions in ``Hand.joint_names`` order."""
    node: int
    """Id of the tree node the pre-grasp was sampled for."""
    face: int
    """Face of that node's box (see ``docs/conventions.md``)."""
    subface: int
    """Sub-face of that face (``row * n_cols + col``)."""
    surface: str
    """The enclosing-surface patch (one of :data:`SURFACES`)."""
    backoff: float = 0.0
    """Metres the hand was moved back along its approach from the enclosing surface."""


@dataclass(frozen=True)
class PreGraspPool:
    """All pre-grasps of an object, stacked (P pre-grasps, J actuated joints)."""

    T_world_hand: np.ndarray
    """(P, 4, 4) float64: hand (palm) poses in the world."""
    approach: np.ndarray
    """(P, 3) float64, unit, world: approach directions (= hand +z)."""
    grasp_type: np.ndarray
    """(P,) str: grasp types (:data:`GRASP_TYPES` values)."""
    spread: np.ndarray
    """(P,) float64, radians: spread of the preshape."""
    q: np.ndarray
    """(P, J) float64, radians: preshape joint positions in ``joint_names`` order."""
    node: np.ndarray
    """(P,) int64: tree node of each pre-grasp."""
    face: np.ndarray
    """(P,) int64: face of the node's box."""
    subface: np.ndarray
    """(P,) int64: sub-face of that face."""
    surface: np.ndarray
    """(P,) int64: index into :data:`SURFACES`."""
    joint_names: tuple[str, ...]
    """Names of the J joints of ``q``."""
    backoff: np.ndarray | None = None
    """(P,) float64, metres: how far the hand was moved back along its approach from the
    enclosing surface to clear the table and the cloud (``None`` = zeros)."""
    candidates: tuple[int, ...] = ()
    """Ids of the nodes that were sampled."""
    fallback: dict[int, str] = field(default_factory=dict)
    """Node id -> the grasp type used instead of the node's own, for the candidates whose own
    type left no pre-grasp (see ``SamplingParams.fallback``)."""
    dropped: dict[str, int] = field(default_factory=dict)
    """Number of samples dropped per reason (keys of :data:`DROP_REASONS`)."""

    def __post_init__(self) -> None:
        P = len(self.node)
        if self.backoff is None:
            object.__setattr__(self, "backoff", np.zeros(P))
        shapes = {
            "backoff": (P,),
            "T_world_hand": (P, 4, 4),
            "approach": (P, 3),
            "grasp_type": (P,),
            "spread": (P,),
            "node": (P,),
            "face": (P,),
            "subface": (P,),
            "surface": (P,),
            "q": (P, len(self.joint_names)),
        }
        for name, shp in shapes.items():
            got = np.shape(getattr(self, name))
            if got != shp:
                raise ValueError(f"PreGraspPool.{name} must have shape {shp}, got {got}")

    def __len__(self) -> int:
        return int(len(self.node))

    def __getitem__(self, i: int) -> PreGrasp:
        i = int(i)
        if not -len(self) <= i < len(self):
            raise IndexError(f"pre-grasp index {i} out of range for a pool of {len(self)}")
        return PreGrasp(
            T_world_hand=self.T_world_hand[i].copy(),
            approach=self.approach[i].copy(),
            grasp_type=str(self.grasp_type[i]),
            spread=float(self.spread[i]),
            q=self.q[i].copy(),
            node=int(self.node[i]),
            face=int(self.face[i]),
            subface=int(self.subface[i]),
            surface=SURFACES[int(self.surface[i])],
            backoff=float(self.backoff[i]),
        )

    def __iter__(self):
        return (self[i] for i in range(len(self)))

    def select(self, index: np.ndarray) -> PreGraspPool:
        """The pool restricted to ``index`` (bool mask (P,) or integer indices)."""
        idx = np.asarray(index)
        return replace(
            self,
            T_world_hand=self.T_world_hand[idx],
            approach=self.approach[idx],
            grasp_type=self.grasp_type[idx],
            spread=self.spread[idx],
            q=self.q[idx],
            node=self.node[idx],
            face=self.face[idx],
            subface=self.subface[idx],
            surface=self.surface[idx],
            backoff=self.backoff[idx],
            dropped=dict(self.dropped),
            fallback=dict(self.fallback),
        )

    def filter(
        self, grasp_type: Any = None, node: int | Sequence[int] | None = None
    ) -> PreGraspPool:
        """The pre-grasps of one grasp type and/or node(s) (``None`` = any)."""
        keep = np.ones(len(self), dtype=bool)
        if grasp_type is not None:
            keep &= self.grasp_type == _type_str(grasp_type)
        if node is not None:
            keep &= np.isin(self.node, np.atleast_1d(np.asarray(node, dtype=np.int64)))
        return self.select(keep)

    def counts(self) -> dict[str, dict]:
        """Pool size per node and per grasp type."""
        nodes, n_counts = np.unique(self.node, return_counts=True)
        types, t_counts = np.unique(self.grasp_type, return_counts=True)
        return {
            "per_node": {int(k): int(v) for k, v in zip(nodes, n_counts, strict=True)},
            "per_type": {str(k): int(v) for k, v in zip(types, t_counts, strict=True)},
        }

    @classmethod
    def empty(cls, joint_names: Sequence[str]) -> PreGraspPool:
        """A pool with no pre-grasps."""
        J = len(joint_names)
        return cls(
            T_world_hand=np.zeros((0, 4, 4)),
            approach=np.zeros((0, 3)),
            grasp_type=np.zeros(0, dtype="<U16"),
            spread=np.zeros(0),
            q=np.zeros((0, J)),
            node=np.zeros(0, dtype=np.int64),
            face=np.zeros(0, dtype=np.int64),
            subface=np.zeros(0, dtype=np.int64),
            surface=np.zeros(0, dtype=np.int64),
            joint_names=tuple(joint_names),
            dropped={r: 0 for r in DROP_REASONS},
        )

    def to_dict(self) -> dict:
        """JSON-ready dict for the ``pool`` section of the result file."""
        names = list(self.joint_names)
        return {
            "count": len(self),
            "candidates": list(self.candidates),
            "dropped": {k: int(v) for k, v in self.dropped.items()},
            "fallback": {str(k): v for k, v in self.fallback.items()},
            **self.counts(),
            "pregrasps": [
                {
                    "index": i,
                    "T_world_hand": self.T_world_hand[i].tolist(),
                    "approach": self.approach[i].tolist(),
                    "grasp_type": str(self.grasp_type[i]),
                    "spread": float(self.spread[i]),
                    "node": int(self.node[i]),
                    "face": int(self.face[i]),
                    "subface": int(self.subface[i]),
                    "surface": SURFACES[int(self.surface[i])],
                    "backoff": float(self.backoff[i]),
                    "preshape": dict(zip(names, map(float, self.q[i]), strict=True)),
                }
                for i in range(len(self))
            ],
        }


def _concat_pools(pools: list[PreGraspPool], joint_names: Sequence[str]) -> PreGraspPool:
    if not pools:
        return PreGraspPool.empty(joint_names)
    return PreGraspPool(
        T_world_hand=np.concatenate([p.T_world_hand for p in pools]),
        approach=np.concatenate([p.approach for p in pools]),
        grasp_type=np.concatenate([p.grasp_type for p in pools]).astype("<U16"),
        spread=np.concatenate([p.spread for p in pools]),
        q=np.concatenate([p.q for p in pools]),
        node=np.concatenate([p.node for p in pools]),
        face=np.concatenate([p.face for p in pools]),
        subface=np.concatenate([p.subface for p in pools]),
        surface=np.concatenate([p.surface for p in pools]),
        backoff=np.concatenate([p.backoff for p in pools]),
        joint_names=tuple(joint_names),
    )


def build_pool(
    points: np.ndarray,
    tree: BoxTree,
    shapes: Sequence[NodeShape],
    masks: FaceMasks,
    hand: Any,
    params: SamplingParams | None = None,
    traversal: Traversal | None = None,
    shape_params: ShapeParams | None = None,
) -> PreGraspPool:
    """The pre-grasp pool of an object.

    points: (N, 3) the cloud (world frame) for the collision filter; tree, shapes, masks: the
    decomposition, its shapes and face masks (``masks.support`` is the support plane or None);
    hand: the ``pregrasp_core.hand.Hand``; traversal: the candidates (computed with
    :func:`traverse` when ``None``).
    """
    params = SamplingParams() if params is None else params
    pts = as_points(points)
    if traversal is None:
        traversal = traverse(tree, shapes, hand, params, shape_params)
    joint_names = tuple(hand.joint_names)
    dropped = {r: 0 for r in DROP_REASONS}
    kd = cKDTree(pts) if len(pts) else None
    # the types each candidate may use, in order: its own, then (fallback) the others that fit
    queue: dict[int, list[str]] = {}
    for i in traversal.candidates:
        own = _type_str(shapes[i].grasp_type)
        queue[i] = [own]
        if params.fallback:
            queue[i] += [
                t
                for t in FALLBACK_ORDER
                if t != own
                and grip_width(tree.nodes[i].box, t)
                <= float(hand.aperture(t)) * params.aperture_scale
            ]
    kept: list[PreGraspPool] = []
    fallback: dict[int, str] = {}
    todo = list(traversal.candidates)
    for attempt in range(len(GRASP_TYPES)):  # own type, then up to 3 fallbacks
        pools = [
            _node_pool(tree.nodes[i], queue[i][attempt], masks, hand, params, dropped)
            for i in todo
            if attempt < len(queue[i])
        ]
        got = _clear_the_hand(
            _concat_pools(pools, joint_names), hand, pts, kd, masks.support, params, dropped
        )
        kept.append(got)
        placed = set(np.unique(got.node).tolist())
        if attempt > 0:
            fallback.update({i: queue[i][attempt] for i in placed})
        todo = [i for i in todo if i not in placed and attempt + 1 < len(queue[i])]
        if not todo:
            break
    pool = _concat_pools(kept, joint_names)
    order = np.lexsort((np.arange(len(pool)), pool.node))  # group by node, stable
    pool = replace(
        pool.select(order), candidates=traversal.candidates, dropped=dropped, fallback=fallback
    )
    logger.info("pool: %d pre-grasps, dropped %s, fallback %s", len(pool), dropped, fallback)
    return pool


def _node_pool(
    nd: Any,
    gt: str,
    masks: FaceMasks,
    hand: Any,
    params: SamplingParams,
    dropped: dict[str, int],
) -> PreGraspPool:
    """The samples of one node for one grasp type on its usable sub-faces, as a pool."""
    every = sample_node(nd.box, gt, params)
    use = usable_subfaces(masks.blocked[nd.id], gt)
    table = np.zeros((6, max(len(u) for u in use) or 1), dtype=bool)  # (6, S_max) usable
    for f, u in enumerate(use):
        table[f, : len(u)] = u
    keep = table[every.face, every.subface]  # (M,)
    ok = replace(
        every,
        T_box_grasp=every.T_box_grasp[keep],
        face=every.face[keep],
        subface=every.subface[keep],
        surface=every.surface[keep],
        aim=every.aim[keep],
    )
    dropped["blocked_subface"] += int(np.count_nonzero(~keep))
    M = len(ok.face)
    # the samples place the hand's grasp centre (a point of the palm plane, hand frame);
    # the hand's origin sits at -grasp_center from it
    T_grasp_hand = np.eye(4)
    T_grasp_hand[:3, 3] = -np.asarray(hand.grasp_center(gt), dtype=np.float64)
    T = nd.box.T_world_box @ ok.T_box_grasp @ T_grasp_hand  # (M, 4, 4)
    q = np.asarray(hand.preshape(gt), dtype=np.float64)
    return PreGraspPool(
        T_world_hand=T,
        approach=T[:, :3, 2].copy(),
        grasp_type=np.full(M, gt, dtype="<U16"),
        spread=np.full(M, float(hand.spread_for(gt))),
        q=np.tile(q, (M, 1)),
        node=np.full(M, nd.id, dtype=np.int64),
        face=ok.face,
        subface=ok.subface,
        surface=ok.surface,
        joint_names=tuple(hand.joint_names),
    )


def _clear_the_hand(
    pool: PreGraspPool,
    hand: Any,
    points: np.ndarray,
    kd: cKDTree | None,
    support: SupportPlane | None,
    params: SamplingParams,
    dropped: dict[str, int],
) -> PreGraspPool:
    """Back every pre-grasp off along its approach line by the smallest multiple of
    ``backoff_step`` (up to ``max_backoff``) at which its open hand is above the support plane
    and holds no cloud point, provided the hand is also clear at ``max_backoff`` (where the
    approach starts from); drop it otherwise (counted in ``dropped``). Levels are tested in the
    order 0, ``max_backoff``, then the ones between, so hopeless pre-grasps cost two tests."""
    P = len(pool)
    if P == 0:
        return pool
    step, n_levels = params.backoff_step, int(np.floor(params.max_backoff / params.backoff_step))
    levels = np.arange(n_levels + 1) * step  # (K,) candidate back-offs, metres
    first = np.zeros(P, dtype=np.int64)  # first level the support allows
    if support is not None:
        low = hand_min_height(hand, pool, support) - params.support_margin  # (P,) above plane
        down = -(pool.approach @ support.normal)  # (P,) > 0: backing off raises the hand
        with np.errstate(divide="ignore", invalid="ignore"):
            need = np.where(low >= 0, 0.0, np.where(down > 1e-9, -low / down, np.inf))
        first = np.ceil(need / step - 1e-6).astype(np.float64)  # 1e-6: round-off
        no_room = ~(first <= n_levels)
        dropped["support"] += int(np.count_nonzero(no_room))
        first = np.where(no_room, n_levels + 1, first).astype(np.int64)
    backoff = np.full(P, np.nan)
    cells: dict = {}  # link cells per preshape, shared by the back-off levels
    hopeless = np.zeros(P, dtype=bool)  # still colliding at the largest back-off

    def test(idx: np.ndarray, k: int) -> np.ndarray:
        T = pool.T_world_hand[idx].copy()
        T[:, :3, 3] -= levels[k] * pool.approach[idx]
        return hand_hits_points(
            hand, T, pool.grasp_type[idx], pool.q[idx], points, kd, params.collision_margin, cells
        )

    # levels in the order 0, then the last (to drop hopeless ones at once), then 1, 2, ...
    order = [0, n_levels] + list(range(1, n_levels)) if n_levels > 0 else [0]
    for k in order:  # loop over the few back-off levels
        todo = np.flatnonzero((first <= k) & np.isnan(backoff) & ~hopeless)
        if len(todo) == 0:
            continue
        hit = test(todo, k)
        if k == n_levels and n_levels > 0:
            hopeless[todo[hit]] = True
            # free at the largest back-off: placed there unless a smaller level also is
            free_last = todo[~hit]
            backoff[free_last] = -1.0  # marker: free at the last level, smaller ones untested
            continue
        done = todo[~hit]
        backoff[done] = levels[k]
    # the marked ones get the smallest free level >= their first, scanning 1 .. n_levels - 1
    marked = np.flatnonzero(backoff == -1.0)
    backoff[marked] = np.nan
    for k in range(1, n_levels):
        todo = marked[(first[marked] <= k) & np.isnan(backoff[marked])]
        if len(todo) == 0:
            continue
        backoff[todo[~test(todo, k)]] = levels[k]
    rest = marked[np.isnan(backoff[marked])]
    backoff[rest] = levels[n_levels] if n_levels > 0 else np.nan
    placed = ~np.isnan(backoff)
    dropped["object_collision"] += int(np.count_nonzero(~placed & (first <= n_levels)))
    out = pool.select(placed)
    T = out.T_world_hand.copy()
    T[:, :3, 3] -= backoff[placed][:, None] * out.approach
    return replace(out, T_world_hand=T, backoff=backoff[placed])


# ----------------------------------------------------------------------------- hand geometry


def hand_corners(hand: Any, q: np.ndarray) -> np.ndarray:
    """(8 L, 3) corners of all the links' collision boxes at configuration ``q`` (J,), hand
    frame."""
    Tb = hand.box_poses(np.asarray(q, dtype=np.float64))  # (L, 4, 4)
    k = np.arange(8)
    signs = np.stack([(k >> 0) & 1, (k >> 1) & 1, (k >> 2) & 1], axis=1) * 2.0 - 1.0  # (8, 3)
    local = signs[None] * hand.link_box_half[:, None, :]  # (L, 8, 3)
    return (np.einsum("lij,lkj->lki", Tb[:, :3, :3], local) + Tb[:, None, :3, 3]).reshape(-1, 3)


def hand_min_height(hand: Any, pool: PreGraspPool, support: SupportPlane) -> np.ndarray:
    """(P,) metres: height above ``support`` of the lowest corner of the links' collision boxes
    of each pre-grasp's open hand (negative: the hand reaches below the plane)."""
    out = np.zeros(len(pool))
    for gt in np.unique(pool.grasp_type):  # loop over the (at most 4) preshapes
        sel = np.flatnonzero(pool.grasp_type == gt)
        corners = hand_corners(hand, pool.q[sel[0]])  # (C, 3) hand frame
        T = pool.T_world_hand[sel]  # (m, 4, 4)
        up_hand = np.einsum("mji,j->mi", T[:, :3, :3], support.normal)  # (m, 3) up in hand frames
        h = corners @ up_hand.T + (T[:, :3, 3] @ support.normal)[None, :]  # (C, m) heights
        out[sel] = h.min(axis=0) - support.height
    return out


def link_cells(hand: Any, q: np.ndarray, margin: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
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
    hand: Any,
    T_world_hand: np.ndarray,
    grasp_type: np.ndarray,
    q: np.ndarray,
    points: np.ndarray,
    kd: cKDTree | None = None,
    margin: float = 0.0,
    cells: dict | None = None,
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
