"""Parameters of the face-mask stage and the support plane."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal

import numpy as np

from ..errors import InputError
from ..geometry import as_points
from ..limits import MAX_HEIGHT, MAX_LENGTH, check_real
from ..tolerances import FACE_OVERLAP_TOL, GEOM_EPS, SUPPORT_PENETRATION_TOL

if TYPE_CHECKING:
    from ..result import JsonDocument


FACE_RULES: tuple[str, ...] = ("face", "subface")
"""Values of :attr:`FaceMaskParams.rule`: the paper's whole-face rule, or the clearance of each
sub-face."""


def _is_vector(value: object) -> bool:
    """True for a sequence or array of real numbers (not a string, not booleans)."""
    if isinstance(value, (str, bytes)):
        return False
    try:
        a = np.asarray(value)
    except (TypeError, ValueError):
        return False
    return a.dtype.kind in "iuf"


@dataclass(frozen=True)
class FaceMaskParams:
    """Parameters of the face masks and of the support plane."""

    clearance: float = 0.025
    """Metres: depth of the slab in front of a face that must stay empty for the face to be free
    (finger thickness about 0.02 m plus a 0.005 m margin)."""
    overlap_tolerance: float = FACE_OVERLAP_TOL
    """Metres: a blocker must penetrate a face's slab deeper than this to block the face (boxes
    that merely touch the slab's border, e.g. a part sitting flush on top of the face's edge,
    do not block)."""
    min_coverage: float = 0.05
    """Fraction (0..1] of a face's area that boxes in front of it (within the clearance) must
    cover for the face to be blocked; a blocker that only grazes a corner of the slab leaves
    the face free (partial contact is left to the hand's collision test)."""
    support: bool = True
    """Whether a support plane (a table under the object) blocks faces."""
    up: tuple[float, float, float] = (0.0, 0.0, 1.0)
    """World 'up' direction: the support plane's normal (normalised on use)."""
    support_height: float | None = None
    """Height of the support plane along ``up`` (metres); ``None`` = the lowest cloud point."""
    support_tolerance: float = SUPPORT_PENETRATION_TOL
    """Metres: a face's slab must reach deeper than this below the plane to be blocked by it."""
    rule: Literal["face", "subface"] = "subface"
    """Which sub-faces may carry pre-grasps. ``"face"``: the paper's rule, whole faces blocked
    by the boxes in front of them (and the support plane), a sub-face usable when its face and
    every adjacent face it borders are free. ``"subface"`` (default): the same sub-faces, each
    judged by the geometry in front of it: the cloud points of the other parts (or, without
    points, their boxes) and the support plane in the slab in front of the sub-face and in
    front of the third of each adjacent face next to it (:func:`usable_subfaces_by_cells`), so
    a handle in the corner of the body's box keeps its outer sub-faces."""

    def __post_init__(self) -> None:
        # bounds: docs/limits.md ("Face masks"); lengths up to MAX_LENGTH (10 m)
        for name in ("clearance", "overlap_tolerance", "support_tolerance"):
            v = check_real(name, getattr(self, name), 0.0, MAX_LENGTH, what="a length", unit=" m")
            object.__setattr__(self, name, v)
        mc = check_real(
            "min_coverage", self.min_coverage, 0.0, 1.0, lo_open=True, what="a fraction"
        )
        object.__setattr__(self, "min_coverage", mc)
        up = np.asarray(self.up, dtype=np.float64) if _is_vector(self.up) else np.zeros(0)
        with np.errstate(over="ignore"):  # a huge vector's norm is inf: refused below
            norm = float(np.linalg.norm(up)) if up.shape == (3,) else 0.0
        if not np.all(np.isfinite(up)) or not (GEOM_EPS <= norm < np.inf):
            raise ValueError(f"up must be a non-zero finite 3-vector, got {self.up!r}")
        object.__setattr__(self, "up", tuple(float(x) for x in up))
        if self.support_height is not None:
            h = check_real(
                "support_height",
                self.support_height,
                -MAX_HEIGHT,
                MAX_HEIGHT,
                what="a height (or None)",
                unit=" m",
            )
            object.__setattr__(self, "support_height", h)
        sup = self.support
        if not (isinstance(sup, (bool, np.bool_, int, np.integer)) and sup in (0, 1)):
            raise ValueError(f"support must be True or False, got {self.support!r}")
        object.__setattr__(self, "support", bool(self.support))
        if self.rule not in FACE_RULES:
            raise ValueError(f"rule must be one of {list(FACE_RULES)}, got {self.rule!r}")


# ----------------------------------------------------------------------------- support plane


@dataclass(frozen=True)
class SupportPlane:
    """The plane the object stands on: points ``p`` with ``normal . p = height``."""

    normal: np.ndarray
    """(3,) float64, unit, world frame: the 'up' direction (the object is on this side)."""
    height: float
    """Metres: offset of the plane along ``normal``."""

    def __post_init__(self) -> None:
        n = np.asarray(self.normal, dtype=np.float64)
        if n.shape != (3,):
            raise ValueError(f"normal must have shape (3,), got {n.shape}")
        norm = np.linalg.norm(n)
        if not np.isfinite(norm) or norm < GEOM_EPS:
            raise ValueError(f"normal must be a non-zero finite vector, got {n.tolist()}")
        object.__setattr__(self, "normal", n / norm)
        object.__setattr__(self, "height", float(self.height))

    @classmethod
    def from_points(
        cls, points: np.ndarray, up: Sequence[float] = (0.0, 0.0, 1.0), height: float | None = None
    ) -> SupportPlane:
        """The plane perpendicular to ``up`` at ``height``, or at the lowest of ``points``."""
        n = np.asarray(up, dtype=np.float64)
        n = n / np.linalg.norm(n)
        if height is None:
            pts = as_points(points)
            if pts.shape[0] == 0:
                raise InputError("the support plane needs at least one cloud point, got none")
            height = float(np.min(pts @ n))
        return cls(normal=n, height=float(height))

    def signed_distance(self, points: np.ndarray) -> np.ndarray:
        """(N,) metres above the plane (negative below) of world ``points`` (N, 3)."""
        return as_points(points) @ self.normal - self.height

    def to_dict(self) -> JsonDocument:
        """JSON-ready dict (normal, height)."""
        return {"normal": self.normal.tolist(), "height": self.height}


def support_plane(points: np.ndarray, params: FaceMaskParams) -> SupportPlane | None:
    """The support plane the parameters ask for, or ``None`` when it is turned off."""
    if not params.support:
        return None
    return SupportPlane.from_points(points, params.up, params.support_height)


# ----------------------------------------------------------------------------- geometry
