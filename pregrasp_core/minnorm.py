"""The point of least norm of a convex hull (Wolfe's algorithm), compiled with numba: the
quality stage's cheap and exact decision of force closure (``docs/quality.md``).

For points ``P`` (m, d), :func:`min_norm_point` returns the point ``x`` of ``conv(P)`` nearest to
the origin with the corral that gives it: at most ``d + 1`` affinely independent points of
``P`` and their convex weights. When ``x != 0`` the direction ``-x / |x|`` separates the origin
from the hull (every point has ``p . x >= |x|^2``); when the corral has ``d + 1`` points with
positive weights, the origin lies inside their simplex, which lies inside the hull. The caller
checks either certificate with plain numpy (:func:`pregrasp_core.quality.closure_certificate`),
so a rounding error here can only make it fall back to a slower exact method, never give a
wrong answer.

numba is imported and the kernel compiled (or loaded from numba's on-disk cache,
``cache=True``) on the first call of :func:`compiled`, never when the package is imported; the
kernel releases Python's global lock (``nogil=True``).

The module also holds the other compiled loops of the quality stage's cheapest bounds (all in
one file, so that numba's on-disk cache, which watches a kernel's own source file only, never
keeps a kernel compiled from an older helper): :func:`walk_loop` (the walk on the polar set of
``quality.walk_bound``) and :func:`cheap_bounds` (``quality.wrench_quality``'s cheapest level
in one call: the rank test, the principal box, the directions' bound in the grasp's frame, the
closure certificate and the walk).
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable

import numpy as np

from .jit import Lazy

_LOCK = threading.Lock()
_COMPILED: Callable[..., tuple[np.ndarray, np.ndarray, int, bool]] | None = None

MAX_ITERATIONS: int = 200
"""Major iterations of Wolfe's algorithm (each adds one point to the corral); it converges in
far fewer (tens) on the quality stage's sets; a set that does not is decided otherwise."""


def compiled() -> Callable[..., tuple[np.ndarray, np.ndarray, int, bool]]:
    """:func:`min_norm_point` compiled by numba (the first call imports numba and compiles it:
    about a second the very first time, then loaded from numba's cache)."""
    global _COMPILED
    if _COMPILED is None:
        with _LOCK:
            if _COMPILED is None:
                from .jit import import_numba

                numba = import_numba()
                _COMPILED = numba.njit(cache=True, nogil=True)(min_norm_point)
    return _COMPILED


def min_norm_point(P: np.ndarray, max_iter: int) -> tuple[np.ndarray, np.ndarray, int, bool]:
    """Wolfe's algorithm on the points ``P`` (m, d): ``(x (d,), corral (d + 1, 2), n, ok)``;
    ``corral[:n, 0]`` are point indices (as floats) and ``corral[:n, 1]`` their weights; ``ok``
    is False when the iterations ran out or an affine step was singular (then only ``x``, a
    point of the hull, is meaningful). Pure Python that numba compiles (:func:`compiled`)."""
    m, d = P.shape
    cap = d + 1
    idx = np.zeros(cap, dtype=np.int64)
    lam = np.zeros(cap)
    alpha = np.zeros(cap)
    x = np.zeros(d)
    scale = 0.0
    best, best_norm = 0, np.inf
    for k in range(m):
        s = 0.0
        for c in range(d):
            s += P[k, c] * P[k, c]
        if s > scale:
            scale = s
        if s < best_norm:
            best, best_norm = k, s
    idx[0] = best
    lam[0] = 1.0
    n = 1
    for c in range(d):
        x[c] = P[best, c]
    ok = False
    for _ in range(max_iter):  # major cycles
        xx = 0.0
        for c in range(d):
            xx += x[c] * x[c]
        if xx <= 1e-28 * scale:  # the origin reached
            ok = True
            break
        j, pj = 0, np.inf
        for k in range(m):
            s = 0.0
            for c in range(d):
                s += P[k, c] * x[c]
            if s < pj:
                j, pj = k, s
        if xx - pj <= 1e-12 * scale:  # no point beyond the plane through x: x is optimal
            ok = True
            break
        seen = False
        for i in range(n):
            if idx[i] == j:
                seen = True
        if seen or n == cap:  # rounding: stop here, undecided
            break
        idx[n] = j
        lam[n] = 0.0
        n += 1
        solved = True
        for _minor in range(cap + 1):  # minor cycles: project onto the corral's affine hull
            # the weights alpha[:n] (summing to 1) of the point of least norm of the affine
            # hull of the corral: [G 1; 1' 0] [a; mu] = [0; 1], G the Gram matrix, by
            # Gaussian elimination with partial pivoting (singular: undecided)
            kk = n + 1
            A = np.zeros((kk, kk))
            b = np.zeros(kk)
            big = 0.0
            for i in range(n):
                for jj in range(n):
                    s = 0.0
                    for c in range(d):
                        s += P[idx[i], c] * P[idx[jj], c]
                    A[i, jj] = s
                    big = max(big, abs(s))
                A[i, n] = 1.0
                A[n, i] = 1.0
            b[n] = 1.0
            tiny = 1e-13 * max(big, 1.0)
            for col in range(kk):
                piv = col
                for r in range(col + 1, kk):
                    if abs(A[r, col]) > abs(A[piv, col]):
                        piv = r
                if abs(A[piv, col]) <= tiny:
                    solved = False
                    break
                if piv != col:
                    for c in range(kk):
                        t = A[col, c]
                        A[col, c] = A[piv, c]
                        A[piv, c] = t
                    t = b[col]
                    b[col] = b[piv]
                    b[piv] = t
                for r in range(col + 1, kk):
                    f = A[r, col] / A[col, col]
                    for c in range(col, kk):
                        A[r, c] -= f * A[col, c]
                    b[r] -= f * b[col]
            if not solved:
                break
            for r in range(kk - 1, -1, -1):
                s = b[r]
                for c in range(r + 1, kk):
                    s -= A[r, c] * b[c]
                b[r] = s / A[r, r]
            for i in range(n):
                alpha[i] = b[i]
            inside = True
            for i in range(n):
                if alpha[i] <= 1e-12:
                    inside = False
            if inside:
                for i in range(n):
                    lam[i] = alpha[i]
                break
            theta = 1.0
            for i in range(n):
                if alpha[i] <= 1e-12:
                    t = lam[i] / (lam[i] - alpha[i])
                    if t < theta:
                        theta = t
            k = 0
            for i in range(n):
                v = (1.0 - theta) * lam[i] + theta * alpha[i]
                if v > 1e-12:
                    idx[k] = idx[i]
                    lam[k] = v
                    k += 1
            n = k
            if n == 0:
                solved = False
                break
        if not solved:
            break
        tot = 0.0
        for i in range(n):
            tot += lam[i]
        for c in range(d):
            s = 0.0
            for i in range(n):
                s += lam[i] * P[idx[i], c]
            x[c] = s / tot
    corral = np.zeros((cap, 2))
    for i in range(n):
        corral[i, 0] = idx[i]
        corral[i, 1] = lam[i]
    return x, corral, n, ok


def walk_loop(w: np.ndarray, u0: np.ndarray, max_steps: int) -> np.ndarray:
    """The direction (6,) where the walk of :func:`pregrasp_core.quality.walk_bound` ends, from
    ``u0`` (unit, with a positive support value). Pure Python that numba compiles."""
    m, d = w.shape
    h = -np.inf
    for i in range(m):
        h = max(h, w[i] @ u0)
    y = u0 / h  # on the boundary of the polar set {y : w y <= 1}
    act = np.empty(d, dtype=np.int64)
    wy = w @ y
    act[0] = int(np.argmax(wy))
    na = 1
    g = np.empty((d, d))
    lo = np.empty((d, d))
    for _ in range(max_steps):
        # the projection of y on the span of the active rows: (N N^T) c = N y by Cholesky
        for a in range(na):
            for b in range(na):
                g[a, b] = w[act[a]] @ w[act[b]]
        ok = True
        for a in range(na):
            s = g[a, a]
            for k in range(a):
                s -= lo[a, k] * lo[a, k]
            if not s > 1e-24 * g[a, a]:
                ok = False
                break
            lo[a, a] = np.sqrt(s)
            for b in range(a + 1, na):
                t = g[b, a]
                for k in range(a):
                    t -= lo[b, k] * lo[a, k]
                lo[b, a] = t / lo[a, a]
        if not ok:
            break
        c = np.empty(na)
        for a in range(na):  # forward then back substitution
            t = w[act[a]] @ y
            for k in range(a):
                t -= lo[a, k] * c[k]
            c[a] = t / lo[a, a]
        for a in range(na - 1, -1, -1):
            t = c[a]
            for k in range(a + 1, na):
                t -= lo[k, a] * c[k]
            c[a] = t / lo[a, a]
        dv = y.copy()
        for a in range(na):
            dv -= c[a] * w[act[a]]
        if dv @ dv <= 1e-18 * (y @ y):
            # y in the cone of the active rows: a local maximum of |y|, else drop a row
            j = int(np.argmin(c))
            if c[j] >= 0.0:
                break
            for a in range(j, na - 1):
                act[a] = act[a + 1]
            na -= 1
            continue
        if na == d:
            break
        wd = w @ dv
        wy = w @ y
        tol = 1e-12 * np.sqrt(dv @ dv)
        best, jb = np.inf, -1
        for i in range(m):
            inside = False
            for a in range(na):
                if act[a] == i:
                    inside = True
                    break
            if not inside and wd[i] > tol:
                t = (1.0 - wy[i]) / wd[i]
                if t < best:
                    best, jb = t, i
        if jb < 0:
            break
        y = y + max(best, 0.0) * dv
        act[na] = jb
        na += 1
    return y / np.sqrt(y @ y)


def _support(w: np.ndarray, u: np.ndarray) -> float:
    """``max_i w_i . u``: the support value of the rows of ``w`` (M, D) along ``u`` (D,)."""
    h = -np.inf
    for i in range(w.shape[0]):
        s = 0.0
        for c in range(w.shape[1]):
            s += w[i, c] * u[c]
        h = max(h, s)
    return h


_min_norm_inline = min_norm_point
""":func:`min_norm_point` as :func:`cheap_bounds` calls it (its compiled, inlined form once
:func:`compiled_cheap_bounds` has run)."""
_walk_inline = walk_loop
""":func:`walk_loop` as :func:`cheap_bounds` calls it (likewise)."""


def cheap_bounds(
    w: np.ndarray,
    n_edges: int,
    dirs: np.ndarray,
    rank_tol: float,
    geom_eps: float,
    not_closure: float,
    proof_min: float,
    max_iter: int,
    walk_steps: int,
) -> tuple[int, float, float, int, float]:
    """``quality.wrench_quality``'s cheapest level of finite wrenches ``w`` (M, D), D = 6 and
    M > D, in one pass: ``(rank, upper, volume, closure, lower)``.

    * ``rank``: of ``w - mean`` (singular values above ``rank_tol`` times the largest); below D
      the rest is not computed (zeros, closure -1);
    * ``volume``: the principal box's (``quality.box_volume_bound``);
    * ``upper``: the smallest support value over ``dirs`` (D, K) turned by the frame of the
      first contact's cone (``quality.wrench_frame``, ``quality.best_direction``), then, when
      force closure is proven, the smaller of it and the walk's (``quality.walk_bound``,
      ``walk_steps`` steps from that direction);
    * ``closure``: 0 when ``upper <= not_closure`` or when Wolfe's point of least norm gives a
      separating direction with a support value at most that; 1 when the origin lies inside a
      simplex of D + 1 wrenches at a distance ``lower >= proof_min`` from its facets
      (``quality.closure_certificate``); -1 when neither.

    The same tests as the numpy functions named, by loops (the sums in another order: values
    equal to theirs to rounding, ``tests/core/test_quality_bounds.py``). Every value returned is
    still the support value of a unit direction or a simplex's distance, so each bound holds
    whatever the rounding. Pure Python that numba compiles (:func:`compiled_cheap_bounds`)."""
    m, d = w.shape
    mean = np.zeros(d)
    for i in range(m):
        for c in range(d):
            mean[c] += w[i, c]
    for c in range(d):
        mean[c] /= m
    cen = np.empty((m, d))
    for i in range(m):
        for c in range(d):
            cen[i, c] = w[i, c] - mean[c]
    _, sv, vt = np.linalg.svd(cen, full_matrices=False)
    top = max(sv[0], geom_eps)
    rank = 0
    for k in range(sv.shape[0]):
        if sv[k] > rank_tol * top:
            rank += 1
    if rank < d:
        return rank, 0.0, 0.0, -1, 0.0
    vol = 1.0  # the box of the points in the principal frame
    for k in range(d):
        lo, hi = np.inf, -np.inf
        for i in range(m):
            p = 0.0
            for c in range(d):
                p += cen[i, c] * vt[k, c]
            lo = min(lo, p)
            hi = max(hi, p)
        vol *= hi - lo
    # the frame of the first contact's cone: n = the mean of its edge forces, a = the first
    # edge minus it, made orthogonal; columns a, n x a, n (identity for a flat cone)
    n0 = n1 = n2 = 0.0
    for e in range(n_edges):
        n0 += w[e, 0]
        n1 += w[e, 1]
        n2 += w[e, 2]
    n0, n1, n2 = n0 / n_edges, n1 / n_edges, n2 / n_edges
    a0, a1, a2 = w[0, 0] - n0, w[0, 1] - n1, w[0, 2] - n2
    na = math.sqrt(a0 * a0 + a1 * a1 + a2 * a2)
    nn = math.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
    R = np.eye(3)
    if na > 1e-9 * max(nn, 1.0) and nn > geom_eps:
        a0, a1, a2 = a0 / na, a1 / na, a2 / na
        n0, n1, n2 = n0 / nn, n1 / nn, n2 / nn
        an = a0 * n0 + a1 * n1 + a2 * n2
        a0, a1, a2 = a0 - an * n0, a1 - an * n1, a2 - an * n2
        na = math.sqrt(a0 * a0 + a1 * a1 + a2 * a2)
        a0, a1, a2 = a0 / na, a1 / na, a2 / na
        R[0, 0], R[1, 0], R[2, 0] = a0, a1, a2
        R[0, 1], R[1, 1], R[2, 1] = n1 * a2 - n2 * a1, n2 * a0 - n0 * a2, n0 * a1 - n1 * a0
        R[0, 2], R[1, 2], R[2, 2] = n0, n1, n2
    # the smallest support value over the turned directions
    u = np.empty(d)
    best_u = np.empty(d)
    upper = np.inf
    for j in range(dirs.shape[1]):
        for r in range(3):
            u[r] = R[r, 0] * dirs[0, j] + R[r, 1] * dirs[1, j] + R[r, 2] * dirs[2, j]
            u[r + 3] = R[r, 0] * dirs[3, j] + R[r, 1] * dirs[4, j] + R[r, 2] * dirs[5, j]
        h = _support(w, u)
        if h < upper:
            upper = h
            best_u[:] = u
    if upper <= not_closure:
        return rank, upper, vol, 0, 0.0
    # the closure certificate: Wolfe's point of least norm, then the simplex it ends on
    x, corral, nc, _ = _min_norm_inline(w, max_iter)
    nx = 0.0
    for c in range(d):
        nx += x[c] * x[c]
    nx = math.sqrt(nx)
    if nx > 0.0:
        if _support(w, -x / nx) <= not_closure:
            return rank, upper, vol, 0, 0.0
    if nc != d + 1:
        return rank, upper, vol, -1, 0.0
    M = np.ones((d + 1, d + 1))  # barycentric coordinates: M lam = (y, 1)
    for a in range(d + 1):
        row = int(corral[a, 0])
        for c in range(d):
            M[c, a] = w[row, c]
    try:
        inv = np.linalg.inv(M)
    except Exception:  # noqa: BLE001 - singular (numba raises LinAlgError)
        return rank, upper, vol, -1, 0.0
    for a in range(d + 1):
        for c in range(d + 1):
            if not math.isfinite(inv[a, c]):
                return rank, upper, vol, -1, 0.0
    for r in range(d + 1):  # the origin's coordinates reproduce (0, 1)
        s = 0.0
        for a in range(d + 1):
            s += M[r, a] * inv[a, d]
        if abs(s - (1.0 if r == d else 0.0)) > 1e-12:
            return rank, upper, vol, -1, 0.0
    lower = np.inf
    for a in range(d + 1):
        g = 0.0
        for c in range(d):
            g += inv[a, c] * inv[a, c]
        lower = min(lower, inv[a, d] / math.sqrt(g))
    if not lower >= proof_min:
        return rank, upper, vol, -1, 0.0
    y = _walk_inline(w, best_u, walk_steps)
    ok = True
    for c in range(d):
        ok = ok and math.isfinite(y[c])
    if ok:
        upper = min(upper, _support(w, y))
    return rank, upper, vol, 1, lower


def _build_cheap_bounds() -> Callable[..., tuple[int, float, float, int, float]]:
    from .jit import inline_helpers, njit

    inline_helpers(globals(), "_support", "_min_norm_inline", "_walk_inline")
    return njit(cheap_bounds)


_CHEAP = Lazy(_build_cheap_bounds)


def compiled_cheap_bounds() -> Callable[..., tuple[int, float, float, int, float]]:
    """:func:`cheap_bounds` compiled by numba (its helpers inlined; the first call imports
    numba and compiles it, then it is loaded from numba's cache)."""
    return _CHEAP.get()
