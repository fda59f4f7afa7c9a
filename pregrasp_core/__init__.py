"""pregrasp_core: the pure numpy/scipy/trimesh/fcl core of pregrasp. Never imports viser or app."""

from .box import OrientedBox
from .errors import DegenerateGeometryError, HandModelError, InputError, PregraspError

__all__ = [
    "DegenerateGeometryError",
    "HandModelError",
    "InputError",
    "OrientedBox",
    "PregraspError",
]
