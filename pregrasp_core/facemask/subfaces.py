"""Sub-faces by grasp type under the whole-face rule (the paper's): schemes, usable cells,
rectangles for drawing."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..box import OrientedBox
from ..shape import GraspType
from ..tolerances import GEOM_EPS
from .faces import ADJACENT, FACE_AXIS, FACE_NORMAL, FACE_RIGHT, FACE_UP


@dataclass(frozen=True)
class SubfaceScheme:
    """How the faces of a box are divided into sub-faces for one grasp type."""

    grid: tuple[tuple[int, int], ...]
    """Per face (6): ``(n_cols, n_rows)`` of the sub-face grid; ``(0, 0)`` = face not used."""

    @property
    def n_subfaces(self) -> np.ndarray:
        """(6,) int: number of sub-faces of each face (0 for unused faces)."""
        return np.array([c * r for c, r in self.grid])

    def borders(self, face: int) -> np.ndarray:
        """(S, 4) bool: which adjacent faces [l, d, r, u] each sub-face of ``face`` borders."""
        nc, nr = self.grid[face]
        s = np.arange(nc * nr)
        col, row = s % max(nc, 1), s // max(nc, 1)
        return np.stack([col == 0, row == 0, col == nc - 1, row == nr - 1], axis=1)

    def cell(
        self, face: int, right: np.ndarray, up: np.ndarray, half_r: float, half_u: float
    ) -> np.ndarray:
        """Sub-face index (...,) of face coordinates ``right``, ``up`` (metres from the face
        centre) on a face of half sizes ``half_r``, ``half_u``."""
        nc, nr = self.grid[face]
        fr = (np.asarray(right) + half_r) / max(2.0 * half_r, GEOM_EPS)
        fu = (np.asarray(up) + half_u) / max(2.0 * half_u, GEOM_EPS)
        col = np.clip(np.floor(fr * nc), 0, nc - 1).astype(np.int64)
        row = np.clip(np.floor(fu * nr), 0, nr - 1).astype(np.int64)
        return row * nc + col


SUBFACE_SCHEMES: dict[str, SubfaceScheme] = {
    # 3 x 3 grid on every face: centre cell bound to nothing, edge cells to one adjacent face,
    # corner cells to two (the paper's Fig. 5e)
    "spherical": SubfaceScheme(grid=((3, 3),) * 6),
    "two_finger_tip": SubfaceScheme(grid=((3, 3),) * 6),
    # cylinder axis = box axis 0: the four side faces have 'right' along it and are cut into three
    # strips along the axis (each strip spans the face across the axis, so it is bound to the two
    # side faces the fingers wrap towards, and the end strips to their cap); the caps (axial
    # approach) are one sub-face bound to all four side faces (the paper's Fig. 5d)
    "cylindrical": SubfaceScheme(grid=((1, 1), (1, 1), (3, 1), (3, 1), (3, 1), (3, 1))),
    # flat part in the plane of axes 0, 1: the hand approaches the rim faces (0..3) in that plane
    # (the circle's samples all lie in the middle row); 3 x 3 like the sphere, so the middle row
    # is bound only to the neighbouring rim faces and the outer rows to the flat faces as well
    "three_finger_tip": SubfaceScheme(grid=((3, 3), (3, 3), (3, 3), (3, 3), (0, 0), (0, 0))),
}
"""Sub-face scheme of each grasp type (keys are the :class:`~pregrasp_core.shape.GraspType`
values)."""


def subface_scheme(grasp_type: GraspType | str) -> SubfaceScheme:
    """The sub-face scheme of a grasp type (a ``GraspType`` or its string value)."""
    key = getattr(grasp_type, "value", grasp_type)
    try:
        return SUBFACE_SCHEMES[str(key)]
    except KeyError:
        raise ValueError(
            f"unknown grasp type {grasp_type!r}; expected one of {sorted(SUBFACE_SCHEMES)}"
        ) from None


def usable_subfaces(blocked: np.ndarray, grasp_type: GraspType | str) -> list[np.ndarray]:
    """Which sub-faces of a box may carry pre-grasps.

    blocked: (6,) bool, the blocked state of the box's faces. Returns a list of 6 arrays
    ``(S_f,) bool``: sub-face ``s`` of face ``f`` is usable when face ``f`` is free and every
    adjacent face the sub-face borders is free.
    """
    b = np.asarray(blocked, dtype=bool)
    if b.shape != (6,):
        raise ValueError(f"blocked must have shape (6,), got {b.shape}")
    scheme = subface_scheme(grasp_type)
    out = []
    for f in range(6):
        borders = scheme.borders(f)  # (S, 4)
        adj_blocked = b[ADJACENT[f]]  # (4,)
        out.append(~b[f] & ~np.any(borders & adj_blocked, axis=1))
    return out


def subface_rectangles(box: OrientedBox, grasp_type: GraspType | str) -> list[np.ndarray]:
    """World corners of every sub-face of ``box`` for drawing: a list of 6 arrays (S_f, 4, 3),
    corners counter-clockwise seen from outside (bottom-left, bottom-right, top-right, top-left).
    """
    scheme = subface_scheme(grasp_type)
    h = box.half_extents
    out = []
    for f in range(6):
        nc, nr = scheme.grid[f]
        if nc * nr == 0:
            out.append(np.zeros((0, 4, 3)))
            continue
        r_ax, u_ax = FACE_RIGHT[f], FACE_UP[f]
        hr, hu = float(np.abs(r_ax) @ h), float(np.abs(u_ax) @ h)
        centre = FACE_NORMAL[f] * h[FACE_AXIS[f]]
        s = np.arange(nc * nr)
        col, row = s % nc, s // nc
        r0 = -hr + 2 * hr * col / nc
        r1 = -hr + 2 * hr * (col + 1) / nc
        u0 = -hu + 2 * hu * row / nr
        u1 = -hu + 2 * hu * (row + 1) / nr
        rs = np.stack([r0, r1, r1, r0], axis=1)  # (S, 4)
        us = np.stack([u0, u0, u1, u1], axis=1)
        p_box = centre + rs[..., None] * r_ax + us[..., None] * u_ax  # (S, 4, 3)
        out.append(box.to_world(p_box.reshape(-1, 3)).reshape(-1, 4, 3))
    return out


# ----------------------------------------------------------------------------- sub-face clearance
