"""pregrasp_core: the pure numpy/scipy/trimesh/fcl core of pregrasp. Never imports viser or app.

The entry points of the stages are re-exported here; each stage's module holds the rest of its
public surface (``docs/architecture.md``). The errors are imported at once; every other name is
imported on first use, so ``import pregrasp_core.errors`` (the CLI's first import) stays light.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

from .errors import (
    DegenerateGeometryError,
    HandModelError,
    InputError,
    PregraspError,
    WorkLimitError,
)

if TYPE_CHECKING:
    from .box import OrientedBox
    from .decomposition import BoxNode, BoxTree, DecompositionParams, decompose
    from .facemask import FaceMaskParams, FaceMasks, SupportPlane, compute_face_masks
    from .limits import WorkLimits
    from .mvbb import MvbbParams, minimum_volume_box
    from .pipeline import PipelineParams, PipelineResult, run_pipeline
    from .result import read_result, write_result
    from .shape import GraspType, NodeShape, ShapeClass, ShapeParams, classify_tree

_LAZY: dict[str, str] = {
    "OrientedBox": "box",
    "BoxNode": "decomposition",
    "BoxTree": "decomposition",
    "DecompositionParams": "decomposition",
    "decompose": "decomposition",
    "FaceMaskParams": "facemask",
    "FaceMasks": "facemask",
    "SupportPlane": "facemask",
    "compute_face_masks": "facemask",
    "WorkLimits": "limits",
    "MvbbParams": "mvbb",
    "minimum_volume_box": "mvbb",
    "PipelineParams": "pipeline",
    "PipelineResult": "pipeline",
    "run_pipeline": "pipeline",
    "read_result": "result",
    "write_result": "result",
    "GraspType": "shape",
    "NodeShape": "shape",
    "ShapeClass": "shape",
    "ShapeParams": "shape",
    "classify_tree": "shape",
}
"""Re-exported name -> the module of this package that defines it (imported on first use)."""

__all__ = [
    "BoxNode",
    "BoxTree",
    "DecompositionParams",
    "DegenerateGeometryError",
    "FaceMaskParams",
    "FaceMasks",
    "GraspType",
    "HandModelError",
    "InputError",
    "MvbbParams",
    "NodeShape",
    "OrientedBox",
    "PipelineParams",
    "PipelineResult",
    "PregraspError",
    "ShapeClass",
    "ShapeParams",
    "SupportPlane",
    "WorkLimitError",
    "WorkLimits",
    "classify_tree",
    "compute_face_masks",
    "decompose",
    "minimum_volume_box",
    "read_result",
    "run_pipeline",
    "write_result",
]


def __getattr__(name: str) -> object:
    """Import the module of a re-exported name on first use (PEP 562)."""
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'pregrasp_core' has no attribute {name!r}")
    value = getattr(importlib.import_module(f".{module}", __name__), name)
    globals()[name] = value  # later look-ups skip this function
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *__all__})
