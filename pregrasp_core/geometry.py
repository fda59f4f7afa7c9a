"""Geometry shared by the stages: input checks, box corners and frame changes.

Every stage coerces its point arrays with :func:`as_points`; the eight corners of a box are
numbered the same way everywhere (:data:`CORNER_SIGNS`: corner k has the sign bits
``(k & 1, k & 2, k & 4)`` on axes 0, 1, 2, see ``docs/conventions.md``). The frame changes
:func:`to_frame` and :func:`to_frame_t` work element by element, so that a point's coordinates
never depend on the other points changed with it.
"""

from __future__ import annotations

import numpy as np

CORNER_SIGNS: np.ndarray = np.stack([(np.arange(8) >> b) & 1 for b in range(3)], axis=1) * 2.0 - 1.0
"""(8, 3) float64: the sign of each corner on the box axes 0, 1, 2 (corner k: bits of k)."""
CORNER_SIGNS.setflags(write=False)


def as_points(points: np.ndarray, name: str = "points", rows: str = "N") -> np.ndarray:
    """``points`` as (N, 3) float64; a ``ValueError`` naming ``name`` and the shape if not
    (``rows``: the letter the message gives the row count, e.g. K for contacts)."""
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"{name} must have shape ({rows}, 3), got {pts.shape}")
    return pts


def box_corners(T_world_box: np.ndarray, half_extents: np.ndarray) -> np.ndarray:
    """(8 L, 3) world corners of L boxes with poses ``T_world_box`` (L, 4, 4) and half extents
    ``half_extents`` (L, 3); box l's corners are rows 8 l .. 8 l + 7 in :data:`CORNER_SIGNS`
    order."""
    local = CORNER_SIGNS[None] * half_extents[:, None, :]  # (L, 8, 3)
    R, t = T_world_box[:, :3, :3], T_world_box[:, None, :3, 3]
    return (np.einsum("lij,lkj->lki", R, local) + t).reshape(-1, 3)


def to_frame(p: np.ndarray, T: np.ndarray) -> np.ndarray:
    """(M, 3) points ``p`` (M, 3) in the frame of the pose ``T`` (4, 4): ``(p - t) R``.

    Element by element, not a BLAS product: a row's result never depends on the other rows
    (their number, their order, the memory alignment), so a search on a subset of the points
    gives bit for bit the coordinates that the whole cloud gives."""
    d = p - T[:3, 3]
    R = T[:3, :3]
    return d[:, 0:1] * R[0] + d[:, 1:2] * R[1] + d[:, 2:3] * R[2]


def to_frame_t(xyz: np.ndarray, T: np.ndarray) -> np.ndarray:
    """:func:`to_frame` for points stored by coordinate: ``xyz`` (3, M) -> (3, M) in the frame of
    ``T`` (4, 4), with the same operations in the same order (so the same numbers), on
    contiguous rows."""
    R = T[:3, :3]
    d0, d1, d2 = xyz[0] - T[0, 3], xyz[1] - T[1, 3], xyz[2] - T[2, 3]
    out = np.empty_like(d0, shape=(3, len(d0)))
    for j in range(3):  # the three output coordinates
        out[j] = d0 * R[0, j] + d1 * R[1, j] + d2 * R[2, j]
    return out


def as_points_like(values: np.ndarray, points: np.ndarray, name: str = "normals") -> np.ndarray:
    """``values`` (normals, colours, ...) as float64 of the shape of ``points`` (N, 3); a
    ``ValueError`` naming ``name`` and both shapes if not."""
    arr = np.asarray(values, dtype=np.float64)
    if arr.shape != points.shape:
        raise ValueError(f"{name} must have shape {points.shape} like points, got {arr.shape}")
    return arr
