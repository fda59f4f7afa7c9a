"""Minimum-volume bounding boxes.

FIRST VERSION (to be replaced by the fast exact-search implementation of issue 2): wraps
``trimesh.bounds.oriented_bounds`` so that downstream code can be written against the API.
"""

from __future__ import annotations

import numpy as np
import trimesh

from .box import OrientedBox, _as_points


def pca_box(points: np.ndarray) -> OrientedBox:
    """Box aligned with the principal axes of ``points`` (N, 3)."""
    pts = _as_points(points)
    centered = pts - pts.mean(axis=0)
    _, vecs = np.linalg.eigh(centered.T @ centered)
    R = vecs[:, ::-1].copy()
    if np.linalg.det(R) < 0:
        R[:, 2] = -R[:, 2]
    return OrientedBox.from_points_in_frame(pts, R)


def minimum_volume_box(points: np.ndarray) -> OrientedBox:
    """The (near-)minimum-volume oriented box around ``points`` (N, 3)."""
    pts = _as_points(points)
    T, _ = trimesh.bounds.oriented_bounds(pts)
    R = np.linalg.inv(T)[:3, :3]
    return OrientedBox.from_points_in_frame(pts, R)
