"""The physics check: a MuJoCo lift test of planned grasps (``docs/simulation.md``).

Importing this package imports MuJoCo; ``pregrasp_core`` itself never does.
"""

from .object_model import (
    ModelError,
    ObjectModel,
    ObjectModelParams,
    model_error,
    object_from_cloud,
    object_from_mesh,
)
from .params import OUTCOMES, PlaybackFrame, SimulationParams, SimulationResult
from .run import (
    GraspSpec,
    LiftSimulator,
    grasp_spec,
    grasp_specs,
    load_object_mesh,
    object_model,
    simulate_grasp,
    simulate_grasps,
    simulate_playback,
    simulator,
)
from .scene import scene_xml

__all__ = [
    "OUTCOMES",
    "GraspSpec",
    "LiftSimulator",
    "ModelError",
    "ObjectModel",
    "ObjectModelParams",
    "PlaybackFrame",
    "SimulationParams",
    "SimulationResult",
    "grasp_spec",
    "grasp_specs",
    "load_object_mesh",
    "model_error",
    "object_from_cloud",
    "object_from_mesh",
    "object_model",
    "scene_xml",
    "simulate_grasp",
    "simulate_grasps",
    "simulate_playback",
    "simulator",
]
