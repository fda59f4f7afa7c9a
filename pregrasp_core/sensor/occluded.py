"""The space a single view cannot see, as an obstacle: ``--occluded occupied`` (issue 13).

A camera sees the object's front. Everything behind the seen surface along the camera's rays,
down to the support plane, may hold object (the mug's handle hidden behind the cup); the
completion (:mod:`.completion`) guesses a back inside it but cannot invent what no symmetry
explains. With ``occluded="occupied"`` the pipeline counts that hidden space as occupied for
collisions: the pool's collision filter and the planner's approach and closing see it as
obstacle points (:func:`occupied_points`), the hand must stay out of it, while the contacts come
only from the real points (seen or completed): a contact the planner found on an occupied point
is dropped and the grasp rescored (``pregrasp_core.planner.assumed.without_occupied``).

Representation: a voxel grid of ``OccludedParams.voxel`` in the support plane's frame over the
completed object's extent grown by ``OccludedParams.margin`` (up from the plane). A voxel is
hidden when its centre lies behind the seen surface of the view's range image
(:class:`~.completion.RangeImage`: the visible points triangulated in a virtual image; a
direction where the camera saw the table or nothing is free). Hidden voxels closer than
``OccludedParams.carve`` to a real point are left out (the hand touches the real points there,
not the obstacle). The obstacle is the hidden region's boundary voxels (every one) and its
interior on a coarser lattice (every ``interior_step``-th voxel along each axis): the planner
and the pool test points in link boxes, so a surface the fingers cannot slip through and an
interior no link box (20 mm wide at the least) fits between is enough; a full grid would cost
several times the points. Points are cheaper than a new occupancy test in the planner: its
collision, closing and penetration checks all take points.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from ..errors import WorkLimitError
from ..facemask import SupportPlane
from ..limits import MAX_LENGTH, MAX_SPACINGS, check_int, check_real
from .completion import RangeImage

OCCLUDED_MODES: tuple[str, ...] = ("auto", "completed", "occupied")
"""Values of ``PipelineParams.occluded``: ``completed`` = the unseen space is free but for the
completion's assumed points; ``occupied`` = it is an obstacle; ``auto`` (the default) =
``occupied``, and ``completed`` again when that plan has no force-closure grasp or the hidden
space passes :data:`MAX_OCCLUDED_VOXELS` (``pregrasp_core.pipeline.run_pipeline``)."""

SLAB_VOXELS: int = 65_536
"""Voxels :func:`occupied_space` tests at once, a slab of its grid (their temporaries take
about 170 bytes each: some 11 MiB)."""

BYTES_PER_VOXEL: int = 20
"""Peak bytes of :func:`occupied_space` per voxel of its grid beyond its slabs' ~11 MiB
(tracemalloc: 17-20 on hidden spaces of 1.4-4.3 million voxels; 171-202 before the grid was
built in slabs)."""

MAX_OCCLUDED_VOXELS: int = 20_000_000
"""Most voxels of the grid :func:`occupied_space` builds: about 400 MB at
:data:`BYTES_PER_VOXEL` and some 10 s of one core (0.5 s per million voxels measured); the
thermos, the largest demo view, needs 0.70 million voxels of 3 mm. Past it a
``WorkLimitError`` is raised before the grid is allocated: the object and its margin span
more than about 0.8 m in every direction."""


@dataclass(frozen=True)
class OccludedParams:
    """How the hidden space of a view is sampled as obstacle points."""

    voxel: float = 0.003
    """Metres: the grid's cell (the obstacle's surface spacing)."""
    margin: float = 0.02
    """Metres: the region is the completed object's extent (in the plane's frame) grown by this
    (up from the support plane)."""
    carve: float = 0.003
    """Metres: hidden voxels this close to a real (seen or completed) point are left out."""
    interior_step: int = 3
    edge_factor: float = 6.0
    """The interior (voxels whose 6 neighbours are all hidden) is kept every this many voxels
    along each axis (9 mm at 3 mm voxels: less than a link box's 20 mm)."""

    def __post_init__(self) -> None:
        # bounds: docs/limits.md ("Sensor input"); the grid's size is limited by MAX_VOXELS
        lengths = (("voxel", MIN_VOXEL, True), ("margin", 0.0, False), ("carve", 0.0, False))
        for name, lo, lo_open in lengths:
            v = check_real(name, getattr(self, name), lo, MAX_LENGTH, lo_open=lo_open,
                           what="a length", unit=" m")  # fmt: skip
            object.__setattr__(self, name, v)
        step = check_int("interior_step", self.interior_step, 1, MAX_INTERIOR_STEP)
        object.__setattr__(self, "interior_step", step)
        edge = check_real("edge_factor", self.edge_factor, 0.0, MAX_SPACINGS, lo_open=True)
        object.__setattr__(self, "edge_factor", edge)


MIN_VOXEL: float = 1e-4
"""Metres: the smallest voxel of the hidden space (0.1 mm; any grid is also limited by
:data:`MAX_VOXELS`)."""

MAX_INTERIOR_STEP: int = 1000
"""Upper bound of ``OccludedParams.interior_step`` (voxels between kept interior voxels)."""


DEFAULT_OCCLUDED: OccludedParams = OccludedParams()
"""The parameters :func:`occupied_space` uses when given none (the pipeline's; a benchmark may
set others here, ``benchmarks/bench_partial_grasps.py --occluded-margin``)."""


def plane_frame(plane: SupportPlane, toward: np.ndarray) -> np.ndarray:
    """(3, 3) columns e1, e2, n: ``n`` the plane's normal, ``e1`` the horizontal part of
    ``toward`` (any horizontal direction when it has none)."""
    n = plane.normal / np.linalg.norm(plane.normal)
    e1 = toward - (toward @ n) * n
    if np.linalg.norm(e1) < 1e-9:
        e1 = np.cross(n, np.eye(3)[int(np.argmin(np.abs(n)))])
    e1 = e1 / np.linalg.norm(e1)
    return np.stack([e1, np.cross(n, e1), n], axis=1)


def hidden(vis: RangeImage, q: np.ndarray) -> np.ndarray:
    """(...,) bool: the points ``q`` (..., 3) lie behind the surface the camera saw (in a seen
    direction, farther than the interpolated seen range) and above the support plane."""
    qc, uv, ijc, inside = vis.locate(q)
    inside &= qc[..., 2] > 0.0
    rng = np.linalg.norm(qc, axis=-1)
    i, j = ijc[..., 0], ijc[..., 1]
    c = vis.coef[i, j]
    D = c[..., 0] + c[..., 1] * uv[..., 0] + c[..., 2] * uv[..., 1]
    above = vis.plane.signed_distance(q.reshape(-1, 3)).reshape(q.shape[:-1]) > 0.0
    return inside & vis.seen[i, j] & (rng > D) & above


@dataclass(frozen=True, eq=False)
class OccupiedSpace:
    """The hidden space of a view sampled as obstacle points."""

    points: np.ndarray
    """(K, 3) the obstacle points (the hidden region's boundary voxels and its interior on a
    coarser lattice), the scene's frame."""
    normals: np.ndarray
    """(K, 3) unit: toward the camera (only for the planner's arrays; no contact keeps them)."""
    grid: np.ndarray
    """(A, B, C) bool: every hidden voxel (before the sampling), axes e1, e2, n of ``frame``."""
    origin: np.ndarray
    """(3,) the centre of voxel (0, 0, 0)."""
    frame: np.ndarray
    """(3, 3) columns e1, e2, n (the plane's normal)."""
    voxel: float
    """Metres: the cell."""

    @property
    def volume(self) -> float:
        """Cubic metres of hidden voxels."""
        return float(np.count_nonzero(self.grid)) * self.voxel**3

    def contains(self, q: np.ndarray) -> np.ndarray:
        """(...,) bool: the points ``q`` (..., 3) fall in a hidden voxel."""
        g = (np.asarray(q, dtype=np.float64) - self.origin) @ self.frame / self.voxel
        ijk = np.floor(g + 0.5).astype(np.int64)
        ok = np.all((ijk >= 0) & (ijk < np.array(self.grid.shape)), axis=-1)
        ijk = np.where(ok[..., None], ijk, 0)
        return ok & self.grid[ijk[..., 0], ijk[..., 1], ijk[..., 2]]


def occupied_space(
    visible: np.ndarray,
    real: np.ndarray,
    viewpoint: np.ndarray,
    plane: SupportPlane,
    params: OccludedParams | None = None,
) -> OccupiedSpace:
    """The space hidden behind the ``visible`` points (N, 3) seen from ``viewpoint`` (3,),
    standing on ``plane``, within the extent of the ``real`` points (M, 3; seen and completed)
    grown by ``params.margin``, as obstacle points (see the module)."""
    prm = DEFAULT_OCCLUDED if params is None else params
    vp = np.asarray(viewpoint, dtype=np.float64)
    vis = RangeImage(np.asarray(visible, dtype=np.float64), vp, plane, edge_factor=prm.edge_factor)
    F = plane_frame(plane, np.asarray(real, dtype=np.float64).mean(axis=0) - vp)
    n = F[:, 2]
    local = real @ F  # (M, 3) e1, e2, n coordinates (n: the plane's offset included)
    p0 = real[0] - float(plane.signed_distance(real[:1])[0]) * n  # a point of the plane
    h0 = float(p0 @ n)  # the plane's n-coordinate
    lo = local.min(axis=0) - prm.margin
    hi = local.max(axis=0) + prm.margin
    lo[2] = h0 + 0.5 * prm.voxel
    v = prm.voxel
    shape = np.maximum(np.ceil((hi - lo) / v).astype(np.int64) + 1, 1)
    n_voxels = int(np.prod(shape))
    if n_voxels > MAX_OCCLUDED_VOXELS:
        span = " x ".join(f"{x:.2f}" for x in hi - lo)
        raise WorkLimitError(
            f"--occluded occupied: the hidden space of this view ({span} m with the margin) "
            f"would take {n_voxels:,} voxels of {v * 1000:.1f} mm, more than "
            f"{MAX_OCCLUDED_VOXELS:,} (about {MAX_OCCLUDED_VOXELS * BYTES_PER_VOXEL // 2**20} "
            "MiB); plan it with --occluded completed, or pick a smaller object (--pick X Y Z)"
        )
    axes = [lo[k] + v * np.arange(shape[k]) for k in range(3)]

    def world(ijk: np.ndarray) -> np.ndarray:
        """(K, 3) world centres of the voxels ``ijk`` (K, 3)."""
        return np.stack([axes[k][ijk[:, k]] for k in range(3)], axis=1) @ F.T

    # the grid in slabs along its first axis (a few MB of temporaries each, not ~200 bytes a
    # voxel for the whole grid at once)
    grid = np.zeros(tuple(int(x) for x in shape), dtype=bool)
    plane_cells = int(shape[1] * shape[2])
    step = max(1, SLAB_VOXELS // max(plane_cells, 1))
    for a0 in range(0, int(shape[0]), step):  # loop over the slabs
        a1 = min(a0 + step, int(shape[0]))
        G = np.stack(np.meshgrid(axes[0][a0:a1], axes[1], axes[2], indexing="ij"), axis=-1)
        grid[a0:a1] = hidden(vis, G @ F.T)
    if prm.carve > 0.0 and np.any(grid):
        tree = cKDTree(real)
        idx = np.flatnonzero(grid)
        flat = grid.reshape(-1)
        for c0 in range(0, len(idx), SLAB_VOXELS):  # loop over chunks of hidden voxels
            part = idx[c0 : c0 + SLAB_VOXELS]
            q = world(np.stack(np.unravel_index(part, grid.shape), axis=1))
            d, _ = tree.query(q, distance_upper_bound=prm.carve)
            flat[part[np.isfinite(d)]] = False
    inner = ndimage.binary_erosion(grid, border_value=0)
    s = max(int(prm.interior_step), 1)
    on = [np.arange(k) % s == 0 for k in shape]
    lattice = on[0][:, None, None] & on[1][None, :, None] & on[2][None, None, :]
    keep = (grid & ~inner) | (inner & lattice)
    pts = np.ascontiguousarray(world(np.argwhere(keep)))
    to_cam = vp - pts
    nrm = to_cam / np.maximum(np.linalg.norm(to_cam, axis=1, keepdims=True), 1e-12)
    for a in (pts, nrm, grid):
        a.setflags(write=False)
    return OccupiedSpace(pts, nrm, grid, lo @ F.T, F, v)


NEIGHBOUR_DEPTH_MAX: float = 0.15
"""Metres: the deepest a neighbour is assumed to reach behind its seen surface (its hidden
space's margin is its width along the table, at least ``OccludedParams.margin``, at most
this)."""

NEIGHBOUR_DEPTH_RATIO: float = 1.0
"""A neighbour's assumed depth behind its seen surface, as a fraction of its width along the
table (1: a can seen from the front is as deep as it is wide)."""


def neighbour_shadows(
    points: np.ndarray,
    labels: np.ndarray,
    clusters: np.ndarray,
    viewpoint: np.ndarray,
    plane: SupportPlane,
    voxel: float,
) -> np.ndarray:
    """(K, 3) the hidden space behind each neighbour of a view's object, as obstacle points:
    for each of ``clusters`` (labels into ``labels`` over ``points``: the other objects on the
    table), :func:`occupied_space` of its seen points, with a margin of its width along the
    table times :data:`NEIGHBOUR_DEPTH_RATIO` (a can seen from the front is as deep as it is
    wide; at least 2 cm, at most :data:`NEIGHBOUR_DEPTH_MAX`) on a grid of ``voxel``. A hand
    that reaches behind a can through its unseen back would otherwise find no point there. A
    neighbour whose grid passes :data:`MAX_OCCLUDED_VOXELS` keeps only its seen points."""
    out = [np.zeros((0, 3))]
    n = np.asarray(plane.normal, dtype=np.float64)
    for c in clusters:  # loop over the few neighbours within reach
        cp = points[labels == c]
        if len(cp) < 3:
            continue
        flat = cp - np.outer(cp @ n, n)
        width = float(np.linalg.norm(np.ptp(flat, axis=0)))
        depth = NEIGHBOUR_DEPTH_RATIO * width
        margin = min(max(DEFAULT_OCCLUDED.margin, depth), NEIGHBOUR_DEPTH_MAX)
        params = OccludedParams(voxel=voxel, margin=margin)
        try:
            out.append(occupied_space(cp, cp, viewpoint, plane, params).points)
        except WorkLimitError:
            continue
    return np.concatenate(out)
