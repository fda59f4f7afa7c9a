"""Shape class and grasp type of each part by PCA (Sainul, Deb & Deb 2019, section II.B).

The eigenvalues ``l1 >= l2 >= l3`` of a part's point covariance are compared through their square
roots, the standard deviations ``s1 >= s2 >= s3`` along the principal axes. A ratio of standard
deviations is a ratio of lengths: for points filling a box it equals the ratio of the box's side
lengths, so the thresholds read like aspect ratios (see ``docs/decomposition.md``):

- 1D when ``s2 / s1 < max_ratio_1d`` (``l1 >> l2 >= l3``: a rod, a handle, a bottle body);
- else 2D when ``s3 / s2 < max_ratio_2d`` (``l1 ~ l2 >> l3``: a plate, a bowl wall, a flat box);
- else 3D (``l1 ~ l2 ~ l3``), split by size: 3D-small when the largest side of the part's box is
  at most ``small_size``, else 3D-large.

Grasp types of the three-finger hand: 1D -> cylindrical, 2D -> three_finger_tip,
3D-large -> spherical, 3D-small -> two_finger_tip.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from .box import OrientedBox
from .decomposition import BoxTree
from .errors import DegenerateGeometryError
from .geometry import as_points
from .limits import MAX_LENGTH, check_real
from .tolerances import GEOM_EPS

if TYPE_CHECKING:
    from .result import JsonDocument


class ShapeClass(str, enum.Enum):
    """PCA shape class of a part."""

    ONE_D = "1D"
    TWO_D = "2D"
    THREE_D_LARGE = "3D-large"
    THREE_D_SMALL = "3D-small"

    def __str__(self) -> str:
        return self.value


class GraspType(str, enum.Enum):
    """Grasp types of the three-finger underactuated hand."""

    CYLINDRICAL = "cylindrical"
    SPHERICAL = "spherical"
    THREE_FINGER_TIP = "three_finger_tip"
    TWO_FINGER_TIP = "two_finger_tip"

    def __str__(self) -> str:
        return self.value


GRASP_TYPES: tuple[str, ...] = tuple(g.value for g in GraspType)
"""The grasp-type strings, in :class:`GraspType` order (the one definition every stage uses)."""

GRASP_TYPE_OF_CLASS: dict[ShapeClass, GraspType] = {
    ShapeClass.ONE_D: GraspType.CYLINDRICAL,
    ShapeClass.TWO_D: GraspType.THREE_FINGER_TIP,
    ShapeClass.THREE_D_LARGE: GraspType.SPHERICAL,
    ShapeClass.THREE_D_SMALL: GraspType.TWO_FINGER_TIP,
}
"""The grasp type assigned to each shape class (the paper's Fig. 3 and 4)."""


@dataclass(frozen=True)
class ShapeParams:
    """Thresholds of the PCA shape classification (defaults reasoned in docs/decomposition.md)."""

    max_ratio_1d: float = 0.55
    """1D when sqrt(l2 / l1) = s2 / s1 is below this (in (0, 1]). For a surface-sampled
    cylinder s2 / s1 ~ 1.2 d / h, so 0.55 means "at least about twice as long as thick"."""
    max_ratio_2d: float = 0.45
    """2D (if not 1D) when sqrt(l3 / l2) = s3 / s2 is below this (in (0, 1]). For a
    surface-sampled plate s3 / s2 ~ 1.7 t / w, so 0.45 means "thickness below about a quarter of
    the width"; for points filling a solid, t / w < 0.45."""
    small_size: float = 0.05
    """Metres: a 3D part whose box's largest side is at most this is 3D-small (two-finger tip
    pinch); above it, 3D-large (spherical wrap). The hand holds up to ~0.13 m; the two spreading
    fingertips pinch parts up to ~0.05 m."""

    def __post_init__(self) -> None:
        # bounds: pregrasp_core.limits and docs/limits.md ("Shape classes")
        for name in ("max_ratio_1d", "max_ratio_2d"):
            v = check_real(name, getattr(self, name), 0.0, 1.0, lo_open=True)
            object.__setattr__(self, name, v)
        v = check_real("small_size", self.small_size, 0.0, MAX_LENGTH, what="a length", unit=" m")
        object.__setattr__(self, "small_size", v)


@dataclass(frozen=True, eq=False)
class NodeShape:
    """PCA shape of one part (one node of the decomposition tree; compared by identity)."""

    eigenvalues: np.ndarray
    """(3,) float64, m^2, descending: eigenvalues l1 >= l2 >= l3 of the points' covariance."""
    shape_class: ShapeClass
    """The PCA shape class."""
    grasp_type: GraspType
    """The grasp type assigned to ``shape_class``."""

    def __post_init__(self) -> None:
        ev = np.array(self.eigenvalues, dtype=np.float64)
        if ev.shape != (3,):
            raise ValueError(f"eigenvalues must have shape (3,), got {ev.shape}")
        ev.setflags(write=False)
        object.__setattr__(self, "eigenvalues", ev)

    def to_dict(self) -> JsonDocument:
        """JSON-ready dict (eigenvalues, shape_class, grasp_type)."""
        return {
            "eigenvalues": self.eigenvalues.tolist(),
            "shape_class": self.shape_class.value,
            "grasp_type": self.grasp_type.value,
        }


def pca_eigenvalues(points: np.ndarray) -> np.ndarray:
    """(3,) descending eigenvalues of the covariance (1/n normalisation) of ``points`` (N, 3)."""
    pts = as_points(points)
    if pts.shape[0] < 2:
        raise DegenerateGeometryError(
            f"PCA needs at least 2 points, got {pts.shape[0]}; use a part with more points"
        )
    centered = pts - pts.mean(axis=0)
    cov = centered.T @ centered / pts.shape[0]  # (3, 3)
    ev = np.linalg.eigvalsh(cov)[::-1]
    return np.maximum(ev, 0.0)  # round-off can give tiny negatives


def is_small(box: OrientedBox, params: ShapeParams | None = None) -> bool:
    """True when the box's largest side is at most ``params.small_size``."""
    params = ShapeParams() if params is None else params
    return bool(box.extents[0] <= params.small_size)


def classify_eigenvalues(
    eigenvalues: np.ndarray, box: OrientedBox, params: ShapeParams | None = None
) -> NodeShape:
    """Shape class of a part from its descending covariance eigenvalues (3,) and its box."""
    params = ShapeParams() if params is None else params
    ev = np.asarray(eigenvalues, dtype=np.float64)
    if ev.shape != (3,):
        raise ValueError(f"eigenvalues must have shape (3,), got {ev.shape}")
    s = np.sqrt(np.maximum(ev, 0.0))
    if not (s[0] >= s[1] >= s[2]):
        raise ValueError(f"eigenvalues must be sorted descending, got {ev.tolist()}")
    if s[0] <= GEOM_EPS:
        raise DegenerateGeometryError(
            "all points of the part coincide: no shape class; remove duplicate points"
        )
    if s[1] / s[0] < params.max_ratio_1d:
        cls = ShapeClass.ONE_D
    elif s[2] / s[1] < params.max_ratio_2d:
        cls = ShapeClass.TWO_D
    elif is_small(box, params):
        cls = ShapeClass.THREE_D_SMALL
    else:
        cls = ShapeClass.THREE_D_LARGE
    return NodeShape(eigenvalues=ev, shape_class=cls, grasp_type=GRASP_TYPE_OF_CLASS[cls])


def classify_points(
    points: np.ndarray, box: OrientedBox, params: ShapeParams | None = None
) -> NodeShape:
    """Shape class and grasp type of the part ``points`` (N, 3) enclosed by ``box``."""
    return classify_eigenvalues(pca_eigenvalues(points), box, params)


def classify_tree(
    tree: BoxTree, points: np.ndarray, params: ShapeParams | None = None
) -> tuple[NodeShape, ...]:
    """Shape of every node of ``tree``, indexed by node id.

    points: (tree.n_points, 3) float64, the cloud the tree was built from.
    """
    pts = as_points(points)
    if pts.shape[0] != tree.n_points:
        raise ValueError(
            f"points must have shape ({tree.n_points}, 3) like the tree's cloud, got {pts.shape}"
        )
    return tuple(classify_points(pts[nd.indices], nd.box, params) for nd in tree.nodes)
