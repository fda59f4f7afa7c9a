"""Depth images as input files: a 16-bit PNG in millimetres, or a 2-D float NPY in metres, with
pinhole intrinsics, read into the scene's points and the camera position (``docs/input.md``,
"Depth-camera input").

The camera file (:class:`~pregrasp_core.sensor.CameraFile`): the **sidecar** ``NAME.json``
beside ``NAME.png`` / ``NAME.npy`` is read when it exists (fx, fy, cx, cy; optionally width and
height, ``T_world_camera``, ``depth_scale``). The ``intrinsics`` argument (the CLI's
``--intrinsics``) overrides it: four numbers ``fx fy cx cy`` (or an :class:`~pregrasp_core.
sensor.Intrinsics`) replace the sidecar's fx, fy, cx, cy and keep its other fields; the path of
a JSON file, or a :class:`~pregrasp_core.sensor.CameraFile` (an upload's), replaces the sidecar.
A camera file with ``T_world_camera`` puts the points in that world frame (the viewpoint is
then the camera's position); otherwise the points stay in the camera frame and the viewpoint is
the origin.

``.npy`` is ambiguous: it is a **depth map** when intrinsics are given or a sidecar JSON exists
(then it must be a 2-D float array in metres), otherwise a point cloud (``numpy_format``).
"""

from __future__ import annotations

import io
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..sensor.depth import CameraFile, Intrinsics, depth_from_png, depth_to_points
from .cloud import FileData

DEPTH_IMAGE_EXTENSIONS: tuple[str, ...] = (".png",)
"""Extensions that are always depth images (``.npy`` is one only with intrinsics, see above)."""

IntrinsicsArg = Intrinsics | CameraFile | str | Path | tuple[float, ...] | list[float] | None
"""What ``intrinsics`` may be: see the module."""


@dataclass(frozen=True, eq=False)
class DepthScene:
    """The points of a depth image and where the camera was."""

    points: np.ndarray
    """(N, 3) float64, metres: one point per valid pixel, world frame of the JSON's
    ``T_world_camera`` when it has one, else the camera frame (OpenCV)."""
    viewpoint: np.ndarray
    """(3,) the camera position in the points' frame."""
    n_pixels: int
    """Pixels of the image (valid or not)."""
    intrinsics: Intrinsics
    """The intrinsics used."""
    intrinsics_source: str
    """Where they came from: ``"--intrinsics"`` (numbers) or the JSON file's path or name."""
    camera: CameraFile | None = None
    """The camera file read (the sidecar, a JSON given, an upload's), None for numbers alone."""
    depth_scale: float = 0.001
    """Metres per stored depth unit used (a PNG's; 1 for an NPY in metres)."""
    shape: tuple[int, int] = (0, 0)
    """(height, width) of the image in pixels."""

    def pixels(self, points: np.ndarray) -> np.ndarray:
        """(N, 2) float ``(column, row)`` of world points (N, 3) in the image (the pinhole
        projection through the camera pose; a point behind the camera gets NaN)."""
        p = np.asarray(points, dtype=np.float64)
        T = None if self.camera is None else self.camera.T_world_camera
        if T is not None:
            p = (p - T[:3, 3]) @ T[:3, :3]  # into the camera frame
        with np.errstate(divide="ignore", invalid="ignore"):
            z = np.where(p[:, 2] > 0.0, p[:, 2], np.nan)
            K = self.intrinsics
            return np.column_stack([K.fx * p[:, 0] / z + K.cx, K.fy * p[:, 1] / z + K.cy])


def sidecar(path: Path | None) -> Path | None:
    """``NAME.json`` beside ``NAME.png`` / ``NAME.npy`` when it exists, else None."""
    if path is None:
        return None
    side = path.with_suffix(".json")
    return side if side.is_file() else None


def is_depth_input(file: FileData, ext: str, intrinsics: IntrinsicsArg) -> bool:
    """True when ``file`` (extension ``ext``) is read as a depth image (see the module)."""
    if ext in DEPTH_IMAGE_EXTENSIONS:
        return True
    return ext == ".npy" and (intrinsics is not None or sidecar(file.path) is not None)


def _decode(file: FileData, ext: str, unit: float | None) -> np.ndarray:
    """(H, W) float64 depth in metres (``unit`` metres per stored value; None: the format's),
    NaN where there is no return."""
    source = file.source
    if ext == ".png":
        return depth_from_png(file.data, source, unit)
    try:
        arr = np.load(io.BytesIO(file.data), allow_pickle=False)
    except Exception as exc:  # noqa: BLE001 - numpy raises ValueError/OSError/EOFError/...
        raise InputError(f"{source}: not a plain NPY array ({exc})") from None
    if not isinstance(arr, np.ndarray):
        raise InputError(f"{source}: an NPZ archive is not a depth image; save one 2-D array")
    if arr.dtype.kind != "f" or arr.ndim != 2:
        raise InputError(
            f"{source}: with intrinsics an NPY is a depth map and must be a 2-D float array in "
            f"metres, got shape {arr.shape} dtype {arr.dtype} (a point cloud must not have "
            "intrinsics nor a sidecar .json)"
        )
    depth = arr.astype(np.float64)
    return depth if unit is None or unit == 1.0 else depth * float(unit)


def missing_intrinsics(source: str, path: Path | None) -> str:
    """The message for a depth image without intrinsics (none given, no sidecar)."""
    if path is None:  # an upload: nothing beside it can be read
        return (
            f"{source}: a depth image needs the camera's intrinsics: give fx fy cx cy (pixels; "
            "the viewer's 'intrinsics' field) or its camera file (upload NAME.json: fx, fy, "
            "cx, cy, optionally width, height, T_world_camera, depth_scale)"
        )
    name = path.with_suffix(".json").name
    return (
        f"{source}: a depth image needs the camera's intrinsics: pass --intrinsics FX FY CX CY "
        f"(pixels) or --intrinsics FILE.json, or put {name} beside it"
    )


def _camera(file: FileData, intrinsics: IntrinsicsArg) -> tuple[Intrinsics, str, CameraFile | None]:
    """(intrinsics, where they came from, the camera file or None); see the module."""
    if isinstance(intrinsics, CameraFile):
        return intrinsics.intrinsics, intrinsics.source, intrinsics
    if isinstance(intrinsics, str | Path):
        cam = CameraFile.read(intrinsics)
        return cam.intrinsics, cam.source, cam
    side = sidecar(file.path)
    if intrinsics is not None:
        if isinstance(intrinsics, Intrinsics):
            K = intrinsics
        else:
            try:
                K = Intrinsics.from_values(intrinsics)
            except InputError as exc:
                raise InputError(f"{file.source}: --intrinsics: {exc}") from None
        if side is None:
            return K, "--intrinsics", None
        cam = CameraFile.read(side).with_intrinsics(K)
        return K, f"--intrinsics (with the rest of {side.name})", cam
    if side is None:
        raise InputError(missing_intrinsics(file.source, file.path))
    cam = CameraFile.read(side)
    return cam.intrinsics, cam.source, cam


def read_depth_image(file: FileData, ext: str, intrinsics: IntrinsicsArg) -> DepthScene:
    """The points of the depth image ``file`` and the camera position (see the module)."""
    K, where, cam = _camera(file, intrinsics)
    unit = None if cam is None else cam.depth_scale
    depth = _decode(file, ext, unit)
    if cam is not None and cam.size is not None and depth.shape != cam.size:
        h, w = cam.size
        raise InputError(
            f"{file.source}: the image is {depth.shape[1]} x {depth.shape[0]} pixels but "
            f"the intrinsics file {cam.source} says {w} x {h}"
        )
    cloud = depth_to_points(depth, K, source=file.source)
    pts, vp = cloud.points, np.zeros(3)
    T = None if cam is None else cam.T_world_camera
    if T is not None:
        pts = pts @ T[:3, :3].T + T[:3, 3]
        vp = T[:3, 3].copy()
    used = unit if unit is not None else (0.001 if ext == ".png" else 1.0)
    return DepthScene(
        np.asarray(pts, dtype=np.float64),
        vp,
        int(depth.size),
        K,
        where,
        cam,
        float(used),
        (int(depth.shape[0]), int(depth.shape[1])),
    )
