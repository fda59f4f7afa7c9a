"""Fingertip pinches: from above for parts on the table, across the thickness of thin parts
(:func:`pinch_samples`).

Decisions beyond the paper (``docs/pregrasps.md`` section 6b). The paper's enclosing surfaces
put the hand at a fixed preshape on a sphere, cylinder or circle around the part; for a part a
few centimetres high on a table the open hand (0.12 m fingers) then reaches below the table
from every direction but straight down, and from straight down the open fingertips land on the
table far from the part. A person picks such a part up with the fingertips, the hand opened
just wider than the part. So every candidate also gets pinches:

- **from above** (with a support plane): the hand approaches straight down, the palm parallel
  to the table, across each of the two horizontal axes of the part's box when its top face is
  within 30 degrees of level, else of its upright box (:func:`~pregrasp_core.mvbb.upright_box`:
  a ball's minimum box can stand on an edge); the fingertips start at the part's mid-height
  (higher when the fingers are too short for that: the palm stays ``standoff`` above the
  part) and the planner's approach then goes on until the part or the table stops it;
- **across a thin part** (smallest box side at most :data:`THIN_PART`: a handle, a wall, a
  wing): from each face around its rim (not from under the table), across the thickness; the
  fingertips start ``standoff`` outside the part and the approach ends at most half a
  thickness inside it (``PreGraspPool.approach_limit``), so that they close on the part and
  not on what lies behind it (the mug's body behind its handle).

The preshape adapts to the part (:func:`pinch_preshape`): every finger straight, turned about
its proximal joint so that its fingertip starts :data:`PINCH_MARGIN` outside the part, all
three fingertips at one depth. Two kinds, by the part's length along the hand's x axis (the
direction f1 and f2 are spread along at spread 0): a part at least :data:`TIP_MIN_LENGTH` long
gets the three-finger tip (thumb against f1 and f2, spread 0) at positions along it; a
shorter part a tripod (spread :data:`TRIPOD_SPREAD`, three fingertips around it, labelled
``spherical``) opened to its cross-section's diagonal. Two fingertips alone (the paper's
two-finger tip) never give force closure with point contacts (two contacts leave the torque
about the line through them free, ``docs/quality.md``), which is why every pinch uses three.
"""

from __future__ import annotations

import weakref
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from ..box import OrientedBox
from ..facemask import FACE_NORMAL, SupportPlane
from ..geometry import box_corners
from ..mvbb import upright_box
from .collision import preshape_box_poses, preshape_box_poses_many
from .params import SamplingParams
from .surfaces import SURFACES, centred_grid, grid_sizes

if TYPE_CHECKING:
    from ..hand import Hand

PINCH_MARGIN: float = 0.008
"""Metres: the fingertips' inner edges start this far outside the part on each side."""

TIP_MIN_LENGTH: float = 0.036
"""Metres: shortest part (along the hand's x axis) whose sides both f1 and f2 reach in the
three-finger tip at spread 0 (their flexion planes are 0.028 m either side of the thumb's and
the fingers 0.02 m wide: 2 x (0.028 - 0.01)); shorter parts get the tripod."""

THIN_PART: float = 0.015
"""Metres: a part whose smallest box side is at most this (a handle, a wall, a wing) also gets
pinches across its thickness from every face around its rim."""

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
    at the same depth: first each finger on its own, its distal link parallel to the approach
    when the proximal joint can reach that distance so (between -30 and +15 degrees: the
    distal link's inner face meets the part's side), else straight, turned about its proximal
    joint (inwards for parts under about 1.5 cm, outwards for parts over about 7 cm); the
    common depth is the shallowest of the three, and the
    other fingers bend to bring their tips up to it (two-link inverse kinematics in the
    flexion plane). ``None`` when a finger cannot reach its point within its joint limits or
    the preshape collides with itself."""
    got = _pinch_flexions(hand, kind, half_width)
    if got is None:
        return None
    q, depth = got
    # the box poses kept per preshape: the pool's height and collision tests reuse them
    return None if hand.self_collisions(q, preshape_box_poses(hand, q)) else (q, depth)


def _pinch_flexions(hand: Hand, kind: str, half_width: float) -> tuple[np.ndarray, float] | None:
    """:func:`pinch_preshape` before its self-collision check: the clamped preshape and the
    depth, ``None`` when a finger cannot reach its point within its joint limits."""
    spread = KINDS[kind][1]
    c = _center(hand, kind)
    q = np.zeros(len(hand.joint_names))
    q[list(hand.joint_names).index("f1_spread")] = spread
    target = []  # per finger: (finger, plane, v, first flexion, its depth)
    for name in FINGERS:  # loop over the three fingers
        f = hand.finger(name)
        p = hand.flexion_plane(name, spread)
        v = float((c - p.origin[:2]) @ p.v[:2]) - (half_width + PINCH_MARGIN)
        t2 = 0.5 * f.thickness
        a = float(np.arcsin(np.clip((v - t2) / f.middle_length, -1.0, 1.0)))
        if abs(v - t2) <= f.middle_length and f.lower[0] <= a <= -f.lower[1]:
            # the distal link parallel to the approach (j2 = -j1): its inner face, not a
            # corner, meets the part's side
            first = (a, -a)
            d = float(p.origin[2]) + f.middle_length * float(np.cos(a)) + f.distal_length
        else:
            # a straight finger turned about j1: the inner edge of its tip at angle q1 is
            # R (cos(q1 + g), sin(q1 + g)) in the flexion plane
            L = f.middle_length + f.distal_length
            R = float(np.hypot(L, t2))
            g = float(np.arctan2(t2, L))
            if abs(v) > R:
                return None
            q1 = float(np.arcsin(v / R)) - g
            if not (f.lower[0] - 1e-12 <= q1 <= f.upper[0] + 1e-12):
                return None
            first = (q1, 0.0)
            d = float(p.origin[2]) + R * float(np.cos(q1 + g))
        target.append((f, p, v, first, d))
    depth = min(t[4] for t in target)
    for f, p, v, start, d in target:  # loop over the three fingers
        flex: tuple[float, float] | None = start
        if d - depth > 1e-9:
            L2 = float(np.hypot(f.distal_length, 0.5 * f.thickness))
            beta = float(np.arctan2(0.5 * f.thickness, f.distal_length))
            flex = _tip_ik(
                f.middle_length, L2, beta, depth - float(p.origin[2]), v, f.lower, f.upper
            )
            if flex is None:
                return None
        q[list(f.flex_index)] = flex
    return np.asarray(hand.clamp(q), dtype=np.float64), depth


_HAND_PINCHES: weakref.WeakKeyDictionary[Hand, dict[tuple[str, float | None], Any]] = (
    weakref.WeakKeyDictionary()
)

HAND_PINCHES_KEPT: int = 4096
"""Pinch preshapes and centres kept per hand by :func:`_pinch_cache` (then it starts again)."""


def _pinch_cache(hand: Hand) -> dict[tuple[str, float | None], Any]:
    """The hand's cache of :func:`pinch_preshape` and :func:`pinch_center`: both are functions
    of their arguments only, and a pool asks for the same ones many times (both rolls of a
    tripod, every candidate, every pool of the viewer's re-plans)."""
    cache = _HAND_PINCHES.get(hand)
    if cache is None or len(cache) > HAND_PINCHES_KEPT:
        cache = {}
        _HAND_PINCHES[hand] = cache
    return cache


def _center(hand: Hand, kind: str) -> np.ndarray:
    """:func:`pinch_center`, computed once per hand and kind (read-only)."""
    cache = _pinch_cache(hand)
    got = cache.get((kind, None))
    if got is None:
        got = cache[(kind, None)] = pinch_center(hand, kind)
        got.setflags(write=False)
    return got


def _preshape(hand: Hand, kind: str, half_width: float) -> tuple[np.ndarray, float] | None:
    """:func:`pinch_preshape`, computed once per hand, kind and half width (the preshape
    read-only: the pool stacks copies of it)."""
    cache = _pinch_cache(hand)
    key = (kind, float(half_width))
    if key not in cache:
        got = pinch_preshape(hand, kind, half_width)
        if got is not None:
            got[0].setflags(write=False)
        cache[key] = got
    return cache[key]


def _preshapes(
    hand: Hand, kind: str, halves: Sequence[float]
) -> list[tuple[np.ndarray, float] | None]:
    """:func:`_preshape` of each half width of ``halves``, those not kept yet together: their
    preshapes one by one (:func:`_pinch_flexions`), their box poses by one batched forward
    kinematics (kept per preshape, :func:`~.collision.preshape_box_poses_many`) and one batched
    self-collision check (``Hand.self_collisions_many``: each verdict that of its own
    ``self_collisions``), the same values as :func:`_preshape` of each."""
    cache = _pinch_cache(hand)
    keys = [(kind, float(h)) for h in halves]
    found = []
    for key in dict.fromkeys(k for k in keys if k not in cache):  # new half widths, once each
        got = _pinch_flexions(hand, kind, float(key[1]))
        if got is None:
            cache[key] = None
        else:
            found.append((key, got))
    if found:
        Q = np.stack([g[0] for _, g in found])
        hits = hand.self_collisions_many(Q, preshape_box_poses_many(hand, Q))
        for (key, (q, depth)), hit in zip(found, hits, strict=True):
            q.setflags(write=False)
            cache[key] = None if hit else (q, depth)
    return [cache[k] for k in keys]


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
    approach_limit: np.ndarray
    """(M,) metres: the longest approach from each (``inf`` for pinches from above, which go
    down until they meet the part or the table)."""
    face: np.ndarray
    """(M,) int64: the box face each pinch comes from (the hand approaches against its
    normal)."""


def _face_pinches(
    hand: Hand,
    box: OrientedBox,
    face: int,
    d: np.ndarray,
    closing_axes: tuple[int, ...],
    floor: float | None,
    kinds: tuple[str, ...],
    every_kind: bool,
    params: SamplingParams,
    points: np.ndarray | None = None,
) -> list[tuple[np.ndarray, np.ndarray, str, float, float]]:
    """Pinches approaching ``box`` along ``-d`` (d: unit, world, about the outward normal of
    ``face``), closing across each box axis of ``closing_axes`` (projected perpendicular to
    ``d``), with the fingertips at the part's middle along ``d`` (not below ``floor`` along
    ``d``, the table) or higher when the fingers are too short: ``(T_world_hand, q, grasp
    type, spread, approach limit)`` each. ``kinds``: the pinch kinds allowed (the tip only
    across a part at least ``TIP_MIN_LENGTH`` long); ``every_kind``: all of them, else the
    first that fits."""
    corners = box_corners(box.T_world_box[None], box.half_extents[None])  # (8, 3)
    heights = corners @ d  # (8,)
    z_top, z_bottom = float(heights.max()), float(heights.min())
    if floor is not None:
        z_bottom = max(z_bottom, floor)
    out = []
    for a_close in closing_axes:  # pinch across each axis
        a_along = 3 - face // 2 - a_close
        c_dir = box.rotation[:, a_close] - (box.rotation[:, a_close] @ d) * d
        c_dir /= np.linalg.norm(c_dir)
        x_dir = np.cross(c_dir, -d)  # hand x = y x z with y = closing, z = approach
        width, length = float(box.extents[a_close]), float(box.extents[a_along])
        chosen = [k for k in kinds if k != "tip" or length >= TIP_MIN_LENGTH]
        if not every_kind:  # by the part's size: the tip when it fits along, else the tripod
            chosen = chosen[:1]
        for kind in chosen:
            out += _placed(
                hand,
                box,
                kind,
                width,
                length,
                c_dir,
                x_dir,
                d,
                z_top,
                z_bottom,
                floor,
                params,
                points,
            )
    return out


def _kind_setup(
    hand: Hand,
    kind: str,
    width: float,
    length: float,
    floor: float | None,
    points: np.ndarray | None,
    params: SamplingParams,
) -> tuple[float, str, float, np.ndarray, np.ndarray, np.ndarray | None, float]:
    """What the placements of one kind start from (:func:`_placed`): ``(width, grasp type,
    spread, tips' centre, offsets along the part, fx, band)``. The tripod encloses the whole
    cross-section (its diagonal is its width); the tip goes to positions along the part
    (the hand's x, symmetric), the tripod about its centre. ``fx`` (3,), the fingers' x
    positions relative to the thumb's plane, and ``band``, the half width of the slice a finger
    closes on, only for a tip from above given the part's points (``fx`` None otherwise)."""
    if kind == "tripod":
        width = float(np.hypot(width, length))
    gt, spread = KINDS[kind]
    c = _center(hand, kind)
    if kind == "tip":
        half_run = max(0.5 * length - 0.5 * TIP_MIN_LENGTH, 0.0)
        offsets = centred_grid(half_run, params.interval)
    else:
        offsets = np.zeros(1)
    fx: np.ndarray | None = None
    band = 0.0
    if kind == "tip" and floor is not None and points is not None and len(points) > 0:
        fx = np.array([hand.flexion_plane(f, 0.0).origin[0] - c[0] for f in FINGERS])
        band = 0.5 * hand.finger("thumb").width
    return width, gt, spread, c, offsets, fx, band


def _placed(
    hand: Hand,
    box: OrientedBox,
    kind: str,
    width: float,
    length: float,
    c_dir: np.ndarray,
    x_dir: np.ndarray,
    d: np.ndarray,
    z_top: float,
    z_bottom: float,
    floor: float | None,
    params: SamplingParams,
    points: np.ndarray | None,
) -> list[tuple[np.ndarray, np.ndarray, str, float, float]]:
    """The pinches of one kind across ``c_dir`` (hand y), ``x_dir`` (hand x) and approach
    ``-d``, both rolls, at positions along the part (tip) or about its centre (tripod).

    With a ``floor`` (a table under the part, pinches from above) the fingertips start at the
    part's middle height (or higher, when the fingers are too short for it) and the approach
    is unlimited (it ends on the part or the table); without one (across a thin part) they
    start ``standoff`` outside the part's near side and go at most to its middle, so that the
    fingertips close on the part and not on what lies beyond it. ``points`` (N, 3), the part's
    points: the three-finger tip from above opens for the part's width under its fingers at
    each position (not the box's), when given (:class:`_NearFingers`: the same numbers as
    :func:`_placed_reference`, which tests every point at every position)."""
    out: list[tuple[np.ndarray, np.ndarray, str, float, float]] = []
    width, gt, spread, c, offsets, fx, band = _kind_setup(
        hand, kind, width, length, floor, points, params
    )
    local = fx is not None
    centre = box.center - (box.center @ d) * d  # the box centre projected on d = 0
    if local:
        assert points is not None and fx is not None
        near = _NearFingers(points, centre, x_dir, fx, band)
    spots = []  # (sign, offset, half width) of every position, both rolls, in order
    slices: list[Slices] = []  # of the local positions, in the same order
    for sign in (1.0, -1.0):  # both rolls: thumb on either side
        for off in offsets:  # a few positions along the part
            half = 0.5 * width
            if local:
                # the part's half width under the three fingers at this position (the toy
                # car between its wheels is narrower than its box)
                got_half = near.half_width(sign, float(off), c_dir)
                if got_half is None:
                    continue
                half, s_all, thumb = got_half
                if thumb is not None:  # a hole under the thumb may be there
                    slices.append((sign, float(off), s_all, thumb))
            spots.append((sign, off, half))
    # the preshapes of every position at once (the new half widths' checks batched)
    shapes = _preshapes(hand, kind, [h for _, _, h in spots])
    for (sign, off, _), got in zip(spots, shapes, strict=True):  # loop over the positions
        if got is None:
            continue
        R = np.stack([sign * x_dir, sign * c_dir, -d], axis=1)  # columns = hand axes
        q_pinch, depth = got
        if floor is not None:
            z_tip = max(0.5 * (z_top + z_bottom), z_top + params.standoff - depth)
            limit = np.inf
        else:
            z_tip = z_top + params.standoff
            limit = params.standoff + min(0.5 * (z_top - z_bottom), 0.5 * float(box.extents[2]))
        p_c = centre + off * sign * x_dir + z_tip * d  # where the tips' centre goes
        T = np.eye(4)
        T[:3, :3] = R
        T[:3, 3] = p_c - R @ np.array([c[0], c[1], depth])
        out.append((T, q_pinch, gt, spread, limit))
    # rim pinches where the thumb's slice has a hole (a ring: the thumb goes into it)
    out += _rim_pinches(hand, slices, centre, x_dir, c_dir, d, z_top, z_bottom, params)
    return out


RIM_MIN_GAP: float = 0.036
"""Metres: the narrowest hole in the material under the thumb that a rim pinch puts the thumb
in (:func:`rim_bar`): its thickness (0.02 m) and :data:`PINCH_MARGIN` on either side."""


def rim_bar(
    s_all: np.ndarray, s_thumb: np.ndarray, side: float, min_gap: float = RIM_MIN_GAP
) -> tuple[float, float] | None:
    """The bar of material a rim pinch closes on, ``(centre, half width)`` along the closing
    coordinate, or None. ``s_all`` (n,): the coordinates of the points under the three
    fingers; ``s_thumb`` (m,): those under the thumb; ``side``: +1 when the thumb lies on the
    positive side of the pinch centre (f1 and f2 on the negative), -1 the other way. The bar
    is the material at the fingers' end of the part: from the part's end under any finger
    (where f1 and f2 close on it from outside) to the edge of the first hole of the thumb's
    slice counted from that end (a gap between its sorted coordinates wider than
    ``min_gap``, where the thumb closes on it from inside). None without such a hole."""
    v = np.sort(np.asarray(s_thumb, dtype=np.float64) * side)  # the thumb's side is now +
    if len(v) < 2 or len(s_all) == 0:
        return None
    gaps = np.flatnonzero(np.diff(v) > min_gap)
    if not len(gaps):
        return None
    inner = float(v[gaps[0]])  # the bar's edge at the hole, where the thumb closes
    outer = float(np.min(np.asarray(s_all, dtype=np.float64) * side))  # the fingers' end
    if not inner > outer:
        return None
    return side * 0.5 * (inner + outer), 0.5 * (inner - outer)


Slices = tuple[float, float, np.ndarray, np.ndarray]
"""One position of a three-finger tip from above: ``(roll sign, offset, s, thumb)``, with ``s``
(n,) the coordinates along the closing direction of the part's points under the three fingers
(relative to the position) and ``thumb`` (n,) bool, which of them are under the thumb."""

HOLE_SLACK: float = 1e-9
"""Metres: the quick test for a hole under the thumb (:func:`_may_have_hole`) looks for gaps
this much narrower than :data:`RIM_MIN_GAP`, so that it never misses one that the exact test
(:func:`rim_bar`) finds in coordinates rounded differently."""


def _rim_pinches(
    hand: Hand,
    slices: Sequence[Slices],
    centre: np.ndarray,
    x_dir: np.ndarray,
    c_dir: np.ndarray,
    d: np.ndarray,
    z_top: float,
    z_bottom: float,
    params: SamplingParams,
) -> list[tuple[np.ndarray, np.ndarray, str, float, float]]:
    """The rim pinches (:func:`_rim_pinch`) of the positions ``slices``, in their order, with
    the heights of the pinches from above."""

    def z_tip_of(depth: float) -> float:
        return max(0.5 * (z_top + z_bottom), z_top + params.standoff - depth)

    found = (
        _rim_pinch(hand, sign, off, s, thumb, centre, x_dir, c_dir, d, z_tip_of)
        for sign, off, s, thumb in slices
    )
    return [p for p in found if p is not None]


def _may_have_hole(v: np.ndarray, min_gap: float) -> bool:
    """False when the values ``v`` (m,) leave no gap wider than ``min_gap`` between them: a
    bin of half that width lies inside any such gap, so a histogram with no empty bin proves
    there is none (a quick test before :func:`rim_bar` sorts them)."""
    if len(v) < 2:
        return False
    lo, hi = float(v.min()), float(v.max())
    if not hi - lo > min_gap:
        return False
    w = 0.5 * min_gap
    counts = np.bincount(((v - lo) / w).astype(np.int64))
    return bool((counts == 0).any())


def _rim_pinch(
    hand: Hand,
    sign: float,
    off: float,
    s: np.ndarray,
    thumb: np.ndarray,
    centre: np.ndarray,
    x_dir: np.ndarray,
    c_dir: np.ndarray,
    d: np.ndarray,
    z_tip_of: Callable[[float], float],
) -> tuple[np.ndarray, np.ndarray, str, float, float] | None:
    """The rim pinch at one position and roll of a three-finger tip from above
    (:func:`_placed`; ``s`` and ``thumb`` as in :data:`Slices`): a tip across the bar of
    material between a hole under the thumb and the part's end at f1 and f2
    (:func:`rim_bar`), centred on the bar, so that the thumb goes into the hole and closes on
    the bar from inside (a ring, a frame or a tape roll lying on the table, lifted by its side
    as a person does: ``docs/pregrasps.md``, 6b). ``z_tip_of``: the fingertips' height for a
    preshape's depth (as the whole-part pinch's). None without a hole the thumb fits in, or
    when no preshape reaches the bar."""
    s_thumb = s[thumb]
    c = _center(hand, "tip")
    thumb_y = float(hand.flexion_plane(FINGERS[0], 0.0).origin[1] - c[1])  # hand y
    bar = rim_bar(s, s_thumb, float(np.sign(sign * thumb_y)))
    if bar is None:
        return None
    shift, half = bar
    got = _preshape(hand, "tip", half)
    if got is None:
        return None
    q_pinch, depth = got
    R = np.stack([sign * x_dir, sign * c_dir, -d], axis=1)  # columns = hand axes
    p_c = centre + off * sign * x_dir + shift * c_dir + z_tip_of(depth) * d
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = p_c - R @ np.array([c[0], c[1], depth])
    gt, spread = KINDS["tip"]
    return T, q_pinch, gt, spread, np.inf


PROJECTION_SLACK: float = 1e-9
"""Metres: a point whose sorted projection (:class:`_NearFingers`) lies this close to the edge
of a finger's band is decided by the exact expressions of :func:`_placed_reference` (the
rounding of either is below 1e-15 m on parts a metre across)."""


def _under_fingers(
    rel: np.ndarray, xs: np.ndarray, fx: np.ndarray, band: float, c_dir: np.ndarray
) -> tuple[float, np.ndarray, np.ndarray | None] | None:
    """:meth:`_NearFingers.half_width` by the reference's expressions: ``rel`` (N, 3), the
    part's points relative to the position, ``xs`` (N,) their coordinates along the hand's x
    axis, ``fx`` the fingers' x (the thumb's first), ``band`` their slices' half width."""
    # under one of the three fingers (one pass per finger: an any() along the short axis of
    # an (N, 3) array cost ten times more)
    at_thumb = np.abs(xs - fx[0]) <= band
    under = at_thumb.copy()
    for x_f in fx[1:]:
        under |= np.abs(xs - x_f) <= band
    if not under.any():
        return None
    s = rel[under] @ c_dir
    thumb = at_thumb[under]
    if not _may_have_hole(s[thumb], RIM_MIN_GAP - HOLE_SLACK):
        return float(np.max(np.abs(s))), s, None
    return float(np.max(np.abs(s))), s, thumb


class _NearFingers:
    """The part's points under the three fingers of a tip from above, at every position and
    roll of :func:`_placed`, from their projections on the hand's x axis sorted once.

    :func:`_placed_reference` computes, per position, ``rel = points - p`` (N, 3) and
    ``xs = rel @ (sign x_dir)`` and keeps the points with ``|xs - fx_k| <= band`` for some
    finger k, then ``max |rel[under] @ c_dir|``. Here ``xs`` is
    ``sign (points - centre) . x_dir - off |x_dir|^2`` up to rounding, so each finger's band
    is an interval of the sorted projections (two binary searches); when no projection lies
    within :data:`PROJECTION_SLACK` of an interval's ends the set is exactly the reference's
    and the width is computed from its rows with the reference's expressions (the same rows
    in the same order: the same numbers); otherwise that position takes the reference's
    full computation."""

    def __init__(
        self, points: np.ndarray, centre: np.ndarray, x_dir: np.ndarray, fx: np.ndarray, band: float
    ) -> None:
        self.points, self.centre, self.x_dir, self.fx, self.band = points, centre, x_dir, fx, band
        proj = (points - centre) @ x_dir  # (N,)
        self.order = np.argsort(proj)
        self.by_coord = np.ascontiguousarray(points.T)  # (3, N)
        self.sorted = proj[self.order]
        self.xx = float(x_dir @ x_dir)
        self._bins: np.ndarray | None = None  # (N,) the points' bins across, once asked

    def _exact(
        self, sign: float, off: float, c_dir: np.ndarray
    ) -> tuple[float, np.ndarray, np.ndarray | None] | None:
        """The reference's expressions (every point)."""
        rel = self.points - (self.centre + off * sign * self.x_dir)  # (N, 3)
        return _under_fingers(rel, rel @ (sign * self.x_dir), self.fx, self.band, c_dir)

    def half_width(
        self, sign: float, off: float, c_dir: np.ndarray
    ) -> tuple[float, np.ndarray, np.ndarray | None] | None:
        """``(half, s, thumb)``: ``half = max |(p - position) . c_dir|`` over the points p
        under a finger at offset ``off`` with roll ``sign``, ``s`` those dot products (in the
        points' order) and ``thumb`` which of them are under the thumb (:data:`Slices`), or
        None when the thumb's slice leaves no hole a rim pinch could use (:func:`_may_have_hole`);
        None: no point under any finger."""
        sb, eps = self.sorted, PROJECTION_SLACK
        lo = np.empty(len(self.fx))
        hi = np.empty(len(self.fx))
        for k, x_f in enumerate(self.fx):  # the three fingers' bands as projection intervals
            a, b = off * self.xx + x_f - self.band, off * self.xx + x_f + self.band
            lo[k], hi[k] = (a, b) if sign > 0 else (-b, -a)
        ends = np.concatenate([lo, hi])
        near = np.searchsorted(sb, ends - eps, "left") != np.searchsorted(sb, ends + eps, "right")
        if near.any():  # a point at a band's edge: the exact expressions decide
            return self._exact(sign, off, c_dir)
        i0, i1 = np.searchsorted(sb, lo, "left"), np.searchsorted(sb, hi, "right")
        if not (i1 > i0).any():
            return None
        under = np.zeros(len(sb), dtype=bool)
        for a, b in zip(i0, i1, strict=True):  # the three fingers
            under[self.order[a:b]] = True
        idx = np.flatnonzero(under)  # the reference's rows, in its order
        p = self.centre + off * sign * self.x_dir
        rel = np.empty((len(idx), 3))  # rel[under], by coordinate (a gather and a subtraction
        for k in range(3):  # per column: faster than a boolean row selection of (N, 3))
            np.subtract(self.by_coord[k].take(idx), p[k], out=rel[:, k])
        s = rel @ c_dir
        if self._bins is None:  # bins along c_dir in the sorted order (the quick hole test)
            across = (self.points - self.centre) @ c_dir  # s up to rounding
            w = 0.5 * (RIM_MIN_GAP - HOLE_SLACK)
            self._bins = np.floor(across / w).astype(np.int64)[self.order]
        b = self._bins[i0[0] : i1[0]]  # the thumb's band (fx[0]): a run of the sorted order
        if len(b) < 2 or not (np.bincount(b - b.min()) == 0).any():
            return float(np.max(np.abs(s))), s, None  # no empty bin: no hole (_may_have_hole)
        at_thumb = np.zeros(len(sb), dtype=bool)
        at_thumb[self.order[i0[0] : i1[0]]] = True
        return float(np.max(np.abs(s))), s, at_thumb[idx]


def _placed_reference(
    hand: Hand,
    box: OrientedBox,
    kind: str,
    width: float,
    length: float,
    c_dir: np.ndarray,
    x_dir: np.ndarray,
    d: np.ndarray,
    z_top: float,
    z_bottom: float,
    floor: float | None,
    params: SamplingParams,
    points: np.ndarray | None,
) -> list[tuple[np.ndarray, np.ndarray, str, float, float]]:
    """:func:`_placed` as it was before the sorted projections (every position tests every
    point of the part; kept as the reference of its tests and benchmark).

    With a ``floor`` (a table under the part, pinches from above) the fingertips start at the
    part's middle height (or higher, when the fingers are too short for it) and the approach
    is unlimited (it ends on the part or the table); without one (across a thin part) they
    start ``standoff`` outside the part's near side and go at most to its middle, so that the
    fingertips close on the part and not on what lies beyond it. ``points`` (N, 3), the part's
    points: the three-finger tip from above opens for the part's width under its fingers at
    each position (not the box's), when given."""
    out: list[tuple[np.ndarray, np.ndarray, str, float, float]] = []
    width, gt, spread, c, offsets, fx, band = _kind_setup(
        hand, kind, width, length, floor, points, params
    )
    local = fx is not None
    centre = box.center - (box.center @ d) * d  # the box centre projected on d = 0
    slices: list[Slices] = []  # of the local positions, in order
    for sign in (1.0, -1.0):  # both rolls: thumb on either side
        R = np.stack([sign * x_dir, sign * c_dir, -d], axis=1)  # columns = hand axes
        for off in offsets:  # a few positions along the part
            half = 0.5 * width
            if local:
                assert points is not None and fx is not None
                # the part's half width under the three fingers at this position (the toy
                # car between its wheels is narrower than its box)
                rel = points - (centre + off * sign * x_dir)  # (N, 3)
                got_half = _under_fingers(rel, rel @ (sign * x_dir), fx, band, c_dir)
                if got_half is None:
                    continue
                half, s_all, thumb = got_half
                if thumb is not None:  # a hole under the thumb may be there
                    slices.append((sign, float(off), s_all, thumb))
            got = _preshape(hand, kind, half)
            if got is None:
                continue
            q_pinch, depth = got
            if floor is not None:
                z_tip = max(0.5 * (z_top + z_bottom), z_top + params.standoff - depth)
                limit = np.inf
            else:
                z_tip = z_top + params.standoff
                limit = params.standoff + min(0.5 * (z_top - z_bottom), 0.5 * float(box.extents[2]))
            p_c = centre + off * sign * x_dir + z_tip * d  # where the tips' centre goes
            T = np.eye(4)
            T[:3, :3] = R
            T[:3, 3] = p_c - R @ np.array([c[0], c[1], depth])
            out.append((T, q_pinch, gt, spread, limit))
    out += _rim_pinches(hand, slices, centre, x_dir, c_dir, d, z_top, z_bottom, params)
    return out


def pinch_samples(
    hand: Hand,
    box: OrientedBox,
    support: SupportPlane | None,
    params: SamplingParams,
    points: np.ndarray | None = None,
) -> PinchSamples | None:
    """The pinches of ``box`` (see the module docstring): from above (with a support plane),
    across each of the two horizontal axes of ``box`` when its top face is within 30 degrees of
    level, else of the upright box of ``points`` (none without them); and for a thin part
    (smallest side at most ``THIN_PART``), across its thickness from each face around its rim.
    ``points`` (N, 3): the part's points (the local width of the pinches from above). ``None``
    when there is none."""
    n_world = FACE_NORMAL @ box.rotation.T  # (6, 3) face normals, world
    found: list[tuple[np.ndarray, np.ndarray, str, float, float]] = []
    faces: list[int] = []
    if support is not None:
        up = support.normal
        top = int(np.argmax(n_world @ up))
        above: OrientedBox | None = box
        if float(n_world[top] @ up) < MAX_TILT_COS:
            # a tilted box (a ball's or a tilted brick's minimum box can stand on an edge):
            # pinch from above across the part's upright box instead, its top face level
            above = upright_box(points, up) if points is not None and len(points) else None
        if above is not None:
            a_top = int(np.argmax((FACE_NORMAL @ above.rotation.T) @ up))
            axes = tuple(a for a in range(3) if a != a_top // 2)
            got = _face_pinches(
                hand, above, a_top, up, axes, support.height, ("tip", "tripod"), False, params,
                points,
            )  # fmt: skip
            found += got
            faces += [top] * len(got)  # the masks of the part's own top face decide
    if float(box.extents[2]) <= THIN_PART:
        for f in range(4):  # the rim faces (axes 0 and 1): across the thickness (axis 2)
            if support is not None and float(n_world[f] @ support.normal) < -0.5:
                continue  # not from under the table
            got = _face_pinches(
                hand, box, f, n_world[f], (2,), None, ("tip", "tripod"), True, params
            )
            found += got
            faces += [f] * len(got)
    if not found:
        return None
    return PinchSamples(
        T_world_hand=np.stack([t[0] for t in found]),
        q=np.stack([t[1] for t in found]),
        grasp_type=np.array([t[2] for t in found], dtype="<U16"),
        spread=np.array([t[3] for t in found]),
        approach_limit=np.array([t[4] for t in found]),
        face=np.array(faces, dtype=np.int64),
    )


def pinch_count_bound(
    boxes: Sequence[OrientedBox], intervals: Sequence[float] | np.ndarray
) -> np.ndarray:
    """(K,) float64: an upper bound on the pinches :func:`pinch_samples` makes over ``boxes``
    at each of the K sampling ``intervals`` (nothing allocated), for the pool's size check.

    Per box, with n the three-finger tip's positions along the box's diagonal: from above,
    2 closing axes x 2 rolls x n, twice (a position can also make a rim pinch,
    :func:`_rim_pinch`); a thin part adds 4 rim faces x 2 kinds x 2 rolls x
    n. (The tripod makes one position, the tip at most n; which face is on top is not
    needed.)"""
    iv = np.atleast_1d(np.asarray(intervals, dtype=np.float64))  # (K,)
    if not boxes:
        return np.zeros(len(iv))
    ext = np.array([b.extents for b in boxes], dtype=np.float64)  # (B, 3)
    # the part's points lie in its box, so no horizontal run of them (the upright box's too)
    # is longer than the box's diagonal
    half_run = np.maximum(0.5 * np.linalg.norm(ext, axis=1) - 0.5 * TIP_MIN_LENGTH, 0.0)  # (B,)
    n = grid_sizes(half_run[:, None], iv[None, :])  # (B, K)
    per_position = 8.0 + 16.0 * (ext[:, 2] <= THIN_PART)  # (B,)
    return (per_position[:, None] * n).sum(axis=0)
