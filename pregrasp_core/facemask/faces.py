"""Face numbering of a box: the faces, their normals, right/up directions and adjacency
(``docs/conventions.md``)."""

from __future__ import annotations

import numpy as np

FACE_NAMES: tuple[str, ...] = ("+x", "-x", "+y", "-y", "+z", "-z")
"""Names of the six faces in the box frame (axis 0 = x is the longest box axis)."""

FACE_AXIS: np.ndarray = np.array([0, 0, 1, 1, 2, 2])
"""(6,) int: the box axis each face is perpendicular to."""

FACE_SIGN: np.ndarray = np.array([1.0, -1.0, 1.0, -1.0, 1.0, -1.0])
"""(6,) float: +1 for the face on the positive side of its axis, -1 otherwise."""

FACE_NORMAL: np.ndarray = np.eye(3)[FACE_AXIS] * FACE_SIGN[:, None]
"""(6, 3) outward unit normals of the faces in the box frame."""

FACE_RIGHT: np.ndarray = np.array(
    [[0, 1, 0], [0, -1, 0], [-1, 0, 0], [1, 0, 0], [1, 0, 0], [1, 0, 0]], dtype=np.float64
)
"""(6, 3) the 'right' direction of each face seen from outside (box frame)."""

FACE_UP: np.ndarray = np.array(
    [[0, 0, 1], [0, 0, 1], [0, 0, 1], [0, 0, 1], [0, 1, 0], [0, -1, 0]], dtype=np.float64
)
"""(6, 3) the 'up' direction of each face seen from outside (box frame); right x up = normal."""


def face_of_direction(direction: np.ndarray) -> np.ndarray:
    """Face index of axis-aligned unit directions (..., 3) in the box frame."""
    d = np.asarray(direction, dtype=np.float64)
    axis = np.argmax(np.abs(d), axis=-1)
    sign = np.take_along_axis(d, axis[..., None], axis=-1)[..., 0]
    return 2 * axis + (sign < 0)


ADJACENT: np.ndarray = np.stack(
    [
        face_of_direction(-FACE_RIGHT),
        face_of_direction(-FACE_UP),
        face_of_direction(FACE_RIGHT),
        face_of_direction(FACE_UP),
    ],
    axis=1,
)
"""(6, 4) int: adjacent faces [l, d, r, u] of each face."""


# ----------------------------------------------------------------------------- parameters
