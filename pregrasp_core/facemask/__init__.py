"""Face masks, the support plane and sub-faces (Sainul, Deb & Deb 2019, section III.C).

Conventions (``docs/conventions.md``, "Faces, adjacency and sub-faces"):

- Faces of a box, in its box frame (axis 0 longest): ``0: +x, 1: -x, 2: +y, 3: -y, 4: +z,
  5: -z``. Face ``f`` has the outward normal ``FACE_NORMAL[f]`` and, seen from outside, a
  ``right`` and an ``up`` direction (``FACE_RIGHT``, ``FACE_UP``; right x up = normal).
- The four adjacent faces of ``f`` are ``ADJACENT[f] = [l, d, r, u]``: the faces whose normals
  are -right, -up, +right and +up.
- The face mask of a box is a 6 x 5 matrix of 0 (free) and 1 (blocked); row ``f`` is
  ``[f, l(f), d(f), r(f), u(f)]``.
- A face is blocked by *blocker boxes* when they penetrate the slab in front of the face (the
  face's rectangle pushed outwards by ``clearance``) by more than ``overlap_tolerance`` and
  together cover at least ``min_coverage`` of the face's area (probed on a grid). It is blocked
  by the support plane when that slab reaches more than ``support_tolerance`` below the plane
  (or below the box's own lowest corner, when that is lower: a tilted box pokes below the table
  without facing it). The blockers of node ``n`` are the boxes of the current decomposition (a
  cut of the tree, the leaves by default) that are neither ``n`` nor one of its ancestors or
  descendants.
- Each face is divided into a grid of sub-faces that depends on the grasp type
  (:data:`SUBFACE_SCHEMES`): cell ``(col, row)`` with ``col`` along ``right`` from the left edge
  and ``row`` along ``up`` from the bottom edge has index ``s = row * n_cols + col``. A cell
  borders the adjacent faces of the face edges it touches; it is usable only when its own face
  and every adjacent face it borders are free.
"""

from __future__ import annotations

from .blocking import (
    COVERAGE_DEPTHS,
    COVERAGE_GRID,
    PAIR_CHUNK,
    SAT_CHUNK,
    blocked_by_support,
    face_coverage,
    face_probe_points,
    face_slabs,
    obb_penetration,
    tree_intervals,
)
from .cells import (
    SUBFACE_GRID,
    face_cell_coords,
    subface_regions,
    usable_subfaces_by_cells,
)
from .faces import (
    ADJACENT,
    FACE_AXIS,
    FACE_NAMES,
    FACE_NORMAL,
    FACE_RIGHT,
    FACE_SIGN,
    FACE_UP,
    face_of_direction,
)
from .masks import (
    FaceMasks,
    compute_face_masks,
    face_mask_matrix,
)
from .params import (
    FACE_RULES,
    FaceMaskParams,
    SupportPlane,
    support_plane,
)
from .subfaces import (
    SUBFACE_SCHEMES,
    SubfaceScheme,
    subface_rectangles,
    subface_scheme,
    usable_subfaces,
)

__all__ = [
    "ADJACENT",
    "COVERAGE_DEPTHS",
    "COVERAGE_GRID",
    "FACE_AXIS",
    "FACE_NAMES",
    "FACE_NORMAL",
    "FACE_RIGHT",
    "FACE_RULES",
    "FACE_SIGN",
    "FACE_UP",
    "FaceMaskParams",
    "FaceMasks",
    "PAIR_CHUNK",
    "SAT_CHUNK",
    "SUBFACE_GRID",
    "SUBFACE_SCHEMES",
    "SubfaceScheme",
    "SupportPlane",
    "blocked_by_support",
    "compute_face_masks",
    "face_cell_coords",
    "face_coverage",
    "face_mask_matrix",
    "face_of_direction",
    "face_probe_points",
    "face_slabs",
    "obb_penetration",
    "subface_rectangles",
    "subface_regions",
    "subface_scheme",
    "support_plane",
    "tree_intervals",
    "usable_subfaces",
    "usable_subfaces_by_cells",
]
