"""Step 2: per finger of the grasp type, the slice of the cloud in its flexion plane (the
points within half a finger width of the plane and within the finger's reach, thinned, plus the
support plane's trace), and the closing of many slices in one call of the hand's batched
closing model."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from .kernels import kernels

if TYPE_CHECKING:
    from ..hand import Finger, FingerClosing, FlexionPlane
    from .context import Context, PlaneArrays, View


@dataclass
class Slice:
    """One finger's slice, ready for the closing model."""

    finger: Finger
    """The finger to close."""
    points_2d: np.ndarray
    """(M + S, 2) the thinned slice points in the flexion-plane frame, then the support trace."""
    q_start: np.ndarray
    """(2,) the finger's preshape flexion."""
    n_obj: int
    """Rows of ``points_2d`` that are cloud points (M; the rest: the support plane)."""
    has_table: bool
    """The support plane crosses the finger's reach."""
    n_slice: int
    """Cloud points in the slice before thinning."""


class ClosedFinger(NamedTuple):
    """What the closing model did with one finger's slice (see :func:`closing_records`)."""

    finger: Finger
    """The finger."""
    closing: FingerClosing
    """The closing model's result for its slice."""
    n_slice: int
    """Cloud points in the slice before thinning."""
    touched: tuple[str, ...]
    """The links that stopped on cloud points (not on the support trace)."""
    on_table: bool
    """The support plane stopped the finger (or held it from the start)."""


def finger_slices(
    ctx: Context, T: np.ndarray, view: View, q0: np.ndarray, gt: str, spread: float
) -> list[Slice]:
    """The slice of every finger of the grasp type for the hand at pose ``T`` (``view``: the
    cloud in that hand frame)."""
    prm = ctx.params
    out = []
    fingers, planes, r_all, per_plane = _plane_arrays(ctx, gt, spread)
    origins, ball2, nrm, shift, band, T_planes, half_width, reach2 = per_plane
    cells = ctx.cells
    uv, first, n_slice = kernels().slices(
        ctx.xyz, cells.order, cells.start, cells.count, view.centres, cells.radius,
        float(sum(view.dz)), origins, ball2, view.T0, view.r, view.z_lo, view.z_hi,
        np.array(view.dz, dtype=np.float64), nrm, shift, band, T_planes, half_width, reach2,
        prm.slice_resolution,
    )  # fmt: skip
    support = _support_in_hand(ctx, T)  # (the same for every finger of the pose)
    for j, (f, plane) in enumerate(zip(fingers, planes, strict=True)):  # <= 3 fingers
        p_slice = uv[first[j] : first[j + 1]]
        table = _support_line_2d(ctx, support, plane, 0.5 * f.width, r_all[j])
        out.append(
            Slice(
                f,
                np.concatenate([p_slice, table]),
                q0[list(f.flex_index)],
                len(p_slice),
                len(table) > 0,
                int(n_slice[j]),
            )
        )
    return out


def _plane_arrays(ctx: Context, gt: str, spread: float) -> PlaneArrays:
    """``(fingers, planes, r_all, arrays)`` of grasp type ``gt`` at ``spread``: the fingers and
    their flexion planes, each finger's reach + margin (F,), and the slice kernel's per-plane
    arguments (origins, 3D reach balls, plane normals (3, F), offsets, band half widths, plane
    frames, half widths, squared 2D reach). A pure function of the hand, the parameters and
    the plane key (cached in ``ctx``, computed as before on first use)."""
    key = (gt, round(float(spread), 12))
    hit = ctx.slice_planes.get(key)
    if hit is not None:
        return hit
    prm = ctx.params
    fingers = tuple(ctx.hand.fingers_for(gt))
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
    origins = np.array([pl.origin for pl in planes])  # (F, 3)
    arrays = (
        origins, np.hypot(r_all, half_w) + 1e-9, nrm, shift, half_w + 1e-9,
        np.array([pl.T_hand_plane for pl in planes]), np.array([0.5 * f.width for f in fingers]),
        np.array([(r + 1e-9) ** 2 for r in r_all]),
    )  # fmt: skip
    hit = (fingers, planes, r_all, arrays)  # (never written to: the threads share them)
    return ctx.slice_planes.setdefault(key, hit)


def _support_in_hand(ctx: Context, T: np.ndarray) -> tuple[np.ndarray, float] | None:
    """The support plane in the frame of the hand at pose ``T``: ``(normal (3,), height)``, None
    without a support plane (:func:`_support_line_2d`'s per-pose part)."""
    if ctx.support is None:
        return None
    n_h = T[:3, :3].T @ np.asarray(ctx.support.normal, dtype=np.float64)  # hand frame
    h_h = float(ctx.support.height) - float(np.asarray(ctx.support.normal) @ T[:3, 3])
    return n_h, h_h


_NO_TRACE: np.ndarray = np.zeros((0, 2))
_NO_TRACE.flags.writeable = False


def _support_line_2d(
    ctx: Context,
    support: tuple[np.ndarray, float] | None,
    plane: FlexionPlane,
    half_width: float,
    reach: float,
) -> np.ndarray:
    """(S, 2) points along the support plane's trace in a finger's flexion plane, spaced by
    ``closing_margin`` within ``reach`` of the finger's first joint (the 2D origin; the moving
    links never get farther), so that the closing model stops a link on the
    table as on the object. The trace is raised by ``half_width |n . plane normal|``: the link
    box is that much lower at its side edges when the plane is tilted. Empty without a support
    plane (``support``: :func:`_support_in_hand` of the hand's pose) or when the flexion plane
    is parallel to it."""
    if support is None:
        return _NO_TRACE
    n_h, h_h = support
    a, b = float(n_h @ plane.u), float(n_h @ plane.v)
    ab = np.hypot(a, b)
    if ab < 1e-6:
        return _NO_TRACE
    target = h_h + half_width * abs(float(n_h @ plane.normal)) - float(n_h @ plane.origin)
    if abs(target) > reach * ab * (1.0 + 1e-9):  # |foot| = |target| / ab > reach, far beyond
        return _NO_TRACE  # any rounding: the test below would say so too
    foot = target * np.array([a, b]) / ab**2  # nearest point of the line to the 2D origin
    d_foot = math.sqrt(float(foot.dot(foot)))  # (= np.linalg.norm(foot): sqrt(x . x))
    if d_foot > reach:
        return _NO_TRACE
    along = np.array([-b, a]) / ab
    half_len = np.sqrt(reach**2 - d_foot**2)  # the chord of the line inside the reach
    step = max(ctx.params.closing_margin, 1e-4)
    t = np.arange(-half_len, half_len + step, step)
    return foot + t[:, None] * along


def thin_2d(p2: np.ndarray, cell: float) -> np.ndarray:
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


def close_slices(ctx: Context, slices: list[Slice]) -> list[FingerClosing]:
    """Close the fingers of many slices with one call of the hand's batched closing model."""
    prm = ctx.params
    return ctx.hand.close_fingers(
        [(sl.finger, sl.points_2d, sl.q_start) for sl in slices],
        n_steps=prm.closing_steps,
        margin=prm.closing_margin,
    )


def closing_records(
    q0: np.ndarray, slices: list[Slice], cls: list[FingerClosing]
) -> tuple[np.ndarray, list[ClosedFinger]]:
    """The joint vector after closing the fingers of ``slices`` (their closings ``cls``) from
    the preshape ``q0``, and what happened to each finger."""
    q = q0.copy()
    closings = []
    for sl, cl in zip(slices, cls, strict=True):  # loop over <= 3 fingers
        f = sl.finger
        q[list(f.flex_index)] = cl.q
        touched = tuple(c.link for c in cl.contacts if c.index < sl.n_obj)
        on_table = any(c.index >= sl.n_obj for c in cl.contacts) or (
            cl.start_in_contact and not touched and sl.has_table
        )
        closings.append(ClosedFinger(f, cl, sl.n_slice, touched, on_table))
    return q, closings
