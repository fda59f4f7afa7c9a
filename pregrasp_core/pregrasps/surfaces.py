"""Samples of the enclosing surface of a box for a grasp type (:func:`sample_node`).

Sphere for spherical and two-finger tip, cylinder (side and caps) for cylindrical, circle for
three-finger tip; the samples lie on the usable sub-faces at a fixed interval, each aims the
hand's approach (+z of the hand frame) at the box (its centre, or its axis for radial cylinder
samples) and rolls the hand so that it closes across the part as its grasp type needs. See
``docs/pregrasps.md`` section 4.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ..box import OrientedBox
from ..errors import PregraspError
from ..facemask import FACE_AXIS, FACE_NORMAL, FACE_RIGHT, FACE_UP, subface_scheme
from ..hand import grasp_type_name
from ..tolerances import GEOM_EPS
from .params import MAX_POOL_SAMPLES, SamplingParams

SURFACES: tuple[str, ...] = ("sphere", "cylinder_side", "cylinder_cap", "circle", "pinch")
"""Names of the enclosing-surface patches a pre-grasp can come from (``pinch``: a fingertip
pinch from above, :mod:`~pregrasp_core.pregrasps.pinch`, not an enclosing surface)."""


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


def _grid_m(half_range: float, step: float) -> int:
    """The m of :func:`centred_grid`: its 2 m + 1 cells have width ~``step``."""
    m = int(round(half_range / step - 0.5)) if step > 0 else 0
    return max(m, 0)


def centred_grid(half_range: float, step: float) -> np.ndarray:
    """Centres of 2 m + 1 equal cells tiling [-half_range, half_range] with width ~``step``:
    symmetric about 0 and always containing 0 (the face's centre line)."""
    m = _grid_m(half_range, step)
    return np.arange(-m, m + 1) * (2.0 * half_range / (2 * m + 1))


def _patch_grids(box: OrientedBox, grasp_type: str) -> list[tuple[int, int, tuple, tuple]]:
    """The grids :func:`sample_node` lays on ``box`` for ``grasp_type``, one row per face:
    ``(patch index into SURFACES, copies, (range_a, divisor_a), (range_b, divisor_b))``; the row
    makes ``copies * size_a * size_b`` samples per roll, where ``size = 2 m + 1`` of
    :func:`centred_grid` over ``[-range, range]`` with step ``interval / divisor``."""
    gt = grasp_type_name(grasp_type)
    h = box.half_extents
    one = (0.0, 1.0)  # a single grid point
    rows = []
    if gt in ("spherical", "two_finger_tip"):
        div = max(float(np.linalg.norm(h)), GEOM_EPS)
        for f in range(6):  # the same angle grids as sample_node
            a = FACE_AXIS[f]
            hr, hu = float(np.abs(FACE_RIGHT[f]) @ h), float(np.abs(FACE_UP[f]) @ h)
            rows.append((0, 1, (np.arctan2(hr, h[a]), div), (np.arctan2(hu, h[a]), div)))
    elif gt == "cylindrical":
        div = max(float(np.hypot(h[1], h[2])), GEOM_EPS)
        for f in range(2, 6):  # along the axis at the interval itself, around it in angle
            hu = float(np.abs(FACE_UP[f]) @ h)
            rows.append((1, 1, (float(h[0]), 1.0), (np.arctan2(hu, h[FACE_AXIS[f]]), div)))
        rows.append((2, 4, one, one))  # two closing directions on each of the two caps
    else:
        div = max(float(np.hypot(h[0], h[1])), GEOM_EPS)
        for f in range(4):
            hr = float(np.abs(FACE_RIGHT[f]) @ h)
            rows.append((3, 1, (np.arctan2(hr, h[FACE_AXIS[f]]), div), one))
    return rows


def grid_sizes(half_range: np.ndarray, step: np.ndarray) -> np.ndarray:
    """``2 m + 1`` of :func:`centred_grid`, element-wise (float64, exact for the sizes that
    matter)."""
    return 2.0 * np.maximum(np.round(half_range / step - 0.5), 0.0) + 1.0


def count_samples(box: OrientedBox, grasp_type: str, interval: float) -> dict[str, int]:
    """Number of samples :func:`sample_node` makes for ``box`` and ``grasp_type`` at this
    ``interval`` on every sub-face (both rolls), per patch of :data:`SURFACES`; computed from
    the grid sizes alone, without allocating them."""
    n = dict.fromkeys(SURFACES, 0)
    for patch, copies, (ra, da), (rb, db) in _patch_grids(box, grasp_type):
        size_a = 2 * _grid_m(ra, interval / da) + 1
        size_b = 2 * _grid_m(rb, interval / db) + 1
        n[SURFACES[patch]] += 2 * copies * size_a * size_b  # both rolls
    return n


def total_samples(
    jobs: Sequence[tuple[OrientedBox, str]], intervals: Sequence[float] | np.ndarray
) -> np.ndarray:
    """(K,) float64: the samples :func:`sample_node` makes over all ``(box, grasp_type)`` of
    ``jobs`` at each of the K ``intervals`` (the sum of :func:`count_samples`, vectorised over
    jobs and intervals; exact integers below 2^53)."""
    rows = [r for box, gt in jobs for r in _patch_grids(box, gt)]
    iv = np.atleast_1d(np.asarray(intervals, dtype=np.float64))  # (K,)
    if not rows:
        return np.zeros(len(iv))
    copies = np.array([r[1] for r in rows], dtype=np.float64)[:, None]  # (T, 1)
    g = np.array([(*r[2], *r[3]) for r in rows], dtype=np.float64)  # (T, 4) ra, da, rb, db
    out = np.zeros(len(iv))
    chunk = max(1, (1 << 16) // len(rows))  # intervals at once: (T, chunk) arrays stay small
    for k in range(0, len(iv), chunk):  # one pass unless both T and K are large
        at = iv[None, k : k + chunk]
        size_a = grid_sizes(g[:, 0:1], at / g[:, 1:2])  # (T, chunk)
        size_b = grid_sizes(g[:, 2:3], at / g[:, 3:4])
        out[k : k + chunk] = 2.0 * (copies * size_a * size_b).sum(axis=0)
    return out


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
    grasp_type: str,
    params: SamplingParams | None = None,
    usable: Sequence[np.ndarray] | None = None,
    max_samples: int = MAX_POOL_SAMPLES,
) -> NodeSamples:
    """Samples of the enclosing surface of ``box`` for ``grasp_type``, in the box frame.

    usable: the usable sub-faces (list of 6 bool arrays, see
    :func:`~pregrasp_core.facemask.usable_subfaces`); ``None`` = every sub-face. Every sample
    comes twice, with the hand rolled by 180 degrees about its approach (the closing axis with
    both signs), so that the set does not depend on the sign convention of the box axes.
    Raises ``PregraspError`` before allocating when the box would get more than
    ``max_samples`` (:func:`count_samples`).
    """
    params = SamplingParams() if params is None else params
    gt = grasp_type_name(grasp_type)
    n = sum(count_samples(box, gt, params.interval).values())
    if n > max_samples:
        raise PregraspError(
            f"sampling a box of extents {np.round(box.extents, 4).tolist()} m for {gt} at "
            f"interval {params.interval:g} m would make {n:,} samples, more than the limit of "
            f"{max_samples:,}: raise the interval (see docs/limits.md)"
        )
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
            tr = centred_grid(np.arctan2(hr, h[a]), step / max(radius, GEOM_EPS))
            tu = centred_grid(np.arctan2(hu, h[a]), step / max(radius, GEOM_EPS))
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
        xs = centred_grid(h[0], step)
        for f in range(2, 6):  # side faces: radial approach towards the axis
            a = FACE_AXIS[f]
            u_ax, n_ax = FACE_UP[f], FACE_NORMAL[f]
            hu = float(np.abs(u_ax) @ h)
            tu = centred_grid(np.arctan2(hu, h[a]), step / max(radius, GEOM_EPS))
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
            tr = centred_grid(np.arctan2(hr, h[a]), step / max(radius, GEOM_EPS))
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
