"""Oriented boxes: the primitive of the decomposition.

Convention (see ``docs/conventions.md``): ``rotation`` is ``R_world_box`` whose columns are the box
axes in the world frame; it is a proper rotation (det = +1). Axes are sorted so that
``extents[0] >= extents[1] >= extents[2]`` (axis 0 is the longest). Signs: axes 0 and 1 are
flipped so that their component of largest magnitude is positive, and axis 2 = axis 0 x axis 1.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from .geometry import CORNER_SIGNS, as_points
from .tolerances import BOX_CONTAINS_TOL

if TYPE_CHECKING:
    from .result import JsonDocument


def canonical_axes(rotation: np.ndarray, extents: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sort axes by decreasing extent and fix their signs (see the module docstring).

    rotation: (3, 3) columns are axes; extents: (3,). Returns (rotation, extents) canonical.
    """
    rotation = np.asarray(rotation, dtype=np.float64)
    extents = np.asarray(extents, dtype=np.float64)
    order = np.argsort(-extents, kind="stable")
    R = rotation[:, order].copy()
    ext = extents[order].copy()
    for k in (0, 1):
        i = np.argmax(np.abs(R[:, k]))
        if R[i, k] < 0:
            R[:, k] = -R[:, k]
    R[:, 2] = np.cross(R[:, 0], R[:, 1])
    return R, ext


@dataclass(frozen=True)
class OrientedBox:
    """A box in space."""

    center: np.ndarray
    """(3,) float64, metres, world frame: the centre of the box."""
    rotation: np.ndarray
    """(3, 3) float64, ``R_world_box``: columns are the box axes, det = +1."""
    extents: np.ndarray
    """(3,) float64, metres: full side lengths along the box axes, sorted decreasing."""

    @classmethod
    def from_points_in_frame(cls, points: np.ndarray, rotation: np.ndarray) -> OrientedBox:
        """The tightest box with the given axes around ``points`` (N, 3), canonicalised."""
        pts = as_points(points)
        R = np.asarray(rotation, dtype=np.float64)
        p_box = pts @ R  # (N, 3) coordinates along the axes
        lo, hi = p_box.min(axis=0), p_box.max(axis=0)
        center = R @ ((lo + hi) / 2.0)
        Rc, ext = canonical_axes(R, hi - lo)
        return cls(center=center, rotation=Rc, extents=ext)

    @property
    def volume(self) -> float:
        """Volume in cubic metres."""
        return float(np.prod(self.extents))

    @property
    def half_extents(self) -> np.ndarray:
        """(3,) half side lengths."""
        return self.extents / 2.0

    @property
    def T_world_box(self) -> np.ndarray:
        """(4, 4) homogeneous transform from box frame to world frame."""
        T = np.eye(4)
        T[:3, :3] = self.rotation
        T[:3, 3] = self.center
        return T

    def to_box(self, points: np.ndarray) -> np.ndarray:
        """World points (N, 3) -> box-frame points ``p_box`` (N, 3)."""
        return (as_points(points) - self.center) @ self.rotation

    def to_world(self, p_box: np.ndarray) -> np.ndarray:
        """Box-frame points (N, 3) -> world points (N, 3)."""
        return as_points(p_box, "p_box") @ self.rotation.T + self.center

    def contains(self, points: np.ndarray, tol: float = BOX_CONTAINS_TOL) -> np.ndarray:
        """(N,) bool: which points lie inside the box grown by ``tol`` on every side."""
        p = np.abs(self.to_box(points))
        return np.all(p <= self.half_extents + tol, axis=1)

    def corners(self) -> np.ndarray:
        """(8, 3) world corners; corner k has sign bits (k & 1, k & 2, k & 4) on axes 0, 1, 2."""
        return self.to_world(CORNER_SIGNS * self.half_extents)

    def transformed(self, T: np.ndarray) -> OrientedBox:
        """This box moved by a rigid transform ``T`` (4, 4)."""
        T = np.asarray(T, dtype=np.float64)
        R = T[:3, :3] @ self.rotation
        Rc, ext = canonical_axes(R, self.extents)
        return OrientedBox(center=T[:3, :3] @ self.center + T[:3, 3], rotation=Rc, extents=ext)

    def to_dict(self) -> JsonDocument:
        """JSON-ready dict (center, rotation as row-major 3x3, extents, volume)."""
        return {
            "center": self.center.tolist(),
            "rotation": self.rotation.tolist(),
            "extents": self.extents.tolist(),
            "volume": self.volume,
        }
