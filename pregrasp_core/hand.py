"""The three-finger underactuated hand: URDF model, batch forward kinematics, preshapes,
apertures, finger flexion planes, the planar closing model, collision geometry and point-in-link
queries.

Frames and names (see ``docs/hand.md`` and ``docs/conventions.md``, "The hand"):

- Hand frame = the URDF root link ``palm``: origin at the centre of the palm's inner face,
  +z = approach direction out of the palm, thumb on -y, spreading fingers f1 (+x) and f2 (-x)
  on +y. Every ``T_hand_link`` here is a link pose in this frame.
- Finger frame (every finger link): ``z_f`` along the straight finger, ``x_f`` = the closing
  direction, ``y_f`` = normal of the flexion plane; flexion joints turn about ``+y_f`` and a
  positive angle closes the finger.
- Flexion-plane 2D frame of a finger: origin at the finger's first flexion joint (``*_j1``),
  2D x = ``u`` = along the straight finger (= hand +z), 2D y = ``v`` = the closing direction.
  In it the middle link spans ``[0, Lm]`` along ``(cos q1, sin q1)`` and the distal link starts at
  ``Lm (cos q1, sin q1)`` along ``(cos(q1 + q2), sin(q1 + q2))``; the palm's inner face is the
  line ``x = -Lk``.

Joint vector ``q`` (J = 7): the actuated joints in yourdfpy's ``actuated_joint_names`` order,
``thumb_j1, thumb_j2, f1_spread, f1_j1, f1_j2, f2_j1, f2_j2``; ``f2_spread`` mimics
``f1_spread`` (multiplier 1, mirrored axis) and is not part of ``q``.
"""

from __future__ import annotations

import functools
import logging
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import fcl
import numpy as np
import trimesh
import yourdfpy

from .box import OrientedBox
from .errors import HandModelError
from .paths import HAND_URDF
from .shape import GRASP_TYPES
from .tolerances import (
    GEOM_EPS,
    HAND_CLOSING_ANGLE_TOL,
    SAT_ABS_ROTATION_EPS,
    SELF_COLLISION_SAT_MARGIN,
)

logger = logging.getLogger(__name__)

FINGER_NAMES: tuple[str, ...] = ("thumb", "f1", "f2")
"""Finger names; finger ``n`` has links ``n_knuckle, n_middle, n_distal`` and joints
``n_j1, n_j2`` (and ``n_spread`` for f1, f2)."""

DEFAULT_COUPLING: float = 1.0
"""Closing model: distal joint speed / proximal joint speed while both close together
(tendon coupling; 1.0 = both joints close at the same rate)."""

DEFAULT_CLOSING_STEPS: int = 64
"""Closing model: samples along each closing phase before the first touching step is refined."""

_REFINE_SAMPLES: int = 32
"""Closing model: most samples per refinement level of the bracket around the first touch."""

_SWEEP_CHUNK: int = 8
"""Closing model: samples in the first chunk of a phase's sweep (the chunks double; the sweep
stops at the first chunk that touches)."""

_REFINE_BUDGET: int = 2000
"""Closing model: a refinement level evaluates about this many (sample, point) pairs: many
samples per level for small slices (few numpy calls), plain bisection for large ones."""

_PAIR_CHUNK: int = 1_000_000
"""Batched point-in-link counts move at most this many (point, hand) pairs at once (memory)."""

_VOXEL: float = 0.004
"""Voxel size (metres) of the hand occupancy grid that culls points before exact box tests."""

_GRID_MAX_CONFIGS: int = 8
"""Batched counts build an occupancy grid per distinct configuration only up to this many
distinct configurations (a pre-grasp pool has one per grasp type); beyond it they cull by each
hand's bounding box."""


# --------------------------------------------------------------------------------------------
# Small value types
# --------------------------------------------------------------------------------------------


def grasp_type_name(grasp_type: object) -> str:
    """The grasp type as its string value; accepts the strings of :data:`GRASP_TYPES` and the
    ``GraspType`` str enum. Raises ``ValueError`` for anything else."""
    value = getattr(grasp_type, "value", grasp_type)
    name = str(value)
    if name not in GRASP_TYPES:
        raise ValueError(f"unknown grasp type {grasp_type!r}; expected one of {GRASP_TYPES}")
    return name


@dataclass(frozen=True)
class Finger:
    """One finger of the hand and its planar geometry (read from the URDF)."""

    name: str
    """"thumb", "f1" or "f2"."""
    links: tuple[str, str, str]
    """(knuckle, middle, distal) link names."""
    flexion_joints: tuple[str, str]
    """(proximal, distal) flexion joint names, e.g. ("f1_j1", "f1_j2")."""
    flex_index: tuple[int, int]
    """Positions of the two flexion joints in ``Hand.joint_names``."""
    spread_joint: str | None
    """The URDF joint that spreads this finger (``f2_spread`` is a mimic of ``f1_spread``);
    None for the thumb, whose knuckle is fixed to the palm."""
    knuckle_length: float
    """Lk, metres: height of the first flexion joint above the palm's inner face."""
    middle_length: float
    """Lm, metres: first to second flexion joint."""
    distal_length: float
    """Ld, metres: second flexion joint to the fingertip."""
    thickness: float
    """Extent of the middle and distal links along the closing direction (metres)."""
    width: float
    """Extent of the links along the flexion-plane normal (metres)."""
    lower: np.ndarray
    """(2,) lower limits of the flexion joints (radians)."""
    upper: np.ndarray
    """(2,) upper limits of the flexion joints (radians)."""


@dataclass(frozen=True)
class FlexionPlane:
    """The plane in which a finger's middle and distal links move, in the hand frame."""

    origin: np.ndarray
    """(3,) position of the finger's first flexion joint (2D origin), hand frame."""
    u: np.ndarray
    """(3,) unit vector along the straight finger (2D x axis); equal to hand +z."""
    v: np.ndarray
    """(3,) unit closing direction (2D y axis)."""
    normal: np.ndarray
    """(3,) unit normal ``u x v`` (the flexion joints' axis)."""

    @property
    def T_hand_plane(self) -> np.ndarray:
        """(4, 4) pose of the plane frame (columns u, v, normal; origin) in the hand frame."""
        T = np.eye(4)
        T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = self.u, self.v, self.normal, self.origin
        return T

    def to_plane(self, p_hand: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Hand-frame points (N, 3) -> (2D coordinates (N, 2), signed offsets along ``normal``
        (N,)). The slice of a finger is the points with ``|offset| <= width / 2``."""
        p = _as_n3(p_hand, "p_hand")
        d = p - self.origin
        return np.stack([d @ self.u, d @ self.v], axis=1), d @ self.normal

    def to_hand(self, p_2d: np.ndarray, offset: np.ndarray | float = 0.0) -> np.ndarray:
        """2D plane points (N, 2) (plus optional offsets along the normal) -> hand frame (N, 3)."""
        p = np.asarray(p_2d, dtype=np.float64)
        if p.ndim != 2 or p.shape[1] != 2:
            raise ValueError(f"p_2d must have shape (N, 2), got {p.shape}")
        off = np.broadcast_to(np.asarray(offset, dtype=np.float64), (p.shape[0],))
        return self.origin + p[:, :1] * self.u + p[:, 1:2] * self.v + off[:, None] * self.normal


@dataclass(frozen=True)
class FingerContact:
    """A contact found by the planar closing model."""

    link: str
    """The touching link (``*_middle`` or ``*_distal``)."""
    point: np.ndarray
    """(2,) the touched point in the finger's flexion-plane frame."""
    index: int
    """Index of the touched point in the ``points_2d`` given to :meth:`Hand.close_finger`."""


@dataclass(frozen=True)
class FingerClosing:
    """Result of closing one finger in its flexion plane (:meth:`Hand.close_finger`)."""

    finger: str
    """Finger name."""
    q: np.ndarray
    """(2,) final flexion angles (proximal, distal), radians, within the joint limits."""
    contact_link: str | None
    """Link of the contact that stopped the finger: the distal link if it touched, else the
    middle link if it touched, else None (no object contact)."""
    contact_point: np.ndarray | None
    """(2,) the point of that contact in the flexion-plane frame, or None."""
    contact_index: int | None
    """Index of that point in ``points_2d``, or None."""
    contacts: tuple[FingerContact, ...]
    """All object contacts in the order they happened (middle first, then distal)."""
    stopped_middle: bool
    """The middle link touched an object point, so the proximal joint stopped there and the
    distal joint closed on alone."""
    stopped_distal: bool
    """The distal link touched an object point and stopped the finger."""
    palm_stop: bool
    """A link reached the palm's inner face (no object contact there) and stopped."""
    at_limits: bool
    """The finger ended at its upper joint limits without any stop."""
    start_in_contact: bool
    """A moving link already touched the points at ``q_start``."""
    path: np.ndarray
    """(S, 2) flexion angles from ``q_start`` to ``q`` (the sampled steps, for animation)."""


# --------------------------------------------------------------------------------------------
# Helpers
# --------------------------------------------------------------------------------------------


def _all3(b: np.ndarray) -> np.ndarray:
    """``np.all(b, axis=-1)`` for a last axis of 3, several times faster."""
    return b[..., 0] & b[..., 1] & b[..., 2]


def _as_n3(p: np.ndarray, name: str) -> np.ndarray:
    arr = np.asarray(p, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"{name} must have shape (N, 3), got {arr.shape}")
    return arr


@dataclass(frozen=True)
class _Joint:
    name: str
    parent: str
    child: str
    origin: np.ndarray  # (4, 4) T_parent_jointframe
    axis: np.ndarray | None  # (3,) unit, None for fixed joints
    source: int  # index in q of the driving actuated joint, -1 for fixed
    multiplier: float
    offset: float


def _circumcircle_2d(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> tuple[np.ndarray, float]:
    """Centre (2,) and radius of the circle through three 2D points."""
    d = 2.0 * (a[0] * (b[1] - c[1]) + b[0] * (c[1] - a[1]) + c[0] * (a[1] - b[1]))
    if abs(d) < GEOM_EPS:
        raise HandModelError("fingertips are collinear; cannot compute a spherical aperture")
    sa, sb, sc = a @ a, b @ b, c @ c
    ux = (sa * (b[1] - c[1]) + sb * (c[1] - a[1]) + sc * (a[1] - b[1])) / d
    uy = (sa * (c[0] - b[0]) + sb * (a[0] - c[0]) + sc * (b[0] - a[0])) / d
    center = np.array([ux, uy])
    return center, float(np.linalg.norm(center - a))


# Preshape flexion (proximal, distal) per grasp type and finger, and the spread. Opening the
# proximal joint to its lower limit (-30 deg) gives the widest enveloping preshape; the tip
# grasps keep the distal links parallel to the approach (-15 deg, +15 deg).
_OPEN_WIDE = (-np.pi / 6.0, 0.0)
_TIPS_UP = (-np.pi / 12.0, np.pi / 12.0)
_THUMB_AWAY = (-np.pi / 6.0, -np.pi / 12.0)
_PRESHAPES: dict[str, tuple[float, dict[str, tuple[float, float]]]] = {
    "cylindrical": (0.0, {"thumb": _OPEN_WIDE, "f1": _OPEN_WIDE, "f2": _OPEN_WIDE}),
    "spherical": (np.pi / 3.0, {"thumb": _OPEN_WIDE, "f1": _OPEN_WIDE, "f2": _OPEN_WIDE}),
    "three_finger_tip": (0.0, {"thumb": _TIPS_UP, "f1": _TIPS_UP, "f2": _TIPS_UP}),
    "two_finger_tip": (np.pi / 2.0, {"thumb": _THUMB_AWAY, "f1": _TIPS_UP, "f2": _TIPS_UP}),
}
_GRASP_FINGERS: dict[str, tuple[str, ...]] = {
    "cylindrical": ("thumb", "f1", "f2"),
    "spherical": ("thumb", "f1", "f2"),
    "three_finger_tip": ("thumb", "f1", "f2"),
    "two_finger_tip": ("f1", "f2"),
}


# --------------------------------------------------------------------------------------------
# The hand
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Hand:
    """The kinematic and geometric model of the hand, loaded once from its URDF.

    Build it with :meth:`Hand.load` (or the cached :func:`load_hand`)."""

    urdf_path: Path
    """The URDF file the model was read from."""
    urdf: yourdfpy.URDF = field(repr=False)
    """The yourdfpy model (scene graph built, meshes not loaded); for viewers and tests."""
    joint_names: tuple[str, ...]
    """The J actuated joints in yourdfpy's ``actuated_joint_names`` order (mimics excluded)."""
    lower: np.ndarray
    """(J,) lower joint limits (radians)."""
    upper: np.ndarray
    """(J,) upper joint limits (radians)."""
    link_names: tuple[str, ...]
    """The L links in URDF order (palm first); the column order of point-in-link queries."""
    fingers: tuple[Finger, ...]
    """Thumb, f1, f2."""
    spread_index: int
    """Position of ``f1_spread`` (the spread of both spreading fingers) in ``joint_names``."""
    link_box_T: np.ndarray = field(repr=False)
    """(L, 4, 4) ``T_link_box``: pose of each link's collision box in its link frame."""
    link_box_half: np.ndarray = field(repr=False)
    """(L, 3) half side lengths of the collision boxes (metres)."""
    link_parent: tuple[int, ...] = field(repr=False)
    """Index of each link's parent link in ``link_names`` (-1 for the palm)."""
    visual_meshes: dict[str, trimesh.Trimesh] = field(repr=False)
    """Visual mesh of each link in its link frame (visual origin applied), face-coloured."""
    _chain: tuple[_Joint, ...] = field(repr=False)

    # ---------------------------------------------------------------- loading
    @classmethod
    def load(cls, urdf_path: Path | str | None = None) -> Hand:
        """Read and check the hand URDF (default ``pregrasp_core.paths.HAND_URDF``)."""
        path = Path(HAND_URDF if urdf_path is None else urdf_path)
        if not path.is_file():
            raise HandModelError(
                f"hand URDF {path} does not exist; reinstall pregrasp or pass the path of "
                "assets/hand.urdf"
            )
        try:
            urdf = yourdfpy.URDF.load(str(path), build_scene_graph=True, load_meshes=False)
        except Exception as exc:  # yourdfpy raises many types on malformed XML
            raise HandModelError(f"cannot parse hand URDF {path}: {exc}") from exc
        if not urdf.validate():
            raise HandModelError(
                f"hand URDF {path} fails yourdfpy validation: {urdf.errors}; fix the file"
            )
        return cls._from_urdf(path, urdf)

    @classmethod
    def _from_urdf(cls, path: Path, urdf: yourdfpy.URDF) -> Hand:
        joint_names = tuple(urdf.actuated_joint_names)
        jmap = {j.name: j for j in urdf.robot.joints}
        link_names = tuple(lk.name for lk in urdf.robot.links)
        if urdf.base_link != "palm":
            raise HandModelError(
                f"hand URDF {path}: root link must be 'palm', got {urdf.base_link!r}"
            )
        lower = np.array([jmap[n].limit.lower for n in joint_names], dtype=np.float64)
        upper = np.array([jmap[n].limit.upper for n in joint_names], dtype=np.float64)

        # kinematic chain in topological order (parents before children)
        child_of = {j.child: j for j in urdf.robot.joints}
        order: list[str] = []
        seen = {"palm"}
        pending = [j for j in urdf.robot.joints]
        while pending:
            ready = [j for j in pending if j.parent in seen]
            if not ready:
                raise HandModelError(f"hand URDF {path}: joints do not form a tree from 'palm'")
            for j in ready:
                order.append(j.name)
                seen.add(j.child)
                pending.remove(j)
        chain = []
        for name in order:
            j = jmap[name]
            origin = np.eye(4) if j.origin is None else np.asarray(j.origin, dtype=np.float64)
            if j.type == "fixed":
                chain.append(_Joint(name, j.parent, j.child, origin, None, -1, 1.0, 0.0))
                continue
            if j.type != "revolute":
                raise HandModelError(f"hand URDF {path}: joint {name} must be revolute or fixed")
            axis = np.asarray(j.axis, dtype=np.float64)
            axis = axis / np.linalg.norm(axis)
            if j.mimic is not None:
                src = joint_names.index(j.mimic.joint)
                mult, off = float(j.mimic.multiplier or 1.0), float(j.mimic.offset or 0.0)
            else:
                src, mult, off = joint_names.index(name), 1.0, 0.0
            chain.append(_Joint(name, j.parent, j.child, origin, axis, src, mult, off))

        # collision boxes and visual meshes
        L = len(link_names)
        box_T = np.zeros((L, 4, 4))
        box_half = np.zeros((L, 3))
        visuals: dict[str, trimesh.Trimesh] = {}
        materials = {m.name: m for m in urdf.robot.materials}
        for i, lk in enumerate(urdf.robot.links):
            if len(lk.collisions) != 1 or lk.collisions[0].geometry.box is None:
                raise HandModelError(
                    f"hand URDF {path}: link {lk.name} needs exactly one collision <box>"
                )
            col = lk.collisions[0]
            box_T[i] = np.eye(4) if col.origin is None else col.origin
            box_half[i] = np.asarray(col.geometry.box.size, dtype=np.float64) / 2.0
            visuals[lk.name] = _load_visual(path, lk, materials)
        parent_idx = tuple(
            -1 if n == "palm" else link_names.index(child_of[n].parent) for n in link_names
        )

        fingers = []
        for fname in FINGER_NAMES:
            links = (f"{fname}_knuckle", f"{fname}_middle", f"{fname}_distal")
            flex = (f"{fname}_j1", f"{fname}_j2")
            for n in links:
                if n not in link_names:
                    raise HandModelError(f"hand URDF {path}: missing link {n}")
            for n in flex:
                if n not in joint_names:
                    raise HandModelError(f"hand URDF {path}: missing actuated joint {n}")
                if not np.allclose(jmap[n].axis, [0.0, 1.0, 0.0]):
                    raise HandModelError(f"hand URDF {path}: flexion joint {n} must turn about y")
            j1, j2 = jmap[flex[0]], jmap[flex[1]]
            mid = link_names.index(links[1])
            dist = link_names.index(links[2])
            # the planar closing model assumes: links start at their joint on the finger axis,
            # equal cross-sections, and the distal joint on the middle link's axis
            for li, length in ((mid, j2.origin[2, 3]), (dist, 2.0 * box_half[dist, 2])):
                expected = np.eye(4)
                expected[2, 3] = length / 2.0
                if not (
                    np.allclose(box_T[li], expected) and np.isclose(box_half[li, 2], length / 2)
                ):
                    raise HandModelError(
                        f"hand URDF {path}: link {link_names[li]}'s box must run from its joint "
                        "along z (origin 0 0 length/2) for the planar closing model"
                    )
            if not (
                np.allclose(box_half[mid, :2], box_half[dist, :2])
                and np.allclose(j2.origin[:3, :3], np.eye(3))
                and np.allclose(j2.origin[:2, 3], 0.0)
            ):
                raise HandModelError(
                    f"hand URDF {path}: finger {fname}: the middle and distal links must have "
                    "equal cross-sections and the distal joint must sit on the middle link's axis"
                )
            spread = f"{fname}_spread" if f"{fname}_spread" in jmap else None
            fingers.append(
                Finger(
                    name=fname,
                    links=links,
                    flexion_joints=flex,
                    flex_index=(joint_names.index(flex[0]), joint_names.index(flex[1])),
                    spread_joint=spread,
                    knuckle_length=float(j1.origin[2, 3]),
                    middle_length=float(j2.origin[2, 3]),
                    distal_length=float(box_T[dist, 2, 3] + box_half[dist, 2]),
                    thickness=float(2.0 * box_half[mid, 0]),
                    width=float(2.0 * box_half[mid, 1]),
                    lower=lower[[joint_names.index(flex[0]), joint_names.index(flex[1])]],
                    upper=upper[[joint_names.index(flex[0]), joint_names.index(flex[1])]],
                )
            )
        if "f1_spread" not in joint_names:
            raise HandModelError(f"hand URDF {path}: f1_spread must be an actuated joint")
        for arr in (lower, upper, box_T, box_half):
            arr.flags.writeable = False  # the model is immutable
        for f in fingers:
            f.lower.flags.writeable = False
            f.upper.flags.writeable = False
        hand = cls(
            urdf_path=path,
            urdf=urdf,
            joint_names=joint_names,
            lower=lower,
            upper=upper,
            link_names=link_names,
            fingers=tuple(fingers),
            spread_index=joint_names.index("f1_spread"),
            link_box_T=box_T,
            link_box_half=box_half,
            link_parent=parent_idx,
            visual_meshes=visuals,
            _chain=tuple(chain),
        )
        logger.debug("loaded hand %s: joints %s", path, joint_names)
        return hand

    # ---------------------------------------------------------------- joints
    @property
    def n_joints(self) -> int:
        """J, the number of actuated joints."""
        return len(self.joint_names)

    def _as_q(self, q: np.ndarray) -> tuple[np.ndarray, bool]:
        """Coerce ``q`` to (B, J); the flag says whether the input was a single (J,) vector."""
        arr = np.asarray(q, dtype=np.float64)
        J = self.n_joints
        if arr.ndim == 1 and arr.shape[0] == J:
            return arr[None, :], True
        if arr.ndim == 2 and arr.shape[1] == J:
            return arr, False
        raise ValueError(f"q must have shape ({J},) or (B, {J}), got {arr.shape}")

    def clamp(self, q: np.ndarray) -> np.ndarray:
        """``q`` ((J,) or (B, J)) clipped to the joint limits."""
        arr = np.asarray(q, dtype=np.float64)
        self._as_q(arr)
        return np.clip(arr, self.lower, self.upper)

    def within_limits(self, q: np.ndarray, tol: float = 1e-9) -> np.ndarray:
        """Whether each configuration respects the limits: bool () for (J,), (B,) for (B, J)."""
        Q, single = self._as_q(q)
        ok = np.all((Q >= self.lower - tol) & (Q <= self.upper + tol), axis=1)
        return ok[0] if single else ok

    def full_cfg(self, q: np.ndarray) -> dict[str, float]:
        """Joint name -> value for every moving joint (actuated and mimic), e.g. for yourdfpy's
        and viser's ``update_cfg`` or the result file."""
        Q, single = self._as_q(q)
        if not single:
            raise ValueError(f"full_cfg takes one configuration ({self.n_joints},), got {Q.shape}")
        out = {}
        for j in self._chain:
            if j.axis is not None:
                out[j.name] = float(j.multiplier * Q[0, j.source] + j.offset)
        return out

    def finger(self, finger: str | Finger) -> Finger:
        """The :class:`Finger` with this name (or the finger itself)."""
        if isinstance(finger, Finger):
            return finger
        for f in self.fingers:
            if f.name == finger:
                return f
        raise ValueError(f"unknown finger {finger!r}; expected one of {FINGER_NAMES}")

    def with_flexion(self, q: np.ndarray, finger: str | Finger, q_flex: np.ndarray) -> np.ndarray:
        """A copy of ``q`` (J,) with the finger's two flexion joints set to ``q_flex`` (2,)."""
        Q, single = self._as_q(q)
        if not single:
            raise ValueError(f"q must have shape ({self.n_joints},), got {Q.shape}")
        f = self.finger(finger)
        out = Q[0].copy()
        out[list(f.flex_index)] = np.asarray(q_flex, dtype=np.float64).reshape(2)
        return out

    # ---------------------------------------------------------------- kinematics
    def fk_array(self, q: np.ndarray) -> np.ndarray:
        """Link poses ``T_hand_link`` as one array: (B, L, 4, 4) for ``q`` (B, J), in
        ``link_names`` order; (L, 4, 4) for ``q`` (J,). Vectorised over configurations."""
        Q, single = self._as_q(q)
        R, t = self._fk_rt(Q)
        B, L = R.shape[0], R.shape[1]
        out = np.zeros((B, L, 4, 4))
        out[:, :, :3, :3] = R
        out[:, :, :3, 3] = t
        out[:, :, 3, 3] = 1.0
        return out[0] if single else out

    def _fk_rt(self, Q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rotations (B, L, 3, 3) and translations (B, L, 3) of every link for ``Q`` (B, J).

        Per joint: ``R_child = R_parent R_origin R_axis(angle)`` with Rodrigues' formula written
        as ``A R_axis = A + sin(angle) A K + (1 - cos(angle)) A K^2`` (A = R_parent R_origin,
        K the axis' cross-product matrix), so every product is a (3B, 3) x (3, 3) matrix product;
        the rotation about the joint origin leaves the translation alone."""
        B = Q.shape[0]
        L = len(self.link_names)
        R = np.empty((L, B, 3, 3))  # link-major so that every R[i] is contiguous
        t = np.empty((L, B, 3))
        root = self.link_names.index("palm")
        R[root] = np.eye(3)  # the palm (root) is the hand frame
        t[root] = 0.0
        for j, (ip, ic, K, K2) in zip(self._chain, self._chain_index, strict=True):
            Rp = R[ip].reshape(3 * B, 3)  # rows of the parent rotations
            A = Rp @ j.origin[:3, :3]  # (3B, 3): R_parent R_origin
            t[ic] = t[ip] + (Rp @ j.origin[:3, 3]).reshape(B, 3)
            if K is None:
                R[ic] = A.reshape(B, 3, 3)
                continue
            angle = j.multiplier * Q[:, j.source] + j.offset
            s = np.repeat(np.sin(angle), 3)[:, None]  # (3B, 1): one per row
            c1 = np.repeat(1.0 - np.cos(angle), 3)[:, None]
            R[ic] = (A + s * (A @ K) + c1 * (A @ K2)).reshape(B, 3, 3)
        return R.transpose(1, 0, 2, 3), t.transpose(1, 0, 2)

    @functools.cached_property
    def _chain_index(self) -> tuple[tuple[int, int, np.ndarray | None, np.ndarray | None], ...]:
        """Per chain joint: (parent link index, child link index, K (3, 3), K^2 (3, 3))."""
        index = {n: i for i, n in enumerate(self.link_names)}
        out = []
        for j in self._chain:
            if j.axis is None:
                out.append((index[j.parent], index[j.child], None, None))
                continue
            x, y, z = j.axis
            K = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
            out.append((index[j.parent], index[j.child], K, K @ K))
        return tuple(out)

    def fk(self, q: np.ndarray) -> dict[str, np.ndarray]:
        """Link name -> ``T_hand_link``: (B, 4, 4) for ``q`` (B, J), (4, 4) for ``q`` (J,)."""
        T = self.fk_array(q)
        return {n: T[..., i, :, :] for i, n in enumerate(self.link_names)}

    def box_poses(self, q: np.ndarray) -> np.ndarray:
        """Collision box poses ``T_hand_box``: (B, L, 4, 4) for (B, J), (L, 4, 4) for (J,)."""
        return self.fk_array(q) @ self.link_box_T

    def fingertips(self, q: np.ndarray) -> dict[str, np.ndarray]:
        """Finger name -> fingertip centre (end of the distal link on its axis) in the hand frame:
        (B, 3) for ``q`` (B, J), (3,) for (J,)."""
        T = self.fk_array(q)
        out = {}
        for f in self.fingers:
            Td = T[..., self.link_names.index(f.links[2]), :, :]
            out[f.name] = Td[..., :3, 3] + f.distal_length * Td[..., :3, 2]
        return out

    def tip_pads(self, q: np.ndarray) -> dict[str, np.ndarray]:
        """Finger name -> the fingertip's inner edge (end of the distal link, on the closing side,
        in the flexion plane): the point apertures are measured between. (3,) or (B, 3)."""
        T = self.fk_array(q)
        out = {}
        for f in self.fingers:
            Td = T[..., self.link_names.index(f.links[2]), :, :]
            out[f.name] = (
                Td[..., :3, 3]
                + f.distal_length * Td[..., :3, 2]
                + 0.5 * f.thickness * Td[..., :3, 0]
            )
        return out

    def flexion_plane(self, finger: str | Finger, spread: float = 0.0) -> FlexionPlane:
        """The finger's flexion plane in the hand frame for a spread angle (ignored for the
        thumb). Independent of the flexion angles."""
        f = self.finger(finger)
        q = np.zeros(self.n_joints)
        q[self.spread_index] = float(spread)
        T = self.fk_array(q)
        Tk = T[self.link_names.index(f.links[0])]  # knuckle frame: axes of the finger frame
        Tm = T[self.link_names.index(f.links[1])]  # origin = first flexion joint
        return FlexionPlane(
            origin=Tm[:3, 3].copy(), u=Tk[:3, 2].copy(), v=Tk[:3, 0].copy(), normal=Tk[:3, 1].copy()
        )

    # ---------------------------------------------------------------- grasp types
    def spread_for(self, grasp_type: object) -> float:
        """Spread angle (radians) of a grasp type: 0, pi/3, 0, pi/2."""
        return float(_PRESHAPES[grasp_type_name(grasp_type)][0])

    def fingers_for(self, grasp_type: object) -> tuple[Finger, ...]:
        """The fingers a grasp type closes (two-finger tip: f1 and f2; the thumb stays open)."""
        return tuple(self.finger(n) for n in _GRASP_FINGERS[grasp_type_name(grasp_type)])

    def preshape(self, grasp_type: object) -> np.ndarray:
        """(J,) the open configuration a grasp of this type starts from (see ``docs/hand.md``)."""
        spread, flex = _PRESHAPES[grasp_type_name(grasp_type)]
        q = np.zeros(self.n_joints)
        q[self.spread_index] = spread
        for f in self.fingers:
            q[list(f.flex_index)] = flex[f.name]
        return self.clamp(q)

    def aperture(self, grasp_type: object) -> float:
        """Largest object size (metres) the preshape can enclose, measured between the
        fingertips' inner edges (:meth:`tip_pads`): cylindrical and three-finger tip: the gap
        along y between the thumb and the nearer of f1/f2; two-finger tip: the gap along x
        between f1 and f2; spherical: the diameter of the circle through the three pads
        projected onto the palm plane."""
        name = grasp_type_name(grasp_type)
        return self._aperture_and_center(name)[0]

    def grasp_center(self, grasp_type: object) -> np.ndarray:
        """(3,) the point on the palm plane (z = 0), hand frame, under the centre of the space
        the preshape's fingertips enclose: align the object's centre with the line through this
        point along +z (the approach). Not the hand origin for every type (the fingers are not
        placed symmetrically about it, e.g. two-finger tip pinches at y = 0.03)."""
        name = grasp_type_name(grasp_type)
        c = self._aperture_and_center(name)[1]
        return np.array([c[0], c[1], 0.0])

    @functools.cached_property
    def _apertures(self) -> dict[str, tuple[float, np.ndarray]]:
        out = {}
        for name in GRASP_TYPES:
            pads = {k: v[:2] for k, v in self.tip_pads(self.preshape(name)).items()}
            if name in ("cylindrical", "three_finger_tip"):
                gaps = [pads[f][1] - pads["thumb"][1] for f in ("f1", "f2")]
                y_fingers = 0.5 * (pads["f1"][1] + pads["f2"][1])
                cx = (pads["thumb"][0] + pads["f1"][0] + pads["f2"][0]) / 3.0
                out[name] = (float(min(gaps)), np.array([cx, 0.5 * (y_fingers + pads["thumb"][1])]))
            elif name == "two_finger_tip":
                gap = pads["f1"][0] - pads["f2"][0]
                out[name] = (float(gap), 0.5 * (pads["f1"] + pads["f2"]))
            else:
                center, radius = _circumcircle_2d(pads["thumb"], pads["f1"], pads["f2"])
                out[name] = (2.0 * radius, center)
        return out

    def _aperture_and_center(self, name: str) -> tuple[float, np.ndarray]:
        return self._apertures[name]

    @property
    def palm_box(self) -> OrientedBox:
        """The palm's collision box in the hand frame (its top face is the plane z = 0)."""
        i = self.link_names.index("palm")
        T = self.link_box_T[i]
        return OrientedBox(
            center=T[:3, 3].copy(), rotation=T[:3, :3].copy(), extents=2.0 * self.link_box_half[i]
        )

    # ---------------------------------------------------------------- closing model
    def close_finger(
        self,
        finger: str | Finger,
        points_2d: np.ndarray,
        q_start: np.ndarray,
        n_steps: int = DEFAULT_CLOSING_STEPS,
        margin: float = 0.0,
        coupling: float = DEFAULT_COUPLING,
        palm: bool = True,
    ) -> FingerClosing:
        """Close one finger in its flexion plane against points (the slice of the object).

        ``points_2d`` (M, 2) are in the finger's flexion-plane frame (x along the straight
        finger from the first flexion joint, y the closing direction); ``q_start`` (2,) the
        flexion angles to start from (clamped to the limits). The model (DESIGN section 7):

        1. Both joints close together, the distal at ``coupling`` times the proximal rate; a
           joint that reaches its upper limit stays there while the other goes on.
        2. When the middle link touches a point (comes within ``margin`` of it), the proximal
           joint stops and the distal joint closes alone.
        3. When the distal link touches a point, the finger stops.
        4. With ``palm``, the palm's inner face (2D line x = -Lk) stops a link like a point does
           (``palm_stop``), so the model never drives the finger into the palm.

        Every phase is sampled in ``n_steps`` steps, all steps x all points at once, and the
        first touching step is refined (up to 32 samples per level, all at once) until the
        bracket is narrower than ``HAND_CLOSING_ANGLE_TOL``. The returned configuration is the
        last one at which no point is within ``margin`` of a moving link.
        """
        f = self.finger(finger)
        P = np.asarray(points_2d, dtype=np.float64)
        if P.ndim != 2 or P.shape[1] != 2:
            raise ValueError(f"points_2d must have shape (M, 2), got {P.shape}")
        q0 = np.asarray(q_start, dtype=np.float64)
        if q0.shape != (2,):
            raise ValueError(f"q_start must have shape (2,), got {q0.shape}")
        if n_steps < 1:
            raise ValueError(f"n_steps must be >= 1, got {n_steps}")
        if coupling <= 0:
            raise ValueError(f"coupling must be > 0, got {coupling}")
        q0 = np.clip(q0, f.lower, f.upper)
        geo = _FingerGeometry(f, margin, palm)
        # only points within the finger's reach from its first joint can ever be touched
        reach = f.middle_length + np.hypot(f.distal_length, 0.5 * f.thickness) + 2.0 * abs(margin)
        keep = np.flatnonzero(np.einsum("ij,ij->i", P, P) <= reach * reach)  # (M',) into P
        Pr = P[keep]

        def contact(link: str, i: int) -> FingerContact:  # i indexes Pr
            return FingerContact(link, P[keep[i]].copy(), int(keep[i]))

        # ---- phase 1: both joints close together (clipped at their limits)
        def path1(t: np.ndarray) -> np.ndarray:  # (K,) -> (K, 2)
            out = np.empty((t.shape[0], 2))
            np.minimum(q0[0] + t, f.upper[0], out=out[:, 0])
            np.minimum(q0[1] + coupling * t, f.upper[1], out=out[:, 1])
            return out

        t_end = max(f.upper[0] - q0[0], (f.upper[1] - q0[1]) / coupling, 0.0)
        ev1 = _first_event(geo, Pr, path1, t_end, n_steps, links=(True, True))
        contacts: list[FingerContact] = []
        stopped_middle = stopped_distal = palm_stop = False
        start_in_contact = ev1.k_hit == 0
        if ev1.t_hit is None:  # no stop: both joints end at their limits
            path = path1(ev1.t_samples)
            return FingerClosing(
                finger=f.name,
                q=path[-1].copy(),
                contact_link=None,
                contact_point=None,
                contact_index=None,
                contacts=(),
                stopped_middle=False,
                stopped_distal=False,
                palm_stop=False,
                at_limits=True,
                start_in_contact=False,
                path=path,
            )
        q_free = path1(np.array([ev1.t_free]))[0]
        path = np.concatenate([path1(ev1.t_samples[ev1.t_samples < ev1.t_free]), q_free[None]])
        if ev1.distal_hit:  # the distal touched (maybe together with the middle): stop
            if ev1.middle_idx is not None:
                contacts.append(contact(f.links[1], ev1.middle_idx))
                stopped_middle = True
            if ev1.distal_idx is not None:
                contacts.append(contact(f.links[2], ev1.distal_idx))
                stopped_distal = True
            palm_stop = ev1.palm
            return _closing(
                f,
                q_free,
                contacts,
                stopped_middle,
                stopped_distal,
                palm_stop,
                start_in_contact,
                path,
            )

        # ---- phase 2: the middle link stopped; the distal joint closes alone
        if ev1.middle_idx is not None:
            contacts.append(contact(f.links[1], ev1.middle_idx))
            stopped_middle = True
        palm_stop = ev1.palm
        q1 = q_free[0]

        def path2(t: np.ndarray) -> np.ndarray:
            out = np.empty((t.shape[0], 2))
            out[:, 0] = q1
            np.minimum(q_free[1] + t, f.upper[1], out=out[:, 1])
            return out

        t_end2 = max(f.upper[1] - q_free[1], 0.0)
        ev2 = _first_event(geo, Pr, path2, t_end2, n_steps, links=(False, True))
        if ev2.t_hit is None:
            path = np.concatenate([path, path2(ev2.t_samples[1:])])
            return _closing(
                f,
                path[-1].copy(),
                contacts,
                stopped_middle,
                False,
                palm_stop,
                start_in_contact,
                path,
            )
        q_stop = path2(np.array([ev2.t_free]))[0]
        path = np.concatenate(
            [
                path,
                path2(ev2.t_samples[(ev2.t_samples > 0) & (ev2.t_samples < ev2.t_free)]),
                q_stop[None],
            ]
        )
        if ev2.distal_idx is not None:
            contacts.append(contact(f.links[2], ev2.distal_idx))
            stopped_distal = True
        palm_stop = palm_stop or ev2.palm
        return _closing(
            f, q_stop, contacts, stopped_middle, stopped_distal, palm_stop, start_in_contact, path
        )

    def close_fingers(
        self,
        slices: Sequence[tuple[str | Finger, np.ndarray, np.ndarray]],
        n_steps: int = DEFAULT_CLOSING_STEPS,
        margin: float = 0.0,
        coupling: float = DEFAULT_COUPLING,
        palm: bool = True,
    ) -> list[FingerClosing]:
        """:meth:`close_finger` for many slices at once: result ``i`` equals
        ``close_finger(*slices[i], n_steps, margin, coupling, palm)``.

        ``slices``: ``(finger, points_2d (M_i, 2), q_start (2,))`` per slice, any fingers and
        sizes (``M_i`` may be 0); the results come in the same order, and contact indices refer
        to each slice's own ``points_2d``. The same model and the same sampling as
        :meth:`close_finger` (coarse steps, refinement of the bracket of the first touch with
        the same samples per level, the event at its end), each stage run for all slices
        together, every point with its own slice's path. The coarse sweep goes through the steps
        in order and tests a point only at the steps where it may touch (conservative
        advancement from its distance to the links), so most (step, point) pairs are never
        evaluated; see ``docs/hand.md``. Memory: O(points) per step of the sweep and at most
        ``_BATCH_PAIRS`` (point, sample) pairs per refinement chunk. The hit tests write each
        2-term dot product out where :meth:`close_finger` uses a matrix product (equal up to the
        last bit, which can only matter for a point within ~1e-18 m of a link's boundary)."""
        if n_steps < 1:
            raise ValueError(f"n_steps must be >= 1, got {n_steps}")
        if coupling <= 0:
            raise ValueError(f"coupling must be > 0, got {coupling}")
        if len(slices) == 0:
            return []
        fingers: list[Finger] = []
        pts: list[np.ndarray] = []
        q0 = np.empty((len(slices), 2))
        for i, item in enumerate(slices):  # loop over slices: checks and per-slice inputs
            try:
                finger, points_2d, q_start = item
            except (TypeError, ValueError):
                raise ValueError(
                    f"slices[{i}] must be (finger, points_2d, q_start), got {type(item).__name__}"
                ) from None
            fingers.append(self.finger(finger))
            P = np.asarray(points_2d, dtype=np.float64)
            if P.ndim != 2 or P.shape[1] != 2:
                raise ValueError(f"slices[{i}]: points_2d must have shape (M, 2), got {P.shape}")
            qs = np.asarray(q_start, dtype=np.float64)
            if qs.shape != (2,):
                raise ValueError(f"slices[{i}]: q_start must have shape (2,), got {qs.shape}")
            pts.append(P)
            q0[i] = qs
        S = len(fingers)
        geom = np.array(
            [
                (f.knuckle_length, f.middle_length, f.distal_length, 0.5 * f.thickness)
                for f in fingers
            ]
        )  # (S, 4)
        lower = np.array([f.lower for f in fingers])  # (S, 2)
        upper = np.array([f.upper for f in fingers])
        q0 = np.clip(q0, lower, upper)
        # only points within a finger's reach from its first joint can ever be touched
        sizes = np.array([len(P) for P in pts], dtype=np.int64)
        P_all = np.concatenate(pts) if sizes.sum() else np.zeros((0, 2))
        seg_all = np.repeat(np.arange(S), sizes)
        src_all = np.arange(len(P_all)) - np.repeat(np.cumsum(sizes) - sizes, sizes)
        reach = geom[:, 1] + np.hypot(geom[:, 2], geom[:, 3]) + 2.0 * abs(margin)
        keep = np.einsum("ij,ij->i", P_all, P_all) <= (reach * reach)[seg_all]
        if not keep.all():  # (integer indices: much faster than a boolean mask on (N, 2))
            kept = np.flatnonzero(keep)
            P_all, seg_all, src_all = P_all[kept], seg_all[kept], src_all[kept]
        seg = seg_all
        B = _SliceBatch(
            fingers=tuple(fingers),
            Lk=geom[:, 0],
            Lm=geom[:, 1],
            Ld=geom[:, 2],
            h=geom[:, 3],
            upper=upper,
            P=P_all,
            x=np.ascontiguousarray(P_all[:, 0]),
            y=np.ascontiguousarray(P_all[:, 1]),
            seg=seg,
            start=np.concatenate([[0], np.cumsum(np.bincount(seg, minlength=S))]),
            source=src_all,
            margin=float(margin),
            palm=bool(palm),
        )

        # ---- phase 1: both joints close together (clipped at their limits)
        every = np.arange(S)
        A1 = np.array([1.0, float(coupling)])
        t_end = np.maximum(
            np.maximum(upper[:, 0] - q0[:, 0], (upper[:, 1] - q0[:, 1]) / coupling), 0.0
        )
        ev1 = _batch_first_events(B, every, q0, A1, t_end, n_steps, (True, True))
        Q1 = _paths(q0, A1, upper, ev1.t)  # (S, n_steps + 1, 2) the coarse samples
        q_free = _paths(q0, A1, upper, ev1.t_free[:, None])[:, 0]  # (S, 2)
        # ---- phase 2: the middle link stopped; the distal joint closes alone
        two = np.flatnonzero((ev1.k >= 0) & ~ev1.distal_hit)
        ev2 = None
        if len(two):
            A2 = np.array([0.0, 1.0])
            t_end2 = np.maximum(upper[two, 1] - q_free[two, 1], 0.0)
            # the distal joint stays where it is: only the points within the distal link's
            # circumradius (grown by the margin) of it can be touched
            o2x, o2y = B.Lm * np.cos(q_free[:, 0]), B.Lm * np.sin(q_free[:, 0])  # (S,)
            r2 = np.hypot(B.Ld + abs(margin), B.h + abs(margin)) + 1e-9  # (S,)
            dx, dy = B.x - o2x[B.seg], B.y - o2y[B.seg]
            near2 = dx * dx + dy * dy <= (r2 * r2)[B.seg]
            ev2 = _batch_first_events(
                B, two, q_free[two], A2, t_end2, n_steps, (False, True), may_touch=near2
            )
            Q2 = _paths(q_free[two], A2, upper[two], ev2.t)
            q_stop = _paths(q_free[two], A2, upper[two], ev2.t_free[:, None])[:, 0]
        # ---- the results, per slice: which case, the end configuration, flags, path lengths
        found1 = ev1.k >= 0
        stop1 = found1 & ev1.distal_hit  # phase 1 ended by the distal (or its palm test)
        in2 = np.zeros(S, dtype=bool)
        in2[two] = True
        found2 = np.zeros(S, dtype=bool)
        q_end = Q1[every, ev1.n_t - 1].copy()  # (S, 2) no stop: the last coarse sample
        q_end[stop1] = q_free[stop1]
        valid1 = np.arange(n_steps + 1)[None, :] < ev1.n_t[:, None]
        j1 = np.count_nonzero((ev1.t < ev1.t_free[:, None]) & valid1, axis=1)  # a prefix
        dis2 = np.full(S, -1, dtype=np.int64)
        palm2 = np.zeros(S, dtype=bool)
        row2 = np.full(S, -1, dtype=np.int64)
        j2 = np.zeros(S, dtype=np.int64)
        if len(two):
            row2[two] = np.arange(len(two))
            f2 = ev2.k >= 0
            found2[two] = f2
            q_end[two] = np.where(f2[:, None], q_stop, Q2[np.arange(len(two)), ev2.n_t - 1])
            valid2 = np.arange(n_steps + 1)[None, :] < ev2.n_t[:, None]
            j2[two] = np.count_nonzero((ev2.t < ev2.t_free[:, None]) & valid2, axis=1)
            dis2[two] = np.where(f2, ev2.distal_idx, -1)
            palm2[two] = f2 & ev2.palm
        mid1 = np.where(found1, ev1.middle_idx, -1)
        dis1 = np.where(stop1, ev1.distal_idx, -1)
        stopped_middle = mid1 >= 0
        stopped_distal = (dis1 >= 0) | (dis2 >= 0)
        palm_stop = found1 & (ev1.palm | palm2)
        at_limits = ~found1 | (
            np.all(np.abs(q_end - upper) <= HAND_CLOSING_ANGLE_TOL, axis=1) & ~stopped_distal
        )
        q_out = np.where(found1[:, None], np.clip(q_end, lower, upper), q_end)
        c_idx = np.stack([mid1, dis1, dis2])  # (3, S) the contacts' points in B.P, -1 for none
        P_c = B.P[np.maximum(c_idx, 0)] if len(B.P) else np.zeros((3, S, 2))  # (3, S, 2)
        src = B.source[np.maximum(c_idx, 0)] if len(B.P) else np.zeros((3, S), dtype=np.int64)

        out: list[FingerClosing] = []
        for s in range(S):  # loop over slices: the small result objects
            f = fingers[s]
            if not found1[s]:  # no stop: both joints end at their limits
                path = Q1[s, : ev1.n_t[s]].copy()
            elif not in2[s]:
                path = np.concatenate([Q1[s, : j1[s]], q_free[s : s + 1]])
            else:
                r = row2[s]
                tail = (
                    [Q2[r, 1 : j2[s]], q_stop[r : r + 1]] if found2[s] else [Q2[r, 1 : ev2.n_t[r]]]
                )
                path = np.concatenate([Q1[s, : j1[s]], q_free[s : s + 1], *tail])
            contacts = tuple(
                FingerContact(f.links[1 if c == 0 else 2], P_c[c, s].copy(), int(src[c, s]))
                for c, i in enumerate((mid1[s], dis1[s], dis2[s]))
                if i >= 0
            )
            last = contacts[-1] if contacts else None
            out.append(
                FingerClosing(
                    finger=f.name,
                    q=q_out[s].copy(),  # (own arrays, as close_finger's)
                    contact_link=None if last is None else last.link,
                    contact_point=None if last is None else last.point,
                    contact_index=None if last is None else last.index,
                    contacts=contacts,
                    stopped_middle=bool(stopped_middle[s]),
                    stopped_distal=bool(stopped_distal[s]),
                    palm_stop=bool(palm_stop[s]),
                    at_limits=bool(at_limits[s]),
                    start_in_contact=bool(ev1.k[s] == 0),
                    path=path,
                )
            )
        return out

    # ---------------------------------------------------------------- points in links
    def points_in_links(self, p_hand: np.ndarray, q: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """(N, L) bool: point n lies inside link l's collision box grown by ``margin`` on every
        side, for one configuration ``q`` (J,). Columns in ``link_names`` order."""
        p = _as_n3(p_hand, "p_hand")
        Q, single = self._as_q(q)
        if not single:
            raise ValueError(f"q must have shape ({self.n_joints},), got {Q.shape}")
        Tb = self.box_poses(Q[0])  # (L, 4, 4)
        R = Tb[:, :3, :3]  # (L, 3, 3) box axes as columns
        L = R.shape[0]
        # box-frame coordinates of every point in every box with one matrix product:
        # local[n, l, k] = p[n] . R[l][:, k] - t[l] . R[l][:, k]
        Rcat = R.transpose(1, 0, 2).reshape(3, 3 * L)  # (3, 3L)
        off = np.einsum("lj,ljk->lk", Tb[:, :3, 3], R).reshape(3 * L)
        local = (p @ Rcat - off).reshape(-1, L, 3)  # (N, L, 3)
        return _all3(np.abs(local) <= self.link_box_half + margin)

    def points_in_hand(self, p_hand: np.ndarray, q: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """(N,) bool: point inside any link (grown by ``margin``) at configuration ``q`` (J,)."""
        return np.any(self.points_in_links(p_hand, q, margin), axis=1)

    def link_point_counts(
        self,
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
        pts = _as_n3(points, "points")
        T = np.asarray(T_world_hand, dtype=np.float64)
        if T.ndim != 3 or T.shape[1:] != (4, 4):
            raise ValueError(f"T_world_hand must have shape (G, 4, 4), got {T.shape}")
        G, L, N = T.shape[0], len(self.link_names), pts.shape[0]
        Q = np.asarray(q, dtype=np.float64)
        if Q.ndim == 1:
            Qb, _ = self._as_q(Q)
            inverse = np.zeros(G, dtype=np.int64)
        else:
            Qall, _ = self._as_q(Q)
            if Qall.shape[0] != G:
                raise ValueError(
                    f"q must have shape ({self.n_joints},) or ({G}, {self.n_joints}), got {Q.shape}"
                )
            Qb, inverse = np.unique(Qall, axis=0, return_inverse=True)
            inverse = inverse.reshape(-1)
        counts = np.zeros((G, L), dtype=np.int64)
        if G == 0 or N == 0:
            return counts
        # per distinct configuration: box-frame transform as one (3, 3L) product
        Tb = self.box_poses(Qb)  # (U, L, 4, 4)
        Rb = Tb[:, :, :3, :3]
        Rcat = Rb.transpose(0, 2, 1, 3).reshape(-1, 3, 3 * L)  # (U, 3, 3L)
        off = np.einsum("ulj,uljk->ulk", Tb[:, :, :3, 3], Rb).reshape(-1, 3 * L)  # (U, 3L)
        half = self.link_box_half + margin  # (L, 3)
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
                u = inverse[g0:g1]
                inb = (p_hand >= box_lo[u]) & (p_hand <= box_hi[u])  # (N, Gc, 3)
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
        self,
        points: np.ndarray,
        T_world_hand: np.ndarray,
        q: np.ndarray,
        margin: float = 0.0,
    ) -> np.ndarray:
        """(G,) bool: any of ``points`` (N, 3, world) inside any link of hand g (see
        :meth:`link_point_counts`)."""
        return self.link_point_counts(points, T_world_hand, q, margin).sum(axis=1) > 0

    # ---------------------------------------------------------------- fcl and meshes
    def collision_objects(self, q: np.ndarray) -> dict[str, fcl.CollisionObject]:
        """Link name -> python-fcl box object placed at configuration ``q`` (J,), hand frame."""
        Q, single = self._as_q(q)
        if not single:
            raise ValueError(f"q must have shape ({self.n_joints},), got {Q.shape}")
        Tb = self.box_poses(Q[0])
        out = {}
        for i, n in enumerate(self.link_names):
            geom = fcl.Box(*(2.0 * self.link_box_half[i]))
            out[n] = fcl.CollisionObject(geom, fcl.Transform(Tb[i, :3, :3], Tb[i, :3, 3]))
        return out

    @functools.cached_property
    def self_collision_pairs_checked(self) -> tuple[tuple[str, str], ...]:
        """Link pairs the self-collision check tests: all pairs except parent and child links
        (which touch at their joint by construction)."""
        pairs = []
        L = len(self.link_names)
        for a in range(L):
            for b in range(a + 1, L):
                if self.link_parent[a] == b or self.link_parent[b] == a:
                    continue
                pairs.append((self.link_names[a], self.link_names[b]))
        return tuple(pairs)

    def self_collisions(
        self, q: np.ndarray, box_poses: np.ndarray | None = None
    ) -> list[tuple[str, str]]:
        """The link pairs (of :attr:`self_collision_pairs_checked`) whose boxes intersect at
        configuration ``q`` (J,), by python-fcl. ``box_poses``: :meth:`box_poses` of ``q``
        (L, 4, 4) when the caller already has them (saves the forward kinematics).

        The ball test of :meth:`self_collisions_many` skips pairs proven apart and python-fcl
        decides the rest, so the answer is python-fcl's on every checked pair (the batch's
        separating-axis filter does not pay for one hand; see ``_SAT_MIN_PAIRS``)."""
        Q, single = self._as_q(q)
        if not single:
            raise ValueError(f"q must have shape ({self.n_joints},), got {Q.shape}")
        if box_poses is None:
            Tb = self.box_poses(Q[0])  # (L, 4, 4)
        else:
            Tb = np.asarray(box_poses, dtype=np.float64)
            if Tb.shape != (len(self.link_names), 4, 4):
                raise ValueError(
                    f"box_poses must have shape ({len(self.link_names)}, 4, 4), got {Tb.shape}"
                )
        return self._self_collisions_of(Tb[None])[0]

    def self_collisions_many(
        self, Q: np.ndarray, box_poses: np.ndarray | None = None
    ) -> list[list[tuple[str, str]]]:
        """:meth:`self_collisions` for B configurations ``Q`` (B, J) at once: result ``b`` equals
        ``self_collisions(Q[b])`` exactly (same pairs, same order). ``box_poses``: :meth:`box_poses`
        of ``Q`` (B, L, 4, 4) when the caller already has them. B = 0 gives ``[]``.

        Per (configuration, checked pair), all at once: the circumscribed-ball test, then (when
        at least ``_SAT_MIN_PAIRS`` candidates are left, i.e. for batches) an exact oriented-box
        separating-axis test (3 + 3 face normals, 9 edge cross products) that calls a pair apart
        only when an axis parts the boxes by more than ``SELF_COLLISION_SAT_MARGIN``; python-fcl
        decides the rest (touching or intersecting boxes, a few per closed hand), so every
        verdict is python-fcl's."""
        Qa = np.asarray(Q, dtype=np.float64)
        J, L = self.n_joints, len(self.link_names)
        if Qa.ndim != 2 or Qa.shape[1] != J:
            raise ValueError(f"Q must have shape (B, {J}), got {Qa.shape}")
        B = Qa.shape[0]
        if box_poses is None:
            if B == 0:
                return []
            Tb = self.box_poses(Qa)  # (B, L, 4, 4)
        else:
            Tb = np.asarray(box_poses, dtype=np.float64)
            if Tb.shape != (B, L, 4, 4):
                raise ValueError(f"box_poses must have shape ({B}, {L}, 4, 4), got {Tb.shape}")
            if B == 0:
                return []
        return self._self_collisions_of(Tb)

    def _self_collisions_of(self, Tb: np.ndarray) -> list[list[tuple[str, str]]]:
        """The intersecting checked pairs of each of B hands given their box poses Tb
        (B, L, 4, 4): ball test, separating-axis test, python-fcl on what is left."""
        ia, ib, reach = self._self_pair_spheres  # (P,), (P,), (P,)
        B = Tb.shape[0]
        out: list[list[tuple[str, str]]] = [[] for _ in range(B)]
        c = Tb[:, :, :3, 3]  # (B, L, 3) box centres
        # exact pre-test: boxes whose circumscribed balls are apart cannot intersect
        gap = np.linalg.norm(c[:, ia] - c[:, ib], axis=2) - reach  # (B, P)
        bb, kk = np.nonzero(gap <= 1e-6)  # (N,) candidates, by configuration then pair order
        if len(bb) == 0:
            return out
        la, lb = ia[kk], ib[kk]  # (N,) link indices of each candidate
        if len(bb) >= _SAT_MIN_PAIRS:
            Tt = Tb.transpose(2, 3, 0, 1)  # (4, 4, B, L) view: gathers come out pair-last
            half = np.asarray(self.link_box_half, dtype=np.float64).T  # (3, L)
            apart = _obb_apart(
                Tt[:3, :3, bb, la], Tt[:3, 3, bb, la], half[:, la],
                Tt[:3, :3, bb, lb], Tt[:3, 3, bb, lb], half[:, lb],
            )  # fmt: skip
            todo = np.flatnonzero(~apart)  # candidates python-fcl decides (few)
        else:  # one hand's candidates: python-fcl on each is cheaper (measured)
            todo = np.arange(len(bb))
        if len(todo) == 0:
            return out
        geoms = self._link_fcl_boxes
        objs: dict[tuple[int, int], fcl.CollisionObject] = {}  # (hand, link) -> placed box
        req = fcl.CollisionRequest()
        pairs = self.self_collision_pairs_checked
        # loop over the pairs no separating axis parts (a few per hand); plain ints (fast keys)
        for b, k, *links in zip(*(x[todo].tolist() for x in (bb, kk, la, lb)), strict=True):
            for li in links:  # place each link box of this hand once
                if (b, li) not in objs:
                    objs[(b, li)] = fcl.CollisionObject(
                        geoms[li], fcl.Transform(Tb[b, li, :3, :3], Tb[b, li, :3, 3])
                    )
            res = fcl.CollisionResult()
            if fcl.collide(objs[(b, links[0])], objs[(b, links[1])], req, res) > 0:
                out[b].append(pairs[k])
        return out

    @functools.cached_property
    def _self_pair_spheres(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per checked self-collision pair: link indices a, b (P,) and the sum of the two
        boxes' circumscribed radii (P,)."""
        index = {n: i for i, n in enumerate(self.link_names)}
        ia = np.array([index[a] for a, _ in self.self_collision_pairs_checked], dtype=np.int64)
        ib = np.array([index[b] for _, b in self.self_collision_pairs_checked], dtype=np.int64)
        r = np.linalg.norm(np.asarray(self.link_box_half, dtype=np.float64), axis=1)
        return ia, ib, r[ia] + r[ib]

    @functools.cached_property
    def _link_fcl_boxes(self) -> tuple[fcl.Box, ...]:
        """python-fcl box geometry of every link (immutable; shared by the collision objects)."""
        return tuple(fcl.Box(*(2.0 * h)) for h in np.asarray(self.link_box_half, dtype=np.float64))

    def self_collision(self, q: np.ndarray) -> bool:
        """True when two non-adjacent links' collision boxes intersect at ``q`` (J,)."""
        return len(self.self_collisions(q)) > 0

    def hand_mesh(self, q: np.ndarray) -> trimesh.Trimesh:
        """The visual mesh of the whole hand at configuration ``q`` (J,), in the hand frame,
        with per-face colours from the URDF materials."""
        T = self.fk_array(np.asarray(q, dtype=np.float64))
        if T.ndim != 3:
            raise ValueError(f"q must have shape ({self.n_joints},), got {np.shape(q)}")
        parts = []
        for i, n in enumerate(self.link_names):
            m = self.visual_meshes[n].copy()
            m.apply_transform(T[i])
            parts.append(m)
        return trimesh.util.concatenate(parts)

    def collision_mesh(self, q: np.ndarray) -> trimesh.Trimesh:
        """The collision boxes at ``q`` (J,) as one mesh in the hand frame (for drawing)."""
        Tb = self.box_poses(np.asarray(q, dtype=np.float64))
        if Tb.ndim != 3:
            raise ValueError(f"q must have shape ({self.n_joints},), got {np.shape(q)}")
        parts = [
            trimesh.creation.box(extents=2.0 * self.link_box_half[i], transform=Tb[i])
            for i in range(len(self.link_names))
        ]
        return trimesh.util.concatenate(parts)


# --------------------------------------------------------------------------------------------
# Box-box separating axes (the self-collision pre-filter)
# --------------------------------------------------------------------------------------------

_SAT_MIN_PAIRS: int = 40
"""Self-collision: the separating-axis pre-filter runs only when at least this many (hand, link
pair) candidates pass the ball test, so never for one hand (36 checked pairs). Its fixed numpy
cost (about 80 us) exceeds python-fcl on each candidate (about 1 us a test plus 3-4 us per placed
link box) for one hand at every candidate count (measured: 98 vs 60 us at 0-5 candidates, 275 vs
162 us at 24-36), and pays off for a batch (``benchmarks/bench_hand.py``). Either way the answer
is python-fcl's."""

_I1 = np.array([1, 2, 0])
"""The first of the two other axes of axis i (i + 1 mod 3)."""
_I2 = np.array([2, 0, 1])
"""The second of the two other axes of axis i (i + 2 mod 3)."""


def _obb_apart(
    Ra: np.ndarray,
    ca: np.ndarray,
    ha: np.ndarray,
    Rb: np.ndarray,
    cb: np.ndarray,
    hb: np.ndarray,
    margin: float = SELF_COLLISION_SAT_MARGIN,
) -> np.ndarray:
    """(N,) bool: oriented boxes a and b of each of N pairs are proven apart, i.e. one of the 15
    separating axes (the 3 + 3 face normals, the 9 cross products of an edge direction of a with
    one of b) parts them by more than ``margin`` (metres). False means "not proven": on every
    axis the boxes overlap, touch or are closer than the margin.

    Pair index last (every operation runs over contiguous length-N rows): ``Ra``, ``Rb``
    (3, 3, N) rotations, ``Ra[:, i, n]`` = axis i of box a of pair n; ``ca``, ``cb`` (3, N)
    centres; ``ha``, ``hb`` (3, N) half sides; all in one frame. Everything is expressed in a's
    frame: ``C = Ra^T Rb`` (b's axes as columns), ``t = Ra^T (cb - ca)``. ``|C|`` is padded by
    ``SAT_ABS_ROTATION_EPS`` (near-parallel edges), which only grows the projected radii. An
    axis u_i x v_j is not a unit vector: its length ``|(C[i1, j], C[i2, j])|`` scales the
    margin, so that the margin is metres along the unit axis. The 9 cross-product axes are
    tested only on the pairs the 6 face normals leave."""
    d = cb - ca  # (3, N)
    # (3, 3, N): C[i, j] = u_i . v_j
    C = Ra[0, :, None] * Rb[0, None] + Ra[1, :, None] * Rb[1, None] + Ra[2, :, None] * Rb[2, None]
    t = Ra[0] * d[0] + Ra[1] * d[1] + Ra[2] * d[2]  # (3, N): b's centre in a's frame
    A = np.abs(C) + SAT_ABS_ROTATION_EPS  # (3, 3, N)
    # a's face normals u_i: |t_i| - (ha_i + sum_j |C_ij| hb_j)
    s_a = np.abs(t) - ha - (A[:, 0] * hb[0] + A[:, 1] * hb[1] + A[:, 2] * hb[2])  # (3, N)
    # b's face normals v_j: |sum_i C_ij t_i| - (sum_i |C_ij| ha_i + hb_j)
    s_b = np.abs(C[0] * t[0] + C[1] * t[1] + C[2] * t[2])
    s_b -= A[0] * ha[0] + A[1] * ha[1] + A[2] * ha[2] + hb  # (3, N)
    apart = (np.maximum(s_a, s_b) > margin).any(axis=0)  # (N,)
    left = np.flatnonzero(~apart)  # pairs no face normal parts
    if len(left) == 0:
        return apart
    C, A, t = C[:, :, left], A[:, :, left], t[:, left]
    ha, hb = ha[:, left], hb[:, left]
    # u_i x v_j, (3, 3, M) indexed [i, j]; i1, i2 (j1, j2) are the two other axes of i (j):
    # |t_i2 C_i1j - t_i1 C_i2j| - (ha_i1 |C_i2j| + ha_i2 |C_i1j| + hb_j1 |C_ij2| + hb_j2 |C_ij1|)
    C1, C2 = C[_I1], C[_I2]
    s_x = np.abs(t[_I2, None] * C1 - t[_I1, None] * C2)
    s_x -= ha[_I1, None] * A[_I2] + ha[_I2, None] * A[_I1]
    s_x -= hb[None, _I1] * A[:, _I2] + hb[None, _I2] * A[:, _I1]
    length = np.sqrt(C1 * C1 + C2 * C2)  # |u_i x v_j|
    apart[left] = (s_x > margin * length).any(axis=(0, 1))
    return apart


# --------------------------------------------------------------------------------------------
# Occupancy grid of the hand (cull for the batched point-in-link counts)
# --------------------------------------------------------------------------------------------


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
    def build(cls, Rcat, off, half, centers, Rb) -> _OccupancyGrid:
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


# --------------------------------------------------------------------------------------------
# Closing-model internals
# --------------------------------------------------------------------------------------------


class _FingerGeometry:
    """Planar link rectangles of one finger: hit tests for many configurations x points."""

    def __init__(self, f: Finger, margin: float, palm: bool) -> None:
        self.f = f
        self.m = float(margin)
        self.h = 0.5 * f.thickness
        self.palm = palm

    def hits(self, Q: np.ndarray, P: np.ndarray, links: tuple[bool, bool]):
        """For configurations Q (K, 2) and points P (M, 2): (middle (K, M), distal (K, M),
        palm (K,)) bool; a link touches a point within ``margin``."""
        f, m, h = self.f, self.m, self.h
        K, M = Q.shape[0], P.shape[0]
        # d (K, 2) along a link, n (K, 2) across it; filled in place (no np.stack: this runs
        # ~40 times per closing on small arrays, where numpy's call overhead dominates)
        a1 = Q[:, 0]
        a2 = Q[:, 0] + Q[:, 1]
        d1 = np.empty((K, 2))
        d2 = np.empty((K, 2))
        np.cos(a1, out=d1[:, 0])
        np.sin(a1, out=d1[:, 1])
        np.cos(a2, out=d2[:, 0])
        np.sin(a2, out=d2[:, 1])
        n1 = d1[:, ::-1].copy()
        n1[:, 0] *= -1.0
        n2 = d2[:, ::-1].copy()
        n2[:, 0] *= -1.0
        o2 = f.middle_length * d1  # (K, 2) second joint
        mid = dis = None
        if M:
            if links[0]:
                s = d1 @ P.T  # (K, M) along the link
                r = n1 @ P.T  # (K, M) across
                mid = s >= -m  # the same three tests, combined in place
                mid &= s <= f.middle_length + m
                mid &= np.abs(r, out=r) <= h + m
            if links[1]:
                # sum over 2 terms written out (bit-identical to np.sum(., axis=1))
                s = d2 @ P.T
                s -= (d2[:, 0] * o2[:, 0] + d2[:, 1] * o2[:, 1])[:, None]
                r = n2 @ P.T
                r -= (n2[:, 0] * o2[:, 0] + n2[:, 1] * o2[:, 1])[:, None]
                dis = s >= -m
                dis &= s <= f.distal_length + m
                dis &= np.abs(r, out=r) <= h + m
        if mid is None:
            mid = np.zeros((K, M), dtype=bool)
        if dis is None:
            dis = np.zeros((K, M), dtype=bool)
        palm = np.zeros(K, dtype=bool)
        palm_mid = np.zeros(K, dtype=bool)
        if self.palm:
            floor = -f.knuckle_length + m
            # lowest corner of each moving rectangle along the 2D x axis
            low_mid = np.minimum(0.0, f.middle_length * d1[:, 0]) - h * np.abs(n1[:, 0])
            low_dis = o2[:, 0] + np.minimum(0.0, f.distal_length * d2[:, 0]) - h * np.abs(n2[:, 0])
            if links[0]:
                palm_mid = low_mid < floor
            if links[1]:
                palm = low_dis < floor
        return mid, dis, palm_mid, palm

    def distance(self, q: np.ndarray, P: np.ndarray, link: int) -> np.ndarray:
        """(M,) box-distance (Chebyshev-style; < 0 inside) of points to link 0 (middle) or 1
        (distal) at flexion ``q`` (2,)."""
        f, h = self.f, self.h
        a = q[0] if link == 0 else q[0] + q[1]
        d = np.array([np.cos(a), np.sin(a)])
        n = np.array([-d[1], d[0]])
        o = np.zeros(2) if link == 0 else f.middle_length * np.array([np.cos(q[0]), np.sin(q[0])])
        length = f.middle_length if link == 0 else f.distal_length
        s = (P - o) @ d
        r = (P - o) @ n
        return np.maximum(np.abs(s - 0.5 * length) - 0.5 * length, np.abs(r) - h)


@dataclass
class _Event:
    t_samples: np.ndarray  # sampled path parameters before refinement
    t_free: float  # last contact-free parameter
    t_hit: float | None  # first touching parameter (None: no event up to the end)
    k_hit: int | None  # index of the first touching sample
    middle_hit: bool = False
    distal_hit: bool = False
    palm: bool = False
    middle_idx: int | None = None
    distal_idx: int | None = None


def _may_touch(
    geo: _FingerGeometry, P: np.ndarray, Q_bracket: np.ndarray, links: tuple[bool, bool]
) -> np.ndarray:
    """(M,) bool: which points ``P`` (M, 2) may touch a link (``links``: middle, distal) at some
    configuration between ``Q_bracket[0]`` and ``Q_bracket[1]`` (2, 2) along a monotone path.

    Exact superset: a link touches a point when its box-distance (:meth:`_FingerGeometry.distance`,
    1-Lipschitz in the point's link-frame coordinates) is <= margin. Turning the first joint by
    d1 and the sum of the joints by d2 moves a point's middle-link coordinates by at most
    ``|p| d1`` and its distal-link coordinates by at most ``(|p| + Lm) d2 + Lm d1``."""
    qa, qb = Q_bracket
    d1 = abs(float(qb[0] - qa[0]))
    d2 = abs(float((qb[0] + qb[1]) - (qa[0] + qa[1])))
    rho = np.sqrt(np.einsum("ij,ij->i", P, P))  # (M,) distance to the first joint
    lm = geo.f.middle_length
    slack = 1e-9  # metres, far above the rounding of the two ways of computing the distance
    keep = np.zeros(len(P), dtype=bool)
    if links[0]:
        keep |= geo.distance(qb, P, 0) <= geo.m + rho * d1 + slack
    if links[1]:
        keep |= geo.distance(qb, P, 1) <= geo.m + (rho + lm) * d2 + lm * d1 + slack
    return keep


def _first_event(
    geo: _FingerGeometry, P: np.ndarray, path, t_end: float, n_steps: int, links: tuple[bool, bool]
) -> _Event:
    t = np.linspace(0.0, t_end, n_steps + 1) if t_end > 0 else np.zeros(1)
    Q = path(t)  # (K, 2)
    # the samples in growing chunks, in order, up to the first chunk that touches: the samples
    # after the first touch are never needed (same first touching sample as testing all at once)
    k = -1
    lo_k, size = 0, _SWEEP_CHUNK
    while lo_k < len(t):
        hi_k = min(lo_k + size, len(t))
        mid, dis, pmid, pdis = geo.hits(Q[lo_k:hi_k], P, links)
        any_hit = mid.any(axis=1) | dis.any(axis=1) | pmid | pdis  # (chunk,)
        if any_hit.any():
            k = lo_k + int(np.argmax(any_hit))
            break
        lo_k, size = hi_k, 2 * size
    if k < 0:
        return _Event(t_samples=t, t_free=float(t[-1]), t_hit=None, k_hit=None)
    if k == 0:
        lo = hi = 0.0
    else:
        lo, hi = float(t[k - 1]), float(t[k])
        # refine [last free, first touching] by sampling it densely, all samples at once, until
        # it is narrower than the tolerance (each level shrinks it n_ref + 1 times)
        n_ref = max(1, min(_REFINE_SAMPLES, _REFINE_BUDGET // max(P.shape[0], 1)))
        # only the points that can touch a link inside the bracket take part in refining it
        P_ref = P[_may_touch(geo, P, path(np.array([lo, hi])), links)] if len(P) > 16 else P
        while hi - lo > HAND_CLOSING_ANGLE_TOL:
            ts = np.linspace(lo, hi, n_ref + 2)[1:-1]
            a, b, c, d = geo.hits(path(ts), P_ref, links)
            hit = a.any(axis=1) | b.any(axis=1) | c | d
            if hit.any():
                j = int(np.argmax(hit))
                lo, hi = (float(ts[j - 1]) if j > 0 else lo), float(ts[j])
            else:
                lo = float(ts[-1])
    a, b, c, d = geo.hits(path(np.array([hi])), P, links)
    ev = _Event(t_samples=t, t_free=lo, t_hit=hi, k_hit=k)
    q_free = path(np.array([lo]))[0]
    if a[0].any():
        idx = np.flatnonzero(a[0])
        ev.middle_idx = int(idx[np.argmin(geo.distance(q_free, P[idx], 0))])
    if b[0].any():
        idx = np.flatnonzero(b[0])
        ev.distal_idx = int(idx[np.argmin(geo.distance(q_free, P[idx], 1))])
    ev.middle_hit = bool(a[0].any() or c[0])
    ev.distal_hit = bool(b[0].any() or d[0])
    ev.palm = bool(c[0] or d[0])
    return ev


def _closing(
    f: Finger,
    q: np.ndarray,
    contacts: list[FingerContact],
    stopped_middle: bool,
    stopped_distal: bool,
    palm_stop: bool,
    start_in_contact: bool,
    path: np.ndarray,
) -> FingerClosing:
    last = contacts[-1] if contacts else None
    at_limits = bool(np.all(np.abs(q - f.upper) <= HAND_CLOSING_ANGLE_TOL)) and not stopped_distal
    return FingerClosing(
        finger=f.name,
        q=np.clip(q, f.lower, f.upper),
        contact_link=None if last is None else last.link,
        contact_point=None if last is None else last.point,
        contact_index=None if last is None else last.index,
        contacts=tuple(contacts),
        stopped_middle=stopped_middle,
        stopped_distal=stopped_distal,
        palm_stop=palm_stop,
        at_limits=at_limits,
        start_in_contact=start_in_contact,
        path=path,
    )


# --------------------------------------------------------------------------------------------
# Closing model, batched over many slices (Hand.close_fingers)
# --------------------------------------------------------------------------------------------


_BATCH_PAIRS: int = 2_000_000
"""Batched closing: most (point, sample) pairs evaluated at once (memory: a few arrays of this
many entries)."""


@dataclass(frozen=True)
class _SliceBatch:
    """The slices of one :meth:`Hand.close_fingers` call: per-slice finger geometry and the
    points within reach of every slice, concatenated in slice order."""

    fingers: tuple[Finger, ...]
    """(S,) the finger of each slice."""
    Lk: np.ndarray
    """(S,) knuckle lengths."""
    Lm: np.ndarray
    """(S,) middle link lengths."""
    Ld: np.ndarray
    """(S,) distal link lengths."""
    h: np.ndarray
    """(S,) half thicknesses of the links."""
    upper: np.ndarray
    """(S, 2) upper flexion limits."""
    P: np.ndarray
    """(N, 2) the points within reach of all slices (``Pr`` of ``close_finger``), slice by slice."""
    x: np.ndarray
    """(N,) ``P[:, 0]``, contiguous."""
    y: np.ndarray
    """(N,) ``P[:, 1]``, contiguous."""
    seg: np.ndarray
    """(N,) int64 slice of each point (non-decreasing)."""
    start: np.ndarray
    """(S + 1,) int64: the points of slice ``s`` are ``P[start[s]:start[s + 1]]``."""
    source: np.ndarray
    """(N,) int64 index of each point in its slice's ``points_2d``."""
    margin: float
    """Contact margin (metres)."""
    palm: bool
    """Whether the palm's inner face stops a link."""

    @property
    def count(self) -> np.ndarray:
        """(S,) number of points within reach per slice."""
        return np.diff(self.start)


@dataclass(frozen=True)
class _Configs:
    """Link directions of configurations ``Q (R, C, 2)`` (one row of C samples per slice), as
    ``_FingerGeometry.hits`` computes them."""

    d1x: np.ndarray
    d1y: np.ndarray
    d2x: np.ndarray
    d2y: np.ndarray
    cs: np.ndarray  # (R, C) d2 . o2
    cr: np.ndarray  # (R, C) n2 . o2
    palm_mid: np.ndarray  # (R, C) bool
    palm_dis: np.ndarray  # (R, C) bool

    @classmethod
    def of(cls, B: _SliceBatch, sl: np.ndarray, Q: np.ndarray, links: tuple[bool, bool]):
        a1 = Q[..., 0]
        a2 = Q[..., 0] + Q[..., 1]
        d1x, d1y, d2x, d2y = np.cos(a1), np.sin(a1), np.cos(a2), np.sin(a2)
        Lm = B.Lm[sl][:, None]
        o2x, o2y = Lm * d1x, Lm * d1y
        cs = d2x * o2x + d2y * o2y
        cr = -d2y * o2x + d2x * o2y
        palm_mid = np.zeros(Q.shape[:2], dtype=bool)
        palm_dis = np.zeros(Q.shape[:2], dtype=bool)
        if B.palm:
            h = B.h[sl][:, None]
            floor = -B.Lk[sl][:, None] + B.margin
            if links[0]:
                low_mid = np.minimum(0.0, Lm * d1x) - h * np.abs(d1y)
                palm_mid = low_mid < floor
            if links[1]:
                low_dis = o2x + np.minimum(0.0, B.Ld[sl][:, None] * d2x) - h * np.abs(d2y)
                palm_dis = low_dis < floor
        return cls(d1x, d1y, d2x, d2y, cs, cr, palm_mid, palm_dis)


def _pair_hits(
    B: _SliceBatch, cfg: _Configs, rows: np.ndarray, pts: np.ndarray, links: tuple[bool, bool]
) -> tuple[np.ndarray, np.ndarray]:
    """(middle, distal) (Np, C) bool: does point ``pts[i]`` touch the link at the C
    configurations of row ``rows[i]`` of ``cfg``. The same tests as ``_FingerGeometry.hits``,
    with each 2-term dot product written out (the single-slice version uses a matrix product,
    which may round the last bit differently)."""
    m = B.margin
    px = B.x[pts][:, None]
    py = B.y[pts][:, None]
    sl = B.seg[pts]
    C = cfg.d1x.shape[1]
    mid = dis = None
    hm = (B.h[sl] + m)[:, None]
    if links[0]:
        dx, dy = cfg.d1x[rows], cfg.d1y[rows]  # (Np, C)
        s = dx * px + dy * py
        r = -dy * px + dx * py
        mid = s >= -m
        mid &= s <= (B.Lm[sl] + m)[:, None]
        mid &= np.abs(r, out=r) <= hm
    if links[1]:
        dx, dy = cfg.d2x[rows], cfg.d2y[rows]
        s = dx * px + dy * py
        s -= cfg.cs[rows]
        r = -dy * px + dx * py
        r -= cfg.cr[rows]
        dis = s >= -m
        dis &= s <= (B.Ld[sl] + m)[:, None]
        dis &= np.abs(r, out=r) <= hm
    if mid is None:
        mid = np.zeros((len(pts), C), dtype=bool)
    if dis is None:
        dis = np.zeros((len(pts), C), dtype=bool)
    return mid, dis


def _any_hit_ragged(
    B: _SliceBatch,
    cfg: _Configs,
    pts: np.ndarray,
    rows: np.ndarray,
    n_row: np.ndarray,
    links: tuple[bool, bool],
) -> np.ndarray:
    """(R, C) bool: some point (``pts``, with their rows ``rows``) or the palm touches a link
    at the configurations of ``cfg``; row ``i`` uses only its first ``n_row[i]``
    configurations (the others are False): each point is paired with its row's samples only."""
    R, C = cfg.d1x.shape
    out = cfg.palm_mid | cfg.palm_dis
    out &= np.arange(C)[None, :] < n_row[:, None]
    flat = _Configs(*(getattr(cfg, k).reshape(-1, 1) for k in _Configs.__dataclass_fields__))
    reps = n_row[rows]  # (Np,) samples per point
    ends = np.cumsum(reps)
    step = _BATCH_PAIRS
    b0 = 0
    while b0 < len(pts):  # chunks of points (memory)
        b1 = int(np.searchsorted(ends, ends[b0 - 1] + step if b0 else step, side="right"))
        b1 = max(b1, b0 + 1)
        p, rw, rp = pts[b0:b1], rows[b0:b1], reps[b0:b1]
        T = int(rp.sum())
        pair_pt = np.repeat(p, rp)  # (T,)
        j = np.arange(T) - np.repeat(np.cumsum(rp) - rp, rp)  # sample of each pair
        cfg_i = np.repeat(rw, rp) * C + j  # (T,) configuration of each pair
        mid, dis = _pair_hits(B, flat, cfg_i, pair_pt, links)
        mid |= dis
        np.put(out, cfg_i[mid[:, 0]], True)  # flat indices into the (R, C) result
        b0 = b1
    return out


def _points_of(B: _SliceBatch, sl: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The points of the slices ``sl`` (R,) (distinct, increasing) and the row of each in
    ``sl``: ``(pts (Np,), rows (Np,))``."""
    row_of = np.full(len(B.start) - 1, -1, dtype=np.int64)
    row_of[sl] = np.arange(len(sl))
    pts = np.flatnonzero(row_of[B.seg] >= 0)
    return pts, row_of[B.seg[pts]]


def _paths(qb: np.ndarray, A: np.ndarray, upper: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(R, C, 2) ``min(qb + A t, upper)`` for parameters t (R, C): phase 1 is A = (1, coupling),
    phase 2 is A = (0, 1) (the proximal joint stays at ``qb[:, 0]``, which is within limits)."""
    out = np.empty(t.shape + (2,))
    np.minimum(qb[:, None, 0] + A[0] * t, upper[:, None, 0], out=out[..., 0])
    np.minimum(qb[:, None, 1] + A[1] * t, upper[:, None, 1], out=out[..., 1])
    return out


def _batch_distance(B: _SliceBatch, q: np.ndarray, pts: np.ndarray, link: int) -> np.ndarray:
    """(Np,) ``_FingerGeometry.distance`` of points ``pts`` to link 0 (middle) or 1 (distal) at
    their own configuration ``q`` (Np, 2), 2-term dot products written out."""
    sl = B.seg[pts]
    a = q[:, 0] if link == 0 else q[:, 0] + q[:, 1]
    dx, dy = np.cos(a), np.sin(a)
    px, py = B.x[pts], B.y[pts]
    if link == 1:
        px = px - B.Lm[sl] * np.cos(q[:, 0])
        py = py - B.Lm[sl] * np.sin(q[:, 0])
    length = B.Lm[sl] if link == 0 else B.Ld[sl]
    s = px * dx + py * dy
    r = px * -dy + py * dx
    return np.maximum(np.abs(s - 0.5 * length) - 0.5 * length, np.abs(r) - B.h[sl])


def _pair_eval(
    flat: dict,
    ci: np.ndarray,
    px: np.ndarray,
    py: np.ndarray,
    m: float,
    links: tuple[bool, bool],
) -> tuple[np.ndarray, np.ndarray]:
    """For pairs (point ``(px[i], py[i])``, configuration ``ci[i]`` of ``flat``: 1D arrays per
    configuration built by :func:`_coarse_sweep`): ``(hit (T,) bool, clear (T,))``. ``hit``: a
    link touches the point (the tests of ``_pair_hits``, same arithmetic); ``clear``: how long
    (in path parameter) the point surely stays off both links before and after, its Euclidean
    distance to each link's rectangle grown by the margin over the largest speed of that
    rectangle's points (0 when it touches)."""
    hm = np.take(flat["hm"], ci)  # (T,) half thickness + margin
    hit = np.zeros(len(ci), dtype=bool)
    clear = np.full(len(ci), np.inf)
    for link in (0, 1):  # middle, distal
        if not links[link]:
            continue
        dx = np.take(flat["d1x" if link == 0 else "d2x"], ci)
        dy = np.take(flat["d1y" if link == 0 else "d2y"], ci)
        s = dx * px
        s += dy * py
        r = dx * py
        r -= dy * px  # = -dy px + dx py exactly (IEEE sums commute)
        if link == 1:
            s -= np.take(flat["cs"], ci)
            r -= np.take(flat["cr"], ci)
        top = np.take(flat["top0" if link == 0 else "top1"], ci)
        np.abs(r, out=r)
        # distance to the grown rectangle: (max(-m - s, s - top, 0), max(|r| - hm, 0)); a
        # rounded difference has the sign of the exact one (gradual underflow), so both are 0
        # exactly when s >= -m, s <= top and |r| <= hm: the tests of _FingerGeometry.hits
        np.subtract(s, top, out=top)
        np.negative(s, out=s)
        s -= m
        np.maximum(s, top, out=s)
        np.maximum(s, 0.0, out=s)
        r -= hm
        np.maximum(r, 0.0, out=r)
        hit |= np.maximum(s, r, out=top) == 0.0  # (before squaring, which may underflow)
        s *= s
        r *= r
        s += r
        np.sqrt(s, out=s)
        s -= 1e-9  # metres; the slack covers the rounding of both ways of computing
        np.maximum(s, 0.0, out=s)
        s /= np.take(flat["sp0" if link == 0 else "sp1"], ci)
        np.minimum(clear, s, out=clear)
    clear[hit] = 0.0
    return hit, clear


def _coarse_sweep(B, sl, qb, A, upper, t, n_t, step, pts, rows, links):
    """The first touching coarse sample of every slice (``k`` (R,), -1 if none) without testing
    every (sample, point) pair: the samples go in order, and each point is tested at a sample
    only when its last test leaves it possibly touching there (conservative advancement: a point
    at Euclidean distance d from a link's rectangle stays off it while the rectangle moves less
    than d), and not after its slice's first touch. Also ``free`` per point (as ``pts``): the
    point is off both links for every path parameter in ``[0, free)``."""
    R, C1 = t.shape
    Q = _paths(qb, A, upper, t)  # (R, C1, 2) every coarse sample
    cfg = _Configs.of(B, sl, Q, links)
    am = abs(B.margin)
    Lm, h = B.Lm[sl], B.h[sl]
    speed_mid = A[0] * np.hypot(Lm + am, h + am)  # (R,) joint 1 turns at most A[0] per unit t
    speed_dis = (A[0] + A[1]) * np.hypot(B.Ld[sl] + am, h + am) + A[0] * Lm
    flat = {f: getattr(cfg, f).reshape(-1) for f in ("d1x", "d1y", "d2x", "d2y", "cs", "cr")}
    flat["hm"] = np.repeat(h + B.margin, C1)  # (R * C1,) per configuration
    flat["top0"] = np.repeat(Lm + B.margin, C1)
    flat["top1"] = np.repeat(B.Ld[sl] + B.margin, C1)
    flat["sp0"] = np.repeat(speed_mid, C1)
    flat["sp1"] = np.repeat(speed_dis, C1)
    valid = np.arange(C1)[None, :] < n_t[:, None]
    palm = (cfg.palm_mid | cfg.palm_dis) & valid
    best = np.where(palm.any(axis=1), np.argmax(palm, axis=1), C1)  # (R,) first touch so far
    t_flat = t.reshape(-1)
    inv_step = np.divide(1.0, step, out=np.full(R, np.inf), where=step > 0)
    free = np.zeros(len(pts))  # each point is off the links for all t in [0, free)
    px, py = B.x[pts], B.y[pts]
    lim = np.minimum(n_t, best)  # (R,) samples beyond this need no test
    # buckets[k]: the points (positions in pts, increasing in each part) to test at coarse
    # sample k; every point starts at sample 0 and, untouched, moves on to the first sample its
    # clearance does not cover
    buckets: list[list[np.ndarray]] = [[] for _ in range(C1)]
    buckets[0].append(np.arange(len(pts)))
    for k in range(C1):  # loop over closing steps, in order: a slice stops at its first touch
        if not buckets[k]:
            continue
        parts, buckets[k] = buckets[k], []
        if k == 0 and np.all(lim > 0):  # every point (no gathers)
            pos, rw, ppx, ppy, f = parts[0], rows, px, py, free
        else:
            pos = parts[0] if len(parts) == 1 else np.concatenate(parts)
            pos = pos[lim[rows[pos]] > k]
            if len(pos) == 0:
                continue
            rw, ppx, ppy, f = rows[pos], px[pos], py[pos], free[pos]
        ci = rw * C1 + k
        hit, clear = _pair_eval(flat, ci, ppx, ppy, B.margin, links)
        tk = np.take(t_flat, ci)
        # the certified intervals (tk - clear, tk + clear) of a point chain up from t = 0 (its
        # next test is at or before tk + clear, unless it is pushed to the next sample)
        free[pos] = np.where(tk - clear < f, np.maximum(f, tk + clear), f)
        if hit.any():
            best[rw[hit]] = k  # the first touch of these slices (the samples go in order)
            lim = np.minimum(n_t, best)
        # next sample that the point may touch at (never beyond the first sample after tk + clear)
        with np.errstate(invalid="ignore", over="ignore"):
            nxt = np.floor((tk + clear) * inv_step[rw])
        nxt = np.where(np.isfinite(nxt), np.minimum(nxt, C1), C1).astype(np.int64)
        nxt = np.maximum(nxt, k + 1)
        keep = np.flatnonzero(~hit & (nxt < lim[rw]))
        if len(keep) == 0:
            continue
        nk = nxt[keep]
        # stable (a radix sort for 16-bit keys): positions stay increasing within each part
        order = keep[np.argsort(nk.astype(np.int16) if C1 < 2**15 else nk, kind="stable")]
        pos, nxt = pos[order], nxt[order]
        cut = np.flatnonzero(np.diff(nxt)) + 1
        starts = np.concatenate([[0], cut])
        ends = np.concatenate([cut, [len(nxt)]])
        for a, b in zip(starts, ends, strict=True):  # loop over distinct next samples (< C1)
            buckets[int(nxt[a])].append(pos[a:b])
    k = np.where(best < n_t, best, -1)
    return k, free


@dataclass
class _BatchEvents:
    """First events of one phase for R slices (arrays (R,) unless noted)."""

    t: np.ndarray  # (R, n_steps + 1) coarse samples (only the first ``n_t`` are used)
    n_t: np.ndarray  # number of coarse samples (n_steps + 1, or 1 when t_end <= 0)
    k: np.ndarray  # first touching coarse sample, -1 if none
    t_free: np.ndarray
    t_hit: np.ndarray  # nan if none
    middle_hit: np.ndarray
    distal_hit: np.ndarray
    palm: np.ndarray
    middle_idx: np.ndarray  # point (index into B.P), -1 if none
    distal_idx: np.ndarray


def _batch_first_events(
    B: _SliceBatch,
    sl: np.ndarray,
    qb: np.ndarray,
    A: np.ndarray,
    t_end: np.ndarray,
    n_steps: int,
    links: tuple[bool, bool],
    may_touch: np.ndarray | None = None,
) -> _BatchEvents:
    """``_first_event`` for the slices ``sl`` (R,) (distinct, increasing) with paths
    ``min(qb + A t, upper)`` (qb (R, 2)) and parameter ranges ``t_end`` (R,), level by level
    for all slices together. ``may_touch`` (N,) bool: only these points can touch a link along
    the paths (an exact superset; None: all points)."""
    R = len(sl)
    upper = B.upper[sl]
    m = B.margin
    # coarse samples: np.linspace(0, t_end, n_steps + 1) (arange * step + 0, last = t_end)
    n_t = np.where(t_end > 0, n_steps + 1, 1)
    step = np.where(t_end > 0, t_end, 0.0) / n_steps
    t = np.arange(n_steps + 1, dtype=np.float64)[None, :] * step[:, None]
    t += 0.0
    t[:, -1] = np.where(t_end > 0, t_end, 0.0)
    pts_all, rows_all = _points_of(B, sl)
    if may_touch is not None:
        sel = may_touch[pts_all]
        pts_all, rows_all = pts_all[sel], rows_all[sel]
    k, free = _coarse_sweep(B, sl, qb, A, upper, t, n_t, step, pts_all, rows_all, links)
    has = k >= 0
    lo = np.zeros(R)
    hi = np.zeros(R)
    pos = has & (k > 0)
    lo[pos] = t[pos, k[pos] - 1]
    hi[pos] = t[pos, k[pos]]
    # the points that may touch a link in [lo, hi]: those that the sweep did not certify off the
    # links over [0, hi] (an exact superset)
    r_all = rows_all
    near = has[r_all] & ~(hi[r_all] < free)
    p_near, r_near = pts_all[near], r_all[near]
    # of those, the ones that may touch a link between the bracket's ends along the path
    # (_may_touch: the same exact superset, from the distances at hi)
    Qb = _paths(qb, A, upper, np.stack([lo, hi], axis=1))  # (R, 2, 2)
    qa, qz = Qb[r_near, 0], Qb[r_near, 1]
    d1 = np.abs(qz[:, 0] - qa[:, 0])
    d2 = np.abs((qz[:, 0] + qz[:, 1]) - (qa[:, 0] + qa[:, 1]))
    P_near = B.P[p_near]
    rho = np.sqrt(np.einsum("ij,ij->i", P_near, P_near))
    lm = B.Lm[B.seg[p_near]]
    keep = np.zeros(len(p_near), dtype=bool)
    if links[0]:
        keep |= _batch_distance(B, qz, p_near, 0) <= m + rho * d1 + 1e-9
    if links[1]:
        keep |= _batch_distance(B, qz, p_near, 1) <= m + (rho + lm) * d2 + lm * d1 + 1e-9
    p_near, r_near = p_near[keep], r_near[keep]
    # refinement of [last free, first touching], all slices level by level, each with its own
    # number of samples per level (as _first_event: _REFINE_BUDGET // points within reach)
    ref = np.flatnonzero(pos)
    if len(ref):
        cnt = B.count[sl[ref]]
        n_ref = np.maximum(1, np.minimum(_REFINE_SAMPLES, _REFINE_BUDGET // np.maximum(cnt, 1)))
        row_of = np.full(R, -1, dtype=np.int64)
        row_of[ref] = np.arange(len(ref))
        sel = row_of[r_near] >= 0
        p_ref, r_ref = p_near[sel], row_of[r_near[sel]]
        f_lo, f_hi = lo[ref], hi[ref]
        n_max = int(n_ref.max())
        j_all = np.arange(1, n_max + 1, dtype=np.float64)[None, :]
        while True:
            live = np.flatnonzero(f_hi - f_lo > HAND_CLOSING_ANGLE_TOL)
            if len(live) == 0:
                break
            # np.linspace(lo, hi, n_ref + 2)[1:-1] per slice, padded to n_max samples
            stp = (f_hi[live] - f_lo[live]) / (n_ref[live] + 1)
            ts = j_all * stp[:, None]
            ts += f_lo[live][:, None]
            valid = j_all <= n_ref[live][:, None]
            ts = np.where(valid, ts, f_hi[live][:, None])
            Q = _paths(qb[ref[live]], A, upper[ref[live]], ts)
            cfg = _Configs.of(B, sl[ref[live]], Q, links)
            row_of = np.full(len(ref), -1, dtype=np.int64)
            row_of[live] = np.arange(len(live))
            sel = row_of[r_ref] >= 0
            hit = _any_hit_ragged(B, cfg, p_ref[sel], row_of[r_ref[sel]], n_ref[live], links)
            found = hit.any(axis=1)
            j = np.argmax(hit, axis=1)
            rows = np.arange(len(live))
            prev = np.where(j > 0, ts[rows, np.maximum(j - 1, 0)], f_lo[live])
            f_lo[live] = np.where(found, prev, ts[rows, n_ref[live] - 1])
            f_hi[live] = np.where(found, ts[rows, j], f_hi[live])
        lo[ref], hi[ref] = f_lo, f_hi
    # the event at hi (tested on the points that may touch there, a superset of those that do):
    # the touching point of least distance per link
    ev = np.flatnonzero(has)
    mid_idx = np.full(R, -1, dtype=np.int64)
    dis_idx = np.full(R, -1, dtype=np.int64)
    middle_hit = np.zeros(R, dtype=bool)
    distal_hit = np.zeros(R, dtype=bool)
    palm = np.zeros(R, dtype=bool)
    if len(ev):
        Qh = _paths(qb[ev], A, upper[ev], hi[ev][:, None])  # (E, 1, 2)
        cfg = _Configs.of(B, sl[ev], Qh, links)
        row_of = np.full(R, -1, dtype=np.int64)
        row_of[ev] = np.arange(len(ev))
        p_ev, r_ev = p_near, row_of[r_near]
        a, b = _pair_hits(B, cfg, r_ev, p_ev, links)
        q_free = _paths(qb[ev], A, upper[ev], lo[ev][:, None])[:, 0]  # (E, 2)
        for link, hits, out in ((0, a[:, 0], mid_idx), (1, b[:, 0], dis_idx)):
            if not hits.any():
                continue
            cand, crow = p_ev[hits], r_ev[hits]
            dist = _batch_distance(B, q_free[crow], cand, link)
            order = np.lexsort((cand, dist, crow))  # per row: least distance, then lowest index
            cand, crow, dist = cand[order], crow[order], dist[order]
            first = np.flatnonzero(np.concatenate([[True], crow[1:] != crow[:-1]]))
            best = cand[first]
            # a near-tie of two distances (the single version's matrix product may round the
            # last bit otherwise): decide it with _FingerGeometry.distance itself
            nxt = first + 1
            ok = nxt < len(crow)
            tie = np.zeros(len(first), dtype=bool)
            tie[ok] = (crow[nxt[ok]] == crow[first[ok]]) & (
                dist[nxt[ok]] - dist[first[ok]] <= 1e-15
            )
            for i in np.flatnonzero(tie):  # rare
                e = crow[first[i]]
                c = p_ev[hits][r_ev[hits] == e]
                s = sl[ev[e]]
                geo = _FingerGeometry(B.fingers[s], m, B.palm)
                best[i] = c[np.argmin(geo.distance(q_free[e], B.P[c], link))]
            out[ev[crow[first]]] = best
        am = np.zeros(len(ev), dtype=bool)
        bm = np.zeros(len(ev), dtype=bool)
        am[r_ev[a[:, 0]]] = True
        bm[r_ev[b[:, 0]]] = True
        middle_hit[ev] = am | cfg.palm_mid[:, 0]
        distal_hit[ev] = bm | cfg.palm_dis[:, 0]
        palm[ev] = cfg.palm_mid[:, 0] | cfg.palm_dis[:, 0]
    t_free = np.where(has, lo, t[np.arange(R), n_t - 1])
    return _BatchEvents(
        t=t,
        n_t=n_t,
        k=k,
        t_free=t_free,
        t_hit=np.where(has, hi, np.nan),
        middle_hit=middle_hit,
        distal_hit=distal_hit,
        palm=palm,
        middle_idx=mid_idx,
        distal_idx=dis_idx,
    )


def _load_visual(urdf_path: Path, link, materials: dict) -> trimesh.Trimesh:
    """The link's visual mesh in its link frame, coloured by its URDF material."""
    if len(link.visuals) != 1 or link.visuals[0].geometry.mesh is None:
        raise HandModelError(f"hand URDF {urdf_path}: link {link.name} needs one visual <mesh>")
    vis = link.visuals[0]
    mesh_path = urdf_path.parent / vis.geometry.mesh.filename
    if not mesh_path.is_file():
        raise HandModelError(
            f"hand mesh {mesh_path} (link {link.name}) is missing; run scripts/make_hand_meshes.py"
        )
    mesh = trimesh.load(str(mesh_path), force="mesh")
    if vis.origin is not None:
        mesh.apply_transform(vis.origin)
    rgba = (0.7, 0.7, 0.7, 1.0)
    mat = vis.material
    if mat is not None and mat.color is None and mat.name in materials:
        mat = materials[mat.name]  # a reference to a robot-level material
    if mat is not None and mat.color is not None:
        rgba = tuple(mat.color.rgba)
    mesh.visual.face_colors = np.round(np.asarray(rgba) * 255).astype(np.uint8)
    return mesh


@functools.lru_cache(maxsize=4)
def load_hand(urdf_path: Path | str | None = None) -> Hand:
    """:meth:`Hand.load`, cached per path (the model is immutable)."""
    return Hand.load(urdf_path)
