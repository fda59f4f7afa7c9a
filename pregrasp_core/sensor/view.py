"""One call from a depth-camera scene to the object cloud the pipeline takes: :func:`prepare_view`.

Chain: optional statistical outlier removal of the scene, :func:`~.table.segment_table` (the
support plane, the table's points, the object), on a noisy view the object's points projected
onto their local planes (:func:`~.smooth.smooth_view`: the range noise off the contacts),
optional :func:`~.completion.complete_view` (the unseen back, flagged ``assumed``). The
result, :class:`SensorView`, carries everything the pipeline, the planner and the viewer
need: the object's points, which of them are assumed, the viewpoint, the support plane (as
face-mask parameters too) and the masks over the scene.

Normals of a single view: orient the **visible** points' normals toward the viewpoint; the
assumed points take the normals of the visible points they were copied from, moved by the
symmetry (:meth:`SensorView.full_normals`); orienting them toward the camera would be wrong,
since they face away from it.

PCD files carry the sensor pose in their header (``VIEWPOINT tx ty tz qw qx qy qz``):
:func:`pcd_viewpoint` reads it without reading the points.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from ..errors import InputError
from ..facemask import FaceMaskParams, SupportPlane
from ..geometry import as_points
from .completion import CompletedView, CompletionParams, complete_view
from .smooth import smooth_view
from .table import SegmentParams, TableSegmentation, remove_outliers, segment_table
from .veils import VeilParams, flying_points

SMOOTH_K: int = 24
"""Neighbours of the projection that takes the range noise off the object's points
(:func:`~.smooth.smooth_view`), when the table shows noise."""

SMOOTH_MIN_SIGMA: float = 0.0003
"""Metres: the object's points are smoothed when the table's residual spread reaches this (a
noise-free view, such as one rendered without noise, is left exactly as it is)."""

PCD_HEADER_BYTES: int = 64 * 1024
"""Most bytes read looking for a PCD header's ``VIEWPOINT`` line."""


@dataclass(frozen=True, eq=False)
class SensorView:
    """The object of a depth-camera scene, ready for the pipeline."""

    points: np.ndarray
    """(M, 3) float64: the object's points (visible, then assumed), the scene's frame, metres."""
    assumed: np.ndarray
    """(M,) bool: True for points assumed by the completion (draw them in their own colour)."""
    viewpoint: np.ndarray
    """(3,) the camera position in the scene's frame."""
    plane: SupportPlane
    """The support plane (normal toward the object and the camera)."""
    segmentation: TableSegmentation
    """The scene split into table, object and the rest (masks over the scene's points)."""
    completion: CompletedView | None
    """The completion, or None when it was not asked for."""
    kept: np.ndarray
    """(N,) bool over the scene's input points: those kept by the flying-pixel test and the
    outlier removal (all True without them); the segmentation's masks index the kept points."""
    flying: np.ndarray | None = None
    """(K, 3) the scene's points dropped as flying pixels (:mod:`.veils`; the viewer draws them
    in their own colour); None without the test."""

    @property
    def n_flying(self) -> int:
        """Number of the scene's points dropped as flying pixels (0 without the test)."""
        return 0 if self.flying is None else len(self.flying)

    @property
    def n_visible(self) -> int:
        """Number of the object's visible points."""
        return int(np.count_nonzero(~self.assumed))

    def face_mask_params(self, base: FaceMaskParams | None = None) -> FaceMaskParams:
        """``base`` (default parameters when None) with this view's support plane."""
        base = FaceMaskParams() if base is None else base
        return dataclasses.replace(
            base,
            support=True,
            up=(float(self.plane.normal[0]), float(self.plane.normal[1]),
                float(self.plane.normal[2])),
            support_height=float(self.plane.height),
        )  # fmt: skip

    def full_normals(self, visible_normals: np.ndarray) -> np.ndarray:
        """(M, 3) normals of every point from those of the visible points (n_visible, 3): the
        assumed points take their source's normal moved by the symmetry, a skirt's points
        their own (``CompletedView.skirt_normals``)."""
        nv = np.asarray(visible_normals, dtype=np.float64)
        if nv.shape != (self.n_visible, 3):
            raise ValueError(
                f"visible_normals must have shape ({self.n_visible}, 3), got {nv.shape}"
            )
        if self.completion is None:
            return nv.copy()
        R = self.completion.transform[:3, :3]
        out = nv[self.completion.source]
        mv = self.completion.moved
        out[mv] = out[mv] @ R.T
        out[self.completion.skirt] = self.completion.skirt_normals
        return out


def prepare_view(
    points: np.ndarray,
    viewpoint: np.ndarray | tuple[float, float, float],
    pick: np.ndarray | tuple[float, float, float] | None = None,
    complete: bool = True,
    segment: SegmentParams | None = None,
    completion: CompletionParams | None = None,
    outliers: tuple[int, float] | None = None,
    smooth: int | None = None,
    veils: VeilParams | None = None,
) -> SensorView:
    """The object of the scene ``points`` (N, 3) seen from ``viewpoint`` (see the module).

    ``pick``: a point near the wanted object (default: the largest cluster). ``complete``: add
    the unseen back (``completion`` parameters; default tolerance ``max(3 mm, 3 sigma)`` of the
    table's noise). ``outliers``: ``(k, std_ratio)`` of a statistical outlier removal run first
    (default: none). ``smooth``: neighbours of the projection of the object's points onto their
    local planes (:func:`~.smooth.smooth_view`); None = ``SMOOTH_K`` when the table's noise
    ``sigma`` reaches ``SMOOTH_MIN_SIGMA``, 0 = never. The segmentation's masks and points
    stay those of the scene. ``veils``: the flying-pixel test run before everything else
    (:func:`~.veils.flying_points`; None = off, the default).
    """
    pts = as_points(points)
    vp = np.asarray(viewpoint, dtype=np.float64)
    if vp.shape != (3,) or not np.all(np.isfinite(vp)):
        raise ValueError(f"viewpoint must be a finite 3-vector, got {viewpoint!r}")
    fly = np.zeros(len(pts), dtype=bool) if veils is None else flying_points(pts, vp, veils)
    kept = ~fly
    if outliers is not None:
        idx = np.flatnonzero(kept)
        kept[idx[~remove_outliers(pts[idx], k=outliers[0], std_ratio=outliers[1])]] = False
    seg = segment_table(pts[kept], viewpoint=vp, pick=pick, params=segment)
    obj = seg.object_points
    if smooth is None:
        smooth = SMOOTH_K if seg.sigma >= SMOOTH_MIN_SIGMA else 0
    if smooth:
        obj = smooth_view(obj, smooth)
    done = None
    if complete:
        params = completion or CompletionParams(tolerance=max(0.003, 3.0 * seg.sigma))
        done = complete_view(obj, vp, seg.plane, params)
        out, assumed = done.points, done.assumed
    else:
        out, assumed = obj, np.zeros(len(obj), dtype=bool)
    kept.setflags(write=False)
    flying = None if veils is None else pts[fly]
    return SensorView(out, assumed, vp.copy(), seg.plane, seg, done, kept, flying)


def pcd_viewpoint(path: str | Path) -> np.ndarray | None:
    """``T_world_sensor`` (4, 4) from a PCD header's ``VIEWPOINT`` line, or None when the header
    has none or gives the identity ``0 0 0 1 0 0 0``: every PCD writer puts that default there,
    so it cannot tell "camera at the origin" (a cloud in the camera frame) from "not set"; the
    caller decides (e.g. ``--viewpoint 0 0 0``)."""
    p = Path(path)
    if not p.is_file():
        raise InputError(f"{p}: file not found; check the path")
    with open(p, "rb") as f:
        head = f.read(PCD_HEADER_BYTES)
    return pcd_viewpoint_of(head, str(p))


def pcd_viewpoint_of(data: bytes, source: str) -> np.ndarray | None:
    """:func:`pcd_viewpoint` of a PCD file's bytes ``data`` (an upload), ``source`` its name."""
    head = bytes(data[:PCD_HEADER_BYTES])
    for raw in head.split(b"\n"):
        line = raw.decode("ascii", errors="replace").strip()
        if line.upper().startswith("DATA"):
            break
        if not line.upper().startswith("VIEWPOINT"):
            continue
        try:
            vals = np.array([float(v) for v in line.split()[1:]])
        except ValueError:
            raise InputError(f"{source}: malformed VIEWPOINT line {line[:80]!r}") from None
        if vals.shape != (7,) or not np.all(np.isfinite(vals)):
            raise InputError(
                f"{source}: VIEWPOINT must hold 7 numbers (tx ty tz qw qx qy qz), got {line[:80]!r}"
            )
        q = vals[3:]
        if np.linalg.norm(q) < 1e-9:
            raise InputError(f"{source}: the VIEWPOINT quaternion is zero")
        if np.allclose(vals, [0, 0, 0, 1, 0, 0, 0]):
            return None
        T = np.eye(4)
        T[:3, :3] = Rotation.from_quat([q[1], q[2], q[3], q[0]]).as_matrix()  # xyzw
        T[:3, 3] = vals[:3]
        return T
    return None
