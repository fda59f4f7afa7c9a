"""The public loaders: a file or an upload's bytes -> :class:`PointCloud`. The extension picks
the reader from ``READERS``; size limits are checked before anything is parsed."""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path

from ..errors import InputError, PregraspError
from .cloud import (
    DEFAULT_MAX_BYTES,
    DEFAULT_N_POINTS,
    SUPPORTED_EXTENSIONS,
    CloudInfo,
    FileData,
    PointCloud,
    RawCloud,
    check_request,
    describe_error,
    finish_cloud,
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
) -> PointCloud:
    """Read a point cloud or a mesh file into a :class:`PointCloud` (see ``docs/input.md``).

    path: the file; its extension picks the format. n_points: points sampled on a mesh, and the
    cap for a cloud (None: a cloud keeps all points, a mesh gets ``DEFAULT_N_POINTS``). seed:
    sampling seed. scale: multiplies the coordinates (0.001 for a file in millimetres).
    max_bytes: larger files are refused.
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
    return _load(file, ext, n_points, seed, scale)


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
    ext = extension(source)
    if not isinstance(data, bytes | bytearray | memoryview):
        raise ValueError(f"data must be bytes, got {type(data).__name__}")
    data = bytes(data)
    check_size(len(data), max_bytes, source)
    file = FileData(data=data, source=source, path=None, max_bytes=max_bytes)
    return _load(file, ext, n_points, seed, scale)


def extension(source: str) -> str:
    """The lower-case extension of ``source`` if supported, else :class:`InputError`."""
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


def check_size(size: int, max_bytes: int, source: str) -> None:
    """Refuse an empty input or one larger than ``max_bytes``."""
    if size == 0:
        raise InputError(f"{source}: the file is empty; give a file with points or a mesh")
    if size > max_bytes:
        raise InputError(
            f"{source}: the file is {size / 2**20:.1f} MiB, more than the limit of "
            f"{max_bytes / 2**20:.1f} MiB; downsample it or raise max_bytes"
        )


def _load(
    file: FileData, ext: str, n_points: int | None, seed: int, scale: float | None
) -> PointCloud:
    check_request(n_points, scale, file.source, seed)
    fmt = ext[1:]
    try:
        parsed = READERS[ext](file)
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
    if isinstance(parsed, TriangleMesh):
        return sample_mesh(parsed, file.source, fmt, n_points, seed, scale)
    info = CloudInfo(format=fmt, kind="cloud", n_read=parsed.n_read, warnings=parsed.warnings)
    return finish_cloud(
        parsed.points, parsed.normals, file.source, info, scale=scale, n_points=n_points, seed=seed
    )
