"""The cloud every reader produces: ``PointCloud``, the input limits and the shared validation
(non-finite rows, scaling, subsampling, point count and degeneracy)."""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypedDict

import numpy as np

from ..errors import DegenerateGeometryError, InputError
from ..tolerances import FLAT_EXTENT, GEOM_EPS, UNIT_NORMAL_TOL

if TYPE_CHECKING:
    from ..facemask import SupportPlane
    from ..sensor import SensorView

logger = logging.getLogger(__name__)

DEFAULT_N_POINTS: int = 20000
"""Points sampled on a mesh (and the cap for a cloud) unless told otherwise."""

DEFAULT_MAX_BYTES: int = 200 * 1024 * 1024
"""Largest input accepted (bytes): files, uploads and the decompressed arrays of an NPZ."""

MIN_POINTS: int = 16
"""Fewest finite points a usable cloud has: the default normal estimation uses 16 neighbours
(``NormalParams.k``), so a smaller cloud would fail later with no file name."""

MAX_POINTS: int = 10_000_000
"""Most points ``n_points`` may ask for (memory guard)."""

MAX_COORDINATE: float = 1e9
"""Largest coordinate magnitude accepted (metres, after scaling): beyond it the file is surely
not in metres (and squares of the coordinates could overflow)."""

MILLIMETRE_EXTENT: float = 5.0
"""A cloud whose bounding box is longer than this (metres) probably is in millimetres: warn."""

STRAY_FRACTION: float = 0.01
"""At most this fraction of a cloud's points may be dropped as strays (:func:`drop_strays`):
more than that far away is a second object, not noise."""

CLOUD_EXTENSIONS: tuple[str, ...] = (".ply", ".pcd", ".xyz", ".txt", ".csv", ".npy", ".npz")
"""Point-cloud formats (a ``.ply`` with faces is read as a mesh)."""

MESH_EXTENSIONS: tuple[str, ...] = (".obj", ".stl", ".off", ".glb", ".gltf", ".ply")
"""Mesh formats, sampled on their surface."""

SUPPORTED_EXTENSIONS: tuple[str, ...] = tuple(dict.fromkeys(CLOUD_EXTENSIONS + MESH_EXTENSIONS))
"""Every extension :func:`~pregrasp_core.io.load_point_cloud` accepts."""


class CloudInfo(TypedDict, total=False):
    """How a cloud was read (``PointCloud.info``)."""

    format: str
    """``ply``, ``pcd``, ``xyz``, ``txt``, ``csv``, ``npy``, ``npz``, ``obj``, ``stl``, ``off``,
    ``glb``, ``gltf`` or ``array``."""
    kind: str
    """``cloud``, ``mesh`` or ``depth`` (a depth image)."""
    n_read: int
    """Rows read, or mesh vertices."""
    n_dropped_nonfinite: int
    """Rows dropped for a NaN or infinite coordinate."""
    n_dropped_strays: int
    """Points dropped far outside the others (:func:`drop_strays`; absent when none)."""
    scale: float
    """Factor applied to the coordinates."""
    seed: int | None
    """Seed of the sampling / subsampling (None for an array)."""
    warnings: list[str]
    """Recoverable oddities, also logged."""
    n_faces: int
    """Meshes: triangles used."""
    area: float
    """Meshes: surface area, m^2, after scaling."""
    watertight: bool
    """Meshes: closed surface (trimesh's ``is_watertight``)."""
    n_subsampled_from: int
    """Clouds cut to ``n_points``: the point count before."""
    scene: dict[str, Any]
    """Scenes (depth images, PCDs with a ``VIEWPOINT``, ``--scene``): ``n_scene`` (points of
    the scene), ``n_table``, ``n_visible`` and ``n_assumed`` (the object's points seen and
    added by the completion), ``viewpoint``, ``plane`` (the table: normal and height) and
    ``completion`` (``rotation``, ``mirror`` or None)."""
    depth: dict[str, Any]
    """Depth images: ``intrinsics`` (fx, fy, cx, cy in use), ``intrinsics_from`` (the camera
    file, or ``--intrinsics``), ``camera_file`` (the JSON read, or None), ``depth_scale``
    (metres per stored unit used) and ``pose`` (whether ``T_world_camera`` placed the points)."""


@dataclass(frozen=True, eq=False)
class PointCloud:
    """An object's points in metres, in the file's frame (called world), with optional normals.

    The arrays are read-only. Build one with :meth:`from_array` or
    :func:`~pregrasp_core.io.load_point_cloud`, which validate; the plain constructor only
    coerces and checks shapes.
    """

    points: np.ndarray
    """(N, 3) float64, metres, world frame. Finite, N >= ``MIN_POINTS``."""
    normals: np.ndarray | None = None
    """(N, 3) float64 unit vectors (outward for a mesh), or None when the input had none."""
    source: str = "array"
    """Where the points came from: the file path, the uploaded file's name, or ``"array"``."""
    info: CloudInfo = field(default_factory=lambda: CloudInfo())
    """How it was read: ``format`` (e.g. ``"ply"``), ``kind`` (``"cloud"`` or ``"mesh"``),
    ``n_read`` (rows read, or mesh vertices), ``n_dropped_nonfinite``, ``scale``, ``seed`` (of
    the sampling/subsampling; None for an array), ``warnings`` (list of str); meshes add
    ``n_faces``, ``area`` (m^2, after scaling) and ``watertight``; clouds cut to ``n_points`` add
    ``n_subsampled_from``; clouds with stray points add ``n_dropped_strays``; scenes add
    ``scene`` (:class:`CloudInfo`)."""
    viewpoint: np.ndarray | None = None
    """(3,) the camera position (metres, world frame) of a single view, or None (a complete
    cloud): the pipeline turns the normals toward it unless ``--viewpoint`` says otherwise."""
    sensor: SensorView | None = None
    """A scene's object (:class:`~pregrasp_core.sensor.SensorView`: the support plane, which
    points are assumed, their normals), or None. Its ``points`` are this cloud's points."""
    support: SupportPlane | None = None
    """The table the object of a complete scene stood on (a mesh or a fused scan read with
    ``--scene`` and no viewpoint: its table found and removed), or None; the pipeline takes it
    as the support plane, as a single view's ``sensor.plane``."""
    obstacles: np.ndarray | None = None
    """(K, 3) float64: the rest of a scene near the object (its other objects, a wall behind
    it: ``sensor.table.scene_obstacles``), which the hand must clear and never touches; None
    for a cloud without a scene."""

    @property
    def assumed(self) -> np.ndarray | None:
        """(N,) bool: the points assumed by the completion of a single view (draw them in their
        own colour), or None when every point was read."""
        return None if self.sensor is None else self.sensor.assumed

    def __post_init__(self) -> None:
        pts = np.array(self.points, dtype=np.float64)  # a private copy we may freeze
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise ValueError(f"points must have shape (N, 3), got {pts.shape}")
        pts.setflags(write=False)
        object.__setattr__(self, "points", pts)
        if self.normals is not None:
            nrm = np.array(self.normals, dtype=np.float64)
            if nrm.shape != pts.shape:
                raise ValueError(
                    f"normals must have shape {pts.shape} like points, got {nrm.shape}"
                )
            nrm.setflags(write=False)
            object.__setattr__(self, "normals", nrm)
        if self.viewpoint is not None:
            vp = np.array(self.viewpoint, dtype=np.float64)
            if vp.shape != (3,) or not np.all(np.isfinite(vp)):
                raise ValueError(f"viewpoint must be a finite 3-vector, got {self.viewpoint!r}")
            vp.setflags(write=False)
            object.__setattr__(self, "viewpoint", vp)
        if self.sensor is not None and len(self.sensor.points) != len(pts):
            raise ValueError(
                f"sensor holds {len(self.sensor.points)} points but the cloud {len(pts)}"
            )
        if self.obstacles is not None:
            obs = np.array(self.obstacles, dtype=np.float64).reshape(-1, 3)
            if not np.all(np.isfinite(obs)):
                raise ValueError("obstacles must be finite")
            obs.setflags(write=False)
            object.__setattr__(self, "obstacles", obs)

    @property
    def n_points(self) -> int:
        """Number of points N."""
        return int(self.points.shape[0])

    @property
    def bounds(self) -> np.ndarray:
        """(2, 3) axis-aligned lower and upper corners (metres)."""
        return np.stack([self.points.min(axis=0), self.points.max(axis=0)])

    @property
    def extents(self) -> np.ndarray:
        """(3,) axis-aligned side lengths (metres)."""
        b = self.bounds
        return b[1] - b[0]

    @property
    def warnings(self) -> list[str]:
        """The warnings raised while reading (``info["warnings"]``)."""
        return list(self.info.get("warnings", []))

    @classmethod
    def from_array(
        cls,
        points: np.ndarray,
        normals: np.ndarray | None = None,
        source: str = "array",
        scale: float | None = None,
    ) -> PointCloud:
        """Validate an (N, 3) array (and optional (N, 3) normals) into a cloud.

        Rows with a non-finite coordinate are dropped with a warning; raises ``ValueError`` for
        wrong shapes, :class:`InputError` when fewer than ``MIN_POINTS`` finite rows remain and
        :class:`DegenerateGeometryError` for identical or collinear points. ``scale`` multiplies
        the points (e.g. 0.001 for millimetres).
        """
        pts = np.asarray(points, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise ValueError(f"points must have shape (N, 3), got {pts.shape}")
        nrm = None
        if normals is not None:
            nrm = np.asarray(normals, dtype=np.float64)
            if nrm.shape != pts.shape:
                raise ValueError(
                    f"normals must have shape {pts.shape} like points, got {nrm.shape}"
                )
        info = CloudInfo(format="array", kind="cloud", n_read=int(pts.shape[0]), seed=None)
        return finish_cloud(pts, nrm, source, info, scale=scale, n_points=None, seed=0)


# ----------------------------------------------------------------------------------------------
# What readers hand over


@dataclass(frozen=True)
class FileData:
    """The bytes of one input and where they came from (what every reader receives)."""

    data: bytes
    """The whole file (or upload)."""
    source: str
    """The path or the uploaded file's name, quoted in every message."""
    path: Path | None = None
    """The file on disk (None for an upload: nothing beside it may be read)."""
    max_bytes: int = DEFAULT_MAX_BYTES
    """Size limit, also for what the file unpacks to."""


@dataclass(frozen=True)
class RawCloud:
    """The points of a point-cloud file as parsed, before validation (see :func:`finish_cloud`)."""

    points: np.ndarray
    """(N, 3) float64, may hold NaN/inf rows."""
    normals: np.ndarray | None
    """(N, 3) float64 or None."""
    n_read: int
    """Rows read."""
    warnings: list[str] = field(default_factory=list)
    """Warnings raised while parsing."""


# ----------------------------------------------------------------------------------------------
# Validation shared by every reader


def describe_error(exc: BaseException, limit: int = 160) -> str:
    """``"TypeName: message"`` of a parser's exception on one line, at most ``limit`` characters
    of message (error messages quote it and must stay one line)."""
    text = " ".join(str(exc).split())
    if len(text) > limit:
        text = text[: limit - 3] + "..."
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


def add_warning(warnings: list[str], message: str) -> None:
    """Log ``message`` and append it to ``warnings``."""
    logger.warning(message)
    warnings.append(message)


def check_request(n_points: int | None, scale: float | None, source: str, seed: int = 0) -> None:
    """Raise :class:`InputError` for a bad ``n_points``, ``scale`` or ``seed``."""
    if isinstance(seed, bool) or not isinstance(seed, int | np.integer) or seed < 0:
        raise InputError(f"{source}: seed must be a non-negative integer, got {seed!r}")
    if n_points is not None:
        if isinstance(n_points, bool) or not isinstance(n_points, int | np.integer):
            raise InputError(f"{source}: n_points must be an integer, got {n_points!r}")
        if not MIN_POINTS <= int(n_points) <= MAX_POINTS:
            raise InputError(
                f"{source}: n_points must be between {MIN_POINTS} and {MAX_POINTS}, got {n_points}"
            )
    if scale is not None:
        try:
            s = float(scale)
        except (TypeError, ValueError):
            raise InputError(f"{source}: scale must be a number, got {scale!r}") from None
        if not math.isfinite(s) or s <= 0.0:
            raise InputError(f"{source}: scale must be a positive finite number, got {scale!r}")


def split_columns(arr: np.ndarray, source: str, what: str = "column") -> RawCloud:
    """(N, 3) -> points; (N, 6) -> points + normals when columns 4-6 are unit vectors."""
    warns: list[str] = []
    n_cols = arr.shape[1]
    if n_cols not in (3, 6):
        raise InputError(
            f"{source}: wrong {what} count {n_cols}; expected 3 (x y z) or 6 (x y z nx ny nz)"
        )
    pts = arr[:, :3]
    nrm = None
    if n_cols == 6:
        extra = arr[:, 3:]
        with np.errstate(over="ignore", invalid="ignore"):  # huge columns: not unit vectors
            length = np.linalg.norm(extra, axis=1)
        ok = np.isfinite(length) & np.isfinite(pts).all(axis=1)
        if ok.any() and np.all(np.abs(length[ok] - 1.0) < UNIT_NORMAL_TOL):
            nrm = extra
        else:
            add_warning(
                warns,
                f"{source}: columns 4-6 are not unit vectors (colours?); read columns 1-3 as "
                "x y z and ignored the rest",
            )
    return RawCloud(pts, nrm, int(arr.shape[0]), warns)


def finish_cloud(
    pts: np.ndarray,
    nrm: np.ndarray | None,
    source: str,
    info: CloudInfo,
    scale: float | None,
    n_points: int | None,
    seed: int,
) -> PointCloud:
    """Drop non-finite rows, scale, subsample, check count and degeneracy, build the cloud."""
    check_request(n_points, scale, source, seed)
    warns: list[str] = list(info.get("warnings", []))
    info = info.copy()
    n_in = int(pts.shape[0])
    if n_in == 0:
        raise InputError(
            f"{source}: no points in the file; give a file with at least {MIN_POINTS} points"
        )
    finite = np.isfinite(pts).all(axis=1)  # (N,)
    n_bad = int(n_in - np.count_nonzero(finite))
    if n_bad:
        pts = pts[finite]
        nrm = None if nrm is None else nrm[finite]
        add_warning(
            warns, f"{source}: dropped {n_bad} of {n_in} rows with NaN or infinite coordinates"
        )
    if pts.shape[0] < MIN_POINTS:
        raise InputError(
            f"{source}: only {pts.shape[0]} finite points"
            + (f" ({n_bad} NaN/inf rows dropped)" if n_bad else "")
            + f"; at least {MIN_POINTS} are needed: give a denser cloud or a mesh"
        )
    if nrm is not None:
        with np.errstate(over="ignore", invalid="ignore"):  # inf lengths are reported below
            length = np.linalg.norm(nrm, axis=1)  # (N,)
        if not (np.isfinite(length).all() and (length > GEOM_EPS).all()):
            add_warning(warns, f"{source}: some normals are zero or not finite; normals ignored")
            nrm = None
        else:
            nrm = nrm / length[:, None]
    s = 1.0 if scale is None else float(scale)
    if s != 1.0:
        with np.errstate(over="ignore"):  # an overflow is reported just below
            pts = pts * s
    largest = float(np.abs(pts).max())  # finite unless the scaling overflowed
    if not largest <= MAX_COORDINATE:
        raise InputError(
            f"{source}: coordinates reach {largest:.3g} m (after scale {s:g}), beyond "
            f"{MAX_COORDINATE:.0e} m; the file is not in metres or is corrupt: check it, or "
            "pass a scale"
        )
    pts, nrm = subsample(pts, nrm, n_points, seed, info)
    near = drop_strays(pts, source, warns)
    if near is not None:
        pts = pts[near]
        nrm = None if nrm is None else nrm[near]
        info["n_dropped_strays"] = int(len(near) - np.count_nonzero(near))
    check_geometry(pts, source, warns)
    info["n_dropped_nonfinite"] = n_bad
    info["scale"] = s
    info["warnings"] = warns
    info.setdefault("n_read", n_in)
    info.setdefault("seed", int(seed))
    return PointCloud(points=pts, normals=nrm, source=source, info=info)


def subsample(
    pts: np.ndarray, nrm: np.ndarray | None, n_points: int | None, seed: int, info: CloudInfo
) -> tuple[np.ndarray, np.ndarray | None]:
    """``pts`` (N, 3) and ``nrm`` cut to ``n_points`` points drawn without replacement (seeded,
    kept in their order), ``info["n_subsampled_from"]`` set; as they are when N <= n_points."""
    if n_points is None or pts.shape[0] <= n_points:
        return pts, nrm
    rng = np.random.default_rng(seed)
    keep = np.sort(rng.choice(pts.shape[0], size=int(n_points), replace=False))
    info["n_subsampled_from"] = int(pts.shape[0])
    return pts[keep], None if nrm is None else nrm[keep]


def drop_strays(pts: np.ndarray, source: str, warns: list[str]) -> np.ndarray | None:
    """(N,) bool, the points to keep, when a few points (at most :data:`STRAY_FRACTION` of them)
    lie far outside the rest, else None (keep all). "Far": beyond the box of the 1st to 99th
    percentiles per axis grown on every side by its own longest side (at least 1 mm) -- a
    scanner's stray return, a vertex left at 10^6 m in a mesh. Within that reach, or more of
    them, the points are kept: a second object, a table, a long part. A stray point left in
    would stretch the decomposition's root box and the collision grids over the whole distance
    (one point at 10^6 m asked the pool for 4.8 billion samples)."""
    lo, hi = np.percentile(pts, [1.0, 99.0], axis=0)  # (3,) each
    reach = max(float(np.max(hi - lo)), 1e-3)
    far = np.any((pts < lo - reach) | (pts > hi + reach), axis=1)  # (N,)
    n_far = int(np.count_nonzero(far))
    if n_far == 0 or n_far > STRAY_FRACTION * len(pts):
        return None
    worst = pts[far][int(np.argmax(np.abs(pts[far] - 0.5 * (lo + hi)).max(axis=1)))]
    add_warning(
        warns,
        f"{source}: dropped {n_far} stray point(s) of {len(pts)}, more than {reach:.3g} m "
        f"outside the box of the others (the farthest at ({worst[0]:.4g}, {worst[1]:.4g}, "
        f"{worst[2]:.4g})): a scanner's stray returns or a stray vertex",
    )
    return ~far


def check_geometry(pts: np.ndarray, source: str, warns: list[str]) -> None:
    """Identical/collinear -> DegenerateGeometryError; coplanar and huge extents -> warnings."""
    centered = pts - pts.mean(axis=0)
    cov = centered.T @ centered / pts.shape[0]  # (3, 3)
    _, vecs = np.linalg.eigh(cov)  # ascending eigenvalues; columns are principal axes
    spread = np.sort(np.ptp(centered @ vecs, axis=0))  # (3,) extents along principal axes
    if spread[2] < FLAT_EXTENT:
        raise DegenerateGeometryError(
            f"{source}: all {pts.shape[0]} points are identical (spread {spread[2]:.2e} m); "
            "a box needs points that span a volume or at least a plane"
        )
    if spread[1] < FLAT_EXTENT:
        raise DegenerateGeometryError(
            f"{source}: all points lie on one line (off-line spread {spread[1]:.2e} m); "
            "a box needs points that span a plane or a volume"
        )
    if spread[0] < FLAT_EXTENT:
        add_warning(
            warns,
            f"{source}: all points lie in one plane (thickness {spread[0]:.2e} m); the boxes "
            "will be flat, which is a valid answer for a flat object",
        )
    extent = float(np.ptp(pts, axis=0).max())
    if extent > MILLIMETRE_EXTENT:
        add_warning(
            warns,
            f"{source}: the cloud is {extent:.1f} m long, which looks like millimetres; "
            "pass scale=0.001 (--scale 0.001) if the file is in millimetres",
        )
