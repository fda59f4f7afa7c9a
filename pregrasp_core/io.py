"""Point-cloud input: read clouds and meshes from files or uploaded bytes into a PointCloud.

Formats (the file name's extension picks the parser, case-insensitive):

- point clouds: PLY without faces (ascii, binary little/big endian), PCD (PCL's format; ascii and
  binary, ``binary_compressed`` is refused with a message), XYZ/TXT/CSV (3 columns, or 6 with
  normals; whitespace or comma separated; ``#`` comments; a column-name first line is skipped),
  NPY (``allow_pickle=False``) and NPZ (key ``points`` or a single array; optional ``normals``);
- meshes: OBJ, STL, OFF, GLB/GLTF and PLY with faces, sampled uniformly on the surface to
  ``n_points`` points with ``seed`` (area-weighted, the face normal of each sample kept as its
  normal). Same bytes + same ``n_points`` + same ``seed`` = same cloud.

A point cloud larger than ``n_points`` is subsampled to ``n_points`` points (seeded, without
replacement, in file order); ``n_points=None`` keeps every point of a cloud.

Every problem with the input raises :class:`~pregrasp_core.errors.InputError` (or
:class:`~pregrasp_core.errors.DegenerateGeometryError` for identical/collinear points) whose
message names the file, the problem and what to do; nothing is ever unpickled or executed.
Recoverable oddities (non-finite rows dropped, coplanar points, millimetre-looking extents,
ignored columns) are logged with ``logging`` and listed in ``PointCloud.info["warnings"]``.
"""

from __future__ import annotations

import io as _io
import logging
import math
import warnings
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .errors import DegenerateGeometryError, InputError
from .tolerances import FLAT_EXTENT, GEOM_EPS, UNIT_NORMAL_TOL

logger = logging.getLogger(__name__)

DEFAULT_N_POINTS: int = 20000
"""Points sampled on a mesh (and the cap for a cloud) unless told otherwise."""

DEFAULT_MAX_BYTES: int = 200 * 1024 * 1024
"""Largest input accepted (bytes): files, uploads and the decompressed arrays of an NPZ."""

MIN_POINTS: int = 10
"""Fewest finite points a usable cloud has (a box needs a handful; fewer is surely a mistake)."""

MAX_POINTS: int = 10_000_000
"""Most points ``n_points`` may ask for (memory guard)."""

MAX_COORDINATE: float = 1e9
"""Largest coordinate magnitude accepted (metres, after scaling): beyond it the file is surely
not in metres (and squares of the coordinates could overflow)."""

MILLIMETRE_EXTENT: float = 5.0
"""A cloud whose bounding box is longer than this (metres) probably is in millimetres: warn."""

CLOUD_EXTENSIONS: tuple[str, ...] = (".ply", ".pcd", ".xyz", ".txt", ".csv", ".npy", ".npz")
"""Point-cloud formats (a ``.ply`` with faces is read as a mesh)."""

MESH_EXTENSIONS: tuple[str, ...] = (".obj", ".stl", ".off", ".glb", ".gltf", ".ply")
"""Mesh formats, sampled on their surface."""

SUPPORTED_EXTENSIONS: tuple[str, ...] = tuple(dict.fromkeys(CLOUD_EXTENSIONS + MESH_EXTENSIONS))
"""Every extension :func:`load_point_cloud` accepts."""


@dataclass(frozen=True, eq=False)
class PointCloud:
    """An object's points in metres, in the file's frame (called world), with optional normals.

    The arrays are read-only. Build one with :meth:`from_array` or :func:`load_point_cloud`,
    which validate; the plain constructor only coerces and checks shapes.
    """

    points: np.ndarray
    """(N, 3) float64, metres, world frame. Finite, N >= ``MIN_POINTS``."""
    normals: np.ndarray | None = None
    """(N, 3) float64 unit vectors (outward for a mesh), or None when the input had none."""
    source: str = "array"
    """Where the points came from: the file path, the uploaded file's name, or ``"array"``."""
    info: dict[str, Any] = field(default_factory=dict)
    """How it was read: ``format`` (e.g. ``"ply"``), ``kind`` (``"cloud"`` or ``"mesh"``),
    ``n_read`` (rows read, or mesh vertices), ``n_dropped_nonfinite``, ``scale``, ``seed`` (of
    the sampling/subsampling; None for an array), ``warnings`` (list of str); meshes add
    ``n_faces``, ``area`` (m^2, after scaling) and ``watertight``; clouds cut to ``n_points`` add
    ``n_subsampled_from``."""

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
        info = {"format": "array", "kind": "cloud", "n_read": int(pts.shape[0]), "seed": None}
        return _finish(pts, nrm, source, info, scale=scale, n_points=None, seed=0)


# ----------------------------------------------------------------------------------------------
# Public loaders


def load_point_cloud(
    path: str | Path,
    n_points: int | None = DEFAULT_N_POINTS,
    seed: int = 0,
    scale: float | None = None,
    max_bytes: int = DEFAULT_MAX_BYTES,
) -> PointCloud:
    """Read a point cloud or a mesh file into a :class:`PointCloud` (see the module docstring).

    path: the file; its extension picks the format. n_points: points sampled on a mesh, and the
    cap for a cloud (None: a cloud keeps all points, a mesh gets ``DEFAULT_N_POINTS``). seed:
    sampling seed. scale: multiplies the coordinates (0.001 for a file in millimetres).
    max_bytes: larger files are refused.
    """
    p = Path(path)
    source = str(p)
    ext = _extension(source)
    if not p.exists():
        raise InputError(f"{source}: file not found; check the path")
    if not p.is_file():
        raise InputError(f"{source}: not a regular file; give the path of a point-cloud or mesh")
    try:
        size = p.stat().st_size
    except OSError as exc:
        raise InputError(f"{source}: cannot read the file ({exc})") from exc
    _check_size(size, max_bytes, source)
    try:
        data = p.read_bytes()
    except OSError as exc:
        raise InputError(f"{source}: cannot read the file ({exc})") from exc
    return _load(data, ext, source, n_points, seed, scale, max_bytes, path=p)


def load_point_cloud_bytes(
    data: bytes,
    filename: str,
    n_points: int | None = DEFAULT_N_POINTS,
    seed: int = 0,
    scale: float | None = None,
    max_bytes: int = DEFAULT_MAX_BYTES,
) -> PointCloud:
    """Like :func:`load_point_cloud` for the bytes of an uploaded file named ``filename``.

    The extension of ``filename`` picks the format; nothing outside ``data`` is read (a GLTF
    must embed its buffers; use GLB).
    """
    source = str(filename)
    ext = _extension(source)
    if not isinstance(data, bytes | bytearray | memoryview):
        raise ValueError(f"data must be bytes, got {type(data).__name__}")
    data = bytes(data)
    _check_size(len(data), max_bytes, source)
    return _load(data, ext, source, n_points, seed, scale, max_bytes, path=None)


# ----------------------------------------------------------------------------------------------
# Dispatch and validation


def _extension(source: str) -> str:
    name = Path(source).name.lower()
    ext = Path(name).suffix
    if ext not in SUPPORTED_EXTENSIONS:
        shown = ext if ext else "(none)"
        raise InputError(
            f"{source}: unknown file extension {shown}; supported: "
            f"{', '.join(SUPPORTED_EXTENSIONS)} (point clouds: PLY, PCD, XYZ/TXT/CSV, NPY, NPZ; "
            "meshes: OBJ, STL, OFF, GLB/GLTF, PLY with faces)"
        )
    return ext


def _check_size(size: int, max_bytes: int, source: str) -> None:
    if size == 0:
        raise InputError(f"{source}: the file is empty; give a file with points or a mesh")
    if size > max_bytes:
        raise InputError(
            f"{source}: the file is {size / 2**20:.1f} MiB, more than the limit of "
            f"{max_bytes / 2**20:.1f} MiB; downsample it or raise max_bytes"
        )


def _check_request(n_points: int | None, scale: float | None, source: str, seed: int = 0) -> None:
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


def _load(
    data: bytes,
    ext: str,
    source: str,
    n_points: int | None,
    seed: int,
    scale: float | None,
    max_bytes: int,
    path: Path | None,
) -> PointCloud:
    _check_request(n_points, scale, source, seed)
    if ext == ".ply":
        header = _parse_ply_header(data, source)
        if header.n_faces > 0:
            mesh = _load_mesh(data, "ply", source, path)
            return _sample_mesh(mesh, source, "ply", n_points, seed, scale)
        pts, nrm, n_read, warns = _read_ply_cloud(data, header, source)
        fmt = "ply"
    elif ext == ".pcd":
        pts, nrm, n_read, warns = _read_pcd(data, source)
        fmt = "pcd"
    elif ext in (".xyz", ".txt", ".csv"):
        pts, nrm, n_read, warns = _read_text(data, source)
        fmt = ext[1:]
    elif ext == ".npy":
        pts, nrm, n_read, warns = _read_npy(data, source)
        fmt = "npy"
    elif ext == ".npz":
        pts, nrm, n_read, warns = _read_npz(data, source, max_bytes)
        fmt = "npz"
    else:  # a mesh format
        mesh = _load_mesh(data, ext[1:], source, path)
        return _sample_mesh(mesh, source, ext[1:], n_points, seed, scale)
    info = {"format": fmt, "kind": "cloud", "n_read": n_read, "warnings": warns}
    return _finish(pts, nrm, source, info, scale=scale, n_points=n_points, seed=seed)


def _warn(warnings: list[str], message: str) -> None:
    logger.warning(message)
    warnings.append(message)


def _finish(
    pts: np.ndarray,
    nrm: np.ndarray | None,
    source: str,
    info: dict[str, Any],
    scale: float | None,
    n_points: int | None,
    seed: int,
) -> PointCloud:
    """Drop non-finite rows, scale, subsample, check count and degeneracy, build the cloud."""
    _check_request(n_points, scale, source, seed)
    warns: list[str] = list(info.get("warnings", []))
    info = dict(info)
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
        _warn(warns, f"{source}: dropped {n_bad} of {n_in} rows with NaN or infinite coordinates")
    if pts.shape[0] < MIN_POINTS:
        raise InputError(
            f"{source}: only {pts.shape[0]} finite points"
            + (f" ({n_bad} NaN/inf rows dropped)" if n_bad else "")
            + f"; at least {MIN_POINTS} are needed: give a denser cloud or a mesh"
        )
    if nrm is not None:
        length = np.linalg.norm(nrm, axis=1)  # (N,)
        if not (np.isfinite(length).all() and (length > GEOM_EPS).all()):
            _warn(warns, f"{source}: some normals are zero or not finite; normals ignored")
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
    if n_points is not None and pts.shape[0] > n_points:
        rng = np.random.default_rng(seed)
        keep = np.sort(rng.choice(pts.shape[0], size=int(n_points), replace=False))
        info["n_subsampled_from"] = int(pts.shape[0])
        pts = pts[keep]
        nrm = None if nrm is None else nrm[keep]
    _check_geometry(pts, source, warns)
    info.update(n_dropped_nonfinite=n_bad, scale=s, warnings=warns)
    info.setdefault("n_read", n_in)
    info.setdefault("seed", int(seed))
    return PointCloud(points=pts, normals=nrm, source=source, info=info)


def _check_geometry(pts: np.ndarray, source: str, warns: list[str]) -> None:
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
        _warn(
            warns,
            f"{source}: all points lie in one plane (thickness {spread[0]:.2e} m); the boxes "
            "will be flat, which is a valid answer for a flat object",
        )
    extent = float(np.ptp(pts, axis=0).max())
    if extent > MILLIMETRE_EXTENT:
        _warn(
            warns,
            f"{source}: the cloud is {extent:.1f} m long, which looks like millimetres; "
            "pass scale=0.001 (--scale 0.001) if the file is in millimetres",
        )


# ----------------------------------------------------------------------------------------------
# Meshes


def _load_mesh(data: bytes, fmt: str, source: str, path: Path | None) -> Any:
    """trimesh.Trimesh of every triangle in the file (scene transforms applied)."""
    import trimesh

    try:
        # Numeric warnings from trimesh on absurd values: the checks after loading report them.
        with warnings.catch_warnings(), np.errstate(all="ignore"):
            warnings.simplefilter("ignore", RuntimeWarning)
            if fmt == "gltf" and path is not None:
                # A .gltf on disk may reference .bin/.png files beside it: let trimesh find them.
                scene = trimesh.load_scene(str(path), file_type="gltf")
            else:
                scene = trimesh.load_scene(_io.BytesIO(data), file_type=fmt)
            mesh = scene.to_mesh()
    except Exception as exc:  # noqa: BLE001 - any parser failure is the input's fault
        hint = (
            "; a GLTF uploaded alone must embed its buffers, export it as .glb"
            if fmt == "gltf"
            else ""
        )
        raise InputError(
            f"{source}: cannot read it as a {fmt.upper()} mesh ({type(exc).__name__}: {exc})"
            f"{hint}; check that the file is a valid {fmt.upper()} file"
        ) from exc
    if mesh is None or len(getattr(mesh, "faces", ())) == 0:
        raise InputError(
            f"{source}: no triangles could be read from the {fmt.upper()} file; check that it is "
            "a valid mesh with faces, or give a point-cloud format (PLY, PCD, XYZ, NPY)"
        )
    return mesh


def _sample_mesh(
    mesh: Any, source: str, fmt: str, n_points: int | None, seed: int, scale: float | None
) -> PointCloud:
    """Area-weighted uniform samples on the triangles, face normals as normals."""
    import trimesh

    warns: list[str] = []
    verts = np.asarray(mesh.vertices, dtype=np.float64)  # (V, 3)
    faces = np.asarray(mesh.faces, dtype=np.int64)  # (F, 3)
    bad_vert = ~np.isfinite(verts).all(axis=1)
    if bad_vert.any():
        keep = ~bad_vert[faces].any(axis=1)
        _warn(
            warns,
            f"{source}: {int(bad_vert.sum())} vertices are NaN/inf; dropped the "
            f"{int((~keep).sum())} faces using them",
        )
        faces = faces[keep]
        verts = np.where(bad_vert[:, None], 0.0, verts)
    s = 1.0 if scale is None else float(scale)
    largest = float(np.abs(verts).max()) * s if len(verts) else 0.0
    if not largest <= MAX_COORDINATE:
        raise InputError(
            f"{source}: vertex coordinates reach {largest:.3g} m (after scale {s:g}), beyond "
            f"{MAX_COORDINATE:.0e} m; the file is not in metres or is corrupt: check it, or "
            "pass a scale"
        )
    tri = verts[faces]  # (F, 3, 3)
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])  # (F, 3)
    area2 = np.linalg.norm(cross, axis=1)  # (F,) twice the areas
    total = 0.5 * float(area2.sum()) if len(faces) else 0.0
    if not total > GEOM_EPS**2:
        raise InputError(
            f"{source}: the mesh has zero surface area ({len(faces)} usable faces); "
            "give a mesh with non-degenerate triangles"
        )
    n = DEFAULT_N_POINTS if n_points is None else int(n_points)
    clean = trimesh.Trimesh(vertices=verts, faces=faces, process=False, validate=False)
    pts, face_idx = trimesh.sample.sample_surface(clean, n, face_weight=area2, seed=seed)
    pts = np.asarray(pts, dtype=np.float64)
    # Unit face normals from the winding (zero-area faces are never sampled).
    normals = cross[face_idx] / area2[face_idx, None]  # (n, 3)
    watertight = bool(getattr(mesh, "is_watertight", False)) and not bad_vert.any()
    flip, n_flipped = _inside_out_faces(faces, tri[:, 0], cross)
    if n_flipped:
        normals = np.where(flip[face_idx, None], -normals, normals)
        _warn(
            warns,
            f"{source}: {n_flipped} closed part(s) of the mesh are wound inside-out; "
            "their normals were flipped outwards",
        )
    info = {
        "format": fmt,
        "kind": "mesh",
        "n_read": int(len(verts)),
        "n_faces": int(len(faces)),
        "area": total * s * s,
        "watertight": watertight,
        "warnings": warns,
    }
    return _finish(pts, normals, source, info, scale=scale, n_points=None, seed=seed)


def _inside_out_faces(
    faces: np.ndarray, v0: np.ndarray, cross: np.ndarray
) -> tuple[np.ndarray, int]:
    """Faces of closed, consistently wound parts with negative signed volume (inside-out).

    faces: (F, 3) vertex indices; v0: (F, 3) first vertex of each face; cross: (F, 3) the
    (unnormalised) face normals. Parts are edge-connected components; a part is closed when each
    of its edges has exactly two faces, and consistently wound when each edge is used once in
    each direction. Returns ((F,) bool: flip this face's normal, number of parts flipped).
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    n_f = len(faces)
    n_v = int(faces.max()) + 1
    directed = faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)  # (3F, 2) edges as wound
    undirected = np.sort(directed, axis=1)
    # Edges as int64 keys (a * n_v + b): 1-D unique is much faster than unique rows.
    _, edge_id, edge_count = np.unique(
        undirected[:, 0] * n_v + undirected[:, 1], return_inverse=True, return_counts=True
    )  # edge_id: (3F,) index of each face edge among the unique edges
    # Faces and edges as one bipartite graph: its components are the edge-connected parts.
    n_e = len(edge_count)
    face_of_edge = np.repeat(np.arange(n_f), 3)  # (3F,)
    graph = coo_matrix(
        (np.ones(3 * n_f), (face_of_edge, n_f + edge_id)), shape=(n_f + n_e, n_f + n_e)
    )
    _, labels = connected_components(graph, directed=False)
    _, part = np.unique(labels[:n_f], return_inverse=True)  # (F,) part of each face
    n_parts = int(part.max()) + 1
    _, dir_id, dir_count = np.unique(
        directed[:, 0] * n_v + directed[:, 1], return_inverse=True, return_counts=True
    )
    # (3F,) edge is open or non-manifold, or two faces wind it the same way
    bad_edge = (edge_count[edge_id] != 2) | (dir_count[dir_id] != 1)
    bad_face = bad_edge.reshape(n_f, 3).any(axis=1)
    bad_part = np.bincount(part, weights=bad_face, minlength=n_parts) > 0
    volume6 = np.bincount(part, weights=np.einsum("ij,ij->i", v0, cross), minlength=n_parts)
    flip_part = ~bad_part & (volume6 < 0.0)
    return flip_part[part], int(flip_part.sum())


# ----------------------------------------------------------------------------------------------
# Text formats: XYZ / TXT / CSV


def _decode(data: bytes, source: str, what: str) -> str:
    if b"\x00" in data:
        raise InputError(f"{source}: contains binary data, not {what} text; check the format")
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise InputError(
            f"{source}: is not UTF-8/ASCII text ({exc.reason} at byte {exc.start}); "
            f"{what} files are text, check the format"
        ) from exc


def _loadtxt(lines: list[str] | str, source: str, what: str) -> np.ndarray:
    """Numbers of whitespace/comma-separated text rows as an (R, C) float64 array."""
    text = lines if isinstance(lines, str) else "\n".join(lines)
    text = text.replace(",", " ")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # "input contained no data" -> handled below
            arr = np.loadtxt(_io.StringIO(text), dtype=np.float64, comments="#", ndmin=2)
    except ValueError as exc:
        msg = str(exc)
        if "number of columns" in msg:
            problem = f"rows have different numbers of columns ({msg.split(';')[0]})"
        else:
            problem = f"non-numeric data ({msg})"
        raise InputError(
            f"{source}: {what}: {problem}; every row must hold the same count of numbers"
        ) from None
    return arr


def _is_numeric_row(line: str) -> bool:
    try:
        [float(t) for t in line.split("#", 1)[0].replace(",", " ").split()]
    except ValueError:
        return False
    return True


def _read_text(data: bytes, source: str) -> tuple[np.ndarray, np.ndarray | None, int, list[str]]:
    warns: list[str] = []
    text = _decode(data, source, "XYZ")
    lines = text.splitlines()
    # A column-name line such as "x,y,z" before the data (common in CSV) is skipped.
    first = next((i for i, ln in enumerate(lines) if ln.strip() and ln.lstrip()[0] != "#"), None)
    if first is not None and not _is_numeric_row(lines[first]):
        if any(c.isalpha() for c in lines[first]) and first + 1 < len(lines):
            _warn(warns, f"{source}: skipped the header line {lines[first].strip()[:60]!r}")
            del lines[first]
    arr = _loadtxt(lines, source, "XYZ/TXT data")
    if arr.size == 0:
        raise InputError(f"{source}: no data rows (only comments or blank lines)")
    return _split_columns(arr, source, warns, "column")


def _split_columns(
    arr: np.ndarray, source: str, warns: list[str], what: str
) -> tuple[np.ndarray, np.ndarray | None, int, list[str]]:
    """(N, 3) -> points; (N, 6) -> points + normals when columns 4-6 are unit vectors."""
    n_cols = arr.shape[1]
    if n_cols not in (3, 6):
        raise InputError(
            f"{source}: wrong {what} count {n_cols}; expected 3 (x y z) or 6 (x y z nx ny nz)"
        )
    pts = arr[:, :3]
    nrm = None
    if n_cols == 6:
        extra = arr[:, 3:]
        length = np.linalg.norm(extra, axis=1)
        ok = np.isfinite(length) & np.isfinite(pts).all(axis=1)
        if ok.any() and np.all(np.abs(length[ok] - 1.0) < UNIT_NORMAL_TOL):
            nrm = extra
        else:
            _warn(
                warns,
                f"{source}: columns 4-6 are not unit vectors (colours?); read columns 1-3 as "
                "x y z and ignored the rest",
            )
    return pts, nrm, int(arr.shape[0]), warns


# ----------------------------------------------------------------------------------------------
# NPY / NPZ


def _numeric_array(arr: Any, source: str, what: str) -> np.ndarray:
    arr = np.asarray(arr)
    if arr.dtype.kind not in "fiu":
        raise InputError(
            f"{source}: {what} has dtype {arr.dtype}, expected a float or integer array of "
            "shape (N, 3) or (N, 6)"
        )
    if arr.ndim != 2:
        raise InputError(f"{source}: {what} has shape {arr.shape}, expected (N, 3) or (N, 6)")
    return arr.astype(np.float64)


def _read_npy(data: bytes, source: str) -> tuple[np.ndarray, np.ndarray | None, int, list[str]]:
    try:
        arr = np.load(_io.BytesIO(data), allow_pickle=False)
    except Exception as exc:  # noqa: BLE001 - numpy raises ValueError/OSError/EOFError/...
        raise InputError(
            f"{source}: not a readable NPY file ({type(exc).__name__}: {exc}); save it with "
            "numpy.save of a float array (object arrays are refused)"
        ) from exc
    if not isinstance(arr, np.ndarray):
        raise InputError(f"{source}: not an NPY array (an NPZ archive? rename it .npz)")
    return _split_columns(_numeric_array(arr, source, "the array"), source, [], "column")


def _read_npz(
    data: bytes, source: str, max_bytes: int
) -> tuple[np.ndarray, np.ndarray | None, int, list[str]]:
    try:
        with zipfile.ZipFile(_io.BytesIO(data)) as zf:
            unpacked = sum(i.file_size for i in zf.infolist())
    except Exception as exc:  # noqa: BLE001 - zipfile raises BadZipFile, ValueError, ...
        raise InputError(
            f"{source}: not a readable NPZ archive ({type(exc).__name__}: {exc}); save it with "
            "numpy.savez(points=...)"
        ) from exc
    if unpacked > max_bytes:
        raise InputError(
            f"{source}: the NPZ unpacks to {unpacked / 2**20:.1f} MiB, more than the limit of "
            f"{max_bytes / 2**20:.1f} MiB; downsample it or raise max_bytes"
        )
    try:
        with np.load(_io.BytesIO(data), allow_pickle=False) as npz:
            keys = list(npz.files)
            if "points" in keys:
                key = "points"
            elif len(keys) == 1:
                key = keys[0]
            else:
                raise InputError(
                    f"{source}: NPZ holds arrays {keys} but none is named 'points'; save the "
                    "points under the key 'points' (optional 'normals')"
                )
            arr = npz[key]
            normals = npz["normals"] if "normals" in keys and key != "normals" else None
    except InputError:
        raise
    except Exception as exc:  # noqa: BLE001
        raise InputError(
            f"{source}: cannot read the NPZ arrays ({type(exc).__name__}: {exc}); save float "
            "arrays with numpy.savez (object arrays are refused)"
        ) from exc
    pts = _numeric_array(arr, source, f"array '{key}'")
    warns: list[str] = []
    if normals is None:
        return _split_columns(pts, source, warns, "column")
    if pts.shape[1] != 3:
        raise InputError(
            f"{source}: array '{key}' has shape {pts.shape}, expected (N, 3) with 'normals'"
        )
    nrm = _numeric_array(normals, source, "array 'normals'")
    if nrm.shape != pts.shape:
        raise InputError(
            f"{source}: 'normals' has shape {nrm.shape}, expected {pts.shape} like 'points'"
        )
    return pts, nrm, int(pts.shape[0]), warns


# ----------------------------------------------------------------------------------------------
# PLY

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}  # fmt: skip


@dataclass(frozen=True)
class _PlyElement:
    name: str
    count: int
    props: tuple[tuple[str, str, bool], ...]
    """(name, numpy type code, is_list) per property."""


@dataclass(frozen=True)
class _PlyHeader:
    fmt: str
    """ascii, binary_little_endian or binary_big_endian."""
    elements: tuple[_PlyElement, ...]
    data_start: int
    """Byte offset of the body."""

    @property
    def n_faces(self) -> int:
        return sum(e.count for e in self.elements if e.name == "face")


def _parse_ply_header(data: bytes, source: str) -> _PlyHeader:
    def bad(problem: str) -> InputError:
        return InputError(
            f"{source}: malformed PLY header: {problem}; re-export the file as PLY "
            "(ascii or binary)"
        )

    if not data.startswith(b"ply"):
        raise bad("it does not start with 'ply'")
    end = data.find(b"end_header")
    if end < 0:
        raise bad("no 'end_header' line")
    nl = data.find(b"\n", end)
    data_start = len(data) if nl < 0 else nl + 1
    try:
        head = data[:end].decode("ascii")
    except UnicodeDecodeError:
        raise bad("non-ASCII bytes in the header") from None
    fmt = None
    elements: list[list[Any]] = []
    for raw in head.splitlines()[1:]:
        tok = raw.split()
        if not tok or tok[0] in ("comment", "obj_info"):
            continue
        if tok[0] == "format":
            if len(tok) < 2 or tok[1] not in (
                "ascii",
                "binary_little_endian",
                "binary_big_endian",
            ):
                raise bad(f"unknown format line {raw.strip()!r}")
            fmt = tok[1]
        elif tok[0] == "element":
            if len(tok) != 3 or not tok[2].isdigit():
                raise bad(f"bad element line {raw.strip()!r}")
            elements.append([tok[1], int(tok[2]), []])
        elif tok[0] == "property":
            if not elements:
                raise bad("a property before any element")
            if len(tok) == 5 and tok[1] == "list":
                if tok[2] not in _PLY_TYPES or tok[3] not in _PLY_TYPES:
                    raise bad(f"unknown type in {raw.strip()!r}")
                elements[-1][2].append((tok[4], _PLY_TYPES[tok[3]], True))
            elif len(tok) == 3 and tok[1] in _PLY_TYPES:
                elements[-1][2].append((tok[2], _PLY_TYPES[tok[1]], False))
            else:
                raise bad(f"bad property line {raw.strip()!r}")
        else:
            raise bad(f"unexpected line {raw.strip()!r}")
    if fmt is None:
        raise bad("no 'format' line")
    return _PlyHeader(
        fmt=fmt,
        elements=tuple(_PlyElement(n, c, tuple(p)) for n, c, p in elements),
        data_start=data_start,
    )


def _read_ply_cloud(
    data: bytes, header: _PlyHeader, source: str
) -> tuple[np.ndarray, np.ndarray | None, int, list[str]]:
    """The vertex element of a PLY without faces."""
    names = [e.name for e in header.elements]
    if "vertex" not in names:
        raise InputError(f"{source}: the PLY has no 'vertex' element; nothing to read")
    vi = names.index("vertex")
    vertex = header.elements[vi]
    prop_names = [p[0] for p in vertex.props]
    if not {"x", "y", "z"} <= set(prop_names):
        raise InputError(
            f"{source}: the PLY vertex element has properties {prop_names}, no x, y, z"
        )
    if any(p[2] for p in vertex.props):
        raise InputError(
            f"{source}: the PLY vertex element has list properties, which are not supported; "
            "re-export with scalar x y z (nx ny nz)"
        )
    before = header.elements[:vi]
    if header.fmt == "ascii":
        text = _decode(data[header.data_start :], source, "ascii PLY")
        lines = text.splitlines()
        skip = sum(e.count for e in before)
        rows = lines[skip : skip + vertex.count]
        if len(rows) < vertex.count:
            raise InputError(
                f"{source}: truncated PLY: the header promises {vertex.count} vertices, the "
                f"file holds {len(rows)}; re-export the file"
            )
        if vertex.count == 0:
            raise InputError(f"{source}: the PLY has 0 vertices; nothing to read")
        arr = _loadtxt(rows, source, "ascii PLY vertices")
        if arr.shape[1] != len(prop_names):
            raise InputError(
                f"{source}: wrong column count in the ascii PLY: {arr.shape[1]} numbers per "
                f"vertex, the header declares {len(prop_names)}"
            )
        col = {n: arr[:, i] for i, n in enumerate(prop_names)}
    else:
        order = "<" if header.fmt == "binary_little_endian" else ">"
        if any(p[2] for e in before for p in e.props if e.count):
            raise InputError(
                f"{source}: binary PLY with list elements before the vertices is not supported; "
                "re-export with the vertex element first"
            )
        offset = header.data_start + sum(
            e.count * np.dtype([(p[0], order + p[1]) for p in e.props]).itemsize for e in before
        )
        dt = np.dtype([(p[0], order + p[1]) for p in vertex.props])
        need = offset + vertex.count * dt.itemsize
        if vertex.count == 0:
            raise InputError(f"{source}: the PLY has 0 vertices; nothing to read")
        if len(data) < need:
            raise InputError(
                f"{source}: truncated PLY: the header promises {vertex.count} vertices "
                f"({need} bytes), the file has {len(data)} bytes; re-export the file"
            )
        rec = np.frombuffer(data, dtype=dt, count=vertex.count, offset=offset)
        col = {n: rec[n].astype(np.float64) for n in prop_names}
    pts = np.column_stack([col["x"], col["y"], col["z"]])
    nrm = None
    if {"nx", "ny", "nz"} <= set(prop_names):
        nrm = np.column_stack([col["nx"], col["ny"], col["nz"]])
    return pts, nrm, int(vertex.count), []


# ----------------------------------------------------------------------------------------------
# PCD (Point Cloud Library)

_PCD_KEYS = ("VERSION", "FIELDS", "SIZE", "TYPE", "COUNT", "WIDTH", "HEIGHT", "VIEWPOINT",
             "POINTS", "DATA")  # fmt: skip


def _read_pcd(data: bytes, source: str) -> tuple[np.ndarray, np.ndarray | None, int, list[str]]:
    def bad(problem: str) -> InputError:
        return InputError(
            f"{source}: malformed PCD header: {problem}; re-save the cloud with PCL "
            "(pcl::io::savePCDFile) as ascii or binary"
        )

    header: dict[str, list[str]] = {}
    pos = 0
    while True:
        nl = data.find(b"\n", pos)
        line_b = data[pos:] if nl < 0 else data[pos:nl]
        pos = len(data) if nl < 0 else nl + 1
        try:
            line = line_b.decode("ascii").strip()
        except UnicodeDecodeError:
            raise bad("non-ASCII bytes in the header") from None
        if line and not line.startswith("#"):
            tok = line.split()
            key = tok[0].upper()
            if key not in _PCD_KEYS:
                raise bad(f"unexpected line {line[:60]!r}")
            header[key] = tok[1:]
            if key == "DATA":
                break
        if nl < 0:
            raise bad("no DATA line")
    for key in ("FIELDS", "SIZE", "TYPE", "WIDTH", "HEIGHT"):
        if key not in header:
            raise bad(f"no {key} line")
    fields = header["FIELDS"]
    n_f = len(fields)
    counts_s = header.get("COUNT", ["1"] * n_f)
    if not (len(header["SIZE"]) == len(header["TYPE"]) == len(counts_s) == n_f) or n_f == 0:
        raise bad(
            f"FIELDS ({n_f}), SIZE ({len(header['SIZE'])}), TYPE ({len(header['TYPE'])}) and "
            f"COUNT ({len(counts_s)}) must list the same number of entries"
        )
    try:
        sizes = [int(s) for s in header["SIZE"]]
        counts = [int(c) for c in counts_s]
        width = int(header["WIDTH"][0])
        height = int(header["HEIGHT"][0])
        n_pts = int(header["POINTS"][0]) if "POINTS" in header else width * height
    except (ValueError, IndexError):
        raise bad("SIZE, COUNT, WIDTH, HEIGHT and POINTS must be integers") from None
    types = [t.upper() for t in header["TYPE"]]
    dtypes = []
    for name, t, s, c in zip(fields, types, sizes, counts, strict=True):
        if t not in ("F", "I", "U") or s not in (1, 2, 4, 8) or (t == "F" and s not in (4, 8)):
            raise bad(f"field {name!r} has unsupported TYPE {t} SIZE {s}")
        if c < 1:
            raise bad(f"field {name!r} has COUNT {c}")
        code = {"F": "f", "I": "i", "U": "u"}[t] + str(s)
        dtypes.append((name, "<" + code, (c,)) if c > 1 else (name, "<" + code))
    if n_pts < 0 or width < 0 or height < 0:
        raise bad("negative WIDTH, HEIGHT or POINTS")
    for axis in ("x", "y", "z"):
        if axis not in fields:
            raise InputError(f"{source}: the PCD has fields {fields}, no {axis!r}; nothing to read")
    if n_pts == 0:
        raise InputError(f"{source}: the PCD declares 0 points; nothing to read")
    mode = header["DATA"][0].lower() if header["DATA"] else ""
    if mode == "ascii":
        text = _decode(data[pos:], source, "ascii PCD")
        arr = _loadtxt(text, source, "ascii PCD data")
        n_cols = sum(counts)
        if arr.size == 0:
            raise InputError(f"{source}: the ascii PCD has no data rows; re-save the cloud")
        if arr.shape[1] != n_cols:
            raise InputError(
                f"{source}: wrong column count in the ascii PCD: {arr.shape[1]} numbers per "
                f"row, the header declares {n_cols}"
            )
        if arr.shape[0] != n_pts:
            raise InputError(
                f"{source}: the PCD header declares {n_pts} points, the data has "
                f"{arr.shape[0]} rows; re-save the cloud"
            )
        starts = np.cumsum([0] + counts[:-1])
        col = {f: arr[:, st] for f, st in zip(fields, starts, strict=True)}
    elif mode == "binary":
        dt = np.dtype(dtypes)
        need = n_pts * dt.itemsize
        if len(data) - pos < need:
            raise InputError(
                f"{source}: truncated PCD: the header declares {n_pts} points ({need} bytes), "
                f"the file holds {len(data) - pos} data bytes; re-save the cloud"
            )
        rec = np.frombuffer(data, dtype=dt, count=n_pts, offset=pos)
        col = {
            f: (rec[f] if rec[f].ndim == 1 else rec[f][:, 0]).astype(np.float64)
            for f in ("x", "y", "z", "normal_x", "normal_y", "normal_z")
            if f in fields
        }
    elif mode == "binary_compressed":
        raise InputError(
            f"{source}: PCD 'DATA binary_compressed' is not supported; re-save it as binary "
            "or ascii (e.g. pcl_convert_pcd_ascii_binary in.pcd out.pcd 1)"
        )
    else:
        raise bad(f"unknown DATA mode {' '.join(header['DATA'])!r} (ascii or binary)")
    pts = np.column_stack([col["x"], col["y"], col["z"]])
    nrm = None
    if {"normal_x", "normal_y", "normal_z"} <= set(fields):
        nrm = np.column_stack([col["normal_x"], col["normal_y"], col["normal_z"]])
    return pts, nrm, int(n_pts), []
