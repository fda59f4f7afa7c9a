"""Grasp quality: Ferrari-Canny epsilon (L1) and the volume of the grasp wrench hull.

Definitions (docs/quality.md, GraspIt-style "unit normal force" L1 metric):

* Contact ``i`` has a point ``p_i`` and a unit normal ``n_i`` that points **into the object**
  (the direction of the normal force the hand applies). Its friction cone is linearised with
  ``m`` edges ``f_ik = n_i + mu (cos t_k a_i + sin t_k b_i)``, ``t_k = 2 pi k / m``, where
  ``(a_i, b_i, n_i)`` is a right-handed orthonormal frame. The edges are *not* normalised: the
  normal component of every edge force is exactly 1 (this is what reproduces the oracle values
  of docs/quality.md to 1e-10; normalised edges would give e.g. 0.4132 instead of 0.4619 for
  the antipodal pair).
* Edge wrench ``w_ik = [f_ik; (p_i - c) x f_ik / rho]``. GraspIt's convention (and Dex-Net's):
  ``c`` is the centroid of the OBJECT (gravity and disturbances act there, not at the
  contacts) and ``rho`` the largest distance from ``c`` to a point of the object, so a torque
  is measured against the largest lever the object offers. The planner passes the cloud's
  centroid and radius (``QualityParams.torque_origin = "object"``, the default); without a
  ``center`` (a bare set of contacts, ``torque_origin = "contacts"``) ``c`` is the contacts'
  centroid and ``rho`` the largest distance from it to a contact.
* The grasp wrench space is the convex hull of all ``w_ik`` (qhull, 6D). ``epsilon`` is the
  smallest distance from the origin to a facet when the origin is strictly inside, else 0 (not
  force closure). ``volume`` is the 6D volume of the hull (0 when it is not full-dimensional).
* Degenerate wrench sets (fewer than two contacts, rank < 6 such as any two-contact grasp with
  torques, qhull failures) give ``epsilon = volume = 0`` and never raise.

The first tangent ``a_i`` fixes how the m-gon is turned about the normal. It is given by the
caller (the planner passes the finger's flexion-plane normal, a direction fixed to the hand, so
the score is exactly invariant under rigid motions of the whole grasp) or, when omitted, by the
rule ``a_i = normalise(e_x - (e_x . n_i) n_i)`` (``e_y`` when ``|n_i . e_x| > 0.9``), a direction
fixed to the world. The hull is computed by qhull without merging (``Q0``): exact (scores equal
the merged hull's to about 1e-15) and the fastest option on these highly coplanar point sets.
qhull checks every new facet and raises when rounding makes the hull concave (about 1 set in 80
of the planner's); the result is also checked here (every wrench on or inside every facet).
When either fails, the hull is built again with the joggle option ``QJ`` (the input perturbed by
about 1e-11, scores to about 1e-10), which always succeeds on full-rank sets.
"""

from __future__ import annotations

import functools
import logging
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.spatial import ConvexHull, QhullError

from .geometry import as_points
from .jit import Lazy, njit
from .limits import MAX_CONE_EDGES, MAX_EXACT_TOP, MAX_FRICTION, MAX_LENGTH, check_int, check_real
from .minnorm import walk_loop
from .tolerances import GEOM_EPS, HULL_CHECK_TOL, QUALITY_EPS, QUALITY_RANK_TOL

logger = logging.getLogger(__name__)

QHULL_OPTIONS = "Q0"
"""qhull options for the 6D wrench hull: no merging, exact (see the module docstring)."""

TORQUE_ORIGINS: tuple[str, ...] = ("object", "contacts")
"""Values of ``QualityParams.torque_origin``."""

QHULL_FALLBACK = "QJ"
"""qhull options when ``QHULL_OPTIONS`` fails or gives an inconsistent hull: joggled input."""


@dataclass(frozen=True)
class QualityParams:
    """Parameters of the grasp quality stage."""

    mu: float = 0.5
    """Coulomb friction coefficient (dimensionless, >= 0)."""
    n_edges: int = 8
    """Number m of edges of each linearised friction cone (>= 3)."""
    torque_scale: float | None = None
    """rho in metres; None = the largest distance from the torque origin to an object point
    (to a contact when the origin is the contacts' centroid)."""
    torque_origin: str = "object"
    """Where torques are taken: 'object' (the object's centroid, GraspIt's convention) or
    'contacts' (the contacts' centroid; the scores of the releases before 0.2)."""
    exact_top: int = 20
    """The planner's scores (epsilon and volume, one 6D hull each) are exact for every grasp
    that can enter the best ``exact_top`` of the ranking and for the best grasp of each grasp
    type; the other kept grasps carry upper bounds, with force closure still exact
    (docs/quality.md). pregrasp plan raises it to its --top and --simulate."""
    exact_all: bool = False
    """Exact scores for every kept grasp instead of bounds for those that cannot reach the
    best ``exact_top`` (slower; the ranking's best ``exact_top`` and each type's best are the
    same either way)."""

    def __post_init__(self) -> None:
        # bounds: pregrasp_core.limits and docs/limits.md ("Quality"); each field is named
        mu = check_real("mu", self.mu, 0.0, MAX_FRICTION, what="a friction coefficient")
        object.__setattr__(self, "mu", mu)
        object.__setattr__(self, "n_edges", check_int("n_edges", self.n_edges, 3, MAX_CONE_EDGES))
        if self.torque_scale is not None:
            rho = check_real(
                "torque_scale",
                self.torque_scale,
                0.0,
                MAX_LENGTH,
                lo_open=True,
                what="None or a length",
                unit=" m",
            )
            object.__setattr__(self, "torque_scale", rho)
        if not isinstance(self.torque_origin, str) or self.torque_origin not in TORQUE_ORIGINS:
            raise ValueError(
                f"torque_origin must be one of {TORQUE_ORIGINS}, got {self.torque_origin!r}"
            )
        object.__setattr__(
            self, "exact_top", check_int("exact_top", self.exact_top, 0, MAX_EXACT_TOP)
        )
        if not isinstance(self.exact_all, (bool, np.bool_)):
            raise ValueError(f"exact_all must be True or False, got {self.exact_all!r}")
        object.__setattr__(self, "exact_all", bool(self.exact_all))


@dataclass(frozen=True)
class GraspQuality:
    """The scores of one set of contacts."""

    epsilon: float
    """Ferrari-Canny epsilon (L1): distance from the origin to the hull boundary; 0 if not FC."""
    volume: float
    """6D volume of the grasp wrench hull (0 when degenerate)."""
    n_contacts: int
    """Number of contacts scored."""
    force_closure: bool
    """True when the origin lies strictly inside the wrench hull (epsilon > 0)."""
    reason: str
    """'' when the hull was computed or bounded, else why the scores are 0 (e.g. 'rank 5 < 6')."""
    epsilon_exact: bool = True
    """False when ``epsilon`` is an upper bound of the exact value (see :func:`grasp_quality`'s
    ``level``); ``force_closure`` is always exact."""
    volume_exact: bool = True
    """False when ``volume`` is an upper bound of the exact value."""
    bound: str = ""
    """How the scores were obtained: '' = exact (hull or degenerate), else the bound of
    :data:`QUALITY_BOUNDS` that gave them."""


def _as_vectors(x: np.ndarray, name: str) -> np.ndarray:
    return as_points(x, name, rows="K")


def cross3(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``np.cross(a, b)`` of (..., 3) arrays (broadcast), by the same products and differences
    in the same order (so equal to the bit), without ``np.cross``'s axis handling (a third of
    the wrenches' construction time)."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return np.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=-1)


def tangent_frames(normals: np.ndarray, tangents: np.ndarray | None = None) -> np.ndarray:
    """Orthonormal frames ``(K, 3, 3)`` whose columns are ``a, b, n`` for each unit normal.

    ``tangents`` (K, 3), optional: a direction per contact; its component orthogonal to ``n`` gives
    ``a``. Where it is missing or (nearly) parallel to ``n`` the world rule of the module docstring
    applies. ``b = n x a`` so that ``(a, b, n)`` is right-handed.
    """
    n = _as_vectors(normals, "normals")
    n = n / np.linalg.norm(n, axis=1, keepdims=True)
    k = len(n)
    ex = np.tile([1.0, 0.0, 0.0], (k, 1))
    ey = np.tile([0.0, 1.0, 0.0], (k, 1))
    ref = np.where(np.abs(n[:, :1]) > 0.9, ey, ex)
    if tangents is not None:
        t = _as_vectors(tangents, "tangents")
        if t.shape != n.shape:
            raise ValueError(f"tangents must have shape {n.shape}, got {t.shape}")
        t_perp = t - np.sum(t * n, axis=1, keepdims=True) * n
        ok = np.linalg.norm(t_perp, axis=1) > 1e-6 * np.maximum(np.linalg.norm(t, axis=1), 1e-300)
        ref = np.where(ok[:, None], t, ref)
    a = ref - np.sum(ref * n, axis=1, keepdims=True) * n
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    b = cross3(n, a)
    return np.stack([a, b, n], axis=2)


@functools.lru_cache(maxsize=16)
def _cone_coefficients(mu: float, n_edges: int) -> np.ndarray:
    """(m, 3) read-only: ``(mu cos t_k, mu sin t_k, 1)``, ``t_k = 2 pi k / m`` (the same values
    every call: computed once per ``(mu, m)``)."""
    t = 2.0 * np.pi * np.arange(n_edges) / n_edges
    coef = np.stack([mu * np.cos(t), mu * np.sin(t), np.ones_like(t)], axis=1)
    coef.flags.writeable = False
    return coef


def friction_cone_edges(
    normals: np.ndarray, mu: float, n_edges: int, tangents: np.ndarray | None = None
) -> np.ndarray:
    """Edge forces ``(K, m, 3)``: ``n + mu (cos t_k a + sin t_k b)`` (normal component 1)."""
    frames = tangent_frames(normals, tangents)  # (K, 3, 3) columns a, b, n
    return np.einsum("kij,mj->kmi", frames, _cone_coefficients(float(mu), int(n_edges)))


def _frames_loop(n: np.ndarray, t: np.ndarray, has_t: bool) -> np.ndarray:
    """:func:`tangent_frames` of unit-able normals ``n`` (K, 3) and tangents ``t`` (K, 3, read
    only when ``has_t``) as one loop: every value by the same floating-point operations in the
    same order as the numpy code (a row's 3-term sums left to right, as numpy reduces them), so
    equal to the bit (``tests/core/test_quality.py``). Compiled by numba (:func:`_kernels`)."""
    k = n.shape[0]
    out = np.empty((k, 3, 3))
    for i in range(k):
        m0, m1, m2 = n[i, 0], n[i, 1], n[i, 2]
        nn = math.sqrt((m0 * m0 + m1 * m1) + m2 * m2)
        n0, n1, n2 = m0 / nn, m1 / nn, m2 / nn
        if abs(n0) > 0.9:
            r0, r1, r2 = 0.0, 1.0, 0.0
        else:
            r0, r1, r2 = 1.0, 0.0, 0.0
        if has_t:
            t0, t1, t2 = t[i, 0], t[i, 1], t[i, 2]
            dot = (t0 * n0 + t1 * n1) + t2 * n2
            p0, p1, p2 = t0 - dot * n0, t1 - dot * n1, t2 - dot * n2
            nt = math.sqrt((t0 * t0 + t1 * t1) + t2 * t2)
            if not nt >= 1e-300:  # np.maximum(nt, 1e-300); NaN stays NaN
                nt = nt if nt != nt else 1e-300
            if math.sqrt((p0 * p0 + p1 * p1) + p2 * p2) > 1e-6 * nt:
                r0, r1, r2 = t0, t1, t2
        dot = (r0 * n0 + r1 * n1) + r2 * n2
        a0, a1, a2 = r0 - dot * n0, r1 - dot * n1, r2 - dot * n2
        na = math.sqrt((a0 * a0 + a1 * a1) + a2 * a2)
        a0, a1, a2 = a0 / na, a1 / na, a2 / na
        out[i, 0, 0], out[i, 1, 0], out[i, 2, 0] = a0, a1, a2
        out[i, 0, 1] = n1 * a2 - n2 * a1
        out[i, 1, 1] = n2 * a0 - n0 * a2
        out[i, 2, 1] = n0 * a1 - n1 * a0
        out[i, 0, 2], out[i, 1, 2], out[i, 2, 2] = n0, n1, n2
    return out


def _wrenches_loop(f: np.ndarray, r: np.ndarray, rho: float) -> np.ndarray:
    """``[f ; r x f / rho]`` as (K * m, 6) for edges ``f`` (K, m, 3) and levers ``r`` (K, 3):
    the operations of :func:`cross3`, then the division, element by element (equal to the
    bit). Compiled by numba (:func:`_kernels`)."""
    k, m = f.shape[0], f.shape[1]
    w = np.empty((k * m, 6))
    for i in range(k):
        a0, a1, a2 = r[i, 0], r[i, 1], r[i, 2]
        for e in range(m):
            b0, b1, b2 = f[i, e, 0], f[i, e, 1], f[i, e, 2]
            row = i * m + e
            w[row, 0], w[row, 1], w[row, 2] = b0, b1, b2
            w[row, 3] = (a1 * b2 - a2 * b1) / rho
            w[row, 4] = (a2 * b0 - a0 * b2) / rho
            w[row, 5] = (a0 * b1 - a1 * b0) / rho
    return w


def _kernels() -> tuple[Callable[..., np.ndarray], Callable[..., np.ndarray]]:
    """``(frames, wrenches)``: :func:`_frames_loop` and :func:`_wrenches_loop` compiled by numba
    (``cache=True``; the first call imports numba and compiles or loads them, never the import
    of this module)."""
    return _KERNELS.get()


_KERNELS = Lazy(lambda: (njit(_frames_loop), njit(_wrenches_loop)))


def contact_wrenches(
    points: np.ndarray,
    normals: np.ndarray,
    params: QualityParams = QualityParams(),  # noqa: B008 (frozen, immutable)
    tangents: np.ndarray | None = None,
    torques: bool = True,
    center: np.ndarray | None = None,
    radius: float | None = None,
) -> np.ndarray:
    """The edge wrenches ``(K * m, 6)`` (or ``(K * m, 3)`` forces when ``torques`` is False).

    points, normals: (K, 3) contact points (metres) and unit normals pointing into the object;
    center: (3,) the torque origin (the object's centroid), None = the contacts' centroid;
    radius: rho when ``params.torque_scale`` is None and a center is given (the largest distance
    from it to an object point); without a center rho is the largest distance to a contact.
    """
    p = _as_vectors(points, "points")
    n = _as_vectors(normals, "normals")
    if p.shape != n.shape:
        raise ValueError(f"points and normals must have the same shape, got {p.shape}, {n.shape}")
    if not torques:
        return friction_cone_edges(n, params.mu, params.n_edges, tangents).reshape(-1, 3)
    # the compiled loops: friction_cone_edges and the torques below, equal to the bit
    frames_loop, wrenches_loop = _kernels()
    if tangents is None:
        frames = frames_loop(np.ascontiguousarray(n), np.zeros((0, 3)), False)
    else:
        t = _as_vectors(tangents, "tangents")
        if t.shape != n.shape:
            raise ValueError(f"tangents must have shape {n.shape}, got {t.shape}")
        frames = frames_loop(np.ascontiguousarray(n), np.ascontiguousarray(t), True)
    coef = _cone_coefficients(float(params.mu), int(params.n_edges))
    f = np.einsum("kij,mj->kmi", frames, coef)  # (K, m, 3)
    if center is None:
        c = p.mean(axis=0)
    else:
        c = np.asarray(center, dtype=np.float64)
        if c.shape != (3,) or not np.isfinite(c).all():
            raise ValueError(f"center must be 3 finite numbers, got {center!r}")
    r = p - c  # (K, 3)
    rho = params.torque_scale
    if rho is None and center is not None and radius is not None:
        rho = float(radius)
    if rho is None:
        rho = float(np.max(np.linalg.norm(r, axis=1))) if len(p) else 0.0
    rho = max(rho, GEOM_EPS)
    return wrenches_loop(f, np.ascontiguousarray(r), float(rho))  # [f ; r x f / rho]


def _exact_hull(w: np.ndarray) -> ConvexHull | None:
    """The hull of ``w`` (M, D) by qhull without merging, or None when qhull reports a
    precision error or the hull fails the check that every point lies on or inside every facet
    (within ``HULL_CHECK_TOL`` times the largest coordinate)."""
    try:
        hull = ConvexHull(w, qhull_options=QHULL_OPTIONS)
    except (QhullError, ValueError) as exc:
        logger.debug("exact hull of %d wrenches failed, joggling: %s", len(w), exc)
        return None
    eq = hull.equations  # (F, D + 1): unit outward normal, offset
    outside = float((w @ eq[:, :-1].T + eq[:, -1]).max())
    if not (np.isfinite(hull.volume) and outside <= HULL_CHECK_TOL * max(np.abs(w).max(), 1.0)):
        logger.debug("exact hull of %d wrenches: a point %.3g outside, joggling", len(w), outside)
        return None
    return hull


def _quick_check(w: np.ndarray) -> str:
    """:func:`_wrench_check`'s tests before the rank's: too few wrenches, a non-finite one."""
    m, d = w.shape
    if m < d + 1:
        return f"{m} wrenches < {d + 1}"
    if not np.isfinite(w).all():
        return "non-finite wrench"
    return ""


def _wrench_check(w: np.ndarray) -> str:
    """'' when the wrenches ``w`` (M, D) span D dimensions (a hull exists), else why not."""
    return _centred_check(w)[0]


def _centred_check(w: np.ndarray) -> tuple[str, np.ndarray | None]:
    """:func:`_wrench_check` of ``w`` (M, D) and the centred wrenches ``w - mean`` it measured
    the rank of (None when it did not get that far), for :func:`box_volume_bound`."""
    reason = _quick_check(w)
    if reason:
        return reason, None
    d = w.shape[1]
    c = w - w.mean(axis=0)
    sv = np.linalg.svd(c, compute_uv=False)
    rank = int(np.sum(sv > QUALITY_RANK_TOL * max(sv[0], GEOM_EPS)))
    if rank < d:
        return f"rank {rank} < {d}", c
    return "", c


def _hull_scores(w: np.ndarray) -> tuple[float, float, str]:
    """``(epsilon, volume, reason)`` of the hull of full-rank wrenches ``w`` (M, D)."""
    hull = _exact_hull(w)
    if hull is None:
        try:
            hull = ConvexHull(w, qhull_options=QHULL_FALLBACK)
        except (QhullError, ValueError) as exc:  # degenerate input: a score of 0, no exception
            logger.debug("qhull failed on %d wrenches: %s", len(w), exc)
            return 0.0, 0.0, "qhull failed"
    # equations: unit outward normal nv and offset o with nv . x + o <= 0 inside;
    # the distance from the origin to facet j is -o_j (negative when the origin is outside it).
    dist = -hull.equations[:, -1]
    eps = float(dist.min())
    if eps <= QUALITY_EPS:
        eps = 0.0
    return eps, float(hull.volume), ""


def hull_quality(wrenches: np.ndarray) -> tuple[float, float, str]:
    """``(epsilon, volume, reason)`` of the convex hull of ``wrenches`` (M, D); never raises.

    ``reason`` is '' when the hull was built, else why both scores are 0.
    """
    w = np.asarray(wrenches, dtype=np.float64)
    if w.ndim != 2:
        raise ValueError(f"wrenches must have shape (M, D), got {w.shape}")
    reason = _wrench_check(w)
    if reason:
        return 0.0, 0.0, reason
    return _hull_scores(w)


# ----------------------------------------------------------------------------- bounds

LEVEL_CHEAPEST: int = 0
"""``level`` of :func:`grasp_quality`: the cheapest scores that still decide force closure
exactly (a bound where it can, the exact hull where the bounds cannot decide)."""
LEVEL_HALF_CONES: int = 1
"""``level``: at least the half-cone bounds (tighter than the directions' bounds)."""
LEVEL_EXACT: int = 2
"""``level``: the exact hull (the default)."""

QUALITY_BOUNDS: tuple[str, ...] = ("directions", "half cones")
"""``GraspQuality.bound`` of the bounded scores of level 0 and 1 ('' = exact), see
docs/quality.md: 'directions' = epsilon bounded by the support values along fixed directions
and, for force closure, along where :func:`walk_bound` ends (0 when force closure is
disproved), the volume by the wrenches' principal box; 'half cones' =
both bounded through the hull of every other cone edge. Force closure is exact in both."""

EPS_BOUND_TOL: float = 1e-9
"""Added to an upper bound of epsilon so that it also bounds the value qhull computes (its
rounding, about 1e-15, and the joggled fallback's perturbation, about 1e-10)."""

VOLUME_BOUND_RTOL: float = 1e-9
"""Relative margin added to an upper bound of the volume, for the same reason."""

NOT_CLOSURE_BOUND: float = 0.5 * QUALITY_EPS
"""An upper bound of epsilon at or below this proves the score 0 (not force closure): the
exact value, within qhull's error (about 1e-10 at worst) of the true one, is then below
``QUALITY_EPS`` and is reported as 0. Many planner grasps have the origin exactly on the hull's
boundary (bounds of about 1e-17)."""


def _unit_directions(n: int, seed: int) -> np.ndarray:
    """(6, n + 12) unit directions: ``n`` seeded random ones and the 12 signed axes."""
    u = np.random.default_rng(seed).normal(size=(6, n))
    u /= np.linalg.norm(u, axis=0)
    return np.hstack([u, np.eye(6), -np.eye(6)])


BOUND_DIRECTIONS: np.ndarray = _unit_directions(256, 15)
"""(6, 268) fixed unit directions of :func:`direction_bound` (seeded: the same every run)."""


def wrench_frame(wrenches: np.ndarray, n_edges: int) -> np.ndarray:
    """(3, 3) a frame fixed to the grasp: the first contact's cone frame ``(a, b, n)`` read
    back from its ``n_edges`` edge forces (the first ``n_edges`` rows of ``wrenches``; ``n`` =
    their mean, ``a`` = the first edge minus it). It turns with the grasp, so bounds taken in
    it do not depend on the world frame. The identity when the cone is flat (``mu`` = 0)."""
    f = np.asarray(wrenches, dtype=np.float64)[:n_edges, :3]
    n = f.mean(axis=0)
    a = f[0] - n
    # (the norms as np.linalg.norm computes a vector's: the square root of its dot product)
    na, nn = math.sqrt(float(a.dot(a))), math.sqrt(float(n.dot(n)))
    if not (na > 1e-9 * max(nn, 1.0) and nn > GEOM_EPS):
        return np.eye(3)
    a, n = a / na, n / nn
    a = a - (a @ n) * n
    a /= math.sqrt(float(a.dot(a)))
    (a0, a1, a2), (n0, n1, n2) = a.tolist(), n.tolist()
    # columns a, n x a (cross3's products and differences, on the same doubles), n
    return np.array(
        [[a0, n1 * a2 - n2 * a1, n0], [a1, n2 * a0 - n0 * a2, n1], [a2, n0 * a1 - n1 * a0, n2]]
    )


def direction_bound(wrenches: np.ndarray, frame: np.ndarray | None = None) -> float:
    """An upper bound of epsilon for 6D wrenches (M, 6): the smallest support value
    ``max_j u . w_j`` over :data:`BOUND_DIRECTIONS`, turned by ``frame`` (3, 3; applied to the
    force and to the torque part; None = the world frame). epsilon is the minimum of the
    support function over every unit direction (the distance to the nearest facet), so each
    direction's value bounds it; a value <= 0 proves the origin is not strictly inside
    (epsilon 0, see :data:`NOT_CLOSURE_BOUND`)."""
    return best_direction(wrenches, frame)[0]


def best_direction(
    wrenches: np.ndarray, frame: np.ndarray | None = None
) -> tuple[float, np.ndarray]:
    """``(value, u)``: :func:`direction_bound` and the direction (6,) that gives it."""
    w = np.asarray(wrenches, dtype=np.float64)
    u = BOUND_DIRECTIONS
    if frame is not None:
        r = np.asarray(frame, dtype=np.float64)
        u = np.vstack([r @ u[:3], r @ u[3:]])
    s = (w @ u).max(axis=0)
    j = int(s.argmin())
    return float(s[j]), u[:, j]


WALK_STEPS: int = 40
"""The most steps of :func:`walk_bound`'s walk (the demo objects' sets take 13-19, median)."""


_WALK = Lazy(lambda: njit(walk_loop))


def walk_bound(wrenches: np.ndarray, u0: np.ndarray, max_steps: int = WALK_STEPS) -> float:
    """An upper bound of epsilon for 6D wrenches (M, 6) whose hull holds the origin: the support
    value along the direction where a walk on the polar set ``{y : w y <= 1}`` ends, started
    at the direction ``u0`` (unit, e.g. :func:`direction_bound`'s). The polar set's vertices
    are the hull's facets (a vertex ``y`` is the facet ``{x : y . x = 1}``, at distance
    ``1 / |y|`` from the origin), so the walk moves ``y`` along its own direction projected on
    the rows it touches (``|y|`` grows), from face to edge to vertex, drops a row whose
    multiplier is negative, and stops where ``y`` lies in the cone of the rows it touches: a
    local maximum of ``|y|``, a facet that is locally the nearest (often the nearest: on the
    demo objects' force-closure grasps the value is epsilon itself on about 60 %, median ratio
    1.000, against 6.9 for the directions' bound, docs/quality.md). Whatever the walk does, the
    value returned is the support value of a unit direction, so it bounds epsilon."""
    w = np.ascontiguousarray(wrenches, dtype=np.float64)
    u = _WALK.get()(w, np.ascontiguousarray(u0, dtype=np.float64), int(max_steps))
    if not np.all(np.isfinite(u)):
        return np.inf
    return float((w @ u).max())


def box_volume_bound(wrenches: np.ndarray, centred: np.ndarray | None = None) -> float:
    """An upper bound of the hull's volume: the volume of the box of the wrenches (M, D) in
    their principal frame (the hull lies inside any box that holds its points). ``centred``:
    ``wrenches - wrenches.mean(axis=0)`` when the caller has it."""
    w = np.asarray(wrenches, dtype=np.float64)
    c = w - w.mean(axis=0) if centred is None else centred
    vt = np.linalg.svd(c, full_matrices=False)[2]
    p = c @ vt.T
    return float(np.prod(p.max(axis=0) - p.min(axis=0)))


def half_cone_bounds(wrenches: np.ndarray, n_edges: int) -> tuple[float, float, float] | None:
    """``(epsilon_lower, epsilon_upper, volume_upper)`` of the hull of ``wrenches`` (K * m, D:
    contact after contact, ``m = n_edges`` edges each) from the hull H of every other edge of
    each cone (half the points, about a quarter of the time):

    * H lies inside the full hull, so when the origin is inside H, H's epsilon (the distance to
      its nearest facet) is a lower bound; when it is not, the value returned (the smallest
      signed facet distance) is <= 0;
    * every facet normal of H is a direction, so the smallest support value of the full set
      over them is an upper bound;
    * with ``c`` the centroid of H's points, the full hull lies in ``c + s (H - c)`` where ``s``
      is the largest ratio over H's facets of the full set's support to H's offset (both
      measured from ``c``), so its volume is at most ``s^D vol(H)``.

    None when the bounds do not apply (fewer than 5 edges, H flat or qhull failing on it).
    """
    w = np.asarray(wrenches, dtype=np.float64)
    m, d = w.shape
    k = m // n_edges if n_edges else 0
    if n_edges < 5 or k * n_edges != m:
        return None
    sub = w.reshape(k, n_edges, d)[:, ::2].reshape(-1, d)
    if _wrench_check(sub):
        return None
    hull = _exact_hull(sub)
    if hull is None:
        return None
    nrm = hull.equations[:, :-1]
    dist = -hull.equations[:, -1]
    support = (w @ nrm.T).max(axis=0)  # (F,) the full set's support along each facet normal
    nc = nrm @ sub.mean(axis=0)
    inner = dist - nc  # distance from the centroid to each facet of H (> 0)
    if not inner.min() > GEOM_EPS:
        return None
    scale = max(1.0, float(((support - nc) / inner).max()))
    return float(dist.min()), float(support.min()), scale**d * float(hull.volume)


CLOSURE_PROOF_MIN: float = 1e-6
"""The smallest distance from the origin to the facets of a simplex of wrenches that is taken
as a proof of force closure (:func:`closure_certificate`): far above the rounding of the 7 x 7
inverse that measures it and above ``QUALITY_EPS``; smaller margins are decided by the hulls."""


def closure_certificate(wrenches: np.ndarray) -> tuple[bool | None, float]:
    """Force closure of 6D wrenches (M, 6) decided without a hull, with a certificate checked
    here: ``(False, 0)`` when the point of the hull nearest to the origin (Wolfe's algorithm,
    :mod:`pregrasp_core.minnorm`) gives a direction whose support value is at most
    :data:`NOT_CLOSURE_BOUND` (epsilon is 0); ``(True, lower)`` when the origin lies inside a
    simplex of 7 of the wrenches at a distance ``lower >= CLOSURE_PROOF_MIN`` from its facets
    (the simplex lies in the hull, so epsilon >= lower); ``(None, 0)`` otherwise."""
    from .minnorm import MAX_ITERATIONS, compiled

    w = np.ascontiguousarray(wrenches, dtype=np.float64)
    d = w.shape[1]
    x, corral, n, _ = compiled()(w, MAX_ITERATIONS)
    nx = float(np.linalg.norm(x))
    if nx > 0.0 and float((w @ (-x / nx)).max()) <= NOT_CLOSURE_BOUND:
        return False, 0.0
    if n != d + 1:
        return None, 0.0
    simplex = w[corral[:n, 0].astype(np.int64)]
    M = np.vstack([simplex.T, np.ones(n)])  # barycentric coordinates: M lam = (y, 1)
    try:
        inv = np.linalg.inv(M)
    except np.linalg.LinAlgError:
        return None, 0.0
    lam = inv[:, -1]  # the origin's
    grad = np.linalg.norm(inv[:, :d], axis=1)  # |gradient| of each coordinate in y
    e = np.zeros(n)
    e[-1] = 1.0
    if not (np.all(np.isfinite(inv)) and np.abs(M @ lam - e).max() <= 1e-12):
        return None, 0.0
    lower = float((lam / grad).min())  # distance from the origin to the simplex's facets
    if lower >= CLOSURE_PROOF_MIN:
        return True, lower
    return None, 0.0


CHEAP_MEMO_SIZE: int = 4096
"""Wrench sets whose cheapest bounds :func:`wrench_quality` keeps (then it starts afresh): the
planner scores every kept grasp at the cheapest level first and refines some of them later
(``planner/rank.py``), which would compute the same bounds of the same wrenches again. The
planner empties it at the end of each plan (:func:`forget_cheap_bounds`), so that a plan never
gains from an earlier one's sets (nor holds their memory)."""

_CHEAP_MEMO: dict[tuple[tuple[int, ...], int, bytes], tuple[float, float, bool | None, float]] = {}
"""(shape, edges per contact, the wrenches' bytes) -> the bounds of
:func:`_cheap_bounds_compiled` of a full-rank set (pure functions of those: a hit gives the
values a new computation would, bit for bit)."""


def forget_cheap_bounds() -> None:
    """Empty the memo of :func:`wrench_quality`'s cheapest bounds (:data:`CHEAP_MEMO_SIZE`)."""
    _CHEAP_MEMO.clear()


def _cheap_bounds_compiled(
    w: np.ndarray, n_edges: int
) -> tuple[str, tuple[float, float, bool | None, float]]:
    """``(reason, (epsilon upper bound, volume upper bound, force closure or None, epsilon lower
    bound))``: :func:`_wrench_check`'s reason ('' for a full-rank set) and
    :func:`wrench_quality`'s cheapest bounds of 6D wrenches ``w`` (M, 6), by one compiled pass
    (:func:`pregrasp_core.minnorm.cheap_bounds`: the tests and bounds of
    :func:`best_direction` in :func:`wrench_frame`, :func:`box_volume_bound`,
    :func:`closure_certificate` and :func:`walk_bound`, the sums in another order; about a
    third of the time of those functions' some 30 numpy calls)."""
    from .minnorm import MAX_ITERATIONS, compiled_cheap_bounds

    reason = _quick_check(w)
    if reason:
        return reason, (0.0, 0.0, None, 0.0)
    rank, upper, vol, closure, lower = compiled_cheap_bounds()(
        np.ascontiguousarray(w), int(n_edges), BOUND_DIRECTIONS, QUALITY_RANK_TOL, GEOM_EPS,
        NOT_CLOSURE_BOUND, CLOSURE_PROOF_MIN, MAX_ITERATIONS, WALK_STEPS,
    )  # fmt: skip
    if rank < w.shape[1]:
        return f"rank {rank} < {w.shape[1]}", (0.0, 0.0, None, 0.0)
    return "", (upper, vol, None if closure < 0 else bool(closure), lower)


def wrench_quality(
    wrenches: np.ndarray, n_contacts: int, n_edges: int, level: int = LEVEL_EXACT
) -> GraspQuality:
    """The scores of ``wrenches`` (K * m, D), contact after contact with ``m = n_edges`` edges
    each, at ``level`` (:data:`LEVEL_CHEAPEST`, :data:`LEVEL_HALF_CONES` or
    :data:`LEVEL_EXACT`). Below the exact level, force closure is still decided exactly:
    bounds are returned only when force closure is proven either way (a separating direction,
    or the origin inside a simplex of wrenches or inside the half-cone hull:
    :func:`closure_certificate`, :func:`half_cone_bounds`); otherwise the exact hull is built.
    Level 0 gives the directions' bounds when the certificate decides, level 1 always adds the
    half-cone bounds (or is exact where they do not apply). Bounded scores are upper bounds
    (margins :data:`EPS_BOUND_TOL`, :data:`VOLUME_BOUND_RTOL`)."""
    w = np.asarray(wrenches, dtype=np.float64)
    if w.ndim != 2:
        raise ValueError(f"wrenches must have shape (M, D), got {w.shape}")
    key = (w.shape, int(n_edges), w.tobytes())
    cheap = _CHEAP_MEMO.get(key)  # (a set seen before passed the check)
    bounded = level < LEVEL_EXACT and w.shape[1] == 6
    if cheap is None and not bounded:
        reason, _ = _centred_check(w)
        if reason:
            return GraspQuality(0.0, 0.0, n_contacts, False, reason)
    if bounded:
        if cheap is None:
            reason, cheap = _cheap_bounds_compiled(w, n_edges)
            if reason:
                return GraspQuality(0.0, 0.0, n_contacts, False, reason)
            if len(_CHEAP_MEMO) >= CHEAP_MEMO_SIZE:
                _CHEAP_MEMO.clear()
            _CHEAP_MEMO[key] = cheap
        upper, vol, closure, lower = cheap
        half = None
        if level > LEVEL_CHEAPEST or closure is None:
            half = half_cone_bounds(w, n_edges)
        if half is None and level > LEVEL_CHEAPEST:
            closure = None  # the half-cone bounds asked for do not apply: exact
        if half is not None:
            upper, vol = min(upper, half[1]), min(vol, half[2])
            lower = max(lower, half[0])
            if closure is None and upper <= NOT_CLOSURE_BOUND:
                closure = False
            if closure is None and lower > QUALITY_EPS + EPS_BOUND_TOL:
                closure = True
        if closure is not None:
            kind = QUALITY_BOUNDS[0 if half is None else 1]
            vol *= 1.0 + VOLUME_BOUND_RTOL
            if not closure:
                return GraspQuality(0.0, vol, n_contacts, False, "", True, False, kind)
            eps = upper + EPS_BOUND_TOL
            return GraspQuality(eps, vol, n_contacts, True, "", False, False, kind)
    eps, vol, reason = _hull_scores(w)
    return GraspQuality(eps, vol, n_contacts, eps > 0.0, reason)


def grasp_quality(
    points: np.ndarray,
    normals: np.ndarray,
    params: QualityParams = QualityParams(),  # noqa: B008 (frozen, immutable)
    tangents: np.ndarray | None = None,
    torques: bool = True,
    center: np.ndarray | None = None,
    radius: float | None = None,
    level: int = LEVEL_EXACT,
) -> GraspQuality:
    """Ferrari-Canny epsilon L1 and wrench-hull volume of a set of contacts.

    points: (K, 3) metres; normals: (K, 3) pointing into the object (normalised here);
    tangents: (K, 3) optional first cone edge direction per contact (see :func:`tangent_frames`);
    torques: False scores the 3D force space only (the antipodal oracle of docs/quality.md);
    center, radius: the torque origin and rho (see :func:`contact_wrenches` and the module
    docstring; :func:`object_frame` gives both for a cloud);
    level: :data:`LEVEL_EXACT` (default) or a cheaper level whose scores may be upper bounds
    (see :func:`wrench_quality`; force closure stays exact).
    """
    p = _as_vectors(points, "points")
    n = _as_vectors(normals, "normals")
    if p.shape != n.shape:
        raise ValueError(f"points and normals must have the same shape, got {p.shape}, {n.shape}")
    k = len(p)
    if k == 0:
        return GraspQuality(0.0, 0.0, 0, False, "no contacts")
    norms = np.linalg.norm(n, axis=1)
    if not (np.isfinite(norms).all() and (norms >= GEOM_EPS).all() and np.isfinite(p).all()):
        return GraspQuality(0.0, 0.0, k, False, "invalid contact normal or point")
    w = contact_wrenches(
        p, n, params, tangents=tangents, torques=torques, center=center, radius=radius
    )
    return wrench_quality(w, k, params.n_edges, level)


def object_frame(points: np.ndarray) -> tuple[np.ndarray, float]:
    """GraspIt's torque origin and scale of an object given by its points (N, 3): the centroid
    and the largest distance from it to a point (metres)."""
    pts = _as_vectors(points, "points")
    if len(pts) == 0:
        raise ValueError("object_frame needs at least one point")
    c = pts.mean(axis=0)
    return c, max(float(np.sqrt(((pts - c) ** 2).sum(axis=1).max())), GEOM_EPS)
