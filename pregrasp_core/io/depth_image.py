"""Depth images as input files: a 16-bit PNG in millimetres, or a 2-D float NPY in metres, with
pinhole intrinsics, read into the scene's points and the camera position (``docs/input.md``,
"Depth-camera input").

Intrinsics, in this order: the ``intrinsics`` argument (an :class:`~pregrasp_core.sensor.
Intrinsics`, four numbers ``fx fy cx cy``, or the path of a JSON file; the CLI's
``--intrinsics``), else the sidecar ``NAME.json`` beside ``NAME.png`` / ``NAME.npy``. A JSON file
with ``T_world_camera`` puts the points in that world frame (the viewpoint is then the camera's
position); otherwise the points stay in the camera frame and the viewpoint is the origin.

``.npy`` is ambiguous: it is a **depth map** when intrinsics are given or a sidecar JSON exists
(then it must be a 2-D float array in metres), otherwise a point cloud (``numpy_format``).
"""

from __future__ import annotations

import io
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..sensor.depth import (
    Intrinsics,
    depth_from_png,
    depth_to_points,
    image_size,
    load_camera_pose,
)
from .cloud import FileData

DEPTH_IMAGE_EXTENSIONS: tuple[str, ...] = (".png",)
"""Extensions that are always depth images (``.npy`` is one only with intrinsics, see above)."""

IntrinsicsArg = Intrinsics | str | Path | tuple[float, ...] | list[float] | None
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
    """Where they came from: ``"--intrinsics"`` (numbers) or the JSON file's path."""


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


def _decode(file: FileData, ext: str) -> np.ndarray:
    """(H, W) float64 depth in metres, NaN where there is no return."""
    source = file.source
    if ext == ".png":
        return depth_from_png(file.data, source)
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
    return arr.astype(np.float64)


def _intrinsics(file: FileData, intrinsics: IntrinsicsArg) -> tuple[Intrinsics, str, Path | None]:
    """(intrinsics, where they came from, the JSON file or None)."""
    if isinstance(intrinsics, Intrinsics):
        return intrinsics, "--intrinsics", None
    if isinstance(intrinsics, str | Path):
        p = Path(intrinsics)
        return Intrinsics.from_json(p), str(p), p
    if intrinsics is not None:
        try:
            return Intrinsics.from_values(intrinsics), "--intrinsics", None
        except InputError as exc:
            raise InputError(f"{file.source}: --intrinsics: {exc}") from None
    side = sidecar(file.path)
    if side is None:
        name = "NAME.json" if file.path is None else file.path.with_suffix(".json").name
        raise InputError(
            f"{file.source}: a depth image needs the camera's intrinsics: pass --intrinsics "
            f"FX FY CX CY (pixels) or --intrinsics FILE.json, or put {name} beside it"
        )
    return Intrinsics.from_json(side), str(side), side


def read_depth_image(file: FileData, ext: str, intrinsics: IntrinsicsArg) -> DepthScene:
    """The points of the depth image ``file`` and the camera position (see the module)."""
    K, where, json_path = _intrinsics(file, intrinsics)
    depth = _decode(file, ext)
    if json_path is not None:
        size = image_size(json_path)
        if size is not None and depth.shape != size:
            raise InputError(
                f"{file.source}: the image is {depth.shape[1]} x {depth.shape[0]} pixels but "
                f"the intrinsics file {json_path} says {size[1]} x {size[0]}"
            )
    cloud = depth_to_points(depth, K, source=file.source)
    pts, vp = cloud.points, np.zeros(3)
    T = None if json_path is None else load_camera_pose(json_path)
    if T is not None:
        pts = pts @ T[:3, :3].T + T[:3, 3]
        vp = T[:3, 3].copy()
    return DepthScene(np.asarray(pts, dtype=np.float64), vp, int(depth.size), K, where)
