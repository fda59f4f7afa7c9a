"""Surface normals of a point cloud by local PCA, oriented outwards.

Estimation: the normal is the eigenvector of the smallest eigenvalue of the covariance of a
point's nearest neighbours (the point itself included); ``curvature`` = l3 / (l1 + l2 + l3)
("surface variation", 0 on a plane, 1/3 for isotropic noise) says how reliable each normal is.

* With reference normals or a viewpoint (mesh-sampled clouds, single views): the ``k`` nearest
  neighbours (the exact grid search below, which gives ``scipy.spatial.cKDTree``'s rows in
  half its time) and the closed-form 3x3 eigenproblem of the kernels below (the vectors of
  ``numpy.linalg.eigh`` to about 1e-15, in an eighth of its time; a test checks them against
  it).
* Without (the clouds the orientation below has to work for): scale selection over k/2, 3k/4, k
  and 3k/2 neighbours (:func:`pca_scales_of`), keeping the smallest neighbourhood whose surface
  variation is below ``SCALE_FLAT`` (else the largest). A rim or lip a few millimetres thick
  looks curved at k neighbours, its normal then lies across the truth, while a sheet thinner
  than the point spacing (both faces sampled) only looks flat at the largest scale. The
  neighbours come from an exact grid search and the 3x3 eigenproblems from a closed form,
  compiled (:mod:`pregrasp_core.normal_kernels`, numba; the rows equal the k-d tree's), run on
  the usable CPUs (``threads``; a thread pool over chunks of rows, numba's own threading is not
  used): every row, and every fixed group of views of the visibility below, is computed on its
  own and summed in a fixed order, so the normals are the same, to the bit, on any number of
  threads.

Orientation (PCA gives a line, not a direction), ``NormalParams.orient``:

* ``"auto"`` (default): ``"reference"`` when the cloud carries normals (mesh-sampled clouds carry
  their face normals), else ``"viewpoint"`` when a camera position is given (single views),
  else ``"visibility"``.
* ``"reference"``: the sign that agrees with the given normals (``n . n_ref >= 0``).
* ``"viewpoint"``: every normal faces the camera at ``NormalParams.viewpoint`` (a surface a
  camera saw faces it; ``n . (viewpoint - p) >= 0``).
* ``"visibility"``: the cloud is looked at from ``n_views`` directions spread evenly on a sphere
  around it (orthographic depth buffers of 2 point spacings per pixel). A point is hidden from a
  direction when it lies behind the tangent plane of its pixel's front-most point, by more than
  ``VISIBILITY_DEPTH_TOL`` spacings plus what a convex surface of radius ``VISIBILITY_CURVATURE``
  spacings curves away over their distance: the back face of a wall a millimetre thick is hidden
  behind the front face's plane, where a depth tolerance would have to be a pixel deep. A seen
  surface faces the viewer, so each sighting votes for the sign of ``n . d`` weighted by ``|n .
  d|``. A point is decided when its votes agree (net over total above ``VISIBILITY_AGREEMENT``). A
  point flat at no scale (a crest: the top of a rolled rim, an edge) has no trustworthy PCA line;
  the direction from its neighbours' centroid to it becomes its normal when the same sightings see
  it from that side (net vote of that direction above the same agreement): on a convex crest it is
  the crest's normal, in a concave crease it points into the solid and the viewers see it from the
  other side. The others (points no direction sees, e.g. deep in a concavity) take the sign of their
  decided neighbours on the same side of the surface (a neighbour's say falls off as ``exp(-(h /
  SAME_SIDE_SIGMA s)^2)`` with its offset h along the normals: the other face of a thin wall has
  none), grown over the k-NN graph; what stays undecided after that is oriented by ``"propagate"``
  seeded at the decided points. Unlike the propagation alone, no single wrong step can flip a whole
  region: every region a viewer can see is decided by what it looks like from outside. Points inside
  the object (a mesh made of interpenetrating bodies has sampled faces inside the solid) are never
  seen and get the propagated sign.
* ``"propagate"``: Hoppe et al. 1992: a minimum spanning tree over the k-NN graph with edge
  weight ``1 - |n_i . n_j| + 3 |cos(edge, n_i)|`` (the tree follows smooth surface; the second
  term, our addition, keeps it from jumping across thin walls, where neighbours sit along the
  normal), seeded in every connected
  component at the point farthest from the cloud's centroid, whose normal is made to point away
  from the centroid (true for any closed surface). The sign flips along the tree are
  accumulated without a Python loop over points: a flip edge gets weight 1, a keep edge
  weight 2, and the parity of the tree-path length from the seed (Dijkstra on the tree, in C) is
  the parity of the number of flips. This orients concave and non-star-shaped surfaces (a torus,
  the inside of a mug) where the centroid rule fails.
* ``"centroid"``: each normal points away from the centroid (correct only for star-shaped clouds
  around their centroid; kept for comparison).
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components, dijkstra, minimum_spanning_tree
from scipy.spatial import cKDTree

from .errors import DegenerateGeometryError
from .geometry import as_points, as_points_like
from .limits import check_int
from .tolerances import GEOM_EPS

logger = logging.getLogger(__name__)

ORIENT_MODES = ("auto", "reference", "viewpoint", "visibility", "propagate", "centroid")

ACROSS_WEIGHT: float = 3.0
"""Weight of the edge-normal alignment term of the propagation graph (see the module docstring)."""

VISIBILITY_PIXEL: float = 2.0
"""Visibility orientation: depth-buffer pixel size in point spacings (the median distance to the
4th nearest neighbour)."""

VISIBILITY_DEPTH_TOL: float = 0.3
"""Visibility orientation: a point is hidden when it lies more than this many spacings behind
the tangent plane of its pixel's front-most point (plus the curvature allowance below)."""

VISIBILITY_CURVATURE: float = 10.0
"""Visibility orientation: radius of curvature (spacings) allowed for: a point at image
distance l from its pixel's front point may lie ``l^2 / (2 r)`` below its tangent plane."""

VISIBILITY_AGREEMENT: float = 0.3
"""Visibility orientation: a point is decided when |net vote| / total vote exceeds this."""

VISIBILITY_MIN_VOTE: float = 0.3
"""Visibility orientation: ... and its total vote (sum of |n . d| over sightings) exceeds this."""

SAME_SIDE_SIGMA: float = 0.3
"""Filling undecided points: a neighbour's weight is ``exp(-(h / (sigma s))^2)``, h its offset
along the normals (s the spacing): neighbours across a thin wall get no say."""

GRID_MAX_CELLS: int = 2_000_000
"""Neighbour search: at most this many grid cells (larger cells for sparse, spread clouds)."""

GRID_CROWDED: int = 8
"""Neighbour search: a cell may hold at most this many times k points (else smaller cells, or
the k-d tree for a clump no cell size splits)."""

GRID_MAX_RING: int = 4
"""Neighbour search: rings of cells searched before a row is handed to a k-d tree."""

FILL_ROUNDS: int = 30
"""Filling undecided points: at most this many rounds of growth over the k-NN graph."""

VISIBILITY_GROUPS: int = 4
"""Visibility orientation: the views are summed in this many groups of consecutive views (one
thread each; a fixed number, so that the sums do not depend on the threads)."""

CHUNK_MIN_ROWS: int = 512
"""Threads: work of fewer rows than this per thread runs on the calling thread."""

SCALE_FLAT: float = 0.02
"""Scale selection of the PCA (clouds without normals): the smallest neighbourhood whose surface
variation is below this is used (a rim thinner than the neighbourhood looks curved at k)."""


def pca_scales_of(k: int, n_points: int) -> tuple[int, ...]:
    """Neighbourhood sizes tried by the scale selection for base size ``k``: k/2, 3k/4, k and
    3k/2 (at least 3, at most the number of points), ascending."""
    cand = {max(3, k // 2), max(3, (3 * k) // 4), k, (3 * k + 1) // 2}
    return tuple(sorted(min(c, n_points) for c in cand))


@dataclass(frozen=True)
class NormalParams:
    """Parameters of normal estimation."""

    k: int = 16
    """Neighbours per point (the point itself included), >= 3; a cloud without normals tries
    k/2, 3k/4, k and 3k/2 per point and keeps the smallest that looks flat."""
    orient: str = "auto"
    """One of ``ORIENT_MODES`` (see the module docstring)."""
    viewpoint: tuple[float, float, float] | None = None
    """Metres, the cloud's frame: the camera that saw a single-view cloud; its normals then face
    it (``orient='auto'`` uses it when given, ``'viewpoint'`` needs it)."""
    n_views: int = 64
    """Visibility orientation: viewpoints on a sphere around the cloud, in [6, 1000]."""

    def __post_init__(self) -> None:
        object.__setattr__(self, "k", check_int("k", self.k, 3, 200))
        if not isinstance(self.orient, str) or self.orient not in ORIENT_MODES:
            raise ValueError(f"orient must be one of {ORIENT_MODES}, got {self.orient!r}")
        object.__setattr__(self, "n_views", check_int("n_views", self.n_views, 6, 1000))
        if self.viewpoint is not None:
            try:
                vp = np.asarray(self.viewpoint, dtype=np.float64)
            except (TypeError, ValueError, OverflowError):
                vp = np.full(0, np.nan)
            if vp.shape != (3,) or not np.all(np.isfinite(vp)):
                raise ValueError(f"viewpoint must be 3 finite numbers, got {self.viewpoint!r}")
            object.__setattr__(self, "viewpoint", tuple(float(v) for v in vp))
        if self.orient == "viewpoint" and self.viewpoint is None:
            raise ValueError("orient='viewpoint' needs a viewpoint")


@dataclass(frozen=True)
class CloudNormals:
    """Unit normals of a cloud, one per point."""

    normals: np.ndarray
    """(N, 3) float64 unit vectors, world frame, pointing out of the object."""
    curvature: np.ndarray
    """(N,) float64 surface variation l3 / (l1 + l2 + l3) of each neighbourhood, in [0, 1/3]."""
    orient: str
    """The orientation rule that was applied (one of ``ORIENT_MODES`` but ``'auto'``)."""
    crest: np.ndarray | None = None
    """(N,) bool: the points whose normal is the crest rule's (orientation by visibility only:
    flat at no scale, the direction away from their neighbours' centroid), None otherwise."""


def usable_cpus() -> int:
    """The CPUs this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # not on Linux
        return os.cpu_count() or 1


def _run_rows(
    fn: Callable[..., Any], n: int, threads: int, *args: Any, min_rows: int = CHUNK_MIN_ROWS
) -> None:
    """``fn(a0, a1, *args)`` over the rows [0, n) in contiguous chunks, on ``threads`` threads
    (0: the usable CPUs; at least ``min_rows`` rows per thread). The kernels write each row on
    its own, from the same inputs whatever the chunk: the result does not depend on the
    threads."""
    t = min(threads or usable_cpus(), max(1, n // min_rows))
    if t <= 1:
        fn(0, n, *args)
        return
    bounds = np.linspace(0, n, 2 * t + 1).astype(np.int64)  # 2 per thread: a slow thread lags less
    # a pool per call, its threads joined before returning: a process that forks (the planner's
    # copies of itself) must run one thread only
    with ThreadPoolExecutor(t, thread_name_prefix="normals") as ex:
        futures = [
            ex.submit(fn, int(a), int(b), *args)
            for a, b in zip(bounds[:-1], bounds[1:], strict=True)
            if b > a
        ]
        for f in futures:
            f.result()


def _plain_pca(
    points: np.ndarray, k: int, threads: int = 0
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The k nearest neighbours of every point (itself first; distances (N, k), ids (N, k)) and
    the PCA normals and surface variation of each neighbourhood, the normals of the
    ``reference`` and ``viewpoint`` rules: the exact neighbours of :func:`nearest_neighbours`
    (a compiled grid search, the k-d tree's answer: the same rows, equal distances by index;
    half the time of the tree's queries), then the covariance and its closed-form smallest
    eigenvector (:func:`~pregrasp_core.normal_kernels.pca_rows` at the one scale k) in row
    chunks on ``threads`` threads (0: the usable CPUs; both kernels run without the GIL). Each
    row is computed from the same inputs by the same operations whatever its chunk, so the
    result does not depend on the threads, to the bit (a test checks it against one call over
    all rows, and the vectors against ``numpy.linalg.eigh``)."""
    from . import normal_kernels as nk

    pts = np.ascontiguousarray(points, dtype=np.float64)
    n = len(pts)
    dist, nbr = _Grid(pts, k).query(k, threads=threads)
    normals = np.empty((n, 3))
    curvature = np.empty(n)
    scales = np.array([k], dtype=np.int64)
    _run_rows(
        lambda a0, a1: nk.pca_rows(pts, nbr, scales, 0.0, a0, a1, normals, curvature), n, threads
    )
    return dist, nbr, normals, curvature


def _orient_propagate(
    points: np.ndarray,
    normals: np.ndarray,
    nbr: np.ndarray,
    seeds: np.ndarray | None = None,
    seed_signs: np.ndarray | None = None,
) -> np.ndarray:
    """Consistent signs (N,) of ``normals`` by MST propagation (see the module docstring).

    seeds: (S,) point indices whose signs are known (``seed_signs`` (S,) of +-1; default +1, i.e.
    the seeds' normals are right as they are); every other point takes the sign carried along
    the tree from its nearest seed. Without seeds, each component is seeded at its point farthest
    from the centroid, oriented away from it."""
    n_pts, k = nbr.shape
    rows = np.repeat(np.arange(n_pts), k - 1)
    cols = nbr[:, 1:].ravel()
    dots = np.einsum("ij,ij->i", normals[rows], normals[cols])
    d = points[cols] - points[rows]
    # |cos| of the edge with the normal: ~0 along the surface, ~1 across a thin wall
    across = np.abs(np.einsum("ij,ij->i", d, normals[rows])) / np.maximum(
        np.linalg.norm(d, axis=1), GEOM_EPS
    )
    # small positive floor: zero weights would vanish from the sparse matrix
    weight = 1.0 - np.abs(dots) + ACROSS_WEIGHT * across + 1e-6
    graph = coo_matrix((weight, (rows, cols)), shape=(n_pts, n_pts)).tocsr()
    graph = graph.maximum(graph.T)  # symmetric k-NN graph
    tree = minimum_spanning_tree(graph).tocoo()
    ti, tj = tree.row, tree.col
    flip = np.einsum("ij,ij->i", normals[ti], normals[tj]) < 0.0
    parity_w = np.where(flip, 1.0, 2.0)
    ptree = coo_matrix((parity_w, (ti, tj)), shape=(n_pts, n_pts)).tocsr()
    if seeds is not None:
        sg = np.ones(len(seeds)) if seed_signs is None else np.asarray(seed_signs, np.float64)
        dist, _, source = dijkstra(
            ptree, directed=False, indices=seeds, min_only=True, return_predecessors=True
        )
        reached = source >= 0
        sign_of = np.zeros(n_pts)
        sign_of[seeds] = sg
        parity = np.rint(np.where(reached, dist, 0.0)).astype(np.int64) % 2
        out = np.where(parity == 1, -1.0, 1.0) * np.where(reached, sign_of[source], 1.0)
        return out
    n_comp, labels = connected_components(ptree, directed=False)
    centroid = points.mean(axis=0)
    far = np.linalg.norm(points - centroid, axis=1)
    # seed of each component: its point farthest from the centroid (loop over components only)
    order = np.lexsort((-far, labels))
    first = np.r_[0, np.flatnonzero(np.diff(labels[order])) + 1]
    seeds = order[first]
    dist = dijkstra(ptree, directed=False, indices=seeds, min_only=True)
    parity = np.rint(dist).astype(np.int64) % 2  # number of flips on the path, mod 2
    seed_sign = np.sign(np.einsum("ij,ij->i", normals[seeds], points[seeds] - centroid))
    seed_sign[seed_sign == 0] = 1.0
    comp_sign = np.empty(n_comp)
    comp_sign[labels[seeds]] = seed_sign
    signs = comp_sign[labels] * np.where(parity == 1, -1.0, 1.0)
    if n_comp > 1:
        logger.info("normal propagation: %d disconnected k-NN components", n_comp)
    return signs


def sphere_directions(n: int) -> np.ndarray:
    """(n, 3) unit vectors spread evenly on the sphere (Fibonacci lattice), deterministic."""
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    phi = np.pi * (1.0 + 5.0**0.5) * i
    r = np.sqrt(np.clip(1.0 - z * z, 0.0, None))
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def _view_frames(n_views: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(V, 3) view directions (towards the viewer) and two (V, 3) unit axes of each image."""
    d = sphere_directions(n_views)
    helper = np.where(np.abs(d[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    u = np.cross(d, helper)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    return d, u, np.cross(d, u)


def _visibility_votes(
    points: np.ndarray,
    normals: np.ndarray,
    spacing: float,
    n_views: int,
    second: np.ndarray | None = None,
    threads: int = 0,
    order: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Net (N,) and total (N,) votes of the sightings (see the module docstring), and the net
    votes (N,) the same sightings give the directions ``second`` (N, 3) (default: normals).
    The views in ``VISIBILITY_GROUPS`` fixed groups of consecutive views, a thread per group,
    each summing its own votes; the groups' sums are added in their order: the same sums for
    any number of threads. ``order`` (N,): a permutation of the points that keeps neighbours
    together (the grid's cell order), in which the kernel reads them (fewer cache misses); the
    votes do not depend on it (equally deep points are ranked by their index)."""
    from . import normal_kernels as nk

    if order is None:
        order = np.arange(len(points))
    rank = np.ascontiguousarray(order)
    normals = normals[order]
    second = None if second is None else second[order]
    points = points[order]
    p = np.ascontiguousarray(points - 0.5 * (points.min(axis=0) + points.max(axis=0)))
    radius = max(float(np.linalg.norm(p, axis=1).max()), GEOM_EPS)
    pix = max(VISIBILITY_PIXEL * spacing, radius * 1e-3)
    g = int(np.ceil(2.0 * radius / pix)) + 2  # pixels per side of every view's buffer
    d, u, w = _view_frames(n_views)
    nrm = np.ascontiguousarray(normals)
    sec = nrm if second is None else np.ascontiguousarray(second)
    tol, curv = VISIBILITY_DEPTH_TOL * spacing, VISIBILITY_CURVATURE * spacing
    n_groups = min(VISIBILITY_GROUPS, n_views)
    acc = np.zeros((n_groups, 3, len(p)))  # per group of views: net, total, net of `second`
    bounds = np.linspace(0, n_views, n_groups + 1).astype(np.int64)
    _run_rows(
        lambda a0, a1: [
            nk.visibility_votes(
                p, nrm, sec, d, u, w, radius, pix, g, tol, curv, rank,
                int(bounds[s]), int(bounds[s + 1]), acc[s, 0], acc[s, 1], acc[s, 2],
            )
            for s in range(a0, a1)
        ],
        n_groups,
        threads,
        min_rows=1,
    )  # fmt: skip
    net, tot, net_m = acc[0, 0].copy(), acc[0, 1].copy(), acc[0, 2].copy()
    for s in range(1, n_groups):  # the groups' sums in their order, whatever the threads
        net += acc[s, 0]
        tot += acc[s, 1]
        net_m += acc[s, 2]
    out = np.empty((3, len(points)))
    out[:, order] = (net, tot, net_m)  # back to the caller's order
    return out[0], out[1], out[2]


def _orient_visibility(
    points: np.ndarray,
    normals: np.ndarray,
    nbr: np.ndarray,
    dist: np.ndarray,
    n_views: int,
    rough: np.ndarray | None = None,
    threads: int = 0,
    order: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Normals (N, 3), their signs (N,) and which points' normal is the crest rule's (N,) bool,
    by visibility, filling and seeded propagation (see the module docstring); ``rough`` (N,)
    bool: the points flat at no scale, whose normal becomes the direction from their
    neighbours' centroid when the viewers see them from that side;
    ``threads`` those of the votes (0: the usable CPUs; the result does not depend on it),
    ``order`` the order the votes read the points in (see :func:`_visibility_votes`)."""
    from . import normal_kernels

    spacing = max(float(np.median(dist[:, min(4, dist.shape[1] - 1)])), GEOM_EPS)
    crest = None
    ridged = np.zeros(len(points), dtype=bool)
    rows = np.flatnonzero(rough) if rough is not None else np.zeros(0, dtype=np.int64)
    if len(rows):
        away = points[rows] - points[nbr[rows]].mean(axis=1)
        away /= np.maximum(np.linalg.norm(away, axis=1, keepdims=True), GEOM_EPS)
        crest = normals.copy()
        crest[rows] = away
    net, total, net_crest = _visibility_votes(
        points, normals, spacing, n_views, crest, threads, order
    )
    decided = (np.abs(net) > VISIBILITY_AGREEMENT * total) & (total > VISIBILITY_MIN_VOTE)
    sign = np.where(decided, np.sign(net), 0.0)
    if crest is not None:
        # a crest seen from the side away from its neighbours: that side is its normal
        seen = (net_crest[rows] > VISIBILITY_AGREEMENT * total[rows]) & (
            total[rows] > VISIBILITY_MIN_VOTE
        )
        ridge = rows[seen]
        normals = normals.copy()
        normals[ridge] = crest[ridge]
        decided[ridge] = True
        sign[ridge] = 1.0
        ridged[ridge] = True
    if decided.all():
        return normals, sign, ridged
    wts = normal_kernels.same_side_weights(points, normals, nbr, SAME_SIDE_SIGMA * spacing, decided)
    sign = normal_kernels.fill_signs(sign, decided, nbr, wts, FILL_ROUNDS)
    left = sign == 0.0
    if left.any():
        if not decided.any():
            return normals, _orient_propagate(points, normals, nbr), ridged
        seeds = np.flatnonzero(~left)
        prop = _orient_propagate(points, normals, nbr, seeds=seeds, seed_signs=sign[seeds])
        sign[left] = prop[left]
    logger.info(
        "visibility orientation: %.1f %% decided, %.1f %% filled, %.2f %% propagated",
        100.0 * decided.mean(),
        100.0 * (1.0 - decided.mean() - left.mean()),
        100.0 * left.mean(),
    )
    return normals, sign, ridged


class _Grid:
    """A uniform grid of cells over a cloud for exact k-nearest-neighbour queries: cubes about
    the k-th neighbour's expected distance for the ``k`` it is built for (any k may be asked)."""

    def __init__(self, points: np.ndarray, k: int) -> None:
        from . import normal_kernels as nk

        self.points = pts = np.ascontiguousarray(points, dtype=np.float64)
        self.lo = lo = pts.min(axis=0)
        extent = np.maximum(pts.max(axis=0) - lo, GEOM_EPS)
        # surface area from the cells a coarse grid occupies -> spacing -> the k-th distance
        h0 = float(np.linalg.norm(extent)) / 100.0
        area = nk.occupied_cells(pts, lo, h0) * h0 * h0
        h = max(float(np.sqrt(k * area / (np.pi * len(pts)))), GEOM_EPS)
        h_min = float(np.cbrt(np.prod(extent) / GRID_MAX_CELLS))  # bounded memory
        # far outliers inflate the estimate: halve the cells while one is crowded
        for _ in range(4):
            h = max(h, h_min)
            dims, most = nk.grid_dims(pts, lo, h)
            if most <= GRID_CROWDED * k or h <= h_min:
                break
            h *= 0.5
        self.h, self.dims = h, dims
        self.crowded = most > GRID_CROWDED * k  # a clump the grid cannot split: the k-d tree
        if not self.crowded:
            self.cell, self.order, self.start, self.ps = nk.grid_build(pts, h, lo, dims)

    def query(
        self, k: int, queries: np.ndarray | None = None, threads: int = 0
    ) -> tuple[np.ndarray, np.ndarray]:
        """Exact (Q, k) distances and indices, as :func:`nearest_neighbours`."""
        from . import normal_kernels as nk

        pts = self.points
        q = np.arange(len(pts)) if queries is None else np.asarray(queries, dtype=np.int64)
        if self.crowded:
            return _tree_rows(pts, q, k)
        qorder = nk.query_order(self.cell, self.dims, q)
        dist = np.empty((len(q), k))
        idx = np.empty((len(q), k), dtype=np.int64)
        unresolved = np.zeros(len(q), dtype=np.bool_)
        _run_rows(
            lambda a0, a1: nk.knn_rows(
                pts, self.cell, self.order, self.start, self.ps, q, qorder, a0, a1, k,
                self.h, self.lo, self.dims, GRID_MAX_RING, dist, idx, unresolved,
            ),
            len(q),
            threads,
        )  # fmt: skip
        if unresolved.any():  # outliers: a few rows
            rows = np.flatnonzero(unresolved)
            dist[rows], idx[rows] = _tree_rows(pts, q[rows], k)
        return dist, idx


def nearest_neighbours(
    points: np.ndarray, k: int, queries: np.ndarray | None = None, threads: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """Exact (Q, k) distances and indices of the k nearest neighbours of the points ``queries``
    (default: all; each row starts with the point itself, then by distance, equal distances by
    index) on a grid of cells about the k-th neighbour's expected distance; the rare rows the
    grid does not settle within a few rings (outliers) are asked of a k-d tree. ``threads``:
    0 for the usable CPUs; the rows do not depend on it."""
    return _Grid(points, k).query(k, queries, threads)


def _tree_rows(points: np.ndarray, q: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """(Q, k) distances and indices of the k nearest of ``points[q]`` by a k-d tree, as the grid
    gives them: the point itself first, then by distance computed as the grid computes it, equal
    distances by index (all the points within the tree's k-th distance are sorted so)."""
    tree = cKDTree(points)
    kth, _ = tree.query(points[q], k=[k])
    dist = np.empty((len(q), k))
    idx = np.empty((len(q), k), dtype=np.int64)
    for r, own in enumerate(q):
        near = np.asarray(tree.query_ball_point(points[own], kth[r, 0] * (1.0 + 1e-9)), np.int64)
        near = near[near != own]
        dx, dy, dz = (points[near] - points[own]).T
        d2 = dx * dx + dy * dy + dz * dz
        best = np.lexsort((near, d2))[: k - 1]
        idx[r] = np.r_[own, near[best]]
        dist[r] = np.sqrt(np.r_[0.0, d2[best]])
    return dist, idx


def scale_selected_normals(
    points: np.ndarray, k: int, threads: int = 0
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Normals (N, 3), surface variation (N,) by scale selection (:func:`pca_scales_of`), and the
    (N, k) distances and indices of the k nearest neighbours (see :func:`_scale_selected`)."""
    return _scale_selected(points, k, threads)[:4]


def _scale_selected(
    points: np.ndarray, k: int, threads: int = 0
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
    """Normals (N, 3), surface variation (N,) by scale selection (:func:`pca_scales_of`), and the
    (N, k) distances and indices of the k nearest neighbours. The largest scale's neighbours
    are searched (on the same grid) only for the points that are flat at none of the smaller
    ones. ``threads``: 0 for the usable CPUs; the result does not depend on it. Last, the
    point ids in the grid's cell order (neighbours together), or None when the grid was not
    used."""
    from . import normal_kernels as nk

    pts = np.ascontiguousarray(points, dtype=np.float64)
    scales = pca_scales_of(k, len(pts))
    small = tuple(s for s in scales if s <= k)
    grid = _Grid(pts, small[-1])
    dist, nbr = grid.query(small[-1], threads=threads)
    normals = np.empty((len(pts), 3))
    variation = np.empty(len(pts))
    sc = np.asarray(small, dtype=np.int64)
    _run_rows(
        lambda a0, a1: nk.pca_rows(pts, nbr, sc, SCALE_FLAT, a0, a1, normals, variation),
        len(pts),
        threads,
    )
    if scales[-1] > small[-1]:
        rough = np.flatnonzero(variation >= SCALE_FLAT)
        if len(rough):
            _, nbr_big = grid.query(scales[-1], rough, threads)
            n_big, v_big = nk.pca_scales(
                pts, nbr_big, np.asarray(scales[-1:], dtype=np.int64), SCALE_FLAT
            )
            normals[rough] = n_big
            variation[rough] = v_big
    order = None if grid.crowded else grid.order
    return normals, variation, dist[:, :k], nbr[:, :k], order


PLAIN_RULES: tuple[str, ...] = ("reference", "viewpoint")
"""The orientation rules whose normals are the plain PCA of the k nearest neighbours (a compiled
pass, about 30 ms of one core at 20,000 points); the others select the scale and orient by
sightings or propagation (several times that)."""


def orient_rule(params: NormalParams, has_reference: bool) -> str:
    """The rule :func:`estimate_normals` applies (``params.orient`` with 'auto' resolved: the
    reference normals when the cloud has them, else the viewpoint when given, else visibility)."""
    if params.orient != "auto":
        return params.orient
    if has_reference:
        return "reference"
    return "viewpoint" if params.viewpoint is not None else "visibility"


def estimate_normals(
    points: np.ndarray,
    params: NormalParams = NormalParams(),  # noqa: B008 (frozen, immutable)
    reference: np.ndarray | None = None,
    *,
    threads: int = 0,
) -> CloudNormals:
    """Unit outward normals of a cloud by local PCA (see the module docstring).

    points: (N, 3) metres, N > params.k; reference: (N, 3) optional normals that fix the sign
    (e.g. ``PointCloud.normals``); ``orient='auto'`` uses them when given. threads: those of the
    compiled kernels of a cloud without normals (0: the usable CPUs); the normals do not depend
    on it, to the bit.
    """
    pts = as_points(points)
    ref = None if reference is None else as_points_like(reference, pts, "reference normals")
    if len(pts) < params.k:
        raise DegenerateGeometryError(
            f"normal estimation needs at least k = {params.k} points, the cloud has {len(pts)}; "
            "use a denser cloud or a smaller k"
        )
    mode = orient_rule(params, ref is not None)
    crest = None
    if mode == "reference" and ref is None:
        raise ValueError("orient='reference' needs reference normals")
    if mode in PLAIN_RULES:
        dist, nbr, normals, curvature = _plain_pca(pts, params.k, threads)
    else:  # no normals to orient by: scale-selected PCA (thin rims), compiled kernels
        normals, curvature, dist, nbr, order = _scale_selected(pts, params.k, threads)
    if mode == "reference":
        assert ref is not None  # checked above
        signs = np.where(np.einsum("ij,ij->i", normals, ref) < 0.0, -1.0, 1.0)
    elif mode == "viewpoint":
        to_cam = np.asarray(params.viewpoint, dtype=np.float64) - pts
        signs = np.where(np.einsum("ij,ij->i", normals, to_cam) < 0.0, -1.0, 1.0)
    elif mode == "visibility":
        rough = curvature >= SCALE_FLAT
        normals, signs, crest = _orient_visibility(
            pts, normals, nbr, dist, params.n_views, rough, threads, order
        )
    elif mode == "centroid":
        out = pts - pts.mean(axis=0)
        signs = np.where(np.einsum("ij,ij->i", normals, out) < 0.0, -1.0, 1.0)
    else:
        signs = _orient_propagate(pts, normals, nbr)
    normals = normals * signs[:, None]
    return CloudNormals(normals=normals, curvature=curvature, orient=mode, crest=crest)
