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

What the camera saw (:class:`RangeImage`): the visible points in a virtual pinhole image centred
on the object, triangulated (Delaunay in the image; triangles with a 3D edge longer than
``edge_factor`` point spacings are dropped, so that no triangle bridges a depth jump or the
silhouette), rasterised on cells of ``cell_factor`` spacings: a cell inside a triangle holds
that triangle's plane of range over the image, so the seen range ``D`` at any image point is
interpolated between the points, not the nearest range of a coarse bin. A copied point ``q``
contradicts the view by its **excess**: how far it lies in front of the seen surface
(``D - range``), below the table, or, in a direction where the camera saw the table or nothing,
how far outside the seen silhouette (its lateral distance to the nearest seen cell, less half a
spacing for where the outline lies between the samples). The excess is continuous across the
silhouette: a copy a fraction of a millimetre outside the outline is not scored like one a
centimetre out, which made the old binned map (``VisibilityMap``, still used by the table's
segmentation) favour copies pulled toward the camera by up to a bin (2-3 mm).

Search: for each family, a coarse grid of the parameters over the object's size, refined twice
around the best (21 x 21, then 11 x 11 at 1/5 and 1/25 of the step for the rotation; 41, then 11
and 11 offsets per mirror angle), scored by the mean of ``min(excess, tolerance) / tolerance``
over the copied points (a seeded subset of ``score_points``). At every level the candidate with
the lowest score wins: the score has a minimum on both sides (copies pushed toward the camera
come in front of the seen surface, copies pushed away leave the silhouette or the seen top), so
the view's evidence places the copy, not a preference for the smallest object. Between the
families' winners within ``family_slack`` of the best, the ones whose copy adds the most unseen
points (within ``NEW_SLACK`` of the most; copied points that are neither dropped nor within a
spacing of a visible point: a mirror parallel to the view only maps the front onto itself)
compete on their footprint (convex hull area of the completed points on the table): among those
within ``AREA_SLACK`` of the smallest footprint, the lowest score wins (a mirror that throws a
seen handle into the hidden space behind the object has a larger footprint; symmetries of a
cylinder that all fit have nearly the same one).

The completed cloud is the visible points plus the copies that do not violate the view (excess
above ``tolerance``) and are not within half a spacing of a visible point (parts the symmetry
maps onto seen surface), those flagged ``assumed``; then the holes of the completed cloud are
closed (:func:`fill_gaps`): where two points less than ``gap_max`` apart have no point near
their midpoint, the midpoint is added, flagged ``assumed`` too, so that a finger cannot slip
between sparse points (the silhouette's grazing samples, the seams the copy leaves).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from scipy.spatial import ConvexHull, Delaunay, cKDTree

from ..errors import DegenerateGeometryError
from ..facemask import SupportPlane
from ..geometry import as_points
from ..limits import (
    MAX_FACTOR,
    MAX_LENGTH,
    MAX_MIN_POINTS,
    MAX_SEED,
    MAX_SPACINGS,
    MIN_CELL_FACTOR,
    check_int,
    check_real,
)

logger = logging.getLogger(__name__)

MIRROR_ANGLES: tuple[float, ...] = tuple(
    np.radians([0.0, 30.0, 45.0, 60.0, 90.0, 120.0, 135.0, 150.0])
)
"""Radians: mirror-plane normals tried, measured from the horizontal viewing direction."""

HOLE_NEIGHBOURS: int = 6
"""An empty bin of a :class:`VisibilityMap` with at least this many of its 8 neighbours seen is
a hole in the sampling and counts as seen."""

NEW_SLACK: float = 0.05
"""Symmetries whose share of new (unseen) copied points is within this of the largest are
equally good; the footprint decides among them."""

AREA_SLACK: float = 0.05
"""Among the symmetries left by ``NEW_SLACK``, those whose footprint is within this share of the
smallest are equally small; the lowest score wins among them."""

OUTLINE_MARGIN: float = 0.5
"""Point spacings: the seen outline is taken this far beyond the last seen cell."""

FILL_NEIGHBOURS: int = 12
"""Neighbours of every point paired with it when the holes are closed (:func:`fill_gaps`)."""

FILL_PASSES: int = 2
"""Rounds of midpoints (each round halves the chords left open)."""

FILL_PAIR: float = 3.0
"""Point spacings: pairs closer than this are neighbours on the surface, not a hole's sides."""

FILL_HOLE: float = 1.5
"""Point spacings: a midpoint with no point within this is in a hole."""

SKIRT_STEP: float = 2.0
"""Point spacings between the points of a skirt (:func:`add_skirt`) down a column, and the side
of the cubes of which each keeps at most one skirt point."""

SKIRT_COLUMN: float = 0.5
"""Point spacings: a skirt has one column per horizontal cell of this side, under the
outermost outline point of the cell."""

SKIRT_COVER: float = 1.5
"""Skirt steps: a skirt point this close to a point of the completed cloud is left out (the
copy or the view already has the wall there), and an outline point this low above the table
gets no column."""

SKIRT_NEIGHBOURS: int = 16
"""Columns of a skirt (its own and the nearest others) whose line along the table gives a
column's outward normal."""

GAP_MAX_DEFAULT: float = 0.01
"""Metres: default ``CompletionParams.gap_max``, about half a finger's width (a wider opening
may be real: the space between a handle and the body)."""


@dataclass(frozen=True)
class CompletionParams:
    """Parameters of :func:`complete_view` (metres unless said)."""

    tolerance: float = 0.003
    """A copied point may lie this much in front of the seen surface, below the table or outside
    the silhouette (the noise of the view; raise it to about 3 sigma of a noisy sensor)."""
    cell_factor: float = 0.5
    """Side of a cell of the :class:`RangeImage`, in median point spacings."""
    edge_factor: float = 3.0
    """Triangles of the range image with a 3D edge longer than this many spacings are dropped
    (they would bridge a depth jump or the silhouette)."""
    score_points: int = 1500
    """Visible points (a seeded subset) copied to score a candidate."""
    family_slack: float = 0.02
    """Families' winners whose score is within this of the best winner compete on how much of
    the unseen they explain (a mirror that maps the front onto itself scores low but adds
    nothing)."""
    gap_max: float = GAP_MAX_DEFAULT
    """Holes of the completed cloud up to about this wide are closed by midpoints
    (:func:`fill_gaps`); 0 = never."""
    seed: int = 0
    """Seed of the scoring subset."""
    skirt: float = 0.015
    """Metres: below the outline of an object seen from above, a wall this deep is assumed
    where no point is (:func:`add_skirt`; the walls under an overhead camera's outline are out
    of its sight and no symmetry copies them); 0 = never."""
    skirt_angle: float = 30.0
    """Degrees: only outline points whose camera ray is within this of the support plane's
    normal (a camera looking down on them) get a skirt; a side camera's outline keeps none, the
    symmetry copy covers its back."""

    def __post_init__(self) -> None:
        # bounds: docs/limits.md ("Sensor input"); each refused value names its field
        def put(name: str, v: float | int) -> None:
            object.__setattr__(self, name, v)

        put("tolerance", check_real("tolerance", self.tolerance, 0.0, MAX_LENGTH, lo_open=True,
                                    what="a length", unit=" m"))  # fmt: skip
        put("gap_max", check_real("gap_max", self.gap_max, 0.0, MAX_LENGTH, what="a length",
                                  unit=" m"))  # fmt: skip
        put("cell_factor", check_real("cell_factor", self.cell_factor, MIN_CELL_FACTOR,
                                      MAX_SPACINGS))  # fmt: skip
        put("edge_factor", check_real("edge_factor", self.edge_factor, 0.0, MAX_SPACINGS,
                                      lo_open=True))  # fmt: skip
        put("family_slack", check_real("family_slack", self.family_slack, 0.0, MAX_FACTOR,
                                       lo_open=True))  # fmt: skip
        put("score_points", check_int("score_points", self.score_points, 10, MAX_MIN_POINTS))
        put("seed", check_int("seed", self.seed, 0, MAX_SEED))
        put("skirt", check_real("skirt", self.skirt, 0.0, MAX_LENGTH, what="a length",
                                unit=" m"))  # fmt: skip
        put("skirt_angle", check_real("skirt_angle", self.skirt_angle, 0.0, 90.0,
                                      what="an angle", unit=" degrees"))  # fmt: skip


@dataclass(frozen=True, eq=False)
class CompletedView:
    """A single view completed by symmetry."""

    points: np.ndarray
    """(N + M, 3) float64: the N visible points, then the M assumed ones (copies, then the
    midpoints that close holes); the input's frame, metres."""
    assumed: np.ndarray
    """(N + M,) bool: True for the assumed points (colour them apart in the viewer)."""
    source: np.ndarray
    """(N + M,) int64: the visible point each point comes from (itself for the visible ones; a
    midpoint takes one end's), so that per-point data follows the copy: e.g. normals
    ``normals[source]``, moved by the symmetry where ``moved`` (``transform[:3, :3]``; an
    isometry maps outward normals to outward normals)."""
    kind: str
    """The symmetry used: ``"rotation"`` or ``"mirror"``."""
    transform: np.ndarray
    """(4, 4) the symmetry as a matrix acting on homogeneous points (det of the 3 x 3 block is
    +1 for the rotation, -1 for the mirror)."""
    violation: float
    """Share of the copied points dropped because the camera saw free space there."""
    viewpoint: np.ndarray
    """(3,) the camera position used."""
    moved: np.ndarray
    """(N + M,) bool: the points whose normal is their source's moved by the symmetry (the
    copies and the midpoints whose end is a copy)."""
    filled: np.ndarray
    """(N + M,) bool: the assumed points that close holes (midpoints, :func:`fill_gaps`)."""
    skirt: np.ndarray
    """(N + M,) bool: the assumed points of the skirt below an outline seen from above
    (:func:`add_skirt`; the last rows)."""
    skirt_normals: np.ndarray
    """(S, 3) unit outward normals of the skirt's points (the rows where ``skirt``), horizontal:
    perpendicular to the support plane's normal."""

    @property
    def copied(self) -> np.ndarray:
        """(N + M,) bool: the assumed points that are copies, ``transform`` applied to their
        source (neither midpoints nor skirt)."""
        return self.assumed & ~self.filled & ~self.skirt

    @property
    def n_visible(self) -> int:
        """Number of visible points N."""
        return int(np.count_nonzero(~self.assumed))


class _VirtualCamera:
    """A virtual pinhole camera at ``viewpoint`` looking at the points' centre, its image rows
    along the support plane (what :class:`VisibilityMap` and :class:`RangeImage` project into),
    and the points' median spacing."""

    def __init__(self, points: np.ndarray, viewpoint: np.ndarray, plane: SupportPlane) -> None:
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

    def project(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """((..., 2) normalised image coordinates, (...,) range) of points ``q`` (..., 3)."""
        qc = (q - self.viewpoint) @ self.R  # (..., 3) virtual camera frame
        z = np.maximum(qc[..., 2], 1e-9)
        return qc[..., :2] / z[..., None], np.linalg.norm(qc, axis=-1)


class VisibilityMap(_VirtualCamera):
    """What the camera saw along each direction: the object's nearest range, or free space."""

    def __init__(self, points: np.ndarray, viewpoint: np.ndarray, plane: SupportPlane,
                 bin_factor: float) -> None:  # fmt: skip
        super().__init__(points, viewpoint, plane)
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


class RangeImage(_VirtualCamera):
    """What the camera saw, interpolated: the seen range at any image point, or how far outside
    the seen silhouette it lies (see the module)."""

    def __init__(self, points: np.ndarray, viewpoint: np.ndarray, plane: SupportPlane,
                 cell_factor: float = 0.5, edge_factor: float = 3.0) -> None:  # fmt: skip
        super().__init__(points, viewpoint, plane)
        uv, rng = self.project(points)
        depth = float(np.median(rng))
        self.cell = cell_factor * max(self.spacing, 1e-6) / depth  # normalised image units
        self.lo = uv.min(axis=0) - 4 * self.cell
        ij = np.floor((uv - self.lo) / self.cell).astype(np.int64)
        self.shape = (int(ij[:, 0].max()) + 5, int(ij[:, 1].max()) + 5)
        tri = Delaunay(uv)
        s = tri.simplices  # (T, 3)
        P = points[s]
        edge = np.max(np.linalg.norm(P - np.roll(P, 1, axis=1), axis=2), axis=1)
        A = np.concatenate([np.ones((len(s), 3, 1)), uv[s]], axis=2)  # rows (1, u, v)
        keep = (edge <= edge_factor * self.spacing) & (np.abs(np.linalg.det(A)) > 1e-18)
        coef = np.zeros((len(s), 3))  # range = c0 + c1 u + c2 v over each triangle
        coef[keep] = np.linalg.solve(A[keep], rng[s[keep]][..., None])[..., 0]
        H, W = self.shape
        gi, gj = np.meshgrid(np.arange(H), np.arange(W), indexing="ij")
        centres = self.lo + (np.stack([gi, gj], axis=-1) + 0.5) * self.cell
        simp = tri.find_simplex(centres.reshape(-1, 2)).reshape(H, W)
        seen = simp >= 0
        seen[seen] = keep[simp[seen]]
        C = np.zeros((H, W, 3))
        C[seen] = coef[simp[seen]]
        # a cell holding a point but no kept triangle (a lone sample at the silhouette): the
        # nearest such point's range
        Dp = np.full((H, W), np.inf)
        np.minimum.at(Dp, (ij[:, 0], ij[:, 1]), rng)
        lone = ~seen & np.isfinite(Dp)
        C[lone, 0] = Dp[lone]
        seen |= lone
        self.seen = seen  # (H, W) bool
        self.coef = C  # (H, W, 3)
        _, near = ndimage.distance_transform_edt(~seen, return_indices=True)
        self.near = near  # (2, H, W): the nearest seen cell of every cell

    def locate(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Where the points ``q`` (..., 3) fall in the image: ``(qc (..., 3) in the virtual
        camera's frame, uv (..., 2) image coordinates, ij (..., 2) their cells (0 where off the
        image), inside (...,) bool: on the image)`` (``inside`` ignores the sign of depth)."""
        qc = (q - self.viewpoint) @ self.R
        uv = qc[..., :2] / np.maximum(qc[..., 2], 1e-9)[..., None]
        ij = np.floor((uv - self.lo) / self.cell).astype(np.int64)
        inside = np.all((ij >= 0) & (ij < np.array(self.shape)), axis=-1)
        return qc, uv, np.where(inside[..., None], ij, 0), inside

    def excess(self, q: np.ndarray) -> np.ndarray:
        """(...,) metres by which the points ``q`` (..., 3) contradict the view: how far they lie
        in front of the seen surface, below the table, or outside the seen silhouette (0 when
        hidden behind the seen surface); inf off the image or behind the camera."""
        qc, uv, ijc, inside = self.locate(q)
        z = qc[..., 2]
        zc = np.maximum(z, 1e-9)
        rng = np.linalg.norm(qc, axis=-1)
        i, j = ijc[..., 0], ijc[..., 1]
        seen = self.seen[i, j]
        c = self.coef[i, j]
        D = c[..., 0] + c[..., 1] * uv[..., 0] + c[..., 2] * uv[..., 1]
        front = np.where(seen, np.maximum(D - rng, 0.0), 0.0)
        ni, nj = self.near[0][i, j], self.near[1][i, j]
        cen = self.lo + (np.stack([ni, nj], axis=-1) + 0.5) * self.cell
        lateral = np.maximum(np.linalg.norm(uv - cen, axis=-1) - 0.5 * self.cell, 0.0) * zc
        outside = np.where(seen, 0.0, np.maximum(lateral - OUTLINE_MARGIN * self.spacing, 0.0))
        above = self.plane.signed_distance(q.reshape(-1, 3)).reshape(q.shape[:-1])
        ex = np.maximum(np.maximum(front, outside), np.maximum(-above, 0.0))
        return np.where(inside & (z > 0.0), ex, np.inf)

    def violates(self, q: np.ndarray, tolerance: float) -> np.ndarray:
        """(...,) bool: the points ``q`` (..., 3) contradict the view by more than ``tolerance``."""
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
    vis = RangeImage(pts, vp, plane, params.cell_factor, params.edge_factor)
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
        best = centres[int(np.argmin(score_of(_rotations(sub, n, centres))))]
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
            rho = float(rhos[int(np.argmin(score_of(_mirrors(sub, m, rhos))))])
        M = np.eye(4)
        M[:3, :3] = np.eye(3) - 2.0 * np.outer(m, m)
        M[:3, 3] = 2.0 * rho * m
        finalists.append(("mirror", M, float(score_of(_mirrors(sub, m, np.array([rho])))[0])))

    # --- among the best: the ones that explain most of the unseen, then the smallest
    # footprints, then the lowest score
    top = min(s for _, _, s in finalists)
    tree = cKDTree(sub)
    ranked: list[tuple[float, float, float, str, np.ndarray]] = []  # (new, area, score, kind, 4x4)
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
        ranked.append((new, area, s, kind, M))
        logger.debug("  %s score %.4f new %.3f area %.5f", kind, s, new, area)
    most = max(r[0] for r in ranked)
    near_most = [r for r in ranked if r[0] >= most - NEW_SLACK]
    smallest = min(r[1] for r in near_most)
    small = [r for r in near_most if r[1] <= smallest * (1.0 + AREA_SLACK)]
    _, _, _, kind, M = min(small, key=lambda r: r[2])
    q = pts @ M[:3, :3].T + M[:3, 3]
    bad = vis.violates(q, tol)
    src = np.nonzero(~bad)[0]  # visible point each kept copy comes from
    if len(src):
        dup, _ = cKDTree(pts).query(q[src], distance_upper_bound=0.5 * vis.spacing)
        src = src[~np.isfinite(dup)]
    q = q[src]
    out = np.concatenate([pts, q])
    source = np.concatenate([np.arange(len(pts)), src]).astype(np.int64)
    moved = np.concatenate([np.zeros(len(pts), bool), np.ones(len(q), bool)])
    n_fill = 0
    if params.gap_max > 0.0:
        out, source, moved = fill_gaps(out, source, moved, vis.spacing, params.gap_max)
        n_fill = len(out) - len(pts) - len(q)
    n_done = len(out)
    sk_points, sk_normals, sk_source = add_skirt(pts, out, vis, params)
    out = np.concatenate([out, sk_points])
    source = np.concatenate([source, sk_source])
    moved = np.concatenate([moved, np.zeros(len(sk_points), bool)])
    idx = np.arange(len(out))
    assumed = idx >= len(pts)
    filled = (idx >= len(pts) + len(q)) & (idx < n_done)
    skirt = idx >= n_done
    for arr in (out, assumed, source, moved, filled, skirt, sk_normals):
        arr.setflags(write=False)
    logger.info(
        "completion: %s, %d points assumed (%d closing holes, %d of a skirt), %.1f %% of the "
        "copy dropped as seen free", kind, len(out) - len(pts), n_fill, len(sk_points),
        100.0 * float(bad.mean()),
    )  # fmt: skip
    return CompletedView(out, assumed, source, kind, M, float(bad.mean()), vp.copy(), moved,
                         filled, skirt, sk_normals)  # fmt: skip


def add_skirt(
    visible: np.ndarray, cloud: np.ndarray, vis: RangeImage, params: CompletionParams
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(points (S, 3), outward normals (S, 3), source (S,))`` of the skirt of a view: below
    every visible point on the outer outline of the seen image (``vis.seen`` with its holes
    filled, less its erosion by a 5 x 5 cell square: below a hole in the sampling of a top face
    lies the object's inside) whose camera ray makes at most ``params.skirt_angle`` with the
    support plane's normal, the points straight down (along the normal) every ``SKIRT_STEP``
    spacings, at most ``params.skirt`` deep and not below the table; those within
    ``SKIRT_COVER`` steps of a point of ``cloud`` (the completed cloud so far) or contradicting
    the view (``vis.violates``) are left out. One column per horizontal cell of ``SKIRT_COLUMN``
    spacings (under the outermost outline point of the cell), then at most one point per cube
    of a step. The normal is horizontal, across the line of the ``SKIRT_NEIGHBOURS`` nearest
    columns, outward (where the image's distance to the unseen falls). The wall of a box, a can
    or a ramekin under an overhead camera's outline is vertical there; a bowl's or a ball's
    curves in below it, and the skirt stays short so that it does not wall off what lies under
    an overhang (``docs/partial-views.md``, "Views from above")."""
    empty = (np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, np.int64))
    if params.skirt <= 0.0:
        return empty
    n = vis.plane.normal
    step = SKIRT_STEP * vis.spacing
    ray = visible - vis.viewpoint
    ray /= np.maximum(np.linalg.norm(ray, axis=1, keepdims=True), 1e-12)
    height = vis.plane.signed_distance(visible)
    steep = -(ray @ n) >= np.cos(np.radians(params.skirt_angle))
    steep &= height > SKIRT_COVER * step
    if not np.any(steep):  # a side camera: no image work
        return empty
    qc, _, ij, inside = vis.locate(visible)
    inside &= qc[:, 2] > 0.0
    silhouette = ndimage.binary_fill_holes(vis.seen)  # the outer outline only: none in a hole
    interior = ndimage.binary_erosion(silhouette, structure=np.ones((5, 5), dtype=bool))
    on_outline = inside & silhouette[ij[:, 0], ij[:, 1]] & ~interior[ij[:, 0], ij[:, 1]]
    idx = np.nonzero(on_outline & steep)[0]
    if not len(idx):
        return empty
    depth_in = ndimage.distance_transform_edt(silhouette)
    # one column per horizontal cell of SKIRT_COLUMN spacings, under its outermost outline point
    e1 = np.cross(n, np.eye(3)[int(np.argmin(np.abs(n)))])
    e1 /= np.linalg.norm(e1)
    flat = visible[idx] @ np.stack([e1, np.cross(n, e1)], axis=1)  # (K, 2) along the table
    order = np.lexsort((idx, depth_in[ij[idx, 0], ij[idx, 1]]))
    column = SKIRT_COLUMN * vis.spacing
    _, first = np.unique(np.floor(flat[order] / column).astype(np.int64), axis=0,
                         return_index=True)  # fmt: skip
    keep = np.sort(order[first])
    idx, flat = idx[keep], flat[keep]
    if len(idx) < 3:
        return empty
    # the outward normal: across the outline's local line (the smallest principal direction of
    # its SKIRT_NEIGHBOURS nearest columns along the table), on the side the image's distance
    # to the unseen falls toward
    _, nb = cKDTree(flat).query(flat, k=min(SKIRT_NEIGHBOURS, len(flat)))
    d = flat[nb] - flat[nb].mean(axis=1, keepdims=True)  # (K, k, 2)
    _, vecs = np.linalg.eigh(np.einsum("kni,knj->kij", d, d))
    across = vecs[:, :, 0] @ np.stack([e1, np.cross(n, e1)])  # (K, 3) horizontal unit
    gu, gv = np.gradient(depth_in)
    away = -(gu[ij[idx, 0], ij[idx, 1]][:, None] * vis.R[:, 0]
             + gv[ij[idx, 0], ij[idx, 1]][:, None] * vis.R[:, 1])  # fmt: skip
    side = np.einsum("ij,ij->i", across, away)
    ok = side != 0.0
    idx, out = idx[ok], across[ok] * np.sign(side[ok])[:, None]
    reach = np.minimum(height[idx], params.skirt)  # (K,) metres down
    k = np.floor(reach / step).astype(np.int64)  # points below each outline point
    src = np.repeat(idx, k)
    t = (np.arange(int(k.sum())) - np.repeat(np.cumsum(k) - k, k) + 1) * step
    q = visible[src] - t[:, None] * n
    nrm = np.repeat(out, k, axis=0)
    if not len(q):
        return empty
    near, _ = cKDTree(cloud).query(q)
    keep = (near > SKIRT_COVER * step) & ~vis.violates(q, params.tolerance)
    q, nrm, src = q[keep], nrm[keep], src[keep]
    _, first = np.unique(np.floor(q / step).astype(np.int64), axis=0, return_index=True)
    first = np.sort(first)
    return q[first], nrm[first], src[first].astype(np.int64)


def fill_gaps(
    points: np.ndarray, source: np.ndarray, moved: np.ndarray, spacing: float, gap_max: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(points, source, moved)`` with the holes of the cloud ``points`` (N, 3) closed: for
    every point and each of its ``FILL_NEIGHBOURS`` nearest neighbours farther than
    ``FILL_PAIR`` x ``spacing`` but within ``gap_max``, the midpoint is added when no point lies
    within ``FILL_HOLE`` x ``spacing`` of it (one per cell of ``spacing``), in
    ``FILL_PASSES`` rounds; a midpoint takes the ``source`` and ``moved`` of the pair's first
    point. The midpoint of a chord of a convex surface lies inside it by ``d**2 / (8 R)``
    (0.4 mm for a 10 mm hole on a 30 mm radius)."""
    P, S, Mv = points, source, moved
    for _ in range(FILL_PASSES):  # loop over a few rounds
        tree = cKDTree(P)
        k = min(FILL_NEIGHBOURS, len(P) - 1)
        if k < 1:
            break
        d, nb = tree.query(P, k=k + 1, distance_upper_bound=gap_max)
        i = np.repeat(np.arange(len(P)), k)
        j = nb[:, 1:].ravel()
        dd = d[:, 1:].ravel()
        ok = np.isfinite(dd) & (dd > FILL_PAIR * spacing) & (i < j)
        i, j = i[ok], j[ok]
        mid = 0.5 * (P[i] + P[j])
        near, _ = tree.query(mid)
        hole = near > FILL_HOLE * spacing
        mid, i = mid[hole], i[hole]
        if not len(mid):
            break
        _, first = np.unique(np.floor(mid / spacing).astype(np.int64), axis=0, return_index=True)
        first = np.sort(first)
        P = np.concatenate([P, mid[first]])
        S = np.concatenate([S, S[i[first]]])
        Mv = np.concatenate([Mv, Mv[i[first]]])
    return P, S, Mv


def _hull_area(p2: np.ndarray) -> float:
    """Area of the 2-D convex hull of ``p2`` (P, 2) (0 when degenerate)."""
    try:
        return float(ConvexHull(p2).volume)
    except Exception:  # qhull: fewer than 3 points or collinear
        return 0.0
