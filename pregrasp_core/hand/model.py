"""The hand's value types: the model read from the URDF, fingers, flexion planes, the closing
model's results, and the names and defaults the other hand modules share.

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

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import trimesh
import yourdfpy

from ..geometry import as_points
from ..shape import GRASP_TYPES

FINGER_NAMES: tuple[str, ...] = ("thumb", "f1", "f2")
"""Finger names; finger ``n`` has links ``n_knuckle, n_middle, n_distal`` and joints
``n_j1, n_j2`` (and ``n_spread`` for f1, f2)."""

DEFAULT_COUPLING: float = 1.0
"""Closing model: distal joint speed / proximal joint speed while both close together
(tendon coupling; 1.0 = both joints close at the same rate)."""

DEFAULT_CLOSING_STEPS: int = 64
"""Closing model: samples along each closing phase before the first touching step is refined."""


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
        p = as_points(p_hand, "p_hand")
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


@dataclass(frozen=True)
class Joint:
    """One URDF joint of the kinematic chain, with what the forward kinematics needs."""

    name: str
    """The URDF joint name."""
    parent: str
    """Parent link name."""
    child: str
    """Child link name."""
    origin: np.ndarray
    """(4, 4) ``T_parent_joint``: the joint frame in the parent link's frame."""
    axis: np.ndarray | None
    """(3,) unit rotation axis in the joint frame; None for a fixed joint."""
    source: int
    """Index in ``q`` of the actuated joint that drives this one (-1 for a fixed joint)."""
    multiplier: float
    """Angle = ``multiplier * q[source] + offset`` (a mimic joint's multiplier, else 1)."""
    offset: float
    """See ``multiplier`` (a mimic joint's offset, else 0)."""
    parent_index: int
    """Index of the parent link in ``HandModel.link_names``."""
    child_index: int
    """Index of the child link in ``HandModel.link_names``."""
    K: np.ndarray | None
    """(3, 3) cross-product matrix of ``axis`` (None for a fixed joint)."""
    K2: np.ndarray | None
    """(3, 3) ``K @ K`` (None for a fixed joint)."""


@dataclass(frozen=True, eq=False)
class HandModel:
    """The kinematic and geometric description of the hand, as read from its URDF
    (:func:`pregrasp_core.hand.urdf.load_model`); :class:`pregrasp_core.hand.Hand` adds the
    queries. Immutable (its arrays are read-only)."""

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
    chain: tuple[Joint, ...] = field(repr=False)
    """Every URDF joint (fixed, actuated and mimic) in topological order: parents first."""

    @property
    def n_joints(self) -> int:
        """J, the number of actuated joints."""
        return len(self.joint_names)

    def as_q(self, q: np.ndarray) -> tuple[np.ndarray, bool]:
        """Coerce ``q`` to (B, J); the flag says whether the input was a single (J,) vector."""
        arr = np.asarray(q, dtype=np.float64)
        J = self.n_joints
        if arr.ndim == 1 and arr.shape[0] == J:
            return arr[None, :], True
        if arr.ndim == 2 and arr.shape[1] == J:
            return arr, False
        raise ValueError(f"q must have shape ({J},) or (B, {J}), got {arr.shape}")

    def one_q(self, q: np.ndarray) -> np.ndarray:
        """``q`` as one configuration (J,) float64 (:meth:`as_q`'s coercion); a ``ValueError``
        for a batch (B, J) or any other shape."""
        Q, single = self.as_q(q)
        if not single:
            raise ValueError(f"q must have shape ({self.n_joints},), got {Q.shape}")
        return Q[0]

    def finger(self, finger: str | Finger) -> Finger:
        """The :class:`Finger` with this name (or the finger itself)."""
        if isinstance(finger, Finger):
            return finger
        for f in self.fingers:
            if f.name == finger:
                return f
        raise ValueError(f"unknown finger {finger!r}; expected one of {FINGER_NAMES}")
