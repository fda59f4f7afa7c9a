"""Completion of a single view by symmetry, checked against what the camera saw.

A depth camera sees the front of an object; the back is unseen. After Bohg et al., "Mind the
gap - robotic grasping under incomplete observation" (ICRA 2011), the object is assumed
symmetric and the visible points are copied by a symmetry whose parameters are searched under
the visibility constraint: **a copied point must not lie where the camera saw free space**. The
decision and its reasons are in ``docs/partial-views.md``; this module implements it.

Symmetries tried (every one keeps the support plane, so the copy stands on the table too):

- ``"rotation"``: a half turn about an axis along the plane's normal through a point ``c`` of the
  plane (2 parameters, ``c``): ``q = c + 2 ((p - c) . n) n - (p - c)``. Right for boxes,
  cylinders, bottles, bowls, whatever their orientation on the table.
- ``"mirror"``: a reflection in a plane perpendicular to the table, whose normal makes an angle
  ``theta`` in ``MIRROR_ANGLES`` with the horizontal viewing direction, at offset ``rho``
  (1 parameter per angle): Bohg et al.'s hypothesis. Right for objects with one symmetry plane
  (a mug whose handle is seen from the side).

Free space (:class:`VisibilityMap`): the visible points are binned by their direction from the
viewpoint (a virtual pinhole image centred on the object, bins ``bin_factor`` point spacings
wide); a bin with points saw the object at the nearest point's range ``D`` (an empty bin with
at least ``HOLE_NEIGHBOURS`` of its 8 neighbours seen is a hole between points and takes their
nearest range); every other bin saw the table or nothing. A copied point ``q`` **violates** the
view when it lies more than ``tolerance`` below the table, or in a bin without object, or closer
to the camera than ``D - tolerance``.

Search: for each family, a coarse grid of the parameters over the object's size, refined twice
around the best (21 x 21, then 11 x 11 at 1/5 and 1/25 of the step for the rotation; 41, then 11
and 11 offsets per mirror angle), scored by the mean of ``min(excess, tolerance) / tolerance``
over the copied points (a seeded subset of ``score_points``), where ``excess`` is how far a copy
lies in front of the seen surface or below the table (0 when hidden, inf in free space): a
continuous score, so that the tolerance does not let the copy slide toward the camera. At every
level the chosen candidate is, among those within ``score_slack`` of the lowest score, the one
whose copy lies nearest the camera (the smallest object the view allows). Between the families'
winners within ``family_slack`` of the best, the one whose copy adds the most unseen points
(copied points that are neither dropped nor within a spacing of a visible point; a mirror
parallel to the view only maps the front onto itself) wins, and among those within
``NEW_SLACK`` of it the smallest footprint (convex hull area of the completed points on the
table).

The completed cloud is the visible points plus the copies that do not violate the view and are
not within half a spacing of a visible point (parts the symmetry maps onto seen surface), those
flagged ``assumed``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from scipy.spatial import ConvexHull, cKDTree

from ..errors import DegenerateGeometryError
from ..facemask import SupportPlane
from ..geometry import as_points

logger = logging.getLogger(__name__)

MIRROR_ANGLES: tuple[float, ...] = tuple(
    np.radians([0.0, 30.0, 45.0, 60.0, 90.0, 120.0, 135.0, 150.0])
)
"""Radians: mirror-plane normals tried, measured from the horizontal viewing direction."""

HOLE_NEIGHBOURS: int = 6
"""An empty visibility bin with at least this many of its 8 neighbours seen is a hole in the
sampling and counts as seen."""

NEW_SLACK: float = 0.05
"""Symmetries whose share of new (unseen) copied points is within this of the largest are
equally good; the smallest footprint among them wins."""


@dataclass(frozen=True)
class CompletionParams:
    """Parameters of :func:`complete_view` (metres unless said)."""

    tolerance: float = 0.003
    """A copied point may lie this much in front of the seen surface or below the table (the
    noise of the view; raise it to about 3 sigma of a noisy sensor)."""
    bin_factor: float = 1.5
    """Side of a visibility bin, in median point spacings."""
    score_points: int = 1500
    """Visible points (a seeded subset) copied to score a candidate."""
    score_slack: float = 0.002
    """Candidates of one family whose score is within this of the family's best are equally good
    (the nearest to the camera is taken)."""
    family_slack: float = 0.02
    """Families' winners whose score is within this of the best winner compete on how much of
    the unseen they explain (a mirror that maps the front onto itself scores low but adds
    nothing)."""
    seed: int = 0
    """Seed of the scoring subset."""

    def __post_init__(self) -> None:
        for name in ("tolerance", "bin_factor", "score_slack", "family_slack"):
            v = float(getattr(self, name))
            if not (np.isfinite(v) and v > 0.0):
                raise ValueError(f"{name} must be positive, got {v!r}")
            object.__setattr__(self, name, v)
        if int(self.score_points) != self.score_points or self.score_points < 10:
            raise ValueError(f"score_points must be an integer >= 10, got {self.score_points!r}")


@dataclass(frozen=True, eq=False)
class CompletedView:
    """A single view completed by symmetry."""

    points: np.ndarray
    """(N + M, 3) float64: the N visible points, then the M assumed (copied) ones; the input's
    frame, metres."""
    assumed: np.ndarray
    """(N + M,) bool: True for the assumed points (colour them apart in the viewer)."""
    source: np.ndarray
    """(N + M,) int64: the visible point each point comes from (itself for the visible ones), so
    that per-point data follows the copy: e.g. normals ``normals[source] @ transform[:3, :3].T``
    (an isometry maps outward normals to outward normals)."""
    kind: str
    """The symmetry used: ``"rotation"`` or ``"mirror"``."""
    transform: np.ndarray
    """(4, 4) the symmetry as a matrix acting on homogeneous points (det of the 3 x 3 block is
    +1 for the rotation, -1 for the mirror)."""
    violation: float
    """Share of the copied points dropped because the camera saw free space there."""
    viewpoint: np.ndarray
    """(3,) the camera position used."""

    @property
    def n_visible(self) -> int:
        """Number of visible points N."""
        return int(np.count_nonzero(~self.assumed))


class VisibilityMap:
    """What the camera saw along each direction: the object's nearest range, or free space."""

    def __init__(self, points: np.ndarray, viewpoint: np.ndarray, plane: SupportPlane,
                 bin_factor: float) -> None:  # fmt: skip
        self.viewpoint = viewpoint
        self.plane = plane
        centre = points.mean(axis=0)
        f = centre - viewpoint
        f /= np.linalg.norm(f)
        a = plane.normal if abs(float(f @ plane.normal)) < 0.99 else np.eye(3)[np.argmin(np.abs(f))]
        r = np.cross(f, a)
        r /= np.linalg.norm(r)
        self.R = np.stack([r, np.cross(f, r), f], axis=1)  # (3, 3) virtual camera axes (columns)
        d, _ = cKDTree(points).query(points, k=2)
        self.spacing = float(np.median(d[:, 1]))
        uv, rng = self.project(points)
        depth = float(np.median(rng))
        self.cell = bin_factor * max(self.spacing, 1e-6) / depth  # normalised image units
        self.lo = uv.min(axis=0) - 3 * self.cell
        ij = self.bins(uv)
        self.shape = tuple(int(x) + 3 for x in ij.max(axis=0))
        D = np.full(self.shape, np.inf)
        np.minimum.at(D, (ij[:, 0], ij[:, 1]), rng)
        # fill holes: an empty bin with at least HOLE_NEIGHBOURS of its 8 neighbours seen takes
        # their nearest range (the silhouette does not grow: outside an edge only 3 are seen)
        pad = np.pad(D, 1, constant_values=np.inf)
        nbrs = np.stack(
            [
                pad[1 + a : 1 + a + self.shape[0], 1 + b : 1 + b + self.shape[1]]
                for a in (-1, 0, 1)
                for b in (-1, 0, 1)
                if (a, b) != (0, 0)
            ]
        )  # (8, H, W) fmt: skip
        seen = np.isfinite(nbrs).sum(axis=0)
        near = np.where(np.isfinite(D) | (seen < HOLE_NEIGHBOURS), D, nbrs.min(axis=0))
        self.D = near

    def project(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """((..., 2) normalised image coordinates, (...,) range) of points ``q`` (..., 3)."""
        qc = (q - self.viewpoint) @ self.R  # (..., 3) virtual camera frame
        z = np.maximum(qc[..., 2], 1e-9)
        return qc[..., :2] / z[..., None], np.linalg.norm(qc, axis=-1)

    def bins(self, uv: np.ndarray) -> np.ndarray:
        """(..., 2) int64 bin indices (row, column) of image coordinates ``uv`` (..., 2)."""
        return np.floor((uv - self.lo) / self.cell).astype(np.int64)

    def excess(self, q: np.ndarray) -> np.ndarray:
        """(...,) metres by which the points ``q`` (..., 3) contradict the view: how far they lie
        in front of the seen surface or below the table (0 when hidden behind the seen surface),
        inf where the camera saw past them (free space, behind the camera)."""
        uv, rng = self.project(q)
        ij = self.bins(uv)
        inside = np.all((ij >= 0) & (ij < np.array(self.shape)), axis=-1)
        ijc = np.where(inside[..., None], ij, 0)
        D = np.where(inside, self.D[ijc[..., 0], ijc[..., 1]], np.inf)
        above = self.plane.signed_distance(q.reshape(-1, 3)).reshape(q.shape[:-1])
        behind_camera = ((q - self.viewpoint) @ self.R)[..., 2] <= 0.0
        ex = np.maximum(np.maximum(D - rng, -above), 0.0)
        return np.where(np.isfinite(D) & ~behind_camera, ex, np.inf)

    def violates(self, q: np.ndarray, tolerance: float) -> np.ndarray:
        """(...,) bool: the points ``q`` (..., 3) contradict the view by more than ``tolerance``
        (they lie where the camera saw free space)."""
        return self.excess(q) > tolerance


def _rotations(points: np.ndarray, n: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """(C, P, 3) half turns of ``points`` (P, 3) about the axes along ``n`` through ``centres``
    (C, 3)."""
    v = points[None, :, :] - centres[:, None, :]  # (C, P, 3)
    return centres[:, None, :] + 2.0 * (v @ n)[..., None] * n - v


def _mirrors(points: np.ndarray, m: np.ndarray, rho: np.ndarray) -> np.ndarray:
    """(C, P, 3) reflections of ``points`` (P, 3) in the planes ``m . x = rho`` (C,)."""
    s = points @ m  # (P,)
    return points[None] - 2.0 * (s[None, :] - rho[:, None])[..., None] * m


def _pick(score: np.ndarray, depth: np.ndarray, slack: float) -> int:
    """Index of the candidate nearest the camera among those within ``slack`` of the best."""
    ok = score <= score.min() + slack
    return int(np.argmin(np.where(ok, depth, np.inf)))


def complete_view(
    points: np.ndarray,
    viewpoint: np.ndarray | tuple[float, float, float],
    plane: SupportPlane,
    params: CompletionParams | None = None,
) -> CompletedView:
    """Complete the visible object points ``points`` (N, 3) seen from ``viewpoint`` (3,) standing
    on ``plane`` (normal toward the object) by the best symmetry (see the module)."""
    params = CompletionParams() if params is None else params
    pts = as_points(points)
    if len(pts) < 10:
        raise DegenerateGeometryError(f"completion needs at least 10 points, got {len(pts)}")
    vp = np.asarray(viewpoint, dtype=np.float64)
    if vp.shape != (3,) or not np.all(np.isfinite(vp)):
        raise ValueError(f"viewpoint must be a finite 3-vector, got {viewpoint!r}")
    if float(plane.signed_distance(vp[None])[0]) <= 0.0:
        raise ValueError("the viewpoint is not above the support plane (its normal must face it)")
    n = plane.normal
    vis = VisibilityMap(pts, vp, plane, params.bin_factor)
    tol = params.tolerance
    rng = np.random.default_rng(params.seed)
    sub = pts[rng.choice(len(pts), size=min(params.score_points, len(pts)), replace=False)]

    # plane coordinates: e1 = horizontal viewing direction, e2 = n x e1
    centre = pts.mean(axis=0)
    view = centre - vp
    e1 = view - (view @ n) * n
    if np.linalg.norm(e1) < 1e-9:  # camera straight above: any horizontal direction
        e1 = np.cross(n, np.eye(3)[int(np.argmin(np.abs(n)))])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n, e1)
    foot = pts - np.outer(plane.signed_distance(pts), n)  # (N, 3) on the plane
    c0 = foot.mean(axis=0)
    size = float(np.max(np.ptp(np.stack([foot @ e1, foot @ e2], axis=1), axis=0)))
    size = max(size, 10 * vis.spacing)

    def depth_of(copies: np.ndarray) -> np.ndarray:
        return np.linalg.norm(copies.mean(axis=1) - vp, axis=1)  # (C,) range of each copy

    def score_of(copies: np.ndarray) -> np.ndarray:
        return np.minimum(vis.excess(copies), tol).mean(axis=1) / tol  # (C,) in [0, 1]

    finalists: list[tuple[str, np.ndarray, float]] = []  # (kind, 4x4, score)

    # --- half turn about an axis along n: search its foot point (2 parameters)
    best = c0
    step = size / 10.0
    for half, k in ((10, step), (5, step / 5.0), (5, step / 25.0)):
        g = np.arange(-half, half + 1) * k
        a, b = np.meshgrid(g, g, indexing="ij")
        centres = best + a.reshape(-1, 1) * e1 + b.reshape(-1, 1) * e2  # (C, 3)
        copies = _rotations(sub, n, centres)
        i = _pick(score_of(copies), depth_of(copies), params.score_slack)
        best = centres[i]
    M = np.eye(4)
    M[:3, :3] = 2.0 * np.outer(n, n) - np.eye(3)
    M[:3, 3] = 2.0 * best - 2.0 * (best @ n) * n
    finalists.append(("rotation", M, float(score_of(_rotations(sub, n, best[None]))[0])))

    # --- mirror planes perpendicular to the table (1 parameter per angle)
    for theta in MIRROR_ANGLES:
        m = np.cos(theta) * e1 + np.sin(theta) * e2
        rho = float(c0 @ m)
        step = size / 20.0
        for half, k in ((20, step), (5, step / 5.0), (5, step / 25.0)):
            rhos = rho + np.arange(-half, half + 1) * k
            copies = _mirrors(sub, m, rhos)
            i = _pick(score_of(copies), depth_of(copies), params.score_slack)
            rho = float(rhos[i])
        M = np.eye(4)
        M[:3, :3] = np.eye(3) - 2.0 * np.outer(m, m)
        M[:3, 3] = 2.0 * rho * m
        finalists.append(("mirror", M, float(score_of(_mirrors(sub, m, np.array([rho])))[0])))

    # --- among the best: the one that explains most of the unseen, then the smallest footprint
    top = min(s for _, _, s in finalists)
    tree = cKDTree(sub)
    ranked: list[tuple[float, float, str, np.ndarray]] = []  # (new share, area, kind, 4x4)
    logger.debug("finalists: %s", [(k, round(s, 4)) for k, _, s in finalists])
    for kind, M, s in finalists:
        if s > top + params.family_slack:
            continue
        q = sub @ M[:3, :3].T + M[:3, 3]
        q = q[~vis.violates(q, tol)]
        dup, _ = tree.query(q, distance_upper_bound=vis.spacing)
        new = float(np.mean(~np.isfinite(dup))) * len(q) / len(sub) if len(q) else 0.0
        allp = np.concatenate([sub, q]) - c0
        area = _hull_area(np.stack([allp @ e1, allp @ e2], axis=1))
        ranked.append((new, area, kind, M))
        logger.debug("  %s score %.4f new %.3f area %.5f", kind, s, new, area)
    most = max(r[0] for r in ranked)
    near_most = [r for r in ranked if r[0] >= most - NEW_SLACK]
    _, _, kind, M = min(near_most, key=lambda r: r[1])
    q = pts @ M[:3, :3].T + M[:3, 3]
    bad = vis.violates(q, tol)
    src = np.nonzero(~bad)[0]  # visible point each kept copy comes from
    if len(src):
        dup, _ = cKDTree(pts).query(q[src], distance_upper_bound=0.5 * vis.spacing)
        src = src[~np.isfinite(dup)]
    q = q[src]
    out = np.concatenate([pts, q])
    assumed = np.concatenate([np.zeros(len(pts), bool), np.ones(len(q), bool)])
    source = np.concatenate([np.arange(len(pts)), src]).astype(np.int64)
    for arr in (out, assumed, source):
        arr.setflags(write=False)
    logger.info(
        "completion: %s, %d points assumed, %.1f %% of the copy dropped as seen free",
        kind, len(q), 100.0 * float(bad.mean()),
    )  # fmt: skip
    return CompletedView(out, assumed, source, kind, M, float(bad.mean()), vp.copy())


def _hull_area(p2: np.ndarray) -> float:
    """Area of the 2-D convex hull of ``p2`` (P, 2) (0 when degenerate)."""
    try:
        return float(ConvexHull(p2).volume)
    except Exception:  # qhull: fewer than 3 points or collinear
        return 0.0
