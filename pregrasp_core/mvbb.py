"""Minimum-volume oriented bounding boxes (MVBB) of point clouds.

The search (details and complexity in ``docs/mvbb.md``), vectorised over candidates:

1. **Kernels.** In the principal (PCA) frame, the cloud is cut into ``kernel_grid`` x
   ``kernel_grid`` columns along each of the three axes and only the lowest and the highest point
   of every column is kept (O(N)); a ``coarse_grid`` kernel of that kernel is hulled by qhull.
2. **Sweep.** Every distinct hull-face normal (up to sign) and every PCA axis is a candidate
   axis; for each, the in-plane angle is tried on a grid of ``n_angles`` angles over 90 degrees,
   all on the hull vertices at once. Candidates are swept in increasing order of an exact lower
   bound (height times the hull's shadow area), and the sweep stops when the bound exceeds the
   best volume by ``sweep_slack``.
3. **Polish.** The best ``n_refine`` distinct boxes are polished on the fine kernel by a pattern
   search over rotations about 26 stencil directions (per-candidate step halved on failure, an
   active set of points near the faces); this reaches optima that are flush with no hull face,
   which face-normal methods (trimesh) miss. The best box on the whole cloud then gets the cloud
   points near its faces added and is polished down to ``step_min``.
4. **Snap.** Hull facets of the points near the faces whose normals are within ``snap_angle`` of
   a box axis are tried as exact flush faces, completed by the exact minimum-area rectangle
   (rotating calipers over the projected silhouette edges); true volumes decide.
5. **Exact box.** The winning axes are fitted tightly around *all* points, so the box always
   contains the cloud and its volume is the true volume of that orientation.

Coplanar input gives a flat box (extent 0 along the plane normal) from the exact 2D minimum-area
rectangle (rotating calipers on the 2D hull). Fewer than 4 points, identical points and collinear
points raise :class:`~pregrasp_core.errors.DegenerateGeometryError`.
"""

from __future__ import annotations

import functools
import logging
import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial import ConvexHull, QhullError

from .box import OrientedBox, canonical_axes
from .decomposition_kernels import kernels
from .errors import DegenerateGeometryError, InputError
from .geometry import as_points
from .limits import (
    MAX_ANGLES,
    MAX_BATCH,
    MAX_CANDIDATES,
    MAX_COARSE_GRID,
    MAX_FACTOR,
    MAX_GRID,
    MAX_ITERATIONS,
    MAX_REACH,
    MAX_REFINE,
    MAX_ROUNDS,
    MAX_SNAP_GRID,
    MAX_STEP,
    MIN_STEP,
    check_int,
    check_real,
    moved_field,
)
from .tolerances import GEOM_EPS, MVBB_DEGENERATE_REL

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class MvbbParams:
    """Parameters of the MVBB search. The defaults meet the targets of ``docs/mvbb.md``."""

    kernel_grid: int = 16
    """Columns per side of the fine kernel grid (step 1): at most 6 * kernel_grid**2 points are
    kept for the polish. Larger is more exact and slower."""
    coarse_grid: int = 6
    """Columns per side of the coarse kernel whose hull gives the candidate normals (step 1)."""
    n_angles: int = 12
    """In-plane angles tried per candidate normal over 90 degrees (step 2): 12 = 7.5 degree
    steps (the pattern search starts at ``step_start`` and covers the gaps)."""
    max_normals: int = 400
    """At most this many distinct hull-face normals are swept (the largest faces first)."""
    sweep_batch: int = 48
    """Candidate normals swept per batch (step 2)."""
    sweep_slack: float = 0.05
    """The sweep stops when the lower bound of the remaining normals exceeds the best volume so
    far by this fraction (the bound is exact, so only candidates that are this much worse than
    the best are skipped)."""
    n_refine: int = 4
    """Distinct candidates polished by the pattern search (step 3)."""
    step_start: float = math.radians(3.0)
    """First rotation step of the pattern search, radians."""
    step_min: float = math.radians(0.005)
    """The pattern search stops when its step falls below this, radians."""
    active_reach: float = 4.0
    """The pattern search rebuilds its active point set after moves totalling this many steps
    (a larger reach means fewer rebuilds but larger sets; any value is exact)."""
    max_iterations: int = 200
    """Upper bound on pattern-search iterations per call (a safeguard; runs need 10 to 40)."""
    refine_restart_level: int = 4
    """After this many halvings (step ``step_start / 2**4``) only the best box goes on, with the
    cloud points near its faces added (step 3)."""
    polish_grid: int = 16
    """Columns per side of the grid that thins the cloud points added for the final polish."""
    max_rounds: int = 2
    """Rounds of adding cloud points and polishing (the second only if the box on the polishing
    set is not yet the box on the whole cloud)."""
    snap_angle: float = math.radians(0.5)
    """Hull facets whose normal is within this angle of an axis of the polished box are tried as
    exact flush faces (step 4), radians."""
    snap_max: int = 4
    """At most this many snapped boxes (smallest lower bounds first) are judged exactly; 0 skips
    the snap (step 4) altogether."""
    snap_grid: int = 16
    """Columns per side of the grid that thins the points near the box faces before the snap's
    hull."""

    def __post_init__(self) -> None:
        # bounds: pregrasp_core.limits and docs/limits.md ("MVBB"); each keeps a table finite
        ints = {
            "kernel_grid": (1, MAX_GRID),
            "coarse_grid": (1, MAX_COARSE_GRID),
            "n_angles": (1, MAX_ANGLES),
            "max_normals": (1, MAX_CANDIDATES),
            "sweep_batch": (1, MAX_BATCH),
            "n_refine": (1, MAX_REFINE),
            "max_iterations": (1, MAX_ITERATIONS),
            "refine_restart_level": (0, MAX_ROUNDS),
            "polish_grid": (1, MAX_GRID),
            "max_rounds": (0, MAX_ROUNDS),
            "snap_max": (0, MAX_REFINE),
            "snap_grid": (1, MAX_SNAP_GRID),
        }
        for name, (lo, hi) in ints.items():
            object.__setattr__(self, name, check_int(name, getattr(self, name), lo, hi))
        for name, lo_open, top in (
            ("sweep_slack", False, MAX_FACTOR),
            ("active_reach", True, MAX_REACH),
        ):
            v = check_real(name, getattr(self, name), 0.0, top, lo_open=lo_open)
            object.__setattr__(self, name, v)
        start = check_real(
            "step_start", self.step_start, MIN_STEP, MAX_STEP, what="an angle", unit=" rad"
        )
        stop = check_real(
            "step_min", self.step_min, MIN_STEP, MAX_STEP, what="an angle", unit=" rad"
        )
        if stop > start:  # named by the field that was moved (limits.moved_field)
            if moved_field(self, "step_start", "step_min") == "step_start":
                raise ValueError(
                    f"step_start must be an angle in [{stop:g}, {MAX_STEP:g}] rad (at least "
                    f"step_min), got {self.step_start!r}"
                )
            raise ValueError(
                f"step_min must be an angle in [{MIN_STEP:g}, {start:g}] rad (at most "
                f"step_start), got {self.step_min!r}"
            )
        snap = check_real(
            "snap_angle", self.snap_angle, 0.0, MAX_STEP, what="an angle", unit=" rad"
        )
        object.__setattr__(self, "step_start", start)
        object.__setattr__(self, "step_min", stop)
        object.__setattr__(self, "snap_angle", snap)


DEFAULT_PARAMS = MvbbParams()


def pca_box(points: np.ndarray) -> OrientedBox:
    """Box aligned with the principal axes of ``points`` (N, 3), N >= 1.

    The axes are the eigenvectors of the covariance; the box is tight around the points.
    """
    pts = as_points(points)
    if pts.shape[0] == 0:
        raise ValueError("points must have shape (N, 3) with N >= 1, got (0, 3)")
    centered = pts - pts.mean(axis=0)
    _, vecs = np.linalg.eigh(centered.T @ centered)
    R = vecs[:, ::-1].copy()
    if np.linalg.det(R) < 0:
        R[:, 2] = -R[:, 2]
    return _tight_box(np.ascontiguousarray(pts.T), R)


def upright_box(points: np.ndarray, up: np.ndarray) -> OrientedBox:
    """The tightest box around ``points`` (N, 3), N >= 1, with one axis along ``up`` (3,): the
    other two are the sides of the exact minimum-area rectangle of the points projected on the
    plane normal to ``up`` (rotating calipers on their 2D hull; any two horizontal axes when
    that hull is degenerate: a vertical line or a flat vertical wall). Canonicalised like every
    box (axes sorted by extent)."""
    pts = as_points(points)
    if pts.shape[0] == 0:
        raise ValueError("points must have shape (N, 3) with N >= 1, got (0, 3)")
    z = np.asarray(up, dtype=np.float64)
    z = z / np.linalg.norm(z)
    e1 = np.cross(z, np.eye(3)[int(np.argmin(np.abs(z)))])
    e1 /= np.linalg.norm(e1)
    R = np.stack([e1, np.cross(z, e1), z], axis=1)
    q2 = (pts @ R[:, :2]).T  # (2, N)
    span = np.ptp(q2, axis=1)
    if pts.shape[0] >= 3 and span.min() > GEOM_EPS * max(1.0, float(span.max())):
        try:
            R = _flat_rotation(q2, R)
        except QhullError:  # collinear in the plane: the axes above are as good as any
            pass
    return OrientedBox.from_points_in_frame(pts, R)


def minimum_volume_box(points: np.ndarray, params: MvbbParams = DEFAULT_PARAMS) -> OrientedBox:
    """The (near-)minimum-volume oriented box around ``points`` (N, 3) float64, metres.

    Returns an :class:`OrientedBox` that contains every point (round-off only), with axes sorted
    by decreasing extent (``docs/conventions.md``). Coplanar points give a flat box (extent 0
    along the normal, up to round-off).

    Raises:
        ValueError: ``points`` is not an (N, 3) array.
        InputError: ``points`` contains NaN or infinite values.
        DegenerateGeometryError: fewer than 4 points, all points identical or all collinear.
    """
    pts = as_points(points)
    n = pts.shape[0]
    if n < 4:
        raise DegenerateGeometryError(
            f"a minimum-volume box needs at least 4 points, got {n}: give a larger cloud"
        )
    if not np.all(np.isfinite(pts)):
        bad = int(np.count_nonzero(~np.all(np.isfinite(pts), axis=1)))
        raise InputError(
            f"{bad} of {n} points contain NaN or inf: drop those rows before fitting a box"
        )
    PT = pts.T.copy(order="C")  # (3, N), always a copy: modified in place below
    origin = PT.mean(axis=1)
    PT -= origin[:, None]

    # Principal frame and degeneracy tests.
    _, vecs = np.linalg.eigh(PT @ PT.T)
    R_pca = vecs[:, ::-1].copy()  # columns: major, middle, minor axis
    if np.linalg.det(R_pca) < 0:
        R_pca[:, 2] = -R_pca[:, 2]
    q = R_pca.T @ PT  # (3, N) coordinates in the PCA frame
    lo, hi = q.min(axis=1), q.max(axis=1)
    ext = hi - lo
    zero = max(GEOM_EPS, MVBB_DEGENERATE_REL * float(ext[0]))
    if ext[0] <= zero:
        raise DegenerateGeometryError(
            f"all {n} points are identical (spread {ext[0]:.3g} m): "
            "a box needs points that span a volume or at least a plane"
        )
    if ext[1] <= zero:
        raise DegenerateGeometryError(
            f"all {n} points are collinear (length {ext[0]:.3g} m, width {ext[1]:.3g} m): "
            "a box needs points that span a volume or at least a plane"
        )
    if ext[2] <= zero:
        logger.debug("coplanar input (%d points): flat box", n)
        flat = _tight_box(PT, _flat_rotation(q[:2], R_pca), origin)
        # Nearly collinear input: round-off in the calipers can leave the rectangle a hair
        # larger than the principal one; keep the smaller.
        pca = _tight_box(PT, R_pca, origin)
        area = [float(b.extents[0] * b.extents[1]) for b in (flat, pca)]
        return flat if area[0] <= area[1] else pca

    # Fine kernel (refinement) and coarse kernel of it (its hull gives the candidate normals).
    fine = np.flatnonzero(_kernel_mask(q, lo, ext, params.kernel_grid))  # (m,) indices
    F = np.take(q, fine, axis=1)  # (3, m); np.take: 2-D fancy indexing is ~5x slower
    S = np.compress(_kernel_mask(F, lo, ext, params.coarse_grid), F, axis=1)  # (3, c)
    try:
        hull = ConvexHull(S.T)
    except QhullError:
        try:
            hull = ConvexHull(S.T, qhull_options="QJ")
        except QhullError:  # pragma: no cover - the PCA test above catches flat input first
            logger.debug("qhull failed on %d kernel points: flat box", S.shape[1])
            return _tight_box(PT, _flat_rotation(q[:2], R_pca), origin)
    Vc = np.take(S, hull.vertices, axis=1)  # (3, h) coarse hull vertices
    # Only fine-kernel points outside the coarse hull (or on it) can be extreme in some direction.
    eq = hull.equations  # (faces, 4): unit outward normal, offset
    # outside[j]: the largest signed distance of point j to a hull face, eq[:, :3] @ F +
    # eq[:, 3:] maximised over the faces, is above -GEOM_EPS * ext[0] (one compiled pass, the
    # same products as BLAS: decomposition_kernels)
    outside = kernels().outside(eq, F, -GEOM_EPS * float(ext[0]))
    R_local = _search(Vc, eq[:, :3], _face_areas(S, hull.simplices), fine[outside], q, params)
    return _tight_box(PT, R_pca @ R_local, origin)


# --------------------------------------------------------------------------------------------
# Steps


def _tight_box(PT: np.ndarray, R: np.ndarray, origin: np.ndarray | None = None) -> OrientedBox:
    """The box with axes ``R`` (3, 3) tight around ``PT`` (3, N) (+ ``origin`` (3,)), canonical."""
    q = R.T @ PT  # (3, N)
    lo, hi = q.min(axis=1), q.max(axis=1)
    center = R @ ((lo + hi) / 2.0)
    if origin is not None:
        center = center + origin
    Rc, ext = canonical_axes(R, hi - lo)
    return OrientedBox(center=center, rotation=Rc, extents=ext)


def _kernel_mask(q: np.ndarray, lo: np.ndarray, ext: np.ndarray, grid: int) -> np.ndarray:
    """(N,) bool: the lowest and the highest point of every column of a ``grid`` x ``grid``
    grid, along each of the three axes (one point per column and side: the first by index when
    several tie). q: (3, N) points; lo, ext: (3,) their bounds. One compiled pass per axis
    (``decomposition_kernels``)."""
    return kernels().kernel_mask(q, lo, ext, grid)


def _face_areas(S: np.ndarray, simplices: np.ndarray) -> np.ndarray:
    """(F,) areas of the hull triangles ``simplices`` (F, 3) over points ``S`` (3, m)."""
    a, b, c = S[:, simplices[:, 0]], S[:, simplices[:, 1]], S[:, simplices[:, 2]]
    return 0.5 * np.linalg.norm(_cross(b - a, c - a), axis=0)


def _frames_from_normals(normals: np.ndarray) -> np.ndarray:
    """(K, 3) unit normals -> (K, 3, 3) rotations whose third column is the normal: the first
    axis is (world axis least aligned with n) x n, normalised, the second n x the first (one
    compiled loop, ``decomposition_kernels``)."""
    return kernels().frames(np.ascontiguousarray(normals, dtype=np.float64))


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Column-wise cross product of (3, K) arrays (np.cross is slow on small arrays)."""
    return np.stack(
        [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
    )


def _rot_z(angles: np.ndarray) -> np.ndarray:
    """(M,) angles -> (M, 3, 3) rotations about z."""
    c, s = np.cos(angles), np.sin(angles)
    R = np.zeros((len(angles), 3, 3))
    R[:, 0, 0], R[:, 0, 1], R[:, 1, 0], R[:, 1, 1], R[:, 2, 2] = c, -s, s, c, 1.0
    return R


def _volumes(R: np.ndarray, V: np.ndarray) -> np.ndarray:
    """Box volumes around ``V`` (3, h) for rotations ``R`` (K, 3, 3) (columns = axes) -> (K,)."""
    # One (3K, 3) @ (3, h) product instead of K small ones.
    proj = (R.transpose(0, 2, 1).reshape(-1, 3) @ V).reshape(len(R), 3, -1)  # (K, 3, h)
    return np.prod(proj.max(axis=2) - proj.min(axis=2), axis=1)


def _unit_stencil() -> np.ndarray:
    """(26, 3) unit directions of the 3 x 3 x 3 stencil (rotation axes of the pattern search)."""
    g = np.array([-1.0, 0.0, 1.0])
    d = np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1).reshape(-1, 3)
    d = d[np.any(d != 0, axis=1)]
    return d / np.linalg.norm(d, axis=1, keepdims=True)


_STENCIL_DIRS = _unit_stencil()


def _rodrigues(rotvecs: np.ndarray) -> np.ndarray:
    """(K, 3) rotation vectors -> (K, 3, 3) rotation matrices."""
    theta = np.linalg.norm(rotvecs, axis=1)
    k = rotvecs / np.where(theta > 0, theta, 1.0)[:, None]
    K = np.zeros((len(k), 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -k[:, 2], k[:, 1], -k[:, 0]
    K = K - K.transpose(0, 2, 1)
    s, c = np.sin(theta)[:, None, None], np.cos(theta)[:, None, None]
    return np.eye(3) + s * K + (1.0 - c) * (K @ K)


def _candidate_normals(normals: np.ndarray, areas: np.ndarray, max_normals: int) -> np.ndarray:
    """Distinct hull-face normals up to sign, largest faces first: (F, 3) -> (K, 3)."""
    order = np.argsort(-areas, kind="stable")
    n = normals[order]
    # n and -n give the same family of boxes: make the largest component positive.
    i = np.argmax(np.abs(n), axis=1)
    n = n * np.sign(n[np.arange(len(n)), i])[:, None]
    # One int64 key per normal (three 21-bit fields; components in [-1, 1] -> [0, 2e6]):
    # np.unique on a 1-D array is much faster than on rows.
    key = np.round(n * 1e6).astype(np.int64) + 1_000_000
    key = (key[:, 0] << 42) | (key[:, 1] << 21) | key[:, 2]
    _, first = np.unique(key, return_index=True)
    return n[np.sort(first)[:max_normals]]


def _sweep(V: np.ndarray, cand: np.ndarray, n_angles: int) -> tuple[np.ndarray, np.ndarray]:
    """Boxes whose third axis is a candidate normal, with the in-plane angle on a grid.

    V: (3, h) points; cand: (K, 3) unit normals. Returns the frames (K, 3, 3) (third column the
    normal) and the volumes (K, M) around V of the boxes ``frames[k] @ _rot_z(angles[m])``, for
    M = n_angles angles ``m * 90 / M`` degrees (the rotations are built only for the few
    candidates that are kept, see ``_sweep_angles``).
    """
    frames = _frames_from_normals(cand)  # (K, 3, 3)
    angles = _sweep_angles(n_angles)
    c, s = np.cos(angles), np.sin(angles)
    # In-plane coordinates of every angle: rows x_m = c u + s v, y_m = c v - s u of the frame
    # coordinates (u, v, height) = frames[k].T @ V; the compiled loop gives the extents of each
    # and the volumes, the same products as numpy's (2M, 2) @ (K, 2, h) (decomposition_kernels).
    rot2 = np.concatenate([np.stack([c, s], axis=1), np.stack([-s, c], axis=1)])  # (2M, 2)
    return frames, kernels().sweep(frames, V, rot2)


def _sweep_angles(n_angles: int) -> np.ndarray:
    """(M,) in-plane angles of the sweep: M steps over 90 degrees."""
    return np.arange(n_angles) * (0.5 * np.pi / n_angles)


def _search(
    V: np.ndarray,
    normals: np.ndarray,
    areas: np.ndarray,
    fine: np.ndarray,
    Q: np.ndarray,
    p: MvbbParams,
) -> np.ndarray:
    """Best rotation (3, 3) around the cloud ``Q`` (3, N).

    Sweeps candidates on the coarse hull vertices ``V`` (3, h) with hull normals (F, 3) and face
    areas (F,), polishes the best on the fine kernel ``Q[:, fine]`` (``fine``: (m,) indices),
    then adds the points of the whole cloud that touch the polished boxes and polishes again
    with small steps, so that the final choice is made on the true volumes."""
    Vf = np.take(Q, fine, axis=1)
    cand = np.concatenate([np.eye(3), _candidate_normals(normals, areas, p.max_normals)])
    # Lower bound of every box with third axis n: height(n) * shadow area of the hull on the
    # plane normal to n (0.5 * sum of |n . face area vector|; the rectangle contains the shadow).
    # Candidates are swept in increasing order of the bound, in batches, until the bound exceeds
    # the best volume found so far by more than `sweep_slack`.
    height = np.ptp(cand @ V, axis=1)  # (K,)
    shadow = 0.5 * (np.abs(cand @ normals.T) @ areas)  # (K,)
    order = np.argsort(height * shadow, kind="stable")
    bound = (height * shadow)[order]
    frames, vols, best_vol = [], [], np.inf
    for start in range(0, len(order), p.sweep_batch):
        if bound[start] > best_vol * (1.0 + p.sweep_slack):
            break
        fb, vb = _sweep(V, cand[order[start : start + p.sweep_batch]], p.n_angles)
        frames.append(fb)
        vols.append(vb)
        best_vol = min(best_vol, float(vb.min()))
    vol = np.concatenate(vols).reshape(-1)  # (K * M,): normal k, angle m at k * M + m

    # Keep the best n_refine candidates that are not the same box.
    best = np.argsort(vol, kind="stable")[: 8 * p.n_refine]
    k_best, m_best = np.divmod(best, p.n_angles)
    top = np.concatenate(frames)[k_best] @ _rot_z(_sweep_angles(p.n_angles)[m_best])  # (B, 3, 3)
    # same[i, j]: boxes i and j are within 2 steps (every axis of i has an axis of j within
    # that angle, axis order and signs ignored).
    B = len(top)
    gram = top.transpose(0, 2, 1).reshape(3 * B, 3) @ top.transpose(1, 0, 2).reshape(3, 3 * B)
    cosines = np.abs(gram.reshape(B, 3, B, 3)).max(axis=3).min(axis=1)  # (B, B)
    same = cosines >= np.cos(2.0 * p.step_start)
    same_rows = same.tolist()  # Python bools: cheaper than numpy scalars in this small loop
    chosen: list[int] = []
    for i in range(len(top)):
        if not any(same_rows[i][j] for j in chosen):
            chosen.append(i)
        if len(chosen) == p.n_refine:
            break
    starts = top[chosen]
    n_levels = _n_levels(p)
    mid = min(p.refine_restart_level, n_levels - 1)
    # Steps >= step_start / 2**mid: volumes in float32 (relative error ~1e-7, far below what a
    # step changes); the final steps below run in float64.
    cur = _pattern_search(starts, Vf, p, 0, mid, np.float32)  # (T, 3, 3), steps >= level mid
    # Only the best box on the whole cloud goes on to the fine steps.
    cur = cur[[int(np.argmin(_volumes(cur, Q)))]]  # (1, 3, 3)
    # The kernel may miss points that matter for this orientation: add the points of the cloud
    # near a face of the box (within the reach of the remaining steps), thinned to the extremes
    # of a fine grid of columns in the box frame, and polish with the remaining steps. A second
    # round runs only if the box on the polishing set is not the box on the whole cloud.
    radius = float(np.sqrt((Q * Q).sum(axis=0).max()))  # rotations are about the origin
    margin = 2.0 * radius * p.step_start * 0.5**mid
    proj = None  # box-frame coordinates of cur[0], when known
    for k in range(p.max_rounds):
        proj = cur[0].T @ Q  # (3, N) box-frame coordinates
        lo, hi = proj.min(axis=1), proj.max(axis=1)
        if k > 0:
            v_set = float(_volumes(cur, Vf)[0])
            if float(np.prod(hi - lo)) <= v_set * (1.0 + 1e-12):
                break
        near = kernels().near_faces(proj, lo, hi, margin)  # within margin of a face
        near = near[_kernel_mask(np.take(proj, near, axis=1), lo, hi - lo, p.polish_grid)]
        # np.union1d(fine, near) without its sort: both are indices into Q
        in_set = np.zeros(Q.shape[1], dtype=bool)
        in_set[fine] = True
        in_set[near] = True
        fine = np.flatnonzero(in_set)
        Vf = np.take(Q, fine, axis=1)
        cur = _pattern_search(cur, Vf, p, mid, n_levels)
        proj = None  # cur has moved
    return _snap(cur[0], Q, radius, p, proj)


def _snap(
    R: np.ndarray, Q: np.ndarray, radius: float, p: MvbbParams, proj: np.ndarray | None = None
) -> np.ndarray:
    """Snap the polished box ``R`` (3, 3) onto the exact hull faces near its faces.

    The pattern search ends within ``step_min`` of a local optimum. When that optimum has a face
    flush with a hull face (the usual case, and the only one face-normal methods consider), this
    step makes it exact: the hull of the cloud points ``Q`` (3, N) near the box faces (thinned to
    the extremes of a ``snap_grid`` grid of columns in the box frame) is built,
    and for every hull facet whose normal is within ``snap_angle`` of a box axis, the box flush
    with that facet is completed by the exact minimum-area rectangle of the projected hull
    (rotating calipers over the projected silhouette edges). The best of these and ``R`` wins.
    ``proj``: ``R.T @ Q`` (3, N) when the caller has it.
    """
    if p.snap_max <= 0:
        return R
    if proj is None:
        proj = R.T @ Q  # (3, N)
    lo, hi = proj.min(axis=1), proj.max(axis=1)
    # Facets within snap_angle of a face are spanned by points within 2 * radius * snap_angle
    # of it: hull those, thinned to the column extremes of a snap_grid grid. (The snapped boxes
    # are judged on the whole cloud at the end.)
    close_margin = 2.0 * 2.0 * radius * p.snap_angle
    near = kernels().near_faces(proj, lo, hi, close_margin)  # within close_margin of a face
    near = near[_kernel_mask(np.take(proj, near, axis=1), lo, hi - lo, p.snap_grid)]
    Z = np.take(Q, near, axis=1)  # (3, z)
    try:
        hull = ConvexHull(Z.T)
    except QhullError:
        return R
    normals = hull.equations[:, :3]  # (F, 3)
    close = np.abs(normals @ R).max(axis=1) >= np.cos(p.snap_angle)  # (F,)
    if not np.any(close):
        return R
    cand = _candidate_normals(normals[close], np.ones(int(close.sum())), p.snap_max)
    W = np.take(Z, hull.vertices, axis=1)  # (3, h)
    # Hull edges as (facet, neighbour) pairs: the edge of facet f opposite its vertex i is shared
    # with neighbours[f, i].
    simp, nb = hull.simplices, hull.neighbors  # (F, 3) each
    f_idx = np.repeat(np.arange(len(simp)), 3)
    g_idx = nb.reshape(-1)
    e0 = simp[:, [1, 2, 0]].reshape(-1)
    e1 = simp[:, [2, 0, 1]].reshape(-1)
    edge = np.take(Z, e1, axis=1) - np.take(Z, e0, axis=1)  # (3, 3F)
    K = len(cand)
    frames = _frames_from_normals(cand)  # (K, 3, 3), third column = facet normal
    # Silhouette edges (between a facet facing the normal and one facing away) bound the
    # projected hull; the minimum-area rectangle has a side along one of them.
    sil = (normals[f_idx] @ cand.T) * (normals[g_idx] @ cand.T) <= 0.0  # (3F, K)
    eu = edge.T @ frames[:, :, 0].T  # (3F, K) edge components in each facet plane
    ev = edge.T @ frames[:, :, 1].T
    theta = np.mod(np.arctan2(ev, eu), 0.5 * np.pi)  # (3F, K)
    # Only in-plane angles near the polished box's: the near points Z decide those boxes.
    r = R[:, np.argmin(np.abs(cand @ R), axis=1)].T  # (K, 3): a box axis in each facet plane
    phi = np.mod(
        np.arctan2(
            np.einsum("ki,ki->k", frames[:, :, 1], r), np.einsum("ki,ki->k", frames[:, :, 0], r)
        ),
        0.5 * np.pi,
    )  # (K,)
    gap = np.abs(np.mod(theta - phi + 0.25 * np.pi, 0.5 * np.pi) - 0.25 * np.pi)
    e_i, k_i = np.nonzero(sil & (np.hypot(eu, ev) > 0.0) & (gap <= 4.0 * p.snap_angle))
    if len(k_i) == 0:
        return R
    w = (frames.transpose(0, 2, 1).reshape(-1, 3) @ W).reshape(K, 3, -1)  # (K, 3, h)
    height = np.ptp(w[:, 2], axis=1)  # (K,)
    th = theta[e_i, k_i]
    c, s = np.cos(th)[:, None], np.sin(th)[:, None]
    x = c * w[k_i, 0] + s * w[k_i, 1]  # (P, h) for the P (edge, facet) pairs
    y = c * w[k_i, 1] - s * w[k_i, 0]
    vol = (x.max(axis=1) - x.min(axis=1)) * (y.max(axis=1) - y.min(axis=1)) * height[k_i]
    # W is a subset of the cloud, so vol is a lower bound of the true volume: only boxes below
    # the polished box's true volume can win; the best few are judged on the whole cloud.
    true_vol = float(np.prod(hi - lo))
    pick = np.argsort(vol, kind="stable")[: p.snap_max]
    pick = pick[vol[pick] < true_vol]
    if len(pick) == 0:
        return R
    cp, sp = c[pick, 0], s[pick, 0]
    Rz = np.zeros((len(pick), 3, 3))
    Rz[:, 0, 0], Rz[:, 0, 1], Rz[:, 1, 0], Rz[:, 1, 1], Rz[:, 2, 2] = cp, -sp, sp, cp, 1.0
    Rs = frames[k_i[pick]] @ Rz  # (k, 3, 3), increasing lower bound
    # Judged one by one on the whole cloud, in increasing order of the lower bound, until the
    # bound reaches the best true volume (usually after one or two).
    best_R, best_vol = R, true_vol
    for R_snap, bound in zip(Rs, vol[pick].tolist(), strict=True):
        if bound >= best_vol:
            break
        v = float(_volumes(R_snap[None], Q)[0])
        if v < best_vol:
            best_R, best_vol = R_snap, v
    return best_R


def _n_levels(p: MvbbParams) -> int:
    """Number of step sizes of the pattern search (step_start halved down to step_min)."""
    return max(1, int(np.ceil(np.log2(p.step_start / p.step_min))))


@functools.lru_cache(maxsize=16)
def _stencils_t(step_start: float, n_levels: int) -> np.ndarray:
    """(L, 26, 3, 3) read-only: the transposed stencil rotations ``S.T`` of every level, rotations
    by ``step_start / 2**k`` about the 26 stencil directions (cached: the same for every call)."""
    steps = step_start * 0.5 ** np.arange(n_levels)  # (L,)
    S = _rodrigues((steps[:, None, None] * _STENCIL_DIRS[None]).reshape(-1, 3))
    St = np.ascontiguousarray(S.reshape(n_levels, -1, 3, 3).transpose(0, 1, 3, 2))
    St.setflags(write=False)
    return St


def _pattern_search(
    cur: np.ndarray,
    Vf: np.ndarray,
    p: MvbbParams,
    start: int,
    stop: int,
    dtype: type = np.float64,
) -> np.ndarray:
    """Polish rotations ``cur`` (T, 3, 3) around points ``Vf`` (3, f) by a pattern search over
    rotations about the 26 stencil directions. Step level k is the step ``step_start / 2**k``;
    every candidate starts at level ``start`` and moves one level down on failure until level
    ``stop``. Returns (T, 3, 3).

    The rotations are kept transposed (rows = box axes), so that a trial's axes are the rows of
    ``S.T @ C.T``; the extent along trial axis k is measured on the active points of axis k only.
    ``dtype`` is the precision of the volume evaluations (the rotations stay float64): float32
    halves the memory traffic and is ample for steps of a tenth of a degree and more.
    """
    cur_t = np.ascontiguousarray(cur.transpose(0, 2, 1))  # (T, 3, 3), rows = axes
    Vf = np.ascontiguousarray(Vf, dtype=dtype)
    cur_vol = _volumes(cur.astype(dtype), Vf)
    radius = float(np.sqrt((Vf * Vf).sum(axis=0).max()))  # rotations are about the origin
    n_levels = stop
    steps = p.step_start * 0.5 ** np.arange(n_levels)  # (L,)
    stencils_t = _stencils_t(float(p.step_start), int(n_levels))  # (L, 26, 3, 3)
    level = np.full(len(cur), start, dtype=np.int64)  # per-candidate step level
    # The loop is compiled (decomposition_kernels.pattern_search), the same steps as this numpy
    # version, to the bit:
    #   for each iteration: live = candidates with level < n_levels (none: stop);
    #     step = the largest step of the live ones; when spent + step > budget, the active sets
    #     are rebuilt: budget = active_reach * step, spent = 0, margin = 2 radius budget, and the
    #     active points of axis k are those within margin of face +-k of a live box (projected
    #     in the precision of the volumes);
    #     trials: the 26 stencil rotations S.T @ C.T of each live box (rows = trial axes), their
    #     volumes = product over k of the extent along trial axis k of the active points of k;
    #     a box moves to its best trial if that is below its volume * (1 - 1e-12) (and spent +=
    #     step), otherwise its level goes down one step.
    shrink: np.ndarray = np.array([1.0 - 1e-12], dtype=dtype)
    kernels().pattern_search(
        cur_t, cur_vol, Vf, stencils_t, steps, level, radius, float(p.active_reach),
        int(p.max_iterations), shrink,
    )  # fmt: skip
    return np.ascontiguousarray(cur_t.transpose(0, 2, 1))


def _flat_rotation(q2: np.ndarray, R_pca: np.ndarray) -> np.ndarray:
    """Axes of the minimum-area rectangle of coplanar points. q2: (2, N) in-plane coordinates in
    the PCA frame ``R_pca`` (3, 3) whose third axis is the plane normal -> (3, 3) rotation."""
    hull = ConvexHull(q2.T)
    theta = _min_area_rect_angle(q2[:, hull.vertices])
    c, s = np.cos(theta), np.sin(theta)
    return R_pca @ np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _min_area_rect_angle(poly: np.ndarray) -> float:
    """Rotating calipers on a convex polygon ``poly`` (2, h) in order: the angle of the side of
    its minimum-area enclosing rectangle (one side is flush with a polygon edge)."""
    edges = np.roll(poly, -1, axis=1) - poly  # (2, h)
    theta = np.mod(np.arctan2(edges[1], edges[0]), 0.5 * np.pi)  # (h,)
    c, s = np.cos(theta), np.sin(theta)
    x = c[:, None] * poly[0] + s[:, None] * poly[1]  # (h, h): coordinates along the edge
    y = -s[:, None] * poly[0] + c[:, None] * poly[1]
    area = (x.max(axis=1) - x.min(axis=1)) * (y.max(axis=1) - y.min(axis=1))
    return float(theta[int(np.argmin(area))])
