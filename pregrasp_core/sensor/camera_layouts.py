"""Camera files as other tools write them, read into pregrasp's own keys.

A depth image's camera file (``CameraFile``, ``docs/input.md``) has pregrasp's keys ``fx fy cx
cy`` (and optionally ``width height T_world_camera depth_scale``). Camera drivers and libraries
write the same pinhole numbers under other names; :func:`to_pregrasp_keys` recognises these
layouts by their keys and turns them into pregrasp's, so the file a tool wrote can sit beside
the image unchanged:

- **RealSense** (librealsense's ``rs2_intrinsics`` as pyrealsense2 gives it: ``width height
  ppx ppy fx fy model coeffs``; ``depth_scale`` is librealsense's too, metres per unit);
- **ROS CameraInfo** as JSON (``sensor_msgs/CameraInfo``: ``K``, ``D``, ``R``, ``P``, ...,
  ROS 1's capitals or ROS 2's lower case; ``K`` row-major ``[fx 0 cx 0 fy cy 0 0 1]``);
- **ROS calibration file** as JSON (``camera_calibration``'s ``image_width image_height
  camera_matrix {rows cols data} distortion_coefficients ...``);
- **Open3D** (``PinholeCameraIntrinsic``: ``width height intrinsic_matrix``, the 3 x 3 matrix
  column-major; ``PinholeCameraParameters``: that under ``intrinsic`` and ``extrinsic``, the
  world-to-camera 4 x 4 column-major, whose inverse is ``T_world_camera``).

pregrasp back-projects a pinhole camera without distortion: distortion coefficients that are
not all zero are not applied and say so in a note (a depth stream is normally rectified: a
RealSense D4xx's depth coefficients are zero; a ROS ``image_rect`` has its intrinsics in ``P``).
A camera matrix with skew, binning or a region of interest is refused with the numbers to give
instead. Every layout may also carry pregrasp's ``T_world_camera`` and ``depth_scale``.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from ..errors import InputError

JsonDict = dict[str, Any]
"""A JSON object as ``json.loads`` gives it."""

PREGRASP_EXTRA: tuple[str, ...] = ("T_world_camera", "depth_scale")
"""pregrasp's keys any layout may carry besides its own."""

REALSENSE_KEYS: tuple[str, ...] = ("width", "height", "ppx", "ppy", "fx", "fy", "model", "coeffs")
"""The fields of librealsense's ``rs2_intrinsics``."""

ROS_INFO_KEYS: tuple[str, ...] = ("header", "height", "width", "distortion_model", "D", "K", "R",
                                  "P", "binning_x", "binning_y", "roi")  # fmt: skip
"""The fields of ROS's ``sensor_msgs/CameraInfo`` (ROS 2 writes the matrices in lower case)."""

ROS_CALIBRATION_KEYS: tuple[str, ...] = ("image_width", "image_height", "camera_name",
                                         "camera_matrix", "distortion_model",
                                         "distortion_coefficients", "rectification_matrix",
                                         "projection_matrix")  # fmt: skip
"""The keys of the calibration file ROS's ``camera_calibration`` writes."""

OPEN3D_INTRINSIC_KEYS: tuple[str, ...] = ("width", "height", "intrinsic_matrix")
"""Open3D's ``PinholeCameraIntrinsic`` JSON."""

OPEN3D_PARAMETER_KEYS: tuple[str, ...] = ("class_name", "extrinsic", "intrinsic",
                                          "version_major", "version_minor")  # fmt: skip
"""Open3D's ``PinholeCameraParameters`` JSON."""


LAYOUT_KEYS: frozenset[str] = frozenset(
    ("ppx", "ppy", "K", "k", "camera_matrix", "intrinsic_matrix", "intrinsic", "extrinsic")
)
"""Keys that mark a JSON object as one of these layouts' camera files."""


def _numbers(value: object, name: str, n: int | None, where: str) -> np.ndarray:
    """``value`` as ``n`` finite floats (a flat list; ``n`` None: any length), or an error
    naming ``name``."""
    ok = isinstance(value, list) and (n is None or len(value) == n)
    if isinstance(value, list):
        ok = ok and all(
            isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)
            for v in value
        )
    if not ok:
        what = "finite numbers" if n is None else f"{n} finite numbers"
        raise InputError(f"{where}: {name} must be a list of {what}, got {value!r}"[:300])
    return np.array(value, dtype=np.float64)


def _unknown(doc: JsonDict, allowed: tuple[str, ...], layout: str, where: str) -> None:
    extra = sorted(set(doc) - set(allowed) - set(PREGRASP_EXTRA))
    if extra:
        raise InputError(
            f"{where}: unknown keys {extra} for a {layout} camera file; allowed: "
            f"{', '.join(allowed + PREGRASP_EXTRA)}"
        )


def _pinhole(K: np.ndarray, name: str, where: str) -> dict[str, object]:
    """fx fy cx cy of a row-major 3 x 3 camera matrix ``K`` without skew."""
    if K[1] != 0.0:
        raise InputError(
            f"{where}: {name} has skew {K[1]:g} (K[0][1]); pregrasp's pinhole camera has none: "
            "give fx fy cx cy of the rectified image (--intrinsics FX FY CX CY)"
        )
    if K[3] != 0.0 or K[6] != 0.0 or K[7] != 0.0 or K[8] != 1.0:
        raise InputError(
            f"{where}: {name} is not a pinhole camera matrix [fx 0 cx; 0 fy cy; 0 0 1], got "
            f"{K.tolist()}"
        )
    return {"fx": float(K[0]), "fy": float(K[4]), "cx": float(K[2]), "cy": float(K[5])}


def _distortion(coeffs: np.ndarray, name: str, model: object, where: str) -> list[str]:
    """The note for distortion coefficients that are not all zero (none for zeros)."""
    if not np.any(coeffs):
        return []
    return [
        f"{where}: the distortion {name} {np.round(coeffs, 6).tolist()} (model {model!r}) is not "
        "applied: the depth image is taken as undistorted (rectified)"
    ]


def _size(doc: JsonDict, w_key: str, h_key: str) -> dict[str, object]:
    return {k: doc[src] for k, src in (("width", w_key), ("height", h_key)) if src in doc}


def _realsense(doc: JsonDict, where: str) -> tuple[JsonDict, list[str]]:
    _unknown(doc, REALSENSE_KEYS, "RealSense", where)
    missing = [k for k in ("fx", "fy", "ppx", "ppy") if k not in doc]
    if missing:
        raise InputError(f"{where}: the RealSense intrinsics lack {', '.join(missing)} (pixels)")
    out: JsonDict = {"fx": doc["fx"], "fy": doc["fy"], "cx": doc["ppx"], "cy": doc["ppy"]}
    notes: list[str] = []
    if "coeffs" in doc:
        notes = _distortion(_numbers(doc["coeffs"], "coeffs", 5, where), "coeffs",
                            doc.get("model"), where)  # fmt: skip
    return {**out, **_size(doc, "width", "height")}, notes


def _ros_binning(doc: JsonDict, where: str) -> None:
    for key in ("binning_x", "binning_y"):
        b = doc.get(key, 0)
        if b not in (0, 1):
            raise InputError(
                f"{where}: {key} {b!r}: a binned image is not supported; give the binned "
                "image's fx fy cx cy (--intrinsics FX FY CX CY)"
            )
    roi = doc.get("roi")
    if isinstance(roi, dict) and any(roi.get(k, 0) for k in ("x_offset", "y_offset", "height",
                                                             "width")):  # fmt: skip
        raise InputError(
            f"{where}: roi {roi!r}: a region of interest is not supported; give the cropped "
            "image's fx fy cx cy (--intrinsics FX FY CX CY)"
        )


def _ros_info(doc: JsonDict, where: str) -> tuple[JsonDict, list[str]]:
    lower = "k" in doc
    keys = tuple(k.lower() if len(k) == 1 and lower else k for k in ROS_INFO_KEYS)
    _unknown(doc, keys, "ROS CameraInfo", where)
    k, d = ("k", "d") if lower else ("K", "D")
    out = _pinhole(_numbers(doc[k], k, 9, where), k, where)
    _ros_binning(doc, where)
    notes: list[str] = []
    if d in doc:
        notes = _distortion(_numbers(doc[d], d, None, where), d, doc.get("distortion_model"),
                            where)  # fmt: skip
    size: JsonDict = {key: doc[key] for key in ("width", "height") if key in doc}
    if size.get("width") == 0 and size.get("height") == 0:  # CameraInfo's "not calibrated"
        size = {}
    return {**out, **size}, notes


def _matrix_field(doc: JsonDict, key: str, n: int | None, where: str) -> np.ndarray:
    """The ``data`` (``n`` numbers; None: any) of a ``{rows, cols, data}`` of a ROS
    calibration file."""
    m = doc[key]
    if not isinstance(m, dict) or "data" not in m:
        raise InputError(f"{where}: {key} must be an object with rows, cols and data")
    return _numbers(m["data"], f"{key}.data", n, where)


def _ros_calibration(doc: JsonDict, where: str) -> tuple[JsonDict, list[str]]:
    _unknown(doc, ROS_CALIBRATION_KEYS, "ROS calibration", where)
    out = _pinhole(_matrix_field(doc, "camera_matrix", 9, where), "camera_matrix", where)
    notes: list[str] = []
    if "distortion_coefficients" in doc:
        d = _matrix_field(doc, "distortion_coefficients", None, where)
        notes = _distortion(d, "distortion_coefficients", doc.get("distortion_model"), where)
    return {**out, **_size(doc, "image_width", "image_height")}, notes


def _open3d_intrinsic(doc: JsonDict, where: str) -> JsonDict:
    _unknown(doc, OPEN3D_INTRINSIC_KEYS, "Open3D PinholeCameraIntrinsic", where)
    if "intrinsic_matrix" not in doc:
        raise InputError(f"{where}: the Open3D intrinsics lack intrinsic_matrix")
    K = _numbers(doc["intrinsic_matrix"], "intrinsic_matrix", 9, where)
    out = _pinhole(K.reshape(3, 3).T.ravel(), "intrinsic_matrix (column-major)", where)
    return {**out, **_size(doc, "width", "height")}


def _open3d(doc: JsonDict, where: str) -> tuple[JsonDict, list[str]]:
    if "intrinsic" not in doc and "extrinsic" not in doc:
        return _open3d_intrinsic(doc, where), []
    _unknown(doc, OPEN3D_PARAMETER_KEYS, "Open3D PinholeCameraParameters", where)
    inner = doc.get("intrinsic")
    if not isinstance(inner, dict):
        raise InputError(f"{where}: the Open3D camera parameters lack an intrinsic object")
    out = _open3d_intrinsic(inner, where)
    if "extrinsic" in doc and "T_world_camera" in doc:
        raise InputError(f"{where}: give the camera pose once: extrinsic or T_world_camera")
    if "extrinsic" in doc:
        E = _numbers(doc["extrinsic"], "extrinsic", 16, where).reshape(4, 4).T  # world -> camera
        R, t = E[:3, :3], E[:3, 3]
        if not np.allclose(R.T @ R, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0.0:
            raise InputError(f"{where}: extrinsic's rotation is not a proper rotation")
        if not np.allclose(E[3], [0.0, 0.0, 0.0, 1.0]):
            raise InputError(f"{where}: extrinsic's last row must be 0 0 0 1")
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R.T, -R.T @ t
        out["T_world_camera"] = T.tolist()
    return out, []


def to_pregrasp_keys(doc: JsonDict, where: str) -> tuple[JsonDict, str, list[str]]:
    """``(doc in pregrasp's keys, the layout's name, notes)`` for a camera file's JSON object
    ``doc`` (``where`` names the file in errors and notes). A document with none of the other
    layouts' distinguishing keys is returned as it is (layout ``"pregrasp"``), to be checked by
    ``CameraFile.parse``."""
    if "intrinsic_matrix" in doc or "class_name" in doc or "extrinsic" in doc:
        layout, (out, notes) = "Open3D", _open3d(doc, where)
    elif "K" in doc or "k" in doc:
        layout, (out, notes) = "ROS CameraInfo", _ros_info(doc, where)
    elif "camera_matrix" in doc:
        layout, (out, notes) = "ROS calibration", _ros_calibration(doc, where)
    elif "ppx" in doc or "ppy" in doc:
        layout, (out, notes) = "RealSense", _realsense(doc, where)
    else:
        return doc, "pregrasp", []
    for key in PREGRASP_EXTRA:
        if key in doc:
            out[key] = doc[key]
    return out, layout, notes
