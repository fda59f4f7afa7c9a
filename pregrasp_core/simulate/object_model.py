"""The object's collision model for the physics check: convex pieces, mass and inertia.

MuJoCo collides convex shapes only (a mesh geom collides as its convex hull), so a concave
object (a mug, a bowl, a hammer) is modelled as a union of convex pieces. The same algorithm
serves a mesh and a point cloud; only the oriented surface samples differ:

* **mesh**: ``ObjectModelParams.n_samples`` area-weighted samples of the triangles with their
  face normals (seeded);
* **cloud**: the cloud's points with their outward normals (the planner's estimated normals).

From the oriented samples ``(s_i, n_i)``:

1. **Solid points.** The samples, their copies moved ``wall_offset`` inward along ``-n_i`` (so a
   piece always has some thickness, even on a thin wall), and the centres of a regular grid over
   the bounding box that lie inside the object. Inside = the mean of ``(x - s_i) . n_i`` over the
   ``k`` nearest samples is negative (the signed distance to the oriented samples).
2. **Pieces.** A top-down split: start with one piece (all solid points); measure each piece's
   *concavity* = the largest signed distance *outside* the object of points spread over its
   convex hull's facets (centroids and the midpoints between centroid and corners); split the most
   concave piece at the median of its points along their principal axis; repeat until every piece
   is within ``concavity_tol`` of the object or ``max_pieces`` pieces exist. A hull facet that
   bridges a concavity (the mouth of a mug, the inside of a handle) has points far outside the
   object and is split away; facets on cuts between pieces lie inside the object and do not count.
3. **Mass** = ``density`` x volume (clamped to ``[min_mass, max_mass]``): the volume, centre of
   mass and inertia of a watertight mesh come from the mesh itself (trimesh); otherwise from the
   inside grid cells (each a cube of the grid spacing).

The error of the model against the true meshes of the demo objects is in ``docs/simulation.md``
(:func:`model_error`).
"""

from __future__ import annotations

import heapq
import logging
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import ConvexHull, QhullError, cKDTree

from ..errors import DegenerateGeometryError, InputError
from ..geometry import as_points, as_points_like
from ..limits import moved_field, real_or_nan
from ..tolerances import GEOM_EPS

if TYPE_CHECKING:
    import trimesh

logger = logging.getLogger(__name__)

OBJECT_SOURCES: tuple[str, ...] = ("mesh", "cloud")
"""Where an :class:`ObjectModel` was derived from."""


OBJECT_MODEL_INT_BOUNDS: dict[str, int] = {
    "n_samples": 10_000_000,
    "max_pieces": 4096,
    "min_piece_points": 10_000_000,
    "grid_cells": 256,
    "k_neighbours": 200,
}
"""Upper bounds of the collision model's integer fields (the samples and the grid's
``grid_cells**3`` cells are held in memory: 16.8 million cells at 256)."""


@dataclass(frozen=True)
class ObjectModelParams:
    """Parameters of the object's collision model and mass (lengths in metres)."""

    n_samples: int = 20000
    """Surface samples drawn from a mesh (a cloud uses its own points)."""
    seed: int = 0
    """Seed of the mesh sampling."""
    concavity_tol: float = 0.0015
    """A piece is split while points of its hull lie farther than this outside the object."""
    max_pieces: int = 128
    """At most this many convex pieces."""
    min_piece_points: int = 4
    """A piece with fewer solid points than twice this is never split."""
    grid_cells: int = 40
    """Cells of the inside grid along the bounding box's longest side."""
    min_grid_spacing: float = 0.0015
    """The inside grid is never finer than this."""
    wall_offset: float = 0.001
    """Inward offset of the copies of the samples (gives thin walls a thickness)."""
    k_neighbours: int = 8
    """Samples averaged in the inside / outside test."""
    density: float = 500.0
    """kg/m^3: the object's mass is density x volume (a light plastic or wood)."""
    min_mass: float = 0.01
    """kg: lightest object."""
    max_mass: float = 0.5
    """kg: heaviest object (a large object of this density would outweigh what a hand this size
    holds; capping keeps the test about the grasp, not the motor)."""

    def __post_init__(self) -> None:
        for name, hi in OBJECT_MODEL_INT_BOUNDS.items():
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or not 1 <= v <= hi:
                raise ValueError(
                    f"ObjectModelParams.{name} must be an integer in [1, {hi:,}], got {v!r}"
                )
            object.__setattr__(self, name, int(v))
        if isinstance(self.seed, bool) or not isinstance(self.seed, (int, np.integer)):
            raise ValueError(f"ObjectModelParams.seed must be an integer, got {self.seed!r}")
        object.__setattr__(self, "seed", int(self.seed))
        for name in ("concavity_tol", "min_grid_spacing", "density", "min_mass", "max_mass"):
            v = real_or_nan(getattr(self, name))
            if not (np.isfinite(v) and v > 0.0):
                raise ValueError(f"ObjectModelParams.{name} must be a finite number > 0, got {v}")
            object.__setattr__(self, name, v)
        if not (np.isfinite(real_or_nan(self.wall_offset)) and self.wall_offset >= 0.0):
            raise ValueError(f"ObjectModelParams.wall_offset must be >= 0, got {self.wall_offset}")
        object.__setattr__(self, "wall_offset", float(self.wall_offset))
        if self.min_mass > self.max_mass:
            name = moved_field(self, "min_mass", "max_mass")
            raise ValueError(
                f"ObjectModelParams.{name} (min_mass {self.min_mass}, max_mass {self.max_mass}) "
                "must keep min_mass <= max_mass"
            )


@dataclass(frozen=True, eq=False)
class ObjectModel:
    """The object as MuJoCo sees it: convex pieces in the world frame and rigid-body inertia."""

    pieces: tuple[np.ndarray, ...]
    """Per piece, (V_i, 3) float64, metres, world (= input file) frame: its hull's vertices."""
    mass: float
    """kg."""
    com: np.ndarray
    """(3,) float64, metres, world frame: centre of mass."""
    inertia: np.ndarray
    """(3, 3) float64, kg m^2: inertia tensor about ``com``, world axes."""
    volume: float
    """m^3: the volume the mass was computed from (before the mass clamp)."""
    source: str
    """``"mesh"`` or ``"cloud"`` (:data:`OBJECT_SOURCES`)."""
    concavity: float
    """Metres: the largest concavity left in a piece (see the module docstring)."""
    samples: np.ndarray = field(repr=False)
    """(S, 3) float64, world: the oriented surface samples the model was built from."""

    @property
    def n_pieces(self) -> int:
        """Number of convex pieces."""
        return len(self.pieces)

    def to_dict(self) -> dict[str, object]:
        """JSON-ready summary (no vertex lists)."""
        return {
            "source": self.source,
            "n_pieces": self.n_pieces,
            "n_vertices": int(sum(len(p) for p in self.pieces)),
            "mass": self.mass,
            "volume": self.volume,
            "com": self.com.tolist(),
            "concavity": self.concavity,
        }


# ----------------------------------------------------------------------------------------------
# Builders


def object_from_mesh(mesh: trimesh.Trimesh, params: ObjectModelParams | None = None) -> ObjectModel:
    """The collision model of a triangle mesh (world = the mesh's frame, metres).

    A mesh made of several closed parts that overlap (an assembled model: a mug's handle sunk
    into its wall, a thermos's cap) has surfaces inside the object; the samples on them would
    look like a concavity, so the samples lying inside another closed part (winding number
    >= 1/2) are dropped first."""
    import trimesh

    params = ObjectModelParams() if params is None else params
    if len(getattr(mesh, "faces", ())) == 0:
        raise InputError("the object mesh has no triangles; give a mesh with faces or a cloud")
    verts = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(mesh.faces, dtype=np.int64)
    tri = verts[faces]  # (F, 3, 3)
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])  # (F, 3)
    area2 = np.linalg.norm(cross, axis=1)  # (F,)
    if not float(area2.sum()) > GEOM_EPS**2:
        raise DegenerateGeometryError("the object mesh has zero surface area")
    clean = trimesh.Trimesh(vertices=verts, faces=faces, process=False, validate=False)
    pts, face_idx = trimesh.sample.sample_surface(
        clean, params.n_samples, face_weight=area2, seed=params.seed
    )
    pts = np.asarray(pts, dtype=np.float64)
    normals = cross[face_idx] / area2[face_idx, None]  # (S, 3)
    # closed parts (edge-connected components whose every edge has two faces), each oriented
    part_of_face, closed, flip = _closed_parts(clean, tri, cross)
    normals = np.where(flip[part_of_face[face_idx], None], -normals, normals)
    buried = _buried_samples(pts, part_of_face[face_idx], part_of_face, closed, flip, tri)
    keep = ~buried
    mass_props = None
    single = len(closed) == 1 and bool(closed[0])
    if single or (closed.all() and not buried.any()):
        signed = float(np.einsum("ij,ij->i", tri[:, 0], cross).sum() / 6.0)
        if abs(signed) > GEOM_EPS**3:
            m = clean.copy()
            if signed < 0.0:
                m.invert()
            mass_props = (float(m.volume), np.asarray(m.center_mass), np.asarray(m.moment_inertia))
    return _build(pts[keep], normals[keep], "mesh", params, mass_props)


def _closed_parts(
    mesh: trimesh.Trimesh, tri: np.ndarray, cross: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per face its part id (F,); per part: closed (P,) bool and wound inside-out (P,) bool."""
    import trimesh

    F = len(mesh.faces)
    labels = trimesh.graph.connected_component_labels(mesh.face_adjacency, node_count=F)
    n_parts = int(labels.max()) + 1 if F else 0
    # an edge of a closed part appears in exactly two of its faces
    edges = np.sort(mesh.faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)  # (3F, 2)
    _, inv, counts = np.unique(edges, axis=0, return_inverse=True, return_counts=True)
    edge_ok = (counts[inv.reshape(-1)] == 2).reshape(F, 3).all(axis=1)  # (F,)
    closed = np.ones(n_parts, dtype=bool)
    np.logical_and.at(closed, labels, edge_ok)
    vol = np.zeros(n_parts)
    np.add.at(vol, labels, np.einsum("ij,ij->i", tri[:, 0], cross) / 6.0)
    return labels, closed, closed & (vol < 0.0)


def _winding_number(x: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """(M,) generalised winding numbers of points ``x`` (M, 3) for triangles ``tri`` (F, 3, 3)
    (Van Oosterom and Strackee's solid angle; ~1 inside a closed outward surface, ~0 outside)."""
    out = np.zeros(x.shape[0])
    chunk = max(1, 2_000_000 // max(tri.shape[0], 1))
    for s in range(0, x.shape[0], chunk):
        r = tri[None, :, :, :] - x[s : s + chunk, None, None, :]  # (m, F, 3, 3)
        a, b, c = r[:, :, 0], r[:, :, 1], r[:, :, 2]
        la, lb, lc = (np.linalg.norm(v, axis=-1) for v in (a, b, c))
        det = np.einsum("mfj,mfj->mf", a, np.cross(b, c))
        den = (
            la * lb * lc
            + np.einsum("mfj,mfj->mf", a, b) * lc
            + np.einsum("mfj,mfj->mf", b, c) * la
            + np.einsum("mfj,mfj->mf", c, a) * lb
        )
        out[s : s + chunk] = np.arctan2(det, den).sum(axis=1) / (2.0 * np.pi)
    return out


def _buried_samples(
    pts: np.ndarray,
    part_of_sample: np.ndarray,
    part_of_face: np.ndarray,
    closed: np.ndarray,
    flip: np.ndarray,
    tri: np.ndarray,
) -> np.ndarray:
    """(S,) bool: samples inside another closed part (surfaces buried in the object)."""
    buried = np.zeros(pts.shape[0], dtype=bool)
    if len(closed) < 2:
        return buried
    for j in np.flatnonzero(closed):
        tj = tri[part_of_face == j]
        lo, hi = tj.reshape(-1, 3).min(axis=0), tj.reshape(-1, 3).max(axis=0)
        cand = np.flatnonzero(
            (part_of_sample != j) & ~buried & np.all((pts >= lo) & (pts <= hi), axis=1)
        )
        if cand.size == 0:
            continue
        w = _winding_number(pts[cand], tj)
        buried[cand[(-w if flip[j] else w) >= 0.5]] = True
    return buried


def object_from_cloud(
    points: np.ndarray, normals: np.ndarray, params: ObjectModelParams | None = None
) -> ObjectModel:
    """The collision model of a surface point cloud with outward unit normals (world frame)."""
    params = ObjectModelParams() if params is None else params
    pts = as_points(points)
    nrm = as_points_like(normals, pts)
    if pts.shape[0] < 4:
        raise DegenerateGeometryError(
            f"a collision model needs at least 4 cloud points, got {pts.shape[0]}"
        )
    length = np.linalg.norm(nrm, axis=1, keepdims=True)
    return _build(pts, nrm / np.maximum(length, GEOM_EPS), "cloud", params, None)


# ----------------------------------------------------------------------------------------------
# The decomposition


class _Sdf:
    """Signed distance to oriented samples ``(s_i, n_i)``: ``(x - s_i) . n_i``, both for the
    nearest sample and averaged over the k nearest. The nearest alone is right next to thin
    walls (where the k nearest mix both sides of the wall); the mean is steadier near edges.
    A point is inside when both are negative; its distance outside is the larger of the two."""

    def __init__(self, samples: np.ndarray, normals: np.ndarray, k: int) -> None:
        self.tree = cKDTree(samples)
        self.samples = samples
        self.normals = normals
        self.k = max(1, min(k, samples.shape[0]))

    def both(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(M,) nearest-sample and k-mean signed distances of ``x`` (M, 3)."""
        _, idx = self.tree.query(x, k=self.k)
        idx = np.asarray(idx).reshape(x.shape[0], self.k)  # (M, k), nearest first
        d = np.einsum("mkj,mkj->mk", x[:, None, :] - self.samples[idx], self.normals[idx])
        return d[:, 0], d.mean(axis=1)

    def inside(self, x: np.ndarray) -> np.ndarray:
        d1, dk = self.both(x)
        return (d1 < 0.0) & (dk < 0.0)

    def __call__(self, x: np.ndarray) -> np.ndarray:
        d1, dk = self.both(x)
        return np.maximum(d1, dk)


def _grid(lo: np.ndarray, hi: np.ndarray, params: ObjectModelParams) -> tuple[np.ndarray, float]:
    """Cell centres (G, 3) of a regular grid over [lo, hi] and its spacing."""
    h = max(float((hi - lo).max()) / params.grid_cells, params.min_grid_spacing)
    axes = [np.arange(a + 0.5 * h, b, h) for a, b in zip(lo, hi, strict=True)]
    if any(len(a) == 0 for a in axes):
        return np.zeros((0, 3)), h
    g = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    return g, h


def _hull(points: np.ndarray) -> ConvexHull | None:
    try:
        return ConvexHull(points)
    except (QhullError, ValueError):
        try:
            return ConvexHull(points, qhull_options="QJ")
        except (QhullError, ValueError):
            return None


def _thick_hull_vertices(points: np.ndarray, thickness: float) -> np.ndarray | None:
    """The hull vertices of ``points``; flat (or collinear) sets are first given ``thickness``
    along their thinnest principal axes (MuJoCo refuses a mesh with coplanar vertices)."""
    c = points - points.mean(axis=0)
    _, sv, vt = np.linalg.svd(c, full_matrices=False)
    spread = sv / np.sqrt(max(points.shape[0], 1))  # (3,) rms extent per axis
    thin = [k for k in range(len(spread)) if spread[k] < 0.25 * thickness]
    if len(thin) == 3:
        return None
    if thin:
        shifts = [np.zeros(3)]
        for k in thin:
            shifts = [s + e * 0.5 * thickness * vt[k] for s in shifts for e in (-1.0, 1.0)]
        points = np.concatenate([points + s for s in shifts])
    try:
        hull = ConvexHull(points)
    except (QhullError, ValueError):
        return None
    return points[hull.vertices]


def _concavity(points: np.ndarray, sdf: _Sdf, tol: float) -> tuple[float, ConvexHull | None]:
    """Largest signed distance outside the object of points spread over the hull's facets (and
    the hull). A probe lies within its facet's longest edge of a solid point, so facets with all
    edges shorter than ``tol`` cannot exceed it and are not probed."""
    hull = _hull(points)
    if hull is None:
        return 0.0, None
    tri = points[hull.simplices]  # (T, 3, 3)
    edges = np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2).max(axis=1)  # (T,)
    tri = tri[edges > tol]
    if tri.shape[0] == 0:
        return 0.0, hull
    g = tri.mean(axis=1)  # (T', 3) centroids
    probes = np.concatenate([g, 0.5 * (tri + g[:, None, :]).reshape(-1, 3)])  # (4T', 3)
    return float(max(sdf(probes).max(), 0.0)), hull


def _split(points: np.ndarray, overlap: float) -> tuple[np.ndarray, np.ndarray]:
    """Masks of the two halves of ``points`` cut at the median along their principal axis; both
    also keep the points within ``overlap`` of the cut, so the two hulls overlap (no crack
    between them), unless that would leave a half as large as the whole (many points at the cut,
    e.g. a layer of the inside grid)."""
    n = points.shape[0]
    c = points - points.mean(axis=0)
    _, _, vt = np.linalg.svd(c, full_matrices=False)
    t = c @ vt[0]  # (M,)
    order = np.argsort(t, kind="stable")
    left = np.zeros(n, dtype=bool)
    left[order[: n // 2]] = True
    right = ~left
    overlap = min(overlap, 0.05 * float(t[order[-1]] - t[order[0]]))
    cut = 0.5 * (t[order[n // 2 - 1]] + t[order[n // 2]])
    left_o, right_o = left | (t <= cut + overlap), right | (t >= cut - overlap)
    if left_o.sum() < n and right_o.sum() < n:
        return left_o, right_o
    return left, right


def _components(points: np.ndarray, link: float) -> list[np.ndarray]:
    """Index arrays of the clusters of ``points`` linked by distances <= ``link``, the largest
    first (ties: lowest first index)."""
    pairs = cKDTree(points).query_pairs(link, output_type="ndarray")  # (E, 2)
    n = points.shape[0]
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    n_comp, labels = connected_components(graph, directed=False)
    if n_comp == 1:
        return [np.arange(n)]
    groups = [np.flatnonzero(labels == k) for k in range(n_comp)]
    groups.sort(key=lambda g: (-len(g), int(g[0])))
    return groups


def _decompose(
    solid: np.ndarray, sdf: _Sdf, overlap: float, link: float, params: ObjectModelParams
) -> tuple[list[np.ndarray], float]:
    """Convex pieces (their hull vertices) of ``solid`` and the largest concavity left. A piece
    whose points fall into clusters more than ``link`` apart is split into them; else at the
    median (:func:`_split`)."""
    # max-heap on concavity; ties broken by creation order (deterministic)
    counter = 0
    heap: list[tuple[float, int, np.ndarray]] = []
    done: list[tuple[int, np.ndarray, float]] = []

    def push(pts: np.ndarray) -> None:
        nonlocal counter
        conc, hull = _concavity(pts, sdf, params.concavity_tol)
        if conc > params.concavity_tol and pts.shape[0] >= 2 * params.min_piece_points:
            heapq.heappush(heap, (-conc, counter, pts))
        else:
            done.append((counter, pts if hull is None else pts[hull.vertices], conc))
        counter += 1

    push(solid)
    while heap and len(heap) + len(done) < params.max_pieces:
        _, _, pts = heapq.heappop(heap)
        parts = _components(pts, link)
        if len(parts) > 1:  # a piece bridging a gap: its separate clusters first
            for part in parts[: params.max_pieces - len(heap) - len(done)]:
                push(pts[part])
            continue
        left, right = _split(pts, overlap)
        push(pts[left])
        push(pts[right])
    for neg, cid, pts in heap:
        done.append((cid, pts, -neg))
    done.sort(key=lambda item: item[0])
    worst = max((c for _, _, c in done), default=0.0)
    pieces = [_thick_hull_vertices(v, 2.0 * max(params.wall_offset, 1e-4)) for _, v, _ in done]
    return [v for v in pieces if v is not None], worst


def _build(
    samples: np.ndarray,
    normals: np.ndarray,
    source: str,
    params: ObjectModelParams,
    mass_props: tuple[float, np.ndarray, np.ndarray] | None,
) -> ObjectModel:
    sdf = _Sdf(samples, normals, params.k_neighbours)
    lo, hi = samples.min(axis=0), samples.max(axis=0)
    grid, h = _grid(lo, hi, params)
    inside = grid[sdf.inside(grid)] if grid.shape[0] else grid  # (G_in, 3), for the mass
    # the pieces take only the cells deeper than a cell (the inside test can err right at the
    # surface, e.g. just outside an edge); the samples and their inward copies make the shell
    depth = sdf.tree.query(inside)[0] if inside.shape[0] else np.zeros(0)
    solid = np.concatenate([samples, samples - params.wall_offset * normals, inside[depth > h]])
    # linking distance of the clusters: a little more than the grid and the sample spacing
    spacing = float(
        np.median(sdf.tree.query(samples[:: max(1, len(samples) // 2000)], k=2)[0][:, 1])
    )
    pieces, worst = _decompose(solid, sdf, h, 1.5 * max(h, spacing), params)
    if not pieces:
        raise DegenerateGeometryError(
            f"the object's {source} gives no convex piece with a volume; is it flat?"
        )
    if mass_props is not None:
        volume, com, inertia_unit = mass_props  # trimesh: inertia at density 1
        inertia = inertia_unit / max(volume, GEOM_EPS**3)  # per unit mass
    elif inside.shape[0] > 0:
        volume = inside.shape[0] * h**3
        com = inside.mean(axis=0)
        r = inside - com
        # point masses plus each cell's own inertia (a cube of side h: h^2 / 6 per unit mass)
        inertia = (np.eye(3) * np.einsum("ij,ij->", r, r) - r.T @ r) / inside.shape[0]
        inertia = inertia + np.eye(3) * h**2 / 6.0
    else:  # no grid cell inside (a very thin object): the hull pieces' points
        allp = np.concatenate(pieces)
        volume = float(sum(_hull(p).volume for p in pieces if _hull(p) is not None))  # type: ignore[union-attr]
        com = allp.mean(axis=0)
        r = allp - com
        inertia = (np.eye(3) * np.einsum("ij,ij->", r, r) - r.T @ r) / allp.shape[0]
    mass = float(np.clip(params.density * volume, params.min_mass, params.max_mass))
    inertia = mass * inertia
    logger.info(
        "object model from %s: %d pieces, concavity %.2f mm, mass %.3f kg",
        source,
        len(pieces),
        1e3 * worst,
        mass,
    )
    return ObjectModel(
        pieces=tuple(np.ascontiguousarray(p) for p in pieces),
        mass=mass,
        com=np.asarray(com, dtype=np.float64).copy(),
        inertia=0.5 * (inertia + inertia.T),
        volume=float(volume),
        source=source,
        concavity=worst,
        samples=samples,
    )


# ----------------------------------------------------------------------------------------------
# Error against a true mesh


@dataclass(frozen=True)
class ModelError:
    """How far an :class:`ObjectModel` is from the true mesh (metres, m^3)."""

    mean_distance: float
    """Symmetric mean surface distance: the mean over both directions (model surface -> mesh
    surface and mesh surface -> model surface) of the distance to the nearest sample."""
    p95_distance: float
    """95th percentile of the same distances (both directions pooled)."""
    hausdorff: float
    """Largest of the same distances (symmetric Hausdorff distance, sampled)."""
    volume_ratio: float
    """Volume of the union of the pieces / volume inside the mesh (both by the same uniform
    random points; NaN if the mesh is not closed)."""
    iou: float
    """Volume of (union of pieces) & mesh / volume of their union (NaN if not closed)."""


def _in_any_hull(x: np.ndarray, pieces: tuple[np.ndarray, ...], tol: float = 0.0) -> np.ndarray:
    """(M,) bool: inside the union of the pieces' hulls (with a tolerance outward)."""
    out = np.zeros(x.shape[0], dtype=bool)
    for p in pieces:
        hull = _hull(p)
        if hull is None:
            continue
        lo, hi = p.min(axis=0) - tol, p.max(axis=0) + tol
        cand = np.flatnonzero(~out & np.all((x >= lo) & (x <= hi), axis=1))
        if cand.size == 0:
            continue
        eq = hull.equations  # (F, 4): n . x + b <= 0 inside
        inside = np.all(x[cand] @ eq[:, :3].T + eq[:, 3] <= tol, axis=1)
        out[cand[inside]] = True
    return out


def model_surface_samples(
    model: ObjectModel, n: int = 30000, rng: np.random.Generator | None = None
) -> np.ndarray:
    """(M, 3) points on the boundary of the union of the pieces (hull surfaces, minus what lies
    inside another piece), area-weighted, about ``n`` before the removal."""
    import trimesh

    rng = np.random.default_rng(0) if rng is None else rng
    meshes = []
    for p in model.pieces:
        hull = _hull(p)
        if hull is not None:
            meshes.append(trimesh.Trimesh(p, hull.simplices, process=False))
    areas = np.array([m.area for m in meshes])
    counts = np.maximum(1, np.round(n * areas / areas.sum()).astype(int))
    out = []
    for i, (m, c) in enumerate(zip(meshes, counts, strict=True)):
        s, _ = trimesh.sample.sample_surface(m, int(c), seed=int(rng.integers(2**31)))
        others = model.pieces[:i] + model.pieces[i + 1 :]
        keep = ~_in_any_hull(np.asarray(s), others, tol=-1e-6)
        out.append(np.asarray(s)[keep])
    return np.concatenate(out)


def model_error(
    model: ObjectModel, mesh: trimesh.Trimesh, n: int = 30000, n_volume: int = 100000
) -> ModelError:
    """The model's surface distances and volume agreement with the true ``mesh`` (sampled,
    seeded: the same inputs give the same figures)."""
    import trimesh

    rng = np.random.default_rng(0)
    s_model = model_surface_samples(model, n, rng)
    s_mesh, _ = trimesh.sample.sample_surface(mesh, n, seed=1)
    s_mesh = np.asarray(s_mesh)
    d1, _ = cKDTree(s_mesh).query(s_model)  # model -> mesh
    d2, _ = cKDTree(s_model).query(s_mesh)  # mesh -> model
    both = np.concatenate([d1, d2])
    vr = iou = float("nan")
    if bool(mesh.is_watertight):
        lo = np.minimum(mesh.bounds[0], np.concatenate(model.pieces).min(axis=0))
        hi = np.maximum(mesh.bounds[1], np.concatenate(model.pieces).max(axis=0))
        x = lo + (hi - lo) * rng.random((n_volume, 3))
        in_model = _in_any_hull(x, model.pieces)
        if len(mesh.split(only_watertight=False)) > 1:  # overlapping parts: ray parity fails
            in_mesh = _winding_number(x, np.asarray(mesh.triangles)) >= 0.5
        else:
            in_mesh = np.asarray(mesh.contains(x))
        vr = float(in_model.sum() / max(in_mesh.sum(), 1))  # same samples: union volumes
        iou = float((in_model & in_mesh).sum() / max((in_model | in_mesh).sum(), 1))
    return ModelError(
        mean_distance=float(0.5 * (d1.mean() + d2.mean())),
        p95_distance=float(np.percentile(both, 95)),
        hausdorff=float(both.max()),
        volume_ratio=vr,
        iou=iou,
    )
