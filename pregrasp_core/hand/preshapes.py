"""The grasp types' preshapes: the spread and flexion each type starts from, the fingers it
closes, and the aperture and grasp centre of its preshape (see ``docs/hand.md``, "Preshapes,
apertures and grasp centres")."""

from __future__ import annotations

import numpy as np

from ..errors import HandModelError
from ..shape import GRASP_TYPES
from ..tolerances import GEOM_EPS
from .kinematics import clamp, tip_pads
from .model import Finger, HandModel, grasp_type_name

# Preshape flexion (proximal, distal) per grasp type and finger, and the spread. Opening the
# proximal joint to its lower limit (-30 deg) gives the widest enveloping preshape; the tip
# grasps keep the distal links parallel to the approach (-15 deg, +15 deg).
_OPEN_WIDE = (-np.pi / 6.0, 0.0)
_TIPS_UP = (-np.pi / 12.0, np.pi / 12.0)
_THUMB_AWAY = (-np.pi / 6.0, -np.pi / 12.0)
_PRESHAPES: dict[str, tuple[float, dict[str, tuple[float, float]]]] = {
    "cylindrical": (0.0, {"thumb": _OPEN_WIDE, "f1": _OPEN_WIDE, "f2": _OPEN_WIDE}),
    "spherical": (np.pi / 3.0, {"thumb": _OPEN_WIDE, "f1": _OPEN_WIDE, "f2": _OPEN_WIDE}),
    "three_finger_tip": (0.0, {"thumb": _TIPS_UP, "f1": _TIPS_UP, "f2": _TIPS_UP}),
    "two_finger_tip": (np.pi / 2.0, {"thumb": _THUMB_AWAY, "f1": _TIPS_UP, "f2": _TIPS_UP}),
}
_GRASP_FINGERS: dict[str, tuple[str, ...]] = {
    "cylindrical": ("thumb", "f1", "f2"),
    "spherical": ("thumb", "f1", "f2"),
    "three_finger_tip": ("thumb", "f1", "f2"),
    "two_finger_tip": ("f1", "f2"),
}


def _circumcircle_2d(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> tuple[np.ndarray, float]:
    """Centre (2,) and radius of the circle through three 2D points."""
    d = 2.0 * (a[0] * (b[1] - c[1]) + b[0] * (c[1] - a[1]) + c[0] * (a[1] - b[1]))
    if abs(d) < GEOM_EPS:
        raise HandModelError("fingertips are collinear; cannot compute a spherical aperture")
    sa, sb, sc = a @ a, b @ b, c @ c
    ux = (sa * (b[1] - c[1]) + sb * (c[1] - a[1]) + sc * (a[1] - b[1])) / d
    uy = (sa * (c[0] - b[0]) + sb * (a[0] - c[0]) + sc * (b[0] - a[0])) / d
    center = np.array([ux, uy])
    return center, float(np.linalg.norm(center - a))


def spread_for(grasp_type: object) -> float:
    """Spread angle (radians) of a grasp type: 0, pi/3, 0, pi/2."""
    return float(_PRESHAPES[grasp_type_name(grasp_type)][0])


def fingers_for(model: HandModel, grasp_type: object) -> tuple[Finger, ...]:
    """The fingers a grasp type closes (two-finger tip: f1 and f2; the thumb stays open)."""
    return tuple(model.finger(n) for n in _GRASP_FINGERS[grasp_type_name(grasp_type)])


def preshape(model: HandModel, grasp_type: object) -> np.ndarray:
    """(J,) the open configuration a grasp of this type starts from (see ``docs/hand.md``)."""
    spread, flex = _PRESHAPES[grasp_type_name(grasp_type)]
    q = np.zeros(model.n_joints)
    q[model.spread_index] = spread
    for f in model.fingers:
        q[list(f.flex_index)] = flex[f.name]
    return clamp(model, q)


def apertures(model: HandModel) -> dict[str, tuple[float, np.ndarray]]:
    """Grasp type -> (aperture, grasp centre (2,) on the palm plane): the largest object size
    (metres) the preshape can enclose, measured between the fingertips' inner edges
    (:func:`~pregrasp_core.hand.kinematics.tip_pads`): cylindrical and three-finger tip: the gap
    along y between the thumb and the nearer of f1/f2; two-finger tip: the gap along x between
    f1 and f2; spherical: the diameter of the circle through the three pads projected onto the
    palm plane. The centre is that of the gap (of the circle for spherical)."""
    out = {}
    for name in GRASP_TYPES:
        pads = {k: v[:2] for k, v in tip_pads(model, preshape(model, name)).items()}
        if name in ("cylindrical", "three_finger_tip"):
            gaps = [pads[f][1] - pads["thumb"][1] for f in ("f1", "f2")]
            y_fingers = 0.5 * (pads["f1"][1] + pads["f2"][1])
            cx = (pads["thumb"][0] + pads["f1"][0] + pads["f2"][0]) / 3.0
            out[name] = (float(min(gaps)), np.array([cx, 0.5 * (y_fingers + pads["thumb"][1])]))
        elif name == "two_finger_tip":
            gap = pads["f1"][0] - pads["f2"][0]
            out[name] = (float(gap), 0.5 * (pads["f1"] + pads["f2"]))
        else:
            center, radius = _circumcircle_2d(pads["thumb"], pads["f1"], pads["f2"])
            out[name] = (2.0 * radius, center)
    return out
