"""The compiled loops of the decomposition and its MVBB (issue 15) give the numpy results to the
bit.

References: the numpy code they replaced (commit fe74cdf), copied here verbatim in small
functions, and for the kernel mask an independent definition by sorting. Every comparison is
``np.array_equal`` on the raw values (no tolerance), on random clouds with ties, on the demo
clouds and at the smallest shapes (one candidate, two points).
"""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from pregrasp_core import mvbb
from pregrasp_core.decomposition import best_cut
from pregrasp_core.decomposition_kernels import kernels, warm_up
from pregrasp_core.io import load_point_cloud
from pregrasp_core.mvbb import MvbbParams
from pregrasp_core.paths import OBJECTS_DIR

# ---------------------------------------------------------------------------------------------
# numpy references (the code before issue 15)


def kernel_mask_by_sorting(q: np.ndarray, lo: np.ndarray, ext: np.ndarray, grid: int):
    """Independent definition: per axis a and column (cells of the two other axes), the point
    with the largest and the one with the smallest coordinate a, the lowest index on a tie."""
    n = q.shape[1]
    cells = np.minimum(((q - lo[:, None]) / ext[:, None] * grid).astype(np.int64), grid - 1)
    keep = np.zeros(n, dtype=bool)
    idx = np.arange(n)
    for a in range(3):
        col = cells[(a + 1) % 3] * grid + cells[(a + 2) % 3]
        for sign in (1.0, -1.0):
            order = np.lexsort((idx, -sign * q[a], col))  # by column, extreme first, index
            first = np.r_[True, col[order][1:] != col[order][:-1]]
            keep[order[first]] = True
    return keep


def cut_scan_numpy(pT, order, a, lo, hi):
    s = np.take(pT, order, axis=1)
    x = s[a]
    others = s[[b for b in range(3) if b != a]]
    pre = np.maximum.accumulate(others, axis=1)
    pre -= np.minimum.accumulate(others, axis=1)
    rev = others[:, ::-1]
    suf = np.maximum.accumulate(rev, axis=1)
    suf -= np.minimum.accumulate(rev, axis=1)
    suf = suf[:, ::-1]
    left_i, right_i = slice(lo, hi + 1), slice(lo + 1, hi + 2)
    xl, xr = x[left_i], x[right_i]
    total = xl - x[0]
    total *= pre[0, left_i]
    total *= pre[1, left_i]
    v_right = x[-1] - xr
    v_right *= suf[0, right_i]
    v_right *= suf[1, right_i]
    total += v_right
    total[xr <= xl] = np.inf
    j = int(np.argmin(total))
    return j, float(total[j])


def pattern_search_numpy(cur, Vf, p, start, stop, dtype=np.float64):
    cur_t = np.ascontiguousarray(cur.transpose(0, 2, 1))
    Vf = Vf.astype(dtype, copy=False)
    cur_vol = mvbb._volumes(cur.astype(dtype), Vf)
    radius = float(np.sqrt((Vf * Vf).sum(axis=0).max()))
    n_levels = stop
    steps = p.step_start * 0.5 ** np.arange(n_levels)
    stencils_t = mvbb._stencils_t(float(p.step_start), int(n_levels))
    level = np.full(len(cur), start, dtype=np.int64)
    active = [Vf, Vf, Vf]
    spent, budget = 0.0, -1.0
    for _ in range(p.max_iterations):
        live = np.flatnonzero(level < n_levels)
        n_live = len(live)
        if n_live == 0:
            break
        Ct, lv = cur_t[live], level[live]
        step = float(steps[lv].max())
        if spent + step > budget:
            budget, spent = p.active_reach * step, 0.0
            proj = (Ct.astype(dtype).reshape(-1, 3) @ Vf).reshape(n_live, 3, -1)
            margin = 2.0 * radius * budget * (1.0 + 1e-9)
            near = (proj >= proj.max(axis=2, keepdims=True) - margin) | (
                proj <= proj.min(axis=2, keepdims=True) + margin
            )
            near_k = near.any(axis=0)
            active = [np.compress(near_k[k], Vf, axis=1) for k in range(3)]
        trial_t = stencils_t[lv] @ Ct[:, None]
        trial_e = trial_t.astype(dtype, copy=False)
        tv = np.ones((n_live, 26), dtype=dtype)
        for k in range(3):
            pk = trial_e[:, :, k, :].reshape(-1, 3) @ active[k]
            tv *= (pk.max(axis=1) - pk.min(axis=1)).reshape(n_live, 26)
        j = np.argmin(tv, axis=1)
        tbest = tv[np.arange(n_live), j]
        better = tbest < cur_vol[live] * (1.0 - 1e-12)
        if np.any(better):
            spent += step
            up = live[better]
            cur_t[up] = trial_t[better, j[better]]
            cur_vol[up] = tbest[better]
        level[live[~better]] += 1
    return np.ascontiguousarray(cur_t.transpose(0, 2, 1))


def frames_numpy(n):
    helper = np.zeros_like(n)
    helper[np.arange(len(n)), np.argmin(np.abs(n), axis=1)] = 1.0
    u = mvbb._cross(helper.T, n.T).T
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    v = mvbb._cross(n.T, u.T).T
    return np.stack([u, v, n], axis=2)


def sweep_numpy(V, cand, n_angles):
    frames = frames_numpy(cand)
    proj = (frames.transpose(0, 2, 1).reshape(-1, 3) @ V).reshape(len(cand), 3, -1)
    height = proj[:, 2].max(axis=1) - proj[:, 2].min(axis=1)
    angles = mvbb._sweep_angles(n_angles)
    c, s = np.cos(angles), np.sin(angles)
    rot2 = np.concatenate([np.stack([c, s], axis=1), np.stack([-s, c], axis=1)])
    xy = rot2 @ proj[:, :2]
    ext = xy.max(axis=2) - xy.min(axis=2)
    area = ext[:, :n_angles] * ext[:, n_angles:]
    return frames, area * height[:, None]


def outside_numpy(eq, F, thr):
    signed = eq[:, :3] @ F
    signed += eq[:, 3:]
    return signed.max(axis=0) > thr


# ---------------------------------------------------------------------------------------------
# inputs


def _rotations(n: int, seed: int) -> np.ndarray:
    q = np.random.default_rng(seed).normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = q.T
    R = np.stack(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )
    return np.ascontiguousarray(R.transpose(2, 0, 1))


def _clouds():
    """(name, (3, N) centred points): random blobs, a cloud with many ties, demo clouds."""
    rng = np.random.default_rng(5)
    out = [
        ("blob", rng.normal(size=(3, 700)) * np.array([[0.05], [0.02], [0.01]])),
        ("ties", rng.integers(-6, 7, size=(3, 900)).astype(float) * 0.01),
        ("tiny", rng.normal(size=(3, 9)) * 0.03),
    ]
    for name in ("mug_handle", "box_cereal", "tool_frypan"):
        pts = load_point_cloud(OBJECTS_DIR / f"{name}.obj", n_points=4000, seed=1).points
        out.append((name, np.ascontiguousarray((pts - pts.mean(axis=0)).T)))
    return out


CLOUDS = _clouds()
IDS = [c[0] for c in CLOUDS]


# ---------------------------------------------------------------------------------------------
# tests


def test_importing_the_core_does_not_import_numba():
    code = (
        "import sys, pregrasp_core.decomposition, pregrasp_core.mvbb, "
        "pregrasp_core.decomposition_kernels\n"
        "print('numba' in sys.modules)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def test_warm_up_compiles_every_kernel():
    assert warm_up() > 0.0
    k = kernels()
    for name in k._fields:
        assert getattr(k, name).signatures, f"{name} was not compiled by warm_up"


@pytest.mark.parametrize(("name", "q"), CLOUDS, ids=IDS)
@pytest.mark.parametrize("grid", [1, 6, 16])
def test_kernel_mask_is_the_column_extremes(name, q, grid):
    lo, ext = q.min(axis=1), np.ptp(q, axis=1)
    got = kernels().kernel_mask(q, lo, ext, grid)
    assert np.array_equal(got, kernel_mask_by_sorting(q, lo, ext, grid))
    assert got.any()


@pytest.mark.parametrize(("name", "q"), CLOUDS, ids=IDS)
def test_cut_scan_equals_the_numpy_running_extents(name, q):
    n = q.shape[1]
    for a in range(3):
        order = np.argsort(q[a])
        for lo, hi in ((0, n - 2), (min(3, n // 2 - 1), n - min(3, n // 2 - 1) - 2)):
            j, v = kernels().cut_scan(q, order, a, lo, hi)
            j_ref, v_ref = cut_scan_numpy(q, order, a, lo, hi)
            assert (j, np.float64(v).tobytes()) == (j_ref, np.float64(v_ref).tobytes())


def test_cut_scan_with_every_cut_between_equal_values():
    """All coordinates equal along the axis: every cut is inf, argmin's answer is 0."""
    q = np.zeros((3, 10))
    q[1] = np.arange(10.0)
    j, v = kernels().cut_scan(q, np.arange(10), 0, 2, 6)
    assert (j, v) == cut_scan_numpy(q, np.arange(10), 0, 2, 6) == (0, np.inf)
    assert best_cut(q.T, 3) is not None  # the cut goes along axis 1 instead


@pytest.mark.parametrize(("name", "q"), CLOUDS[:2] + CLOUDS[3:], ids=IDS[:2] + IDS[3:])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("n_starts", [1, 4])
def test_pattern_search_equals_the_numpy_loop(name, q, dtype, n_starts):
    p = MvbbParams()
    starts = _rotations(n_starts, seed=n_starts)
    levels = mvbb._n_levels(p)
    for start, stop in ((0, 4), (4, levels), (0, levels)):
        got = mvbb._pattern_search(starts, q, p, start, stop, dtype)
        ref = pattern_search_numpy(starts, q, p, start, stop, dtype)
        assert np.array_equal(got, ref), (start, stop)
        assert not np.array_equal(got, starts)  # it moved


def test_pattern_search_with_one_active_point_per_axis():
    """Two points only: the active sets can hold a single point (a zero extent, whatever the
    product gives)."""
    q = np.array([[0.0, 0.03], [0.0, 0.01], [0.0, 0.02]])
    p = MvbbParams(active_reach=1e-6)
    starts = _rotations(2, seed=3)
    for dtype in (np.float32, np.float64):
        got = mvbb._pattern_search(starts, q, p, 0, 6, dtype)
        assert np.array_equal(got, pattern_search_numpy(starts, q, p, 0, 6, dtype))


def _unit_normals(k: int, seed: int) -> np.ndarray:
    n = np.random.default_rng(seed).normal(size=(k, 3))
    n[0] = (0.0, 0.0, 1.0)  # ties in |n|
    if k > 1:
        n[1] = (1.0, -1.0, 0.0)
    return n / np.linalg.norm(n, axis=1, keepdims=True)


@pytest.mark.parametrize("k", [1, 2, 48])
def test_frames_equal_the_numpy_cross_products(k):
    n = _unit_normals(k, seed=k)
    assert np.array_equal(kernels().frames(n), frames_numpy(n))


@pytest.mark.parametrize(("name", "q"), CLOUDS, ids=IDS)
@pytest.mark.parametrize("k", [1, 48])
def test_sweep_equals_the_numpy_products(name, q, k):
    cand = _unit_normals(k, seed=7)
    for n_angles in (1, 8, 12):
        f_got, v_got = mvbb._sweep(q, cand, n_angles)
        f_ref, v_ref = sweep_numpy(q, cand, n_angles)
        assert np.array_equal(f_got, f_ref) and np.array_equal(v_got, v_ref)


@pytest.mark.parametrize(("name", "q"), CLOUDS, ids=IDS)
def test_outside_equals_the_numpy_table(name, q):
    from scipy.spatial import ConvexHull

    sub = q[:, ::7] if q.shape[1] > 40 else q[:, :5]
    eq = ConvexHull(sub.T).equations
    d = eq[:, :3] @ q + eq[:, 3:]
    for thr in (-1e-12, 0.0, float(np.median(d.max(axis=0)))):
        got = kernels().outside(eq, q, thr)
        assert np.array_equal(got, outside_numpy(eq, q, thr))


@pytest.mark.parametrize(("name", "q"), CLOUDS, ids=IDS)
def test_near_faces_equals_the_numpy_masks(name, q):
    lo, hi = q.min(axis=1), q.max(axis=1)
    for margin in (0.0, 1e-3, 0.25 * float(np.ptp(q, axis=1).min())):
        got = kernels().near_faces(q, lo, hi, margin)
        ref = np.flatnonzero(
            np.any((q >= hi[:, None] - margin) | (q <= lo[:, None] + margin), axis=0)
        )
        assert np.array_equal(got, ref)
