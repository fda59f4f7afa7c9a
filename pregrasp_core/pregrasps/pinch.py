"""Fingertip pinches from above for parts standing on the support plane (:func:`pinch_samples`).

A decision beyond the paper (``docs/pregrasps.md`` section 6b). The paper's enclosing surfaces
put the hand at a fixed preshape on a sphere, cylinder or circle around the part; for a part a
few centimetres high on a table the fully open hand (0.12 m fingers) then reaches below the
table from every direction but straight down, and from straight down the open fingertips land
on the table far from the part. A person picks such a part up with the fingertips from above,
the hand opened just wider than the part. So every candidate whose top face is free also gets
pinches from above:

- the hand approaches straight down (``-up``), the palm parallel to the table;
- the preshape adapts to the part: the fingers' flexion is the first configuration along
  :data:`PINCH_PATH` (from nearly closed to the widest opening) whose fingertip gap exceeds the
  part's width across the pinch by ``2 * PINCH_MARGIN``;
- two kinds, by the part's length along the hand's x axis (the direction the fingers are spread
  along at spread 0): a part at least :data:`TIP_MIN_LENGTH` long gets the three-finger tip
  (thumb against f1 and f2, spread 0) across its width, at positions along its length; a
  shorter part gets a tripod (spread :data:`TRIPOD_SPREAD`, three fingertips around it,
  labelled ``spherical``) about its centre, opened to the part's horizontal diagonal;
- the hand is placed so that its fingertips are at the part's mid-height, or higher when the
  fingers are too short for that (the palm stays ``standoff`` above the part's top).

Two fingertips alone (the paper's two-finger tip) never give force closure with point contacts
(two contacts leave the torque about the line through them free, ``docs/quality.md``), which is
why the small-part pinches use three fingers.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from ..box import OrientedBox
from ..facemask import FACE_NORMAL, SupportPlane
from ..geometry import box_corners
from .params import SamplingParams
from .surfaces import SURFACES, _grid

if TYPE_CHECKING:
    from ..hand import Hand

PINCH_MARGIN: float = 0.008
"""Metres: the fingertips' inner edges start this far outside the part on each side."""

TIP_MIN_LENGTH: float = 0.036
"""Metres: shortest part (along the hand's x axis) whose sides both f1 and f2 reach in the
three-finger tip at spread 0 (their flexion planes are 0.028 m either side of the thumb's and
the fingers 0.02 m wide: 2 x (0.028 - 0.01)); shorter parts get the tripod."""

MAX_TILT_COS: float = float(np.cos(np.deg2rad(30.0)))
"""A box's top face must face up within 30 degrees for pinches from above."""

TRIPOD_SPREAD: float = float(np.deg2rad(60.0))
"""Radians: the tripod's spread. The three closing lines of this hand never meet in one point
(the spreading fingers' flexion planes are offset from their axes); at 40 degrees they pass
within 9 mm of each other (at the spherical pi/3, 14 mm), so the three 0.02 m wide fingertips
all reach a part 1.5 cm across, while f1 and f2 still close 80 degrees apart."""

PINCH_SURFACE: int = SURFACES.index("pinch")
"""Index of ``"pinch"`` in :data:`~pregrasp_core.pregrasps.surfaces.SURFACES`."""

FINGERS: tuple[str, ...] = ("thumb", "f1", "f2")
"""The three fingers a pinch closes."""

KINDS: dict[str, tuple[str, float]] = {
    "tip": ("three_finger_tip", 0.0),
    "tripod": ("spherical", TRIPOD_SPREAD),
}
"""Pinch kind -> (grasp type label, spread)."""


def pinch_center(hand: Hand, kind: str) -> np.ndarray:
    """(2,) hand frame x, y of the line the part's centre goes on: for ``tip`` the thumb's
    flexion plane half-way between the thumb's and the fingers' bases; for ``tripod`` the point
    nearest (least squares) the three closing lines in the palm plane."""
    spread = KINDS[kind][1]
    planes = [hand.flexion_plane(f, spread) for f in FINGERS]
    if kind == "tip":
        return np.array([planes[0].origin[0], 0.5 * (planes[0].origin[1] + planes[1].origin[1])])
    A = np.zeros((2, 2))
    b = np.zeros(2)
    for p in planes:  # loop over the three fingers
        n = np.array([-p.v[1], p.v[0]])  # in-plane normal of the closing line
        A += np.outer(n, n)
        b += n * (n @ p.origin[:2])
    return np.linalg.solve(A, b)


def _tip_ik(
    L1: float, L2: float, beta: float, u: float, v: float, lower: np.ndarray, upper: np.ndarray
) -> tuple[float, float] | None:
    """Flexion (q1, q2) putting a finger's tip inner edge at (u, v) of its flexion plane: links
    ``L1`` (middle) and ``L2`` (distal joint to the inner edge, turned ``beta`` from the distal
    axis); of the two solutions within the limits the one whose distal link is nearer the
    approach; ``None`` when out of reach or limits."""
    cos2 = (u * u + v * v - L1 * L1 - L2 * L2) / (2.0 * L1 * L2)
    if abs(cos2) > 1.0:
        return None
    best: tuple[float, float] | None = None
    for sgn in (1.0, -1.0):  # the two solutions
        a2 = sgn * float(np.arccos(cos2))
        q1 = float(np.arctan2(v, u) - np.arctan2(L2 * np.sin(a2), L1 + L2 * np.cos(a2)))
        q = np.array([q1, a2 - beta])
        if np.all(q >= lower - 1e-12) and np.all(q <= upper + 1e-12):
            if best is None or abs(q.sum()) < abs(sum(best)):
                best = (float(q[0]), float(q[1]))
    return best


def pinch_preshape(hand: Hand, kind: str, half_width: float) -> tuple[np.ndarray, float] | None:
    """The pinch preshape (J,) for a part of half width ``half_width`` about
    :func:`pinch_center`, and the depth of its fingertips below the palm plane (metres).

    Every fingertip's inner edge starts ``half_width + PINCH_MARGIN`` from the centre along its
    finger's closing direction (each finger opens only as far as the part needs), and all three
    at the same depth: first each finger straight, turned about its proximal joint to that
    distance (a straight finger keeps its tip deepest); the common depth is the shallowest of
    the three, and the other fingers bend their distal joints to bring their tips up to it
    (two-link inverse kinematics in the flexion plane). ``None`` when a finger cannot reach
    its point within its joint limits or the preshape collides with itself."""
    spread = KINDS[kind][1]
    c = pinch_center(hand, kind)
    q = np.zeros(len(hand.joint_names))
    q[list(hand.joint_names).index("f1_spread")] = spread
    target = []  # per finger: (finger, plane, v, straight q1, straight depth)
    for name in FINGERS:  # loop over the three fingers
        f = hand.finger(name)
        p = hand.flexion_plane(name, spread)
        v = float((c - p.origin[:2]) @ p.v[:2]) - (half_width + PINCH_MARGIN)
        # inner edge of the straight finger's tip at angle q1: (L cos q1 - t/2 sin q1,
        # L sin q1 + t/2 cos q1) = R (cos(q1 + g), sin(q1 + g)) in the flexion plane
        L = f.middle_length + f.distal_length
        R = float(np.hypot(L, 0.5 * f.thickness))
        g = float(np.arctan2(0.5 * f.thickness, L))
        if abs(v) > R:
            return None
        q1 = float(np.arcsin(v / R)) - g
        target.append((f, p, v, q1, float(p.origin[2]) + R * float(np.cos(q1 + g))))
    depth = min(t[4] for t in target)
    for f, p, v, q1, d in target:  # loop over the three fingers
        if d - depth < 1e-9:
            flex: tuple[float, float] | None = (q1, 0.0)
            if not (f.lower[0] - 1e-12 <= q1 <= f.upper[0] + 1e-12):
                return None
        else:
            L2 = float(np.hypot(f.distal_length, 0.5 * f.thickness))
            beta = float(np.arctan2(0.5 * f.thickness, f.distal_length))
            flex = _tip_ik(
                f.middle_length, L2, beta, depth - float(p.origin[2]), v, f.lower, f.upper
            )
            if flex is None:
                return None
        q[list(f.flex_index)] = flex
    q = np.asarray(hand.clamp(q), dtype=np.float64)
    return None if hand.self_collision(q) else (q, depth)


@dataclass(frozen=True)
class PinchSamples:
    """Pinch pre-grasps of one box (world frame), before the pool's filters."""

    T_world_hand: np.ndarray
    """(M, 4, 4) hand poses."""
    q: np.ndarray
    """(M, J) adapted preshapes."""
    grasp_type: np.ndarray
    """(M,) grasp type labels."""
    spread: np.ndarray
    """(M,) spreads."""
    face: int
    """The box face the pinches come from (the top face)."""


def pinch_samples(
    hand: Hand,
    box: OrientedBox,
    support: SupportPlane,
    params: SamplingParams,
) -> PinchSamples | None:
    """Pinches from above of ``box`` (see the module docstring); ``None`` when the box's top
    face is tilted more than 30 degrees from the table or no preshape encloses the part."""
    up = support.normal
    n_world = FACE_NORMAL @ box.rotation.T  # (6, 3) face normals, world
    top = int(np.argmax(n_world @ up))
    if float(n_world[top] @ up) < MAX_TILT_COS:
        return None
    corners = box_corners(box.T_world_box[None], box.half_extents[None])  # (8, 3)
    heights = corners @ up  # (8,)
    z_top, z_bottom = float(heights.max()), max(float(heights.min()), support.height)
    in_plane = [a for a in range(3) if a != top // 2]
    poses, qs, types, spreads = [], [], [], []
    for a_close, a_along in (in_plane, in_plane[::-1]):  # pinch across each in-plane axis
        c_dir = box.rotation[:, a_close] - (box.rotation[:, a_close] @ up) * up
        c_dir /= np.linalg.norm(c_dir)
        x_dir = np.cross(c_dir, -up)  # hand x = y x z with y = closing, z = approach
        width, length = float(box.extents[a_close]), float(box.extents[a_along])
        kind = "tip" if length >= TIP_MIN_LENGTH else "tripod"
        if kind == "tripod":  # the tripod encloses the whole cross-section (its diagonal)
            width = float(np.hypot(width, length))
        gt, spread = KINDS[kind]
        got = pinch_preshape(hand, kind, 0.5 * width)
        if got is None:
            continue
        q_pinch, depth = got
        c = pinch_center(hand, kind)
        if kind == "tip":
            half_run = max(0.5 * length - 0.5 * TIP_MIN_LENGTH, 0.0)
            offsets = _grid(half_run, params.interval)  # along the hand's x, symmetric
        else:
            offsets = np.zeros(1)
        z_tip = max(0.5 * (z_top + z_bottom), z_top + params.standoff - depth)
        centre = box.center - (box.center @ up) * up  # the box centre projected on z = 0
        for sign in (1.0, -1.0):  # both rolls: thumb on either side
            y = sign * c_dir
            x = sign * x_dir
            R = np.stack([x, y, -up], axis=1)  # (3, 3) columns = hand axes in the world
            for off in offsets:  # a few positions along the part
                p_c = centre + off * x + z_tip * up  # where the tips' centre goes
                origin = p_c - R @ np.array([c[0], c[1], depth])
                T = np.eye(4)
                T[:3, :3] = R
                T[:3, 3] = origin
                poses.append(T)
                qs.append(q_pinch)
                types.append(gt)
                spreads.append(spread)
    if not poses:
        return None
    return PinchSamples(
        T_world_hand=np.stack(poses),
        q=np.stack(qs),
        grasp_type=np.array(types, dtype="<U16"),
        spread=np.array(spreads),
        face=top,
    )
