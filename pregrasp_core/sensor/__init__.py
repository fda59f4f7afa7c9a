"""Depth-sensor input: depth images, the table in a scene, units and single-view completion.

- :mod:`.depth`: depth images (16-bit PNG in mm, float NPY in m) with pinhole
  :class:`Intrinsics` to a camera-frame cloud (OpenCV: +z forward, +x right, +y down);
- :mod:`.table`: the support plane by RANSAC (any orientation), the table's points, the object
  as the largest cluster above it (or the one nearest ``pick``), statistical outlier removal;
- :mod:`.units`: the rule that recognises millimetre clouds;
- :mod:`.completion`: the unseen back of a single view completed by symmetry under the view's
  visibility constraint (``docs/partial-views.md``);
- :mod:`.view`: :func:`prepare_view`, the whole chain in one call (:class:`SensorView`), and the
  PCD header's viewpoint;
- :mod:`.veils`: the flying pixels a depth camera strings along its rays at depth jumps;
- :mod:`.synthetic`: simulated depth views of a mesh on a table (the test data).

See ``docs/input.md`` ("Depth-camera input").
"""

from .completion import CompletedView, CompletionParams, complete_view
from .depth import (
    CameraFile,
    DepthCloud,
    Intrinsics,
    depth_to_points,
    load_camera_pose,
    load_depth_image,
    read_depth_file,
)
from .table import (
    NoTableError,
    SegmentParams,
    TableSegmentation,
    fit_plane_ransac,
    remove_outliers,
    scene_obstacles,
    segment_table,
    voxel_clusters,
)
from .units import UnitGuess, detect_units
from .veils import VeilParams, flying_points
from .view import SensorView, pcd_viewpoint, pcd_viewpoint_of, prepare_view

__all__ = [
    "CameraFile",
    "CompletedView",
    "CompletionParams",
    "DepthCloud",
    "Intrinsics",
    "NoTableError",
    "SegmentParams",
    "SensorView",
    "TableSegmentation",
    "UnitGuess",
    "VeilParams",
    "complete_view",
    "depth_to_points",
    "detect_units",
    "fit_plane_ransac",
    "flying_points",
    "load_camera_pose",
    "load_depth_image",
    "pcd_viewpoint",
    "pcd_viewpoint_of",
    "prepare_view",
    "read_depth_file",
    "remove_outliers",
    "scene_obstacles",
    "segment_table",
    "voxel_clusters",
]
