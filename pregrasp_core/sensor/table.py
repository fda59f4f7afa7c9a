"""The table in a scene cloud: support plane by RANSAC, the object above it, outlier removal.

:func:`segment_table` runs the whole chain on a scene cloud (a depth frame, or a single view with
the table in it) and returns a :class:`TableSegmentation`:

1. **Plane search** (:func:`fit_plane_ransac`), any orientation: ``iterations`` random triplets
   drawn with ``seed`` from a random subset of ``sample`` points, each plane scored by its inliers
   (distance < ``ransac_threshold``) in that subset, all at once as one matrix; the best plane is
   refined by least squares (the smallest principal axis of its inliers in the whole cloud).
2. **Noise band**: the inliers' residual spread, ``sigma = 1.4826 * MAD``, sets the band
   ``|distance| <= max(band_sigmas * sigma, min_band)`` that is the table; the plane is refitted
   on the band once more. The normal is oriented toward the viewpoint (the camera is above the
   table) or, without one, toward the side that holds more of the off-plane points.
3. **Clusters above the table**: points farther than the band above the plane are clustered by
   Euclidean proximity on a voxel grid of side ``cluster_radius`` (occupied voxels that touch,
   26-neighbourhood, are one cluster: scipy's connected components on the voxel graph). The
   object is the largest cluster, or with ``pick`` the cluster with the point nearest ``pick``.
   Clusters smaller than ``min_cluster`` points are never chosen, nor the clusters of the
   table's noise tail (:func:`noise_clusters`: fewer than ``noise_cover`` of their points per
   table point inside their footprint), unless nothing else is left. Clusters of at least
   ``merge_min_points`` points within ``merge_gap`` of the chosen one join it (the object's own
   occlusion cuts a handle off its body), and with a viewpoint those within ``hidden_gap``
   whose image touches the object's (:func:`merge_hidden`), unless both stand on the table
   (``stand_height``: then they are two objects).
   Before that, clusters at least ``background_span`` across are searched for background
   planes (:func:`background_planes`: a wall behind the table, a shelf board; flat, at least
   ``background_span`` by ``background_width``), whose points are set aside and the rest
   clustered anew; when the object then stands on such a plane and not on the plane found
   first (a wall seen larger than the table), the scene is segmented again on that plane.
4. **The object's foot**: the object's points inside the band (the bottom of its walls, within
   the noise of the table) are given back to the object: band points whose projection on the
   plane lies within ``max(band, foot_radius)`` of the projection of one of the object's points
   in the lowest ``foot_height`` above the band (a vertical wall continues straight down).
   Points above the band with fewer than ``min_neighbours`` others near them (the noise tail of
   the table) and points below the band are neither table nor object.

:func:`remove_outliers` is the statistical outlier removal (PCL's ``StatisticalOutlierRemoval``):
a point whose mean distance to its ``k`` nearest neighbours exceeds the mean of that over the
cloud by ``std_ratio`` standard deviations goes.

Frames: the points' own (camera frame for a depth image, world for a PCD); the plane is returned
as a :class:`~pregrasp_core.facemask.SupportPlane` in that frame, ready for
``FaceMaskParams(up=tuple(plane.normal), support_height=plane.height)``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import Delaunay, QhullError, cKDTree

from ..errors import DegenerateGeometryError, InputError
from ..facemask import SupportPlane
from ..geometry import as_points
from ..limits import (
    MAX_LENGTH,
    MAX_MIN_POINTS,
    MAX_NEIGHBOURS,
    MAX_RANSAC_ITERATIONS,
    MAX_SEED,
    MAX_SIGMAS,
    MAX_SPACINGS,
    check_int,
    check_real,
)
from ..tolerances import GEOM_EPS
from .completion import VisibilityMap

logger = logging.getLogger(__name__)

IMAGE_BIN_FACTOR: float = 1.5
"""Side of the image bins of ``hidden_gap``'s test, in median point spacings."""

FOOT_NEIGHBOURS: int = 16
"""Nearest points whose median height decides a band point of the raised foot."""

MAD_TO_SIGMA: float = 1.4826
"""Median absolute deviation to standard deviation for Gaussian residuals."""

NO_TABLE_BEHIND: float = 0.05
"""When nothing stands above the plane found and more than this fraction of the points lies
behind it (the side away from the camera, which a table hides), the plane is not a table: it
cuts through an object seen alone (:class:`NoTableError`)."""


class NoTableError(InputError):
    """A view with no table in it: the plane the search found cuts through the object (a view of
    the object alone, cut out of its scene). The loader reads such a view as one object seen
    from its camera when the scene was only inferred (a PCD's ``VIEWPOINT``, a depth image)."""

    def __init__(self, message: str, behind: int = 0) -> None:
        super().__init__(message)
        self.behind = int(behind)
        """Points behind the plane found."""


@dataclass(frozen=True)
class SegmentParams:
    """Parameters of :func:`segment_table` (metres unless said)."""

    ransac_threshold: float = 0.01
    """Inlier distance of the RANSAC search (larger than the sensor noise along the normal)."""
    iterations: int = 200
    """Random planes tried."""
    sample: int = 5000
    """Points (a seeded random subset) the planes are scored on."""
    band_sigmas: float = 3.0
    """The table is the band within this many residual standard deviations of the plane."""
    min_band: float = 0.001
    """Smallest half-width of the table band (noise-free clouds)."""
    cluster_radius: float = 0.01
    """Voxel side of the Euclidean clustering: gaps wider than about this split clusters."""
    min_cluster: int = 50
    """Clusters with fewer points are never the object."""
    foot_height: float = 0.003
    """Height above the band of the object's points whose footprint claims the band points."""
    foot_radius: float = 0.001
    """Band points closer than ``max(band, foot_radius)`` to that footprint (along the plane)
    are the object's."""
    merge_gap: float = 0.02
    """Clusters of at least ``merge_min_points`` points that come within this of the chosen one
    join it: parts of the object cut off by its own occlusion (a mug's handle seen past the
    body). Objects standing closer than this are one object (0: off)."""
    merge_min_points: int = 10
    """Smallest cluster that ``merge_gap`` and ``hidden_gap`` merge (keeps clumps of table noise
    out)."""
    hidden_gap: float = 0.1
    """With a viewpoint: clusters of at least ``merge_min_points`` points that come within this
    of the object join it when their image touches the object's, seen from the camera, with no
    table seen between them: only an occlusion parts them, and nothing in the view says that
    the object does not continue behind it (a hammer's head whose junction with the handle is
    out of sight, a teddy's arm in front of its body). Objects with the table seen between them
    stay apart; one object partly hidden behind another within this distance joins it, except
    that a ``pick``ed cluster never takes in a larger one (in clutter, the can beside the picked
    ball). 0: off."""
    stand_height: float = 0.005
    """Metres above the band: a cluster with at least ``merge_min_points`` points this low
    stands on the table. ``hidden_gap`` never joins a standing cluster to a standing object:
    two things that each stand on the table are two objects, however one hides the other (a
    cut-off handle, arm or rim hangs above the table). 0: off (session 26)."""
    foot_window: float = 0.008
    """Radius of the neighbourhood whose mean height above the plane decides whether a band
    point is part of the object's foot (a bottom that leaves the table at a shallow angle)."""
    foot_sigmas: float = 4.0
    """A band point belongs to the object when the median height of its neighbours within
    ``foot_window`` exceeds ``max(foot_sigmas * 1.2533 * sigma / sqrt(count), band / 2)`` and
    it connects to the object through such points: the inside floor of a pan, a bottom that
    leaves the table at a shallow angle (0: off)."""
    min_neighbours: int = 2
    """A point above the band with fewer than this many others above the band within
    ``neighbour_spacings`` median spacings is isolated noise, not part of a cluster (0: off).
    Two, because a face seen at a grazing angle is sampled in rows of points far apart."""
    neighbour_spacings: float = 5.0
    """Radius of that neighbour count, in median nearest-neighbour spacings of the points above
    the band."""
    noise_cover: float = 0.1
    """A cluster is the table's noise tail, never the object nor merged into it, when it holds
    fewer than this many points per table point the camera saw inside its footprint (the 2D
    hull of its projection on the plane). An object hides the table under it, so its ratio is
    far above 1; the points of a noisy table's Gaussian tail that clear the band are a few per
    hundred table points, however many of them chain into one cluster (0: off)."""
    background_span: float = 0.5
    """A plane above the table whose points span at least this along one direction (and
    ``background_width`` across it) is background, not an object: a wall behind the table, a
    shelf board, a cabinet's side. No object the hand grasps has a flat face this large (the
    demo objects' largest extent is 0.36 m), while a depth camera that sees a table against a
    wall sees more wall than object. Its points are set aside (neither table nor object,
    never chosen nor merged); when the object stands on such a plane and not on the one
    found first (a wall seen larger than the table), that plane is the table (0: off)."""
    background_width: float = 0.1
    """Smallest extent of a background plane across its span: a ruler or a lath lying on the
    table (long but narrow) stays an object."""
    seed: int = 0
    """Seed of the RANSAC sampling: same seed, same result."""

    def __post_init__(self) -> None:
        # bounds: docs/limits.md ("Sensor input"); each refused value names its field
        def put(name: str, v: float | int) -> None:
            object.__setattr__(self, name, v)

        for name in ("ransac_threshold", "min_band", "cluster_radius", "foot_radius",
                     "foot_window"):  # fmt: skip
            put(name, check_real(name, getattr(self, name), 0.0, MAX_LENGTH, lo_open=True,
                                 what="a length", unit=" m"))  # fmt: skip
        for name in ("foot_height", "merge_gap", "hidden_gap", "stand_height", "background_span",
                     "background_width"):  # fmt: skip
            put(name, check_real(name, getattr(self, name), 0.0, MAX_LENGTH, what="a length",
                                 unit=" m"))  # fmt: skip
        for name in ("band_sigmas", "foot_sigmas"):
            put(name, check_real(name, getattr(self, name), 0.0, MAX_SIGMAS))
        spacings = check_real("neighbour_spacings", self.neighbour_spacings, 0.0, MAX_SPACINGS,
                              lo_open=True)  # fmt: skip
        put("neighbour_spacings", spacings)
        put("min_neighbours", check_int("min_neighbours", self.min_neighbours, 0, MAX_NEIGHBOURS))
        put("iterations", check_int("iterations", self.iterations, 1, MAX_RANSAC_ITERATIONS))
        for name in ("sample", "min_cluster", "merge_min_points"):
            put(name, check_int(name, getattr(self, name), 1, MAX_MIN_POINTS))
        put("noise_cover", check_real("noise_cover", self.noise_cover, 0.0, MAX_SPACINGS))
        put("seed", check_int("seed", self.seed, 0, MAX_SEED))


@dataclass(frozen=True)
class BackgroundPlane:
    """A plane above the table set aside as background (a wall, a board): see
    ``SegmentParams.background_span``."""

    normal: tuple[float, float, float]
    """Unit normal (its sign arbitrary)."""
    height: float
    """Offset: the plane is ``normal . x = height`` (m)."""
    span: float
    """Extent of its points along their longest direction in the plane (1st to 99th
    percentile, m)."""
    width: float
    """Extent across it (m)."""
    n_points: int
    """Points set aside with it."""
    band: float
    """Half-width of its noise band (m)."""

    def describe(self) -> str:
        """E.g. ``"a plane of 1.02 x 0.24 m (58098 points)"``."""
        return f"a plane of {self.span:.2f} x {self.width:.2f} m ({self.n_points} points)"


@dataclass(frozen=True, eq=False)
class TableSegmentation:
    """A scene cloud split into the table, the object and the rest."""

    points: np.ndarray
    """(N, 3) float64: the scene's points (the input), metres."""
    plane: SupportPlane
    """The support plane, normal toward the object side (the camera side)."""
    table_mask: np.ndarray
    """(N,) bool: the table's points (removed from the object)."""
    object_mask: np.ndarray
    """(N,) bool: the object's points (its cluster plus its foot in the table band)."""
    cluster_labels: np.ndarray
    """(N,) int64: cluster of every point above the band (0, 1, ... by decreasing size), -1 for
    the others."""
    band: float
    """Half-width of the table band, metres."""
    sigma: float
    """Robust standard deviation of the table points' distances to the plane, metres."""
    viewpoint: np.ndarray | None = None
    """(3,) the camera position in the points' frame, or None."""
    n_clusters: int = field(default=0)
    """Clusters found above the table."""
    background_mask: np.ndarray | None = None
    """(N,) bool: the points of the background planes set aside (``SegmentParams.background_span``;
    neither table nor object), or None when there are none."""
    background: tuple[BackgroundPlane, ...] = ()
    """The background planes set aside, largest first."""
    obstacle_mask: np.ndarray | None = None
    """(N,) bool: what else stands above the table (the other clusters of at least
    ``min_cluster`` points that are not the table's noise tail, and the background planes):
    the scene the hand must clear (:func:`scene_obstacles`); None when there is nothing."""

    @property
    def object_points(self) -> np.ndarray:
        """(M, 3) the object's points."""
        return self.points[self.object_mask]


def plane_from_points(points: np.ndarray) -> tuple[np.ndarray, float]:
    """Least-squares plane ``(normal (3,), height)`` of ``points`` (smallest principal axis)."""
    c = points.mean(axis=0)
    cov = (points - c).T @ (points - c)
    _, vec = np.linalg.eigh(cov)
    n = vec[:, 0]
    return n, float(n @ c)


def fit_plane_ransac(
    points: np.ndarray,
    threshold: float = 0.01,
    iterations: int = 200,
    sample: int = 5000,
    rng: np.random.Generator | None = None,
) -> tuple[np.ndarray, float, np.ndarray]:
    """The dominant plane of ``points`` (N, 3): ``(normal (3,), height, inliers (N,) bool)``.

    RANSAC over ``iterations`` seeded triplets scored on ``sample`` points, then two rounds of
    least squares on the inliers (distance < ``threshold``) of the whole cloud. The sign of the
    normal is arbitrary here (:func:`segment_table` orients it).
    """
    pts = as_points(points)
    n_pts = len(pts)
    if n_pts < 3:
        raise DegenerateGeometryError(f"a plane needs at least 3 points, got {n_pts}")
    rng = np.random.default_rng(0) if rng is None else rng
    sub = pts[rng.choice(n_pts, size=min(sample, n_pts), replace=False)]  # (S, 3)
    tri = sub[rng.integers(0, len(sub), size=(iterations, 3))]  # (I, 3, 3)
    nrm = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])  # (I, 3)
    length = np.linalg.norm(nrm, axis=1)
    good = length > GEOM_EPS * GEOM_EPS
    if not np.any(good):
        raise DegenerateGeometryError(
            "every RANSAC triplet was collinear: the points are on a line"
        )
    nrm = nrm[good] / length[good, None]
    h = np.einsum("ij,ij->i", nrm, tri[good, 0])  # (I,)
    score = (np.abs(sub @ nrm.T - h) < threshold).sum(axis=0)  # (I,) inliers in the subset
    best = int(np.argmax(score))
    n, height = nrm[best], float(h[best])
    inliers = np.abs(pts @ n - height) < threshold
    for _ in range(2):
        if inliers.sum() < 3:
            break
        n, height = plane_from_points(pts[inliers])
        inliers = np.abs(pts @ n - height) < threshold
    return n, height, inliers


def voxel_clusters(points: np.ndarray, cell: float) -> np.ndarray:
    """(N,) int64 cluster labels of ``points`` (N, 3): voxels of side ``cell`` that touch (26
    neighbours) are one cluster; labels 0, 1, ... by decreasing point count."""
    pts = as_points(points)
    if len(pts) == 0:
        return np.zeros(0, dtype=np.int64)
    ijk = np.floor((pts - pts.min(axis=0)) / cell).astype(np.int64)  # (N, 3) >= 0
    dims = ijk.max(axis=0) + 3  # room for the -1 / +1 neighbours after the +1 shift
    ijk += 1
    key = (ijk[:, 0] * dims[1] + ijk[:, 1]) * dims[2] + ijk[:, 2]
    vox, inverse = np.unique(key, return_inverse=True)  # (V,) sorted voxel keys
    inverse = inverse.reshape(-1)
    n_vox = len(vox)
    offsets = np.array(
        [
            (a, b, c)
            for a in (-1, 0, 1)
            for b in (-1, 0, 1)
            for c in (-1, 0, 1)
            if (a, b, c) > (0, 0, 0)
        ]
    )  # (13, 3) half of the 26 neighbours, fmt: skip
    off_key = (offsets[:, 0] * dims[1] + offsets[:, 1]) * dims[2] + offsets[:, 2]
    nb = vox[:, None] + off_key[None, :]  # (V, 13) neighbour keys
    pos = np.clip(np.searchsorted(vox, nb), 0, n_vox - 1)
    found = vox[pos] == nb
    rows = np.repeat(np.arange(n_vox), found.sum(axis=1))
    cols = pos[found]
    graph = coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(n_vox, n_vox))
    _, vox_label = connected_components(graph, directed=False)
    label = vox_label[inverse]
    counts = np.bincount(label)
    order = np.argsort(-counts, kind="stable")  # biggest first
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    return rank[label].astype(np.int64)


def remove_outliers(points: np.ndarray, k: int = 16, std_ratio: float = 2.0) -> np.ndarray:
    """(N,) bool, True for the points kept by statistical outlier removal (see the module)."""
    pts = as_points(points)
    if int(k) != k or k < 1:
        raise ValueError(f"k must be a positive integer, got {k!r}")
    if not (np.isfinite(std_ratio) and std_ratio > 0.0):
        raise ValueError(f"std_ratio must be positive, got {std_ratio!r}")
    if len(pts) <= k:
        raise DegenerateGeometryError(
            f"outlier removal with k={k} needs more than {k} points, got {len(pts)}"
        )
    dist, _ = cKDTree(pts).query(pts, k=int(k) + 1)  # (N, k + 1), the point itself first
    mean_d = dist[:, 1:].mean(axis=1)
    return mean_d <= mean_d.mean() + std_ratio * mean_d.std()


def noise_clusters(
    above: np.ndarray,
    lab: np.ndarray,
    clusters: np.ndarray,
    band_points: np.ndarray,
    normal: np.ndarray,
    cover: float,
) -> np.ndarray:
    """(len(clusters),) bool: which of ``clusters`` (labels into ``lab``, over the points
    ``above`` the band) are the table's noise tail: fewer than ``cover`` of their points per
    table point (``band_points``) inside their footprint, the 2D hull of their projection on the
    plane of ``normal``. A cluster whose footprint is degenerate (a line) is not noise."""
    out = np.zeros(len(clusters), dtype=bool)
    if cover <= 0.0 or len(band_points) == 0:
        return out
    B = _plane_basis(normal)  # (3, 2)
    table2 = band_points @ B
    for k, c in enumerate(clusters):  # loop over the few clusters of at least min_cluster
        q = above[lab == c] @ B
        lo, hi = q.min(axis=0), q.max(axis=0)
        box = np.all((table2 >= lo) & (table2 <= hi), axis=1)
        if not np.any(box):
            continue
        try:
            inside = Delaunay(q).find_simplex(table2[box]) >= 0
        except QhullError:  # collinear or too few distinct points: a line, not a footprint
            continue
        out[k] = len(q) < cover * int(np.count_nonzero(inside))
    return out


def merge_hidden(
    above: np.ndarray,
    lab: np.ndarray,
    mine: np.ndarray,
    counts: np.ndarray,
    viewpoint: np.ndarray,
    plane: SupportPlane,
    params: SegmentParams,
    band: float,
) -> np.ndarray:
    """``mine`` (A,) bool over the points ``above`` the band (``band`` m about the table's
    plane ``plane``; cluster labels ``lab``, sizes ``counts``) grown by the clusters that
    ``params.hidden_gap`` merges: the clusters of at least
    ``merge_min_points`` points whose image, seen from ``viewpoint``, touches the object's through
    bins where the camera saw something above the table (one 8-connected region of the
    :class:`~.completion.VisibilityMap` of the points above the band: only an occlusion parts
    them) and that come within ``hidden_gap`` of it in space. Repeated until nothing joins.
    When the object stands on the table (``params.stand_height`` above ``band``), a cluster
    that stands on it too is another object and never joins (random clutter: 6 of 60 picked
    objects took in a neighbour they partly hid or that hid them, none with this rule)."""
    vis = VisibilityMap(above, viewpoint, plane, IMAGE_BIN_FACTOR)
    region, _ = ndimage.label(np.isfinite(vis.D), structure=np.ones((3, 3), dtype=bool))
    uv, _ = vis.project(above)
    ij = vis.bins(uv)
    reg = region[ij[:, 0], ij[:, 1]]  # (A,) image region of every point
    mine = mine.copy()
    todo = [int(c) for c in np.nonzero(counts >= params.merge_min_points)[0]]
    todo = [c for c in todo if not np.any(mine & (lab == c))]
    if params.stand_height > 0.0:
        low = above @ np.asarray(plane.normal) - plane.height <= band + params.stand_height
        standing = np.bincount(lab[low], minlength=len(counts)) >= params.merge_min_points
        if np.count_nonzero(mine & low) >= params.merge_min_points:
            todo = [c for c in todo if not standing[c]]
    grown = True
    while grown and todo:  # loop over merges (at most the number of clusters)
        grown = False
        tree = cKDTree(above[mine])
        regions = np.unique(reg[mine])
        for c in list(todo):  # loop over the candidate clusters
            sel = lab == c
            if not np.any(np.isin(reg[sel], regions)):
                continue
            gap, _ = tree.query(above[sel], distance_upper_bound=params.hidden_gap)
            if np.any(np.isfinite(gap)):
                mine |= sel
                todo.remove(c)
                grown = True
    return mine


def raised_foot(
    pts: np.ndarray,
    dist: np.ndarray,
    in_band: np.ndarray,
    object_mask: np.ndarray,
    band: float,
    sigma: float,
    params: SegmentParams,
) -> np.ndarray:
    """(N,) bool: band points that belong to the object because their neighbourhood stands
    above the table (see ``SegmentParams.foot_sigmas``): the band points near the object whose
    ``FOOT_NEIGHBOURS`` nearest points within ``foot_window`` (among those from the band's
    bottom to twice its top) have a median height above the plane over
    ``max(foot_sigmas * 1.2533 * sigma / sqrt(count), band / 2)`` (1.2533: the spread of a
    median of Gaussian heights), kept when they connect to the object through such points or its
    own (steps of at most ``foot_window``)."""
    out = np.zeros(len(pts), dtype=bool)
    w = params.foot_window
    low_obj = object_mask & (dist <= 2.0 * band + w)
    if not np.any(low_obj):
        return out
    # only the surroundings of the object's lower part matter (the chain must reach it)
    lo = pts[low_obj].min(axis=0) - 3.0 * w
    hi = pts[low_obj].max(axis=0) + 3.0 * w
    zone = (dist >= -band) & (dist <= 2.0 * band) & np.all((pts >= lo) & (pts <= hi), axis=1)
    zi = np.nonzero(zone)[0]
    ci = zi[in_band[zi] & ~object_mask[zi]]
    if len(ci) == 0:
        return out
    k = min(FOOT_NEIGHBOURS, len(zi))
    d, j = cKDTree(pts[zi]).query(pts[ci], k=k, distance_upper_bound=w)  # (C, k)
    ok = np.isfinite(d)
    heights = np.where(ok, dist[zi[np.minimum(j, len(zi) - 1)]], np.nan)
    count = ok.sum(axis=1)
    med = np.nanmedian(heights, axis=1)
    thresh = np.maximum(
        params.foot_sigmas * 1.2533 * sigma / np.sqrt(np.maximum(count, 1)), 0.5 * band
    )
    cand = ci[(count >= 3) & (med > thresh)]
    if len(cand) == 0:
        return out
    obj = np.nonzero(low_obj)[0]
    nodes = np.concatenate([obj, cand])
    pairs = cKDTree(pts[nodes]).query_pairs(w, output_type="ndarray")
    graph = coo_matrix(
        (np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(nodes), len(nodes))
    )
    _, comp = connected_components(graph, directed=False)
    keep = np.isin(comp[len(obj) :], np.unique(comp[: len(obj)]))
    out[cand[keep]] = True
    return out


def _plane_basis(n: np.ndarray) -> np.ndarray:
    """(3, 2) two unit vectors spanning the plane perpendicular to ``n``."""
    a = np.eye(3)[int(np.argmin(np.abs(n)))]
    e1 = np.cross(n, a)
    e1 /= np.linalg.norm(e1)
    return np.stack([e1, np.cross(n, e1)], axis=1)


def segment_table(
    points: np.ndarray,
    viewpoint: np.ndarray | tuple[float, float, float] | None = None,
    pick: np.ndarray | tuple[float, float, float] | None = None,
    params: SegmentParams | None = None,
    side: np.ndarray | tuple[float, float, float] | None = None,
) -> TableSegmentation:
    """Find the table in a scene cloud and the object standing on it (see the module).

    Which side of the plane the object is on: the camera's (``viewpoint``); without one, the
    side along ``side`` (a complete scene's up) unless the plane is within 60 degrees of
    parallel to it; else the side with more points. When the plane found first is not what
    the object stands on but one of the background planes above it is (a wall seen larger than
    the table: the table is then a plane above the wall, on the camera's side), the scene is
    segmented again on that plane."""
    params = SegmentParams() if params is None else params
    pts = as_points(points)
    if not np.all(np.isfinite(pts)):
        raise InputError("segment_table: the points hold NaN or infinite coordinates; drop them")
    vp = None
    if viewpoint is not None:
        vp = np.asarray(viewpoint, dtype=np.float64)
        if vp.shape != (3,) or not np.all(np.isfinite(vp)):
            raise ValueError(f"viewpoint must be a finite 3-vector, got {viewpoint!r}")
    up = None if side is None else np.asarray(side, dtype=np.float64)
    rng = np.random.default_rng(params.seed)
    n, h, inl = fit_plane_ransac(
        pts, params.ransac_threshold, params.iterations, params.sample, rng
    )
    seg = _segment_on(pts, n, h, inl, vp, pick, params, up, rng)
    support = _support_plane(seg, params)
    if support is not None:
        n2 = np.asarray(support.normal, dtype=np.float64)
        inl2 = np.abs(pts @ n2 - support.height) < params.ransac_threshold
        try:
            seg2 = _segment_on(pts, n2, support.height, inl2, vp, pick, params, up, rng)
        except InputError:
            seg2 = None
        if seg2 is not None and _stands_on(seg2, params):
            logger.info(
                "table: the object stands on %s above the plane found first, not on that "
                "plane: the table is that plane", support.describe(),
            )  # fmt: skip
            seg = seg2
    logger.info(
        "table: normal %s height %.4f m, sigma %.2g m, %d table points, object %d points "
        "(%d clusters, %d background planes)",
        np.round(seg.plane.normal, 4).tolist(), seg.plane.height, seg.sigma,
        int(seg.table_mask.sum()), int(seg.object_mask.sum()), seg.n_clusters,
        len(seg.background),
    )  # fmt: skip
    return seg


def _stands_on(seg: TableSegmentation, params: SegmentParams) -> bool:
    """Whether the object of ``seg`` reaches its plane: some point within the band plus one
    cluster voxel (its foot, or its bottom when the foot was a background plane's)."""
    obj = seg.points[seg.object_mask]
    if len(obj) == 0:
        return False
    d = obj @ seg.plane.normal - seg.plane.height
    return float(np.min(np.abs(d))) <= seg.band + params.cluster_radius


def _support_plane(seg: TableSegmentation, params: SegmentParams) -> BackgroundPlane | None:
    """The background plane the object of ``seg`` stands on when it does not stand on
    ``seg.plane`` (within the plane's band plus one cluster voxel), the largest of those;
    None otherwise."""
    if not seg.background or _stands_on(seg, params):
        return None
    obj = seg.points[seg.object_mask]
    for b in seg.background:  # largest first; a few planes at most
        d = obj @ np.asarray(b.normal) - b.height
        if float(np.min(np.abs(d))) <= b.band + params.cluster_radius:
            return b
    return None


def _segment_on(
    pts: np.ndarray,
    n: np.ndarray,
    h: float,
    inl: np.ndarray,
    vp: np.ndarray | None,
    pick: np.ndarray | tuple[float, float, float] | None,
    params: SegmentParams,
    up: np.ndarray | None,
    rng: np.random.Generator,
) -> TableSegmentation:
    """:func:`segment_table` on the plane ``n . x = h`` (inliers ``inl`` within the RANSAC
    threshold): its noise band, its side, the clusters above it, the object and its foot."""
    res = pts[inl] @ n - h
    sigma = MAD_TO_SIGMA * float(np.median(np.abs(res - np.median(res))))
    band = max(params.band_sigmas * sigma, params.min_band)
    in_band = np.abs(pts @ n - h) <= band
    if in_band.sum() >= 3:
        n, h = plane_from_points(pts[in_band])
    dist = pts @ n - h
    if vp is not None:
        flip = float(vp @ n - h) < 0.0
    elif up is not None and abs(float(n @ up)) >= 0.5 * float(np.linalg.norm(up)):
        flip = float(n @ up) < 0.0
    else:
        flip = int(np.sum(dist < -band)) > int(np.sum(dist > band))
    if flip:
        n, h, dist = -n, -h, -dist
    in_band = np.abs(dist) <= band
    above = np.nonzero(dist > band)[0]
    if len(above) and params.min_neighbours > 0:
        # isolated points above the band (the table's noise tail) are nobody's
        tree = cKDTree(pts[above])
        spacing, _ = tree.query(pts[above[:: max(1, len(above) // 2000)]], k=2)
        r = params.neighbour_spacings * float(np.median(spacing[:, 1]))
        count = tree.query_ball_point(pts[above], r, return_length=True) - 1  # not itself
        above = above[count >= params.min_neighbours]
    labels = np.full(len(pts), -1, dtype=np.int64)
    object_mask = np.zeros(len(pts), dtype=bool)
    background_mask: np.ndarray | None = None
    obstacle_mask: np.ndarray | None = None
    planes: tuple[BackgroundPlane, ...] = ()
    n_clusters = 0
    if len(above):
        lab = voxel_clusters(pts[above], params.cluster_radius)
        if params.background_span > 0.0:
            bg, found = background_planes(pts[above], lab, params, rng)
            if found and not _picks_background(pts[above], bg, pick):
                rest = voxel_clusters(pts[above][~bg], params.cluster_radius)
                if len(rest) and np.bincount(rest).max() >= params.min_cluster:
                    background_mask = np.zeros(len(pts), dtype=bool)
                    background_mask[above[bg]] = True
                    planes = found
                    above, lab = above[~bg], rest
                else:
                    logger.info(
                        "table: only background planes stand above the table (%s): kept as "
                        "clusters", "; ".join(b.describe() for b in found),
                    )  # fmt: skip
        labels[above] = lab
        counts = np.bincount(lab)
        n_clusters = len(counts)
        eligible = np.nonzero(counts >= params.min_cluster)[0]
        if len(eligible) == 0:
            raise InputError(
                f"no cluster of at least {params.min_cluster} points stands above the table "
                f"(largest: {counts.max()} points); is there an object in the scene?"
            )
        # clusters of the table's noise tail (a noisy sensor, a small object): set aside, unless
        # nothing else is left
        sizable = np.nonzero(counts >= params.merge_min_points)[0]
        noise = sizable[
            noise_clusters(pts[above], lab, sizable, pts[in_band], n, params.noise_cover)
        ]
        if len(noise):
            real = eligible[~np.isin(eligible, noise)]
            if len(real):
                eligible = real
                counts = counts.copy()
                counts[noise] = 0  # never merged into the object either
                logger.info(
                    "table: %d cluster(s) of %d points in all are the table's noise tail",
                    len(noise), int(np.isin(lab, noise).sum()),
                )  # fmt: skip
        if pick is None:
            chosen = int(eligible[0])
        else:
            pk = np.asarray(pick, dtype=np.float64)
            if pk.shape != (3,) or not np.all(np.isfinite(pk)):
                raise ValueError(f"pick must be a finite 3-vector, got {pick!r}")
            cand = np.isin(lab, eligible)
            d2 = np.sum((pts[above][cand] - pk) ** 2, axis=1)
            chosen = int(lab[cand][np.argmin(d2)])
        mine = lab == chosen
        if params.merge_gap > 0.0 and n_clusters > 1:
            # parts of the object that its own occlusion cut off (a handle behind the body)
            gap, _ = cKDTree(pts[above][mine]).query(
                pts[above][~mine], distance_upper_bound=params.merge_gap
            )
            near = np.bincount(lab[~mine][np.isfinite(gap)], minlength=n_clusters)
            merge = np.nonzero((near > 0) & (counts >= params.merge_min_points))[0]
            mine |= np.isin(lab, merge)
        if vp is not None and params.hidden_gap > 0.0 and n_clusters > 1:
            plane = SupportPlane(normal=n, height=h)
            # a picked part takes in what its occlusion cut off, never a larger cluster: in
            # clutter that is the object standing behind or in front of it (a can next to a
            # 4 cm ball), not a piece of the part
            joinable = counts if pick is None else np.where(counts <= counts[chosen], counts, 0)
            mine = merge_hidden(pts[above], lab, mine, joinable, vp, plane, params, band)
        others = np.isin(lab, eligible) & ~mine
        if np.any(others) or background_mask is not None:
            obstacle_mask = np.zeros(len(pts), dtype=bool)
            obstacle_mask[above[others]] = True
            if background_mask is not None:
                obstacle_mask |= background_mask
        object_mask[above[mine]] = True
        # the object's foot inside the band: band points whose neighbourhood stands above the
        # table, then the band points under the lowest slice of all that
        if params.foot_sigmas > 0.0 and np.any(in_band):
            object_mask |= raised_foot(pts, dist, in_band, object_mask, band, sigma, params)
        low = object_mask & (dist <= band + params.foot_height)
        if np.any(low) and np.any(in_band):
            B = _plane_basis(n)  # (3, 2)
            radius = max(band, params.foot_radius)
            near, _ = cKDTree(pts[low] @ B).query(pts[in_band] @ B, distance_upper_bound=radius)
            object_mask[np.nonzero(in_band)[0][np.isfinite(near)]] = True
    else:
        behind = int(np.count_nonzero(dist < -band))
        where = f"{int(in_band.sum())} of {len(pts)} points within {1000.0 * band:.1f} mm of it"
        if behind > NO_TABLE_BEHIND * len(pts):
            raise NoTableError(
                f"no table in the view: nothing stands above the plane found ({where}) and "
                f"{behind} points lie behind it, where a table would hide everything: the view "
                "holds an object alone (cut out of its scene)",
                behind,
            )
        raise InputError(
            f"nothing stands above the table: every point is on the plane found ({where}): the "
            "view holds no object"
        )
    table_mask = in_band & ~object_mask
    if obstacle_mask is not None:
        obstacle_mask &= ~object_mask  # the foot's band points are the object's
    for arr in (labels, object_mask, table_mask, background_mask, obstacle_mask):
        if arr is not None:
            arr.setflags(write=False)
    pts_ro = pts.copy()
    pts_ro.setflags(write=False)
    return TableSegmentation(
        points=pts_ro,
        plane=SupportPlane(normal=n, height=h),
        table_mask=table_mask,
        object_mask=object_mask,
        cluster_labels=labels,
        band=float(band),
        sigma=float(sigma),
        viewpoint=vp,
        n_clusters=n_clusters,
        background_mask=background_mask,
        background=planes,
        obstacle_mask=obstacle_mask,
    )


OBSTACLE_MARGIN: float = 0.3
"""Metres: the scene's other points farther than this from the object's bounding box (grown
along every axis) are not obstacles: beyond the hand's reach from any pre-grasp around it (the
hand is 0.2 m from palm base to fingertip)."""

OBSTACLE_VOXEL: float = 0.004
"""Metres: the obstacle points are thinned to one per voxel of this side; the planner and the
pool test points inside link boxes at least 20 mm wide, so a 4 mm lattice leaves no gap a link
slips through (a wall of 80,000 points becomes about 10,000)."""


def scene_obstacles(
    seg: TableSegmentation,
    near: np.ndarray,
    margin: float = OBSTACLE_MARGIN,
    voxel: float = OBSTACLE_VOXEL,
) -> np.ndarray:
    """(K, 3) the scene's obstacles near an object: the points of ``seg.obstacle_mask`` inside
    the bounding box of ``near`` (the object's points, completed or not) grown by ``margin``,
    one per ``voxel`` (the first in the points' order); empty when there are none."""
    if seg.obstacle_mask is None or len(near) == 0:
        return np.zeros((0, 3))
    pts = seg.points[seg.obstacle_mask]
    lo, hi = near.min(axis=0) - margin, near.max(axis=0) + margin
    pts = pts[np.all((pts >= lo) & (pts <= hi), axis=1)]
    if len(pts) == 0:
        return np.zeros((0, 3))
    ijk = np.floor((pts - lo) / voxel).astype(np.int64)
    _, first = np.unique(ijk, axis=0, return_index=True)
    return pts[np.sort(first)]


def _picks_background(
    above: np.ndarray, bg: np.ndarray, pick: np.ndarray | tuple[float, float, float] | None
) -> bool:
    """Whether ``pick`` asks for a background plane: the point above the table nearest it is
    one of the plane's (the user pointed at the board: it is kept as a cluster)."""
    if pick is None or not np.any(bg):
        return False
    pk = np.asarray(pick, dtype=np.float64)
    if pk.shape != (3,) or not np.all(np.isfinite(pk)):
        raise ValueError(f"pick must be a finite 3-vector, got {pick!r}")
    return bool(bg[int(np.argmin(np.sum((above - pk) ** 2, axis=1)))])


MAX_BACKGROUND_PLANES: int = 4
"""Background planes looked for per cluster (a corner shows two walls and a shelf board)."""


def background_planes(
    above: np.ndarray, lab: np.ndarray, params: SegmentParams, rng: np.random.Generator
) -> tuple[np.ndarray, tuple[BackgroundPlane, ...]]:
    """``(mask (A,) bool, planes)``: the points of ``above`` (cluster labels ``lab``) on
    background planes (``SegmentParams.background_span``) and those planes, largest first.

    Each cluster at least ``background_span`` across (its bounding box's diagonal) is searched
    for its dominant plane by RANSAC, with the table's rules (the band ``band_sigmas`` robust
    deviations of the plane's inliers, at least ``min_band``); when the band's points span
    ``background_span`` by ``background_width`` (1st to 99th percentile along their principal
    directions in the plane) they are set aside and the rest of the cluster searched again, up
    to :data:`MAX_BACKGROUND_PLANES` times. A wall with an object leaning on it loses its plane
    and keeps the object; a box's face, a pan's bottom, a ruler are smaller. The points set
    aside are those within twice the band (the plane's noise tail with it)."""
    mask = np.zeros(len(above), dtype=bool)
    planes: list[BackgroundPlane] = []
    if len(lab) == 0:
        return mask, ()
    counts = np.bincount(lab)
    for c in np.nonzero(counts >= params.min_cluster)[0]:  # loop over the clusters
        members = np.flatnonzero(lab == c)
        if float(np.linalg.norm(np.ptp(above[members], axis=0))) < params.background_span:
            continue
        for _ in range(MAX_BACKGROUND_PLANES):
            m = members[~mask[members]]
            if len(m) < params.min_cluster:
                break
            q = above[m]
            n, h, inl = fit_plane_ransac(
                q, params.ransac_threshold, params.iterations, params.sample, rng
            )
            res = q[inl] @ n - h
            sigma = MAD_TO_SIGMA * float(np.median(np.abs(res - np.median(res))))
            band = max(params.band_sigmas * sigma, params.min_band)
            on = np.abs(q @ n - h) <= band
            if on.sum() < params.min_cluster:
                break
            flat = (q[on] - q[on].mean(axis=0)) @ _plane_basis(n)  # (K, 2)
            _, vecs = np.linalg.eigh(flat.T @ flat)
            along = flat @ vecs  # principal directions, smallest first
            lo, hi = np.percentile(along, [1.0, 99.0], axis=0)
            width, span = (float(v) for v in hi - lo)
            if span < params.background_span or width < params.background_width:
                break
            # set aside with the plane: its Gaussian tail out to twice the band (a few
            # hundred points of a wall that would otherwise come back as a second plane)
            aside = np.abs(q @ n - h) <= 2.0 * band
            mask[m[aside]] = True
            planes.append(
                BackgroundPlane(
                    normal=(float(n[0]), float(n[1]), float(n[2])),
                    height=float(h),
                    span=span,
                    width=width,
                    n_points=int(aside.sum()),
                    band=float(band),
                )  # fmt: skip
            )
    planes.sort(key=lambda b: -b.n_points)
    return mask, tuple(planes)
