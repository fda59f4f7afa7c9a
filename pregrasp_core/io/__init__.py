"""Point-cloud input: read clouds and meshes from files or uploaded bytes into a PointCloud.

Formats (the file name's extension picks the reader in ``READERS``, case-insensitive):

- point clouds: PLY without faces (ascii, binary little/big endian; ``ply``), PCD (PCL's format;
  ascii, binary and binary_compressed, whose LZF ``lzf`` decodes; ``pcd``), XYZ/TXT/CSV (x y z
  first, then optional normals, colours, intensities; whitespace or comma separated; ``#``
  comments; a column-name first line naming x y z picks the columns; ``text``), NPY
  (``allow_pickle=False``) and NPZ (key ``points`` or a single array; optional ``normals``;
  ``numpy_format``);
- meshes: OBJ, STL, OFF, GLB/GLTF and PLY with faces (``mesh``), sampled uniformly on the surface
  to ``n_points`` points with ``seed`` (area-weighted, the face normal of each sample kept as its
  normal). Same bytes + same ``n_points`` + same ``seed`` = same cloud.

A point cloud larger than ``n_points`` is subsampled to ``n_points`` points (seeded, without
replacement, in file order); ``n_points=None`` keeps every point of a cloud.

Every problem with the input raises :class:`~pregrasp_core.errors.InputError` (or
:class:`~pregrasp_core.errors.DegenerateGeometryError` for identical/collinear points) whose
message names the file, the problem and what to do; nothing is ever unpickled or executed.
Recoverable oddities (non-finite rows dropped, coplanar points, millimetre-looking extents,
ignored columns) are logged with ``logging`` and listed in ``PointCloud.info["warnings"]``.
- depth images: a 16-bit PNG in millimetres, or an NPY given intrinsics (``depth_image``),
  read as a scene: the table becomes the support plane, the object is kept and completed
  (``SensorOptions``; also PCD files with a ``VIEWPOINT``). A cloud recognised as millimetres
  (``pregrasp_core.sensor.detect_units``) is scaled by 0.001 with a warning unless a scale is
  given.

See ``docs/input.md``.
"""

from .cloud import (
    CLOUD_EXTENSIONS,
    DEFAULT_MAX_BYTES,
    DEFAULT_N_POINTS,
    MAX_COORDINATE,
    MAX_POINTS,
    MESH_EXTENSIONS,
    MILLIMETRE_EXTENT,
    MIN_POINTS,
    SUPPORTED_EXTENSIONS,
    CloudInfo,
    PointCloud,
)
from .depth_image import DEPTH_IMAGE_EXTENSIONS
from .load import (
    READERS,
    SCENE_OBSTACLES,
    SensorOptions,
    load_point_cloud,
    load_point_cloud_bytes,
)

__all__ = [
    "CLOUD_EXTENSIONS",
    "DEFAULT_MAX_BYTES",
    "DEPTH_IMAGE_EXTENSIONS",
    "DEFAULT_N_POINTS",
    "MAX_COORDINATE",
    "MAX_POINTS",
    "MESH_EXTENSIONS",
    "MILLIMETRE_EXTENT",
    "MIN_POINTS",
    "READERS",
    "SUPPORTED_EXTENSIONS",
    "CloudInfo",
    "PointCloud",
    "SCENE_OBSTACLES",
    "SensorOptions",
    "load_point_cloud",
    "load_point_cloud_bytes",
]
