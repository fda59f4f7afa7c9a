"""The public loaders: a file or an upload's bytes -> :class:`PointCloud`. The extension picks
the reader from ``READERS``; size limits are checked before anything is parsed."""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InputError, PregraspError
from ..sensor import (
    CompletionParams,
    NoTableError,
    SegmentParams,
    SensorView,
    TableSegmentation,
    complete_view,
    detect_units,
    pcd_viewpoint_of,
    prepare_view,
    scene_obstacles,
)
from ..sensor.occluded import neighbour_shadows
from ..sensor.table import OBSTACLE_MARGIN, OBSTACLE_VOXEL
from ..sensor.veils import VeilParams
from .cloud import (
    DEFAULT_MAX_BYTES,
    DEFAULT_N_POINTS,
    MAX_POINTS,
    MIN_POINTS,
    SUPPORTED_EXTENSIONS,
    CloudInfo,
    FileData,
    PointCloud,
    RawCloud,
    add_warning,
    check_request,
    describe_error,
    finish_cloud,
    subsample,
)
from .depth_image import (
    DEPTH_IMAGE_EXTENSIONS,
    DepthScene,
    IntrinsicsArg,
    is_depth_input,
    read_depth_image,
)
from .gltf import read_glb, read_gltf
from .mesh import TriangleMesh, sample_mesh
from .numpy_format import read_npy, read_npz
from .obj import read_obj
from .off import read_off
from .pcd import read_pcd
from .ply import read_ply
from .stl import read_stl
from .text import read_text

logger = logging.getLogger(__name__)

Reader = Callable[[FileData], RawCloud | TriangleMesh]
"""A reader parses one file's bytes into raw points or triangles (validated afterwards)."""


READERS: dict[str, Reader] = {
    ".ply": read_ply,
    ".pcd": read_pcd,
    ".xyz": read_text,
    ".txt": read_text,
    ".csv": read_text,
    ".npy": read_npy,
    ".npz": read_npz,
    ".obj": read_obj,
    ".stl": read_stl,
    ".off": read_off,
    ".glb": read_glb,
    ".gltf": read_gltf,
}
"""Extension (lower case, with the dot) -> reader; one entry per ``SUPPORTED_EXTENSIONS``."""


def load_point_cloud(
    path: str | Path,
    n_points: int | None = DEFAULT_N_POINTS,
    seed: int = 0,
    scale: float | None = None,
    max_bytes: int = DEFAULT_MAX_BYTES,
    sensor: SensorOptions | None = None,
) -> PointCloud:
    """Read a point cloud, a mesh or a depth image into a :class:`PointCloud` (``docs/input.md``).

    path: the file; its extension picks the format. n_points: points sampled on a mesh, and the
    cap for a cloud (None: a cloud keeps all points, a mesh gets ``DEFAULT_N_POINTS``). seed:
    sampling seed. scale: multiplies the coordinates (0.001 for a file in millimetres); None:
    a cloud recognised as millimetres by :func:`~pregrasp_core.sensor.detect_units` is scaled
    by 0.001 with a warning. max_bytes: larger files are refused. sensor: intrinsics,
    viewpoint, scene and pick of depth-camera input (:class:`SensorOptions`).
    """
    p = Path(path)
    source = str(p)
    ext = extension(source)
    if not p.exists():
        raise InputError(f"{source}: file not found; check the path")
    if not p.is_file():
        raise InputError(f"{source}: not a regular file; give the path of a point-cloud or mesh")
    try:
        size = p.stat().st_size
    except OSError as exc:
        raise InputError(f"{source}: cannot read the file ({describe_error(exc)})") from exc
    check_size(size, max_bytes, source)
    try:
        data = p.read_bytes()
    except OSError as exc:
        raise InputError(f"{source}: cannot read the file ({describe_error(exc)})") from exc
    check_size(len(data), max_bytes, source)  # the file may have grown since stat
    file = FileData(data=data, source=source, path=p, max_bytes=max_bytes)
    return _load(file, ext, n_points, seed, scale, sensor)


def load_point_cloud_bytes(
    data: bytes,
    filename: str,
    n_points: int | None = DEFAULT_N_POINTS,
    seed: int = 0,
    scale: float | None = None,
    max_bytes: int = DEFAULT_MAX_BYTES,
    sensor: SensorOptions | None = None,
) -> PointCloud:
    """Like :func:`load_point_cloud` for the bytes of an uploaded file named ``filename``.

    The extension of ``filename`` picks the format; nothing outside ``data`` is read (a GLTF
    must embed its buffers; use GLB; a depth image needs ``sensor.intrinsics``).
    """
    source = str(filename)
    ext = extension(source)
    if not isinstance(data, bytes | bytearray | memoryview):
        raise ValueError(f"data must be bytes, got {type(data).__name__}")
    data = bytes(data)
    check_size(len(data), max_bytes, source)
    file = FileData(data=data, source=source, path=None, max_bytes=max_bytes)
    return _load(file, ext, n_points, seed, scale, sensor)


def extension(source: str) -> str:
    """The lower-case extension of ``source`` if supported, else :class:`InputError`."""
    name = Path(source).name.lower()
    ext = Path(name).suffix
    if ext not in SUPPORTED_EXTENSIONS + DEPTH_IMAGE_EXTENSIONS:
        shown = ext if ext else "(none)"
        raise InputError(
            f"{source}: unknown file extension {shown}; supported: "
            f"{', '.join(SUPPORTED_EXTENSIONS + DEPTH_IMAGE_EXTENSIONS)} (point clouds: PLY, "
            "PCD, XYZ/TXT/CSV, NPY, NPZ; meshes: OBJ, STL, OFF, GLB/GLTF, PLY with faces; depth "
            "images: 16-bit PNG, NPY with intrinsics)"
        )
    return ext


def check_size(size: int, max_bytes: int, source: str) -> None:
    """Refuse an empty input or one larger than ``max_bytes``."""
    if size == 0:
        raise InputError(f"{source}: the file is empty; give a file with points or a mesh")
    if size > max_bytes:
        raise InputError(
            f"{source}: the file is {size / 2**20:.1f} MiB, more than the limit of "
            f"{max_bytes / 2**20:.1f} MiB; downsample it or raise max_bytes"
        )


SCENE_OBSTACLES: tuple[str, ...] = ("all", "seen", "off")
"""The settings of :attr:`SensorOptions.obstacles`, the first the default."""


@dataclass(frozen=True)
class SensorOptions:
    """How depth-camera input is read (``docs/input.md``, "Depth-camera input")."""

    intrinsics: IntrinsicsArg = None
    """A depth image's intrinsics: four numbers ``fx fy cx cy`` or an ``Intrinsics`` (they
    replace the sidecar's fx, fy, cx, cy and keep its other fields), the path of a JSON camera
    file or a ``CameraFile`` (an upload's; either replaces the sidecar); None = the sidecar
    ``NAME.json`` beside the image (``pregrasp_core.io.depth_image``)."""
    viewpoint: tuple[float, float, float] | None = None
    """The camera position (metres, after scaling); None = the PCD header's ``VIEWPOINT``, the
    camera of a depth image, or none."""
    scene: bool | None = None
    """Segment the table and complete the view (:func:`~pregrasp_core.sensor.prepare_view`);
    None = for depth images and for PCD files with a ``VIEWPOINT``."""
    pick: tuple[float, float, float] | None = None
    """A point near the object to keep (metres, after scaling); None = the largest cluster."""
    flying_pixels: bool = False
    """Drop a scene's flying pixels before its table is searched
    (:func:`~pregrasp_core.sensor.veils.flying_points`, ``docs/input.md``); off by default: on
    views without them it drops the last pixel of outlines and faces seen within 10 degrees of
    grazing, which measured worse (``docs/benchmarks.md``)."""
    obstacles: str = "all"
    """What of a scene's rest the hand must clear (``docs/input.md``, "The rest of the scene as
    obstacles"): ``"all"``: the other objects, the background planes and, for a single view,
    the space hidden behind each other object; ``"seen"``: their seen points only; ``"off"``:
    nothing (the object alone, as before session 25)."""

    def __post_init__(self) -> None:
        if self.obstacles not in SCENE_OBSTACLES:
            raise ValueError(
                f"scene obstacles must be one of {', '.join(SCENE_OBSTACLES)}, got "
                f"{self.obstacles!r}"
            )
        for name in ("viewpoint", "pick"):
            v = getattr(self, name)
            if v is not None:
                a = np.asarray(v, dtype=np.float64)
                if a.shape != (3,) or not np.all(np.isfinite(a)):
                    raise ValueError(f"{name} must be 3 finite numbers, got {v!r}")
                object.__setattr__(self, name, tuple(float(x) for x in a))


def _read(file: FileData, ext: str) -> RawCloud | TriangleMesh:
    fmt = ext[1:]
    try:
        return READERS[ext](file)
    except PregraspError:
        raise
    except MemoryError:
        raise InputError(
            f"{file.source}: not enough memory to read the file; downsample it"
        ) from None
    except Exception as exc:  # noqa: BLE001 - a reader bug must still name the file
        logger.exception("unexpected reader failure on %s", file.source)
        raise InputError(
            f"{file.source}: cannot read it as {fmt.upper()} ({describe_error(exc)}); "
            "check that the file is valid"
        ) from exc


def _units(points: np.ndarray, scale: float | None, seed: int, warns: list[str]) -> float | None:
    """``scale``, or 0.001 with a warning when it is None and the points look like millimetres."""
    if scale is not None:
        return scale
    finite = points[np.all(np.isfinite(points), axis=1)]
    if len(finite) < MIN_POINTS:
        return None  # finish_cloud reports it
    guess = detect_units(finite, seed=seed)
    if guess.unit != "mm":
        return None
    add_warning(warns, guess.notice)
    return guess.scale


def _load(
    file: FileData,
    ext: str,
    n_points: int | None,
    seed: int,
    scale: float | None,
    sensor: SensorOptions | None = None,
) -> PointCloud:
    check_request(n_points, scale, file.source, seed)
    opts = SensorOptions() if sensor is None else sensor
    fmt = ext[1:]
    if is_depth_input(file, ext, opts.intrinsics):
        depth = read_depth_image(file, ext, opts.intrinsics)
        info = CloudInfo(format=fmt, kind="depth", n_read=depth.n_pixels, warnings=[])
        for note in () if depth.camera is None else depth.camera.notes:
            add_warning(info["warnings"], note)
        info["depth"] = {
            "intrinsics": depth.intrinsics.to_dict(),
            "intrinsics_from": depth.intrinsics_source,
            "camera_file": None if depth.camera is None else depth.camera.source,
            "camera_layout": None if depth.camera is None else depth.camera.layout,
            "depth_scale": depth.depth_scale,
            "pose": depth.camera is not None and depth.camera.pose is not None,
        }
        s = 1.0 if scale is None else float(scale)  # a depth image is in metres by its format
        vp = depth.viewpoint * s if opts.viewpoint is None else np.asarray(opts.viewpoint)
        scene = finish_cloud(
            depth.points, None, file.source, info, scale=scale, n_points=None, seed=seed
        )
        out = _scene_or_view(
            scene, vp, opts, n_points, seed, opts.scene is not False, opts.scene is None
        )
        _note_image_edge(out, depth, s)
        return out
    parsed = _read(file, ext)
    if isinstance(parsed, TriangleMesh):

        def units(pts: np.ndarray, notices: list[str]) -> float | None:
            return _units(pts, None, seed, notices)

        n_sample = n_points
        if opts.scene and opts.viewpoint is None and n_points is not None:
            n_sample = min(MAX_POINTS, SCENE_OVERSAMPLE * n_points)  # most of it is table
        cloud = sample_mesh(parsed, file.source, fmt, n_sample, seed, scale, units)
        return _scene_or_view(cloud, opts.viewpoint, opts, n_points, seed, bool(opts.scene))
    warns = list(parsed.warnings)
    # (from the bytes: an uploaded PCD's VIEWPOINT counts as a file's)
    T_pcd = pcd_viewpoint_of(file.data, file.source) if ext == ".pcd" else None
    eff_scale = _units(parsed.points, scale, seed, warns)
    info = CloudInfo(format=fmt, kind="cloud", n_read=parsed.n_read, warnings=warns)
    cam: np.ndarray | None = None
    if opts.viewpoint is not None:
        cam = np.asarray(opts.viewpoint, dtype=np.float64)
    elif T_pcd is not None:
        cam = T_pcd[:3, 3] * (1.0 if eff_scale is None else float(eff_scale))
    as_scene = opts.scene if opts.scene is not None else T_pcd is not None
    cloud = finish_cloud(
        parsed.points,
        parsed.normals,
        file.source,
        info,
        scale=eff_scale,
        n_points=None if as_scene else n_points,
        seed=seed,
    )
    return _scene_or_view(cloud, cam, opts, n_points, seed, as_scene, opts.scene is None)


def _scene_or_view(
    cloud: PointCloud,
    viewpoint: np.ndarray | tuple[float, float, float] | None,
    opts: SensorOptions,
    n_points: int | None,
    seed: int,
    as_scene: bool,
    inferred: bool = False,
) -> PointCloud:
    """``cloud`` with its viewpoint, or, for a scene, its object (table removed, completed).
    ``inferred``: the scene was not asked for (a PCD's ``VIEWPOINT``, a depth image): a view
    with no table in it (:class:`~pregrasp_core.sensor.NoTableError`, an object cut out of its
    scene) is then read as one object seen from its camera, cut to ``n_points``, with a
    warning, as ``--no-scene`` reads it; an asked-for scene without a table is an error."""
    if not as_scene:
        if opts.pick is not None:
            raise InputError(f"{cloud.source}: --pick needs a scene (--scene)")
        if viewpoint is None:
            return _with_table_hint(cloud)
        return dataclasses.replace(cloud, viewpoint=np.asarray(viewpoint, dtype=np.float64))
    if viewpoint is None:
        if opts.flying_pixels:
            raise InputError(
                f"{cloud.source}: flying pixels are a camera's: pass --viewpoint X Y Z (metres, "
                "the cloud's frame) with --flying-pixels"
            )
        return complete_scene_object(cloud, opts.pick, n_points, seed, opts.obstacles)
    try:
        view = scene_object(
            cloud,
            np.asarray(viewpoint, dtype=np.float64),
            opts.pick,
            n_points,
            seed,
            opts.flying_pixels,
        )
    except NoTableError as exc:
        if not inferred or opts.pick is not None:
            raise
        return _alone(cloud, np.asarray(viewpoint, dtype=np.float64), n_points, seed, exc)
    info = cloud.info.copy()
    info["scene"] = {
        "n_scene": cloud.n_points,
        "n_table": int(np.count_nonzero(view.segmentation.table_mask)),
        "n_visible": view.n_visible,
        "n_assumed": int(np.count_nonzero(view.assumed)),
        "viewpoint": [float(v) for v in view.viewpoint],
        "plane": view.plane.to_dict(),
        "completion": None if view.completion is None else view.completion.kind,
    }
    if view.completion is not None and view.completion.skirt.any():
        info["scene"]["n_skirt"] = int(np.count_nonzero(view.completion.skirt))
    if opts.flying_pixels:
        info["scene"]["n_flying"] = view.n_flying
    _note_background(info, view.segmentation, cloud.source)
    obstacles = _scene_obstacles(
        info, view.segmentation, view.points, opts.obstacles, view.viewpoint
    )
    if "n_subsampled_from" in info:
        del info["n_subsampled_from"]
    return PointCloud(
        points=view.points,
        normals=None,
        source=cloud.source,
        info=info,
        viewpoint=view.viewpoint,
        sensor=view,
        obstacles=obstacles,
    )


IMAGE_EDGE_PIXELS: float = 1.5
"""A depth image's object point this close to the image's edge (pixels from the outermost
pixel centres) is on the edge."""
IMAGE_EDGE_MIN_POINTS: int = 10
"""Seen object points on the image's edge from which the object runs off the image."""


def _note_image_edge(cloud: PointCloud, depth: DepthScene, scale: float) -> None:
    """Warn (and count in ``scene.n_image_edge``) when the seen points of a depth image's
    object reach the image's edge: the object runs off the image, the part beyond it is
    unseen, and the completion takes the cut for the object's end (grasps around it can
    reach into the real object: ``docs/limits.md``, "Cameras the generated views do not
    use")."""
    scene = cloud.info.get("scene")
    if scene is None or scene.get("complete") or depth.shape == (0, 0):
        return
    seen = cloud.points if cloud.assumed is None else cloud.points[~cloud.assumed]
    uv = depth.pixels(np.asarray(seen) / scale)
    h, w = depth.shape
    m = IMAGE_EDGE_PIXELS
    edge = np.zeros(len(uv), dtype=bool)
    sides = []
    for name, hit in (  # loop over the four sides
        ("left", uv[:, 0] <= m),
        ("right", uv[:, 0] >= w - 1 - m),
        ("top", uv[:, 1] <= m),
        ("bottom", uv[:, 1] >= h - 1 - m),
    ):
        if np.count_nonzero(hit) >= IMAGE_EDGE_MIN_POINTS:
            sides.append(name)
        edge |= hit
    if not sides:
        return
    scene["n_image_edge"] = int(np.count_nonzero(edge))
    _warn(
        cloud.info,
        f"{cloud.source}: the object runs off the image ({' and '.join(sides)} edge: "
        f"{scene['n_image_edge']} of its {len(seen)} seen points on it): what lies beyond is "
        "unseen and the completion takes the cut for the object's end, so grasps there may "
        "reach into the real object; frame the whole object (--pick another one, or move the "
        "camera)",
    )


def _alone(
    cloud: PointCloud, viewpoint: np.ndarray, n_points: int | None, seed: int, why: NoTableError
) -> PointCloud:
    """The view ``cloud`` (every point read, no table in it) as one object seen from
    ``viewpoint``: cut to ``n_points`` by :func:`~.cloud.subsample`, as a cloud is (the same
    points as ``--no-scene``), with the warning that says so."""
    info = cloud.info.copy()
    cam = ", ".join(f"{v:.4g}" for v in viewpoint)
    _warn(
        info,
        f"{cloud.source}: no table in the view (nothing stands above the plane the table search "
        f"found, {why.behind} points lie behind it): read as one object seen from the camera at "
        f"({cam}), its normals facing the camera; its unseen back is not completed (keep the "
        "table in the view for that)",
    )
    pts, nrm = subsample(cloud.points, cloud.normals, n_points, seed, info)
    return PointCloud(points=pts, normals=nrm, source=cloud.source, info=info, viewpoint=viewpoint)


def complete_scene_object(
    scene: PointCloud,
    pick: tuple[float, float, float] | None,
    n_points: int | None,
    seed: int,
    which_obstacles: str = "all",
) -> PointCloud:
    """The object of a complete scene (a mesh or a fused scan with its table, read with
    ``--scene`` and no viewpoint): the table found by RANSAC and removed, the largest cluster
    above it kept (or the one nearest ``pick``) with its normals, cut to ``n_points``; nothing
    is completed (every side was scanned) and the table becomes the cloud's ``support``; the
    scene's rest near the object becomes its ``obstacles`` unless ``which_obstacles`` is ``"off"``
    (:attr:`SensorOptions.obstacles`; a complete scene hides nothing). Up is
    the side along +z unless the table is within 60 degrees of vertical (then the side with
    more points); a table with a bottom (a box in a scene mesh) is its top: a plane parallel to
    the one found, above it, holding at least half as many points, replaces it (twice at
    most). A scene upside down along z (nothing above the table along +z, the objects under
    it: a z-down export) is read with up -z, with a warning."""
    from ..sensor import segment_table

    pts = np.asarray(scene.points)
    idx = np.arange(len(pts))  # the points ``seg`` was found on
    down = False
    try:
        try:
            seg = segment_table(pts, pick=pick, side=(0.0, 0.0, 1.0))
        except NoTableError:
            seg = segment_table(pts, pick=pick, side=(0.0, 0.0, -1.0))
            down = True
        for _ in range(2):  # a table with a bottom: its top is the parallel plane above it
            above = idx[pts[idx] @ seg.plane.normal - seg.plane.height > seg.band]
            try:
                top = segment_table(pts[above], pick=pick, side=seg.plane.normal)
            except PregraspError:
                break
            parallel = float(top.plane.normal @ seg.plane.normal) > np.cos(np.radians(5.0))
            if not (parallel and top.table_mask.sum() >= 0.5 * seg.table_mask.sum()):
                break
            seg, idx = top, above
    except PregraspError as exc:
        raise _scene_failure(
            scene.source, exc, "without --scene the points are read as one object"
        ) from None
    mask = np.zeros(len(pts), dtype=bool)
    mask[idx[seg.object_mask]] = True
    if int(mask.sum()) < MIN_POINTS:
        raise InputError(
            f"{scene.source}: the object above the table has only {int(mask.sum())} points; at "
            f"least {MIN_POINTS} are needed (--pick X Y Z chooses another object)"
        )
    info = scene.info.copy()
    _warn(
        info,
        f"{scene.source}: read as a complete scene (no viewpoint): the table removed "
        f"({len(pts) - int(mask.sum())} points with what lies under it), the object kept whole, "
        "nothing completed; for a single view give the camera with --viewpoint X Y Z",
    )
    if down:
        _warn(
            info,
            f"{scene.source}: the objects lie under the table along +z: the scene is read "
            "upside down (up -z)",
        )
    info["scene"] = {
        "n_scene": scene.n_points,
        "n_table": int(np.count_nonzero(seg.table_mask)),
        "n_object": int(np.count_nonzero(mask)),
        "n_clusters": int(seg.n_clusters),
        "plane": seg.plane.to_dict(),
        "complete": True,
    }
    _note_background(info, seg, scene.source)
    obstacles = _scene_obstacles(info, seg, pts[mask], which_obstacles)
    nrm = None if scene.normals is None else np.asarray(scene.normals)[mask]
    obj, nrm = subsample(pts[mask], nrm, n_points, seed, info)
    return PointCloud(obj, nrm, scene.source, info, support=seg.plane, obstacles=obstacles)


def _warn(info: CloudInfo, text: str) -> None:
    """``info`` with the warning ``text`` added (``add_warning``: each warning once)."""
    warns = list(info.get("warnings", []))
    add_warning(warns, text)
    info["warnings"] = warns


def _scene_failure(source: str, exc: PregraspError, hint: str) -> PregraspError:
    """``exc`` of a scene's segmentation as the loader reports it: the file named, ``hint`` in
    brackets, its type kept (a :class:`NoTableError` with its points behind the plane)."""
    msg = f"{source}: the scene's table and object: {exc} ({hint})"
    if isinstance(exc, NoTableError):
        return NoTableError(msg, exc.behind)
    return type(exc)(msg)


def _scene_obstacles(
    info: CloudInfo,
    seg: TableSegmentation,
    near: np.ndarray,
    which: str,
    viewpoint: np.ndarray | None = None,
) -> np.ndarray | None:
    """The scene's obstacles near the object ``near`` (``sensor.table.scene_obstacles``: its
    other objects and background planes within reach, thinned), and with a ``viewpoint`` and
    ``which`` ``"all"`` the hidden space behind each other object within reach
    (``sensor.occluded.neighbour_shadows``, last, counted in ``scene.n_obstacles_hidden``),
    counted in ``scene.n_obstacles``; None when there are none or ``which`` is ``"off"``
    (:attr:`SensorOptions.obstacles`, kept as ``scene.obstacles``)."""
    info["scene"]["obstacles"] = which
    if which == "off":
        return None
    obstacles = scene_obstacles(seg, near)
    if which == "all" and viewpoint is not None and seg.obstacle_mask is not None and len(near):
        lab = seg.cluster_labels
        objects = seg.obstacle_mask & (lab >= 0)  # not the background planes (label -1)
        if seg.background_mask is not None:
            objects &= ~seg.background_mask
        lo, hi = near.min(axis=0) - OBSTACLE_MARGIN, near.max(axis=0) + OBSTACLE_MARGIN
        objects &= np.all((seg.points >= lo) & (seg.points <= hi), axis=1)
        shadows = neighbour_shadows(
            seg.points, lab, np.unique(lab[objects]), viewpoint, seg.plane, OBSTACLE_VOXEL
        )
        obstacles = np.concatenate([obstacles, shadows])
        if len(shadows):
            info["scene"]["n_obstacles_hidden"] = len(shadows)  # the last ones
    if len(obstacles) == 0:
        return None
    info["scene"]["n_obstacles"] = len(obstacles)
    return obstacles


def _note_background(info: CloudInfo, seg: TableSegmentation, source: str) -> None:
    """``info`` with the scene's background planes (``SegmentParams.background_span``, a wall
    behind the table): ``scene.n_background`` and a warning naming each, when there are any."""
    planes = seg.background
    if not planes:
        return
    info["scene"]["n_background"] = int(sum(b.n_points for b in planes))
    _warn(
        info,
        f"{source}: set aside as background, not an object (a wall, a board: flat and at least "
        f"{SegmentParams().background_span:g} m long): "
        f"{'; '.join(b.describe() for b in planes)}; --pick X Y Z on one keeps it",
    )


SCENE_OVERSAMPLE: int = 8
"""A mesh read as a complete scene is sampled to this many times ``n_points`` (the table takes
most of them), then its object cut to ``n_points``."""

TABLE_HINT_BAND: float = 0.003
"""Half-width (metres) of the lowest layer along +z that :func:`_with_table_hint` looks at."""


def _with_table_hint(cloud: PointCloud) -> PointCloud:
    """``cloud`` with a warning when it looks like an object on a patch of its table (a scan):
    at least a quarter of its points in the lowest 3 mm along +z, that layer at least 25 cm
    across, and what stands above it at most 60 % as wide along x and y (a box lying on its
    side has its bottom face as wide as itself)."""
    pts = np.asarray(cloud.points)
    z = pts[:, 2]
    low = z <= float(z.min()) + 2.0 * TABLE_HINT_BAND
    if low.mean() < 0.25 or low.all():
        return cloud
    span_low = np.ptp(pts[low, :2], axis=0)
    span_up = np.ptp(pts[~low, :2], axis=0)
    if span_low.max() < 0.25 or np.any(span_up > 0.6 * span_low):
        return cloud
    info = cloud.info.copy()
    _warn(
        info,
        f"{cloud.source}: {100.0 * low.mean():.0f} % of the points lie in one plane at its "
        f"lowest z, {span_low[0]:.2f} x {span_low[1]:.2f} m, wider than what stands on it: if "
        "that is a table, read the file with --scene (the table found and removed)",
    )
    return dataclasses.replace(cloud, info=info)


def scene_object(
    scene: PointCloud,
    viewpoint: np.ndarray,
    pick: tuple[float, float, float] | None,
    n_points: int | None,
    seed: int,
    flying_pixels: bool = False,
) -> SensorView:
    """The object of ``scene`` seen from ``viewpoint``: :func:`~pregrasp_core.sensor.prepare_view`
    without completion (``flying_pixels``: its flying-pixel test on), the visible object cut to
    ``n_points // 2`` (seeded), then completed (at most doubles it), so the cloud handed on
    holds at most ``n_points`` points."""
    try:
        veils = VeilParams() if flying_pixels else None
        view = prepare_view(scene.points, viewpoint, pick=pick, complete=False, veils=veils)
        obj = view.points
        if n_points is not None and len(obj) > n_points // 2:
            rng = np.random.default_rng(seed)
            obj = obj[np.sort(rng.choice(len(obj), size=n_points // 2, replace=False))]
        tol = max(0.003, 3.0 * view.segmentation.sigma)
        done = complete_view(obj, viewpoint, view.plane, CompletionParams(tolerance=tol))
    except PregraspError as exc:
        raise _scene_failure(
            scene.source,
            exc,
            "--no-scene reads the points as one object, its normals facing the camera",
        ) from None
    if len(done.points) < MIN_POINTS:
        raise InputError(
            f"{scene.source}: the object above the table has only {len(done.points)} points; "
            f"at least {MIN_POINTS} are needed (--pick X Y Z chooses another object)"
        )
    return dataclasses.replace(view, points=done.points, assumed=done.assumed, completion=done)
