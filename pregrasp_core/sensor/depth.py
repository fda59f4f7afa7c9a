"""Depth images to point clouds: pinhole intrinsics and the back-projection.

Camera frame (OpenCV's): origin at the optical centre, **+z forward** (along the optical axis),
**+x right** and **+y down** in the image. Pixel (row ``i``, column ``j``) is the ray through the
image point ``(u, v) = (j, i)`` (pixel centres at integer coordinates, as OpenCV's and ROS's
``K`` matrices assume), so a pixel with depth ``z`` (the z coordinate, not the range along the
ray) is the point::

    x = (j - cx) * z / fx,   y = (i - cy) * z / fy,   z = z

Depth files:

- ``.png``: a 16-bit single-channel PNG of depth in **millimetres** (the format of Kinect,
  RealSense and the TUM / YCB datasets); 0 means no return;
- ``.npy``: a 2-D float array of depth in **metres** (``numpy.load(..., allow_pickle=False)``);
  0 or NaN means no return.

Intrinsics are four numbers ``fx fy cx cy`` (pixels) or a JSON camera file
``{"fx": .., "fy": .., "cx": .., "cy": ..}``, optionally with ``"width"`` and ``"height"``
(checked against the image), ``"T_world_camera"`` (a 4 x 4 pose, row-major nested lists, read
by :func:`load_camera_pose`) and ``"depth_scale"`` (metres per stored depth unit), read and
checked by :class:`CameraFile`. The viewpoint of a depth cloud is the camera frame's origin.
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InputError
from .camera_layouts import to_pregrasp_keys

MAX_DEPTH_M: float = 100.0
"""Largest depth accepted (metres): beyond it the file is not a depth camera's (or not metres)."""

MIN_RETURNS: int = 10
"""Fewest valid pixels a usable depth image has."""

INTRINSICS_KEYS: tuple[str, ...] = ("fx", "fy", "cx", "cy")
"""Keys an intrinsics JSON file must have."""

OPTIONAL_KEYS: tuple[str, ...] = ("width", "height", "T_world_camera", "depth_scale")
"""Keys an intrinsics JSON file may have besides :data:`INTRINSICS_KEYS`."""

MAX_CAMERA_FILE_BYTES: int = 1 << 20
"""Largest intrinsics JSON file read (bytes): a camera file holds a few numbers."""

DEPTH_EXTENSIONS: tuple[str, ...] = (".png", ".npy")
"""Depth-image formats :func:`load_depth_image` reads."""


def _number(value: object, name: str, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise InputError(f"{where}: {name} must be a number, got {value!r}")
    v = float(value)
    if not math.isfinite(v):
        raise InputError(f"{where}: {name} must be finite, got {value!r}")
    return v


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics of a depth camera, in pixels (OpenCV convention, see the module)."""

    fx: float
    """Focal length along the image's x (columns), pixels, > 0."""
    fy: float
    """Focal length along the image's y (rows), pixels, > 0."""
    cx: float
    """Column of the principal point, pixels."""
    cy: float
    """Row of the principal point, pixels."""

    def __post_init__(self) -> None:
        for name in INTRINSICS_KEYS:
            object.__setattr__(self, name, _number(getattr(self, name), name, "intrinsics"))
        if not (self.fx > 0.0 and self.fy > 0.0):
            raise InputError(
                f"intrinsics: fx and fy must be positive focal lengths in pixels, got "
                f"fx={self.fx}, fy={self.fy}"
            )

    @classmethod
    def from_values(cls, values: object) -> Intrinsics:
        """From four numbers ``(fx, fy, cx, cy)`` (e.g. the CLI's ``--intrinsics fx fy cx cy``)."""
        vals = list(values) if isinstance(values, (list, tuple, np.ndarray)) else None
        if vals is None or len(vals) != 4:
            raise InputError(f"intrinsics: give four numbers fx fy cx cy (pixels), got {values!r}")
        return cls(*vals)

    @classmethod
    def from_json(cls, path: str | Path) -> Intrinsics:
        """From a JSON file ``{"fx": .., "fy": .., "cx": .., "cy": ..}`` (see the module)."""
        return CameraFile.read(path).intrinsics

    def matrix(self) -> np.ndarray:
        """(3, 3) float64 camera matrix ``K``."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def to_dict(self) -> dict[str, float]:
        """JSON-ready dict (fx, fy, cx, cy)."""
        return {k: float(getattr(self, k)) for k in INTRINSICS_KEYS}


def _no_duplicates(pairs: list[tuple[str, object]]) -> dict[str, object]:
    doc: dict[str, object] = {}
    for k, v in pairs:
        if k in doc:
            raise _DuplicateKey(k)
        doc[k] = v
    return doc


class _DuplicateKey(Exception):
    """A JSON object names a key twice (``json`` would keep the last one silently)."""


def _check_depth_scale(value: object, where: str) -> float:
    s = _number(value, "depth_scale", where)
    if s > 1.0:
        raise InputError(
            f"{where}: depth_scale is metres per stored depth unit, in (0, 1] (0.001 for a PNG "
            f"in millimetres), got {value!r}: that is units per metre (as Open3D's depth_scale "
            f"counts); write {1.0 / s:.6g}"
        )
    if not s > 0.0:
        raise InputError(
            f"{where}: depth_scale must be positive (metres per stored depth unit, 0.001 for "
            f"millimetres), got {value!r}"
        )
    return s


def _check_pose(value: object, where: str) -> tuple[tuple[float, ...], ...]:
    try:
        T = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(f"{where}: T_world_camera must be a 4 x 4 array of numbers") from None
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise InputError(f"{where}: T_world_camera must be a finite 4 x 4 array, got {T.shape}")
    R = T[:3, :3]
    if not np.allclose(R.T @ R, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0.0:
        raise InputError(f"{where}: T_world_camera's rotation is not a proper rotation")
    if not np.allclose(T[3], [0.0, 0.0, 0.0, 1.0]):
        raise InputError(f"{where}: T_world_camera's last row must be 0 0 0 1")
    return tuple(tuple(float(v) for v in row) for row in T)


@dataclass(frozen=True)
class CameraFile:
    """A depth image's camera file (the sidecar ``NAME.json``), every field checked.

    ``{"fx": .., "fy": .., "cx": .., "cy": ..}`` (pixels), optionally ``"width"`` and
    ``"height"`` (pixels, checked against the image), ``"T_world_camera"`` (4 x 4, row-major
    nested lists: the camera's pose in the world frame the points are put in) and
    ``"depth_scale"`` (metres per stored depth unit: 0.001 for a PNG in millimetres, the
    default; 0.0001 for a RealSense at 0.1 mm; a float NPY is metres, 1). Any other key is
    refused; a ``"viewpoint"`` key is refused with a pointer to ``T_world_camera`` (a depth
    image's viewpoint is its camera). The layouts other tools write (RealSense, ROS CameraInfo
    or calibration file, Open3D) are read too, into these keys (``sensor/camera_layouts.py``).
    """

    intrinsics: Intrinsics
    """fx, fy, cx, cy."""
    size: tuple[int, int] | None = None
    """``(height, width)`` when the file gives them."""
    pose: tuple[tuple[float, ...], ...] | None = None
    """``T_world_camera`` as four rows, or None (the points stay in the camera frame)."""
    depth_scale: float | None = None
    """Metres per stored depth unit; None = the format's (PNG: millimetres, NPY: metres)."""
    source: str = "camera file"
    """The file's path or name (quoted in messages)."""
    layout: str = "pregrasp"
    """Whose keys the file has: ``"pregrasp"``, ``"RealSense"``, ``"ROS CameraInfo"``, ``"ROS
    calibration"`` or ``"Open3D"``."""
    notes: tuple[str, ...] = ()
    """What reading it left out (distortion coefficients not applied), one sentence each."""

    @property
    def T_world_camera(self) -> np.ndarray | None:
        """(4, 4) float64 pose, or None."""
        return None if self.pose is None else np.array(self.pose, dtype=np.float64)

    def with_intrinsics(self, intrinsics: Intrinsics) -> CameraFile:
        """This file with other fx, fy, cx, cy (``--intrinsics FX FY CX CY`` over a sidecar)."""
        return dataclasses.replace(self, intrinsics=intrinsics)

    @classmethod
    def parse(cls, data: bytes, source: str) -> CameraFile:
        """The camera file in ``data`` (the bytes of ``source``); ``InputError`` naming
        ``source`` and the field at fault."""
        if len(data) > MAX_CAMERA_FILE_BYTES:
            raise InputError(
                f"{source}: {len(data)} bytes, more than the {MAX_CAMERA_FILE_BYTES} bytes a "
                "camera file may have (it holds a few numbers)"
            )
        try:
            doc = json.loads(data.decode("utf-8"), object_pairs_hook=_no_duplicates)
        except _DuplicateKey as e:
            raise InputError(f"{source}: key {e.args[0]!r} given twice") from None
        except (UnicodeDecodeError, ValueError, RecursionError) as e:
            raise InputError(
                f'{source}: not a JSON file ({e}); write {{"fx": .., "fy": .., "cx": .., "cy": ..}}'
            ) from None
        if not isinstance(doc, dict):
            raise InputError(
                f"{source}: the intrinsics must be a JSON object with keys fx, fy, cx, cy"
            )
        doc, layout, notes = to_pregrasp_keys(doc, source)
        if "viewpoint" in doc:
            raise InputError(
                f"{source}: viewpoint: a depth image is seen from its camera; give the camera's "
                "pose as T_world_camera (or pass --viewpoint X Y Z)"
            )
        unknown = sorted(set(doc) - set(INTRINSICS_KEYS) - set(OPTIONAL_KEYS))
        if unknown:
            raise InputError(
                f"{source}: unknown intrinsics keys {unknown}; allowed: "
                f"{', '.join(INTRINSICS_KEYS + OPTIONAL_KEYS)}"
            )
        missing = [k for k in INTRINSICS_KEYS if k not in doc]
        if missing:
            raise InputError(f"{source}: the intrinsics lack {', '.join(missing)} (pixels)")
        vals = [_number(doc[k], k, source) for k in INTRINSICS_KEYS]
        for k, v in zip(("fx", "fy"), vals[:2], strict=True):
            if not v > 0.0:
                raise InputError(
                    f"{source}: fx and fy must be positive focal lengths in pixels, got {k}={v:g}"
                )
        size = None
        if "width" in doc or "height" in doc:
            if "width" not in doc or "height" not in doc:
                raise InputError(f"{source}: give both width and height, or neither")
            w, h = doc["width"], doc["height"]
            ok = all(isinstance(v, int) and not isinstance(v, bool) and v >= 1 for v in (w, h))
            if not ok:
                raise InputError(
                    f"{source}: width and height must be positive integers, got {w!r}, {h!r}"
                )
            size = (int(h), int(w))
        pose = None if "T_world_camera" not in doc else _check_pose(doc["T_world_camera"], source)
        scale = None if "depth_scale" not in doc else _check_depth_scale(doc["depth_scale"], source)
        return cls(Intrinsics(*vals), size, pose, scale, source, layout, tuple(notes))

    @classmethod
    def read(cls, path: str | Path) -> CameraFile:
        """The camera file at ``path`` (see :meth:`parse`)."""
        p = Path(path)
        if not p.is_file():
            raise InputError(f"{p}: intrinsics file not found; check the path")
        try:
            with p.open("rb") as fh:
                data = fh.read(MAX_CAMERA_FILE_BYTES + 1)
        except OSError as e:
            raise InputError(f"{p}: cannot read the intrinsics file ({e.strerror or e})") from None
        return cls.parse(data, str(p))


def image_size(path: str | Path) -> tuple[int, int] | None:
    """``(height, width)`` from an intrinsics JSON file, when it gives them."""
    return CameraFile.read(path).size


def load_camera_pose(path: str | Path) -> np.ndarray | None:
    """``T_world_camera`` (4, 4) float64 from an intrinsics JSON file, or None when absent."""
    return CameraFile.read(path).T_world_camera


@dataclass(frozen=True, eq=False)
class DepthCloud:
    """The points of a depth image, camera frame (OpenCV: +z forward, +x right, +y down)."""

    points: np.ndarray
    """(N, 3) float64, metres, camera frame: one point per valid pixel, in row-major order."""
    pixels: np.ndarray
    """(N, 2) int64: ``(row, column)`` of each point's pixel."""
    shape: tuple[int, int]
    """``(height, width)`` of the image, pixels."""
    intrinsics: Intrinsics
    """The intrinsics used."""
    source: str
    """The depth file's path, or ``"array"``."""

    @property
    def viewpoint(self) -> np.ndarray:
        """(3,) the camera position in the cloud's frame: the origin."""
        return np.zeros(3)

    @property
    def n_points(self) -> int:
        """Number of valid pixels N."""
        return int(self.points.shape[0])


def depth_to_points(depth: np.ndarray, intrinsics: Intrinsics, source: str = "array") -> DepthCloud:
    """Back-project a depth image ``depth`` (H, W) in **metres** (0 or NaN = no return)."""
    d = np.asarray(depth)
    if d.ndim != 2:
        raise InputError(f"{source}: a depth image must be 2-D (H, W), got shape {d.shape}")
    if d.dtype.kind not in "fiu":
        raise InputError(f"{source}: depth must be numbers, got dtype {d.dtype}")
    if min(d.shape) < 1:
        raise InputError(f"{source}: the depth image is empty (shape {d.shape})")
    z = d.astype(np.float64)
    with np.errstate(invalid="ignore"):
        if np.any(np.isinf(z)):
            raise InputError(f"{source}: the depth image holds infinite values; use 0 or NaN")
        if np.any(z < 0.0):
            raise InputError(
                f"{source}: the depth image holds negative depths (min {np.nanmin(z)})"
            )
        valid = np.isfinite(z) & (z > 0.0)
    if not np.any(valid):
        raise InputError(f"{source}: the depth image has no valid pixel (all 0 or NaN)")
    zmax = float(z[valid].max())
    if zmax > MAX_DEPTH_M:
        raise InputError(
            f"{source}: depths reach {zmax:.4g} m (more than {MAX_DEPTH_M:g} m): a float NPY must "
            "hold metres (a PNG is read as millimetres)"
        )
    n_valid = int(valid.sum())
    if n_valid < MIN_RETURNS:
        raise InputError(
            f"{source}: only {n_valid} valid pixels; at least {MIN_RETURNS} are needed"
        )
    rows, cols = np.nonzero(valid)  # row-major order
    zz = z[rows, cols]
    x = (cols - intrinsics.cx) * zz / intrinsics.fx
    y = (rows - intrinsics.cy) * zz / intrinsics.fy
    pts = np.stack([x, y, zz], axis=1)
    pix = np.stack([rows, cols], axis=1).astype(np.int64)
    pts.setflags(write=False)
    pix.setflags(write=False)
    return DepthCloud(
        points=pts,
        pixels=pix,
        shape=(int(d.shape[0]), int(d.shape[1])),
        intrinsics=intrinsics,
        source=source,
    )


def depth_from_png(data: bytes, source: str, unit: float | None = None) -> np.ndarray:
    """(H, W) float64 metres from the bytes of a 16-bit grayscale PNG in millimetres, or in
    ``unit`` metres per stored value (a camera file's ``depth_scale``); 0 = no return -> NaN.
    ``InputError`` naming ``source`` for anything else."""
    import imageio.v3 as iio

    try:
        img = np.asarray(iio.imread(data, extension=".png"))
    except Exception as e:  # noqa: BLE001 - imageio raises many types for a bad file
        raise InputError(f"{source}: cannot read the PNG ({e})") from None
    if img.ndim != 2:
        raise InputError(
            f"{source}: a depth PNG must have one channel, got shape {img.shape}; save the "
            "depth as a 16-bit grayscale PNG in millimetres"
        )
    if img.dtype != np.uint16:
        raise InputError(
            f"{source}: a depth PNG must be 16-bit (millimetres), got {img.dtype}; an 8-bit "
            "PNG is an image, not depth"
        )
    if unit is None or unit == 0.001:
        depth = img.astype(np.float64) / 1000.0
    else:
        depth = img.astype(np.float64) * float(unit)
    depth[img == 0] = np.nan
    return depth


def read_depth_file(path: str | Path, unit: float | None = None) -> np.ndarray:
    """The depth image of ``path`` (H, W) float64 in metres, NaN where there is no return;
    ``unit``: metres per stored value (None: a PNG holds millimetres, an NPY metres)."""
    p = Path(path)
    ext = p.suffix.lower()
    if ext not in DEPTH_EXTENSIONS:
        raise InputError(
            f"{p}: unknown depth-image extension {p.suffix!r}; use a 16-bit PNG in millimetres "
            "(.png) or a float NPY in metres (.npy)"
        )
    if not p.is_file():
        raise InputError(f"{p}: file not found; check the path")
    if p.stat().st_size == 0:
        raise InputError(f"{p}: the file is empty")
    if ext == ".png":
        return depth_from_png(p.read_bytes(), str(p), unit)
    try:
        arr = np.load(p, allow_pickle=False)
    except ValueError as e:
        raise InputError(f"{p}: not a plain NPY array ({e})") from None
    except OSError as e:
        raise InputError(f"{p}: cannot read the NPY ({e})") from None
    if not isinstance(arr, np.ndarray):
        raise InputError(f"{p}: an NPZ archive is not a depth image; save one 2-D array")
    if arr.dtype.kind != "f":
        raise InputError(
            f"{p}: a depth NPY must be a float array in metres, got dtype {arr.dtype} (a 16-bit "
            "millimetre image belongs in a PNG)"
        )
    if arr.ndim != 2:
        raise InputError(f"{p}: a depth NPY must be 2-D (H, W), got shape {arr.shape}")
    depth = arr.astype(np.float64)
    return depth if unit is None or unit == 1.0 else depth * float(unit)


def load_depth_image(
    path: str | Path, intrinsics: Intrinsics | CameraFile | str | Path | object
) -> DepthCloud:
    """The cloud of a depth image in the camera frame (see the module for frame and formats).

    ``intrinsics``: an :class:`Intrinsics`, four numbers ``(fx, fy, cx, cy)``, a
    :class:`CameraFile` or the path of one; a camera file's ``width``/``height`` must match the
    image and its ``depth_scale`` gives the depth unit (its pose is not applied here).
    """
    camera = None
    if isinstance(intrinsics, Intrinsics):
        K = intrinsics
    elif isinstance(intrinsics, CameraFile):
        camera = intrinsics
    elif isinstance(intrinsics, (str, Path)):
        camera = CameraFile.read(intrinsics)
    else:
        K = Intrinsics.from_values(intrinsics)
    if camera is not None:
        K = camera.intrinsics
    depth = read_depth_file(path, None if camera is None else camera.depth_scale)
    if camera is not None and camera.size is not None and depth.shape != camera.size:
        size = camera.size
        raise InputError(
            f"{path}: the image is {depth.shape[1]} x {depth.shape[0]} pixels but the "
            f"intrinsics file {camera.source} says {size[1]} x {size[0]}"
        )
    return depth_to_points(depth, K, source=str(path))


def project_points(points: np.ndarray, intrinsics: Intrinsics) -> np.ndarray:
    """(N, 2) image coordinates ``(u, v)`` = (column, row) of camera-frame ``points`` (N, 3)."""
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"points must have shape (N, 3), got {p.shape}")
    return np.stack(
        [intrinsics.fx * p[:, 0] / p[:, 2] + intrinsics.cx,
         intrinsics.fy * p[:, 1] / p[:, 2] + intrinsics.cy],
        axis=1,
    )  # fmt: skip
