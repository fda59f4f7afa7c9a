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
"""

from __future__ import annotations

import threading
from collections.abc import Callable

import numpy as np

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
