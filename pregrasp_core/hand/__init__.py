"""The three-finger underactuated hand: URDF model, batch forward kinematics, preshapes,
apertures, finger flexion planes, the planar closing model, collision geometry and point-in-link
queries (see ``docs/hand.md``).

Modules: ``model`` (value types), ``urdf`` (reading the URDF), ``kinematics``, ``preshapes``,
``closing`` (one finger) and ``closing_batch`` (many slices, with ``batch_hits`` and
``batch_events``), ``links`` (points in links), ``collision`` (python-fcl, self-collision),
``meshes``; ``hand`` holds :class:`Hand`, the one object over them.
"""

from ..shape import GRASP_TYPES
from .hand import Hand, load_hand
from .model import (
    DEFAULT_CLOSING_STEPS,
    DEFAULT_COUPLING,
    FINGER_NAMES,
    Finger,
    FingerClosing,
    FingerContact,
    FlexionPlane,
    HandModel,
    grasp_type_name,
)

__all__ = [
    "DEFAULT_CLOSING_STEPS",
    "DEFAULT_COUPLING",
    "FINGER_NAMES",
    "GRASP_TYPES",
    "Finger",
    "FingerClosing",
    "FingerContact",
    "FlexionPlane",
    "Hand",
    "HandModel",
    "grasp_type_name",
    "load_hand",
]
