"""The pool's compiled collision test (`pregrasp_core.pregrasps.collision_kernels`).

``hand_hits_points`` runs the kernel; its answers are checked against references from outside
it: the hand model's own test (``Hand.hands_hit_points``: every point against every link box),
a plain numpy all-pairs test of every point against every link cell (the numpy expressions the
kernel reproduces), and the numpy version it replaced (``hand_hits_points_numpy``), on random
poses, on points placed on and around the boxes' faces and the cells' seams, and on the pools
of the demo objects.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pregrasp_core.hand import load_hand
from pregrasp_core.io import load_point_cloud
from pregrasp_core.paths import DEFAULT_OBJECT, demo_objects
from pregrasp_core.pipeline import PipelineParams, run_pipeline
from pregrasp_core.pregrasps import build, collision, collision_kernels
from pregrasp_core.pregrasps.collision import (
    CELL_SEAM,
    hand_hits_points,
    hand_hits_points_numpy,
    link_cells,
)

TYPES = ("cylindrical", "spherical", "three_finger_tip", "two_finger_tip")


@pytest.fixture(scope="module")
def hand():
    return load_hand()


def _poses(rng, n: int, spread: float = 0.25) -> np.ndarray:
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = Rotation.random(n, random_state=int(rng.integers(1 << 30))).as_matrix()
    T[:, :3, 3] = rng.uniform(-spread, spread, (n, 3))
    return T


def _all_pairs(hand, T: np.ndarray, q: np.ndarray, pts: np.ndarray, margin: float) -> np.ndarray:
    """(G,) bool: every point against every link cell of every hand (one preshape ``q``), with
    the numpy expressions of the cells' frames and of the exact test (no pruning at all)."""
    Tc, half = link_cells(hand, q, margin)
    T = np.ascontiguousarray(T)
    centres = np.einsum("gij,cj->gci", T[:, :3, :3], Tc[:, :3, 3])
    centres += T[:, None, :3, 3]  # (G, C, 3)
    R = np.einsum("gij,cjk->gcik", T[:, :3, :3], Tc[:, :3, :3])  # (G, C, 3, 3)
    G, C, N = len(T), len(Tc), len(pts)
    g, c, n = (
        a.reshape(-1) for a in np.meshgrid(np.arange(G), np.arange(C), np.arange(N), indexing="ij")
    )
    local = np.einsum("mj,mjk->mk", pts[n] - centres[g, c], R[g, c])
    inside = np.all(np.abs(local) <= half[c] + CELL_SEAM, axis=1)
    return np.bincount(g[inside], minlength=G) > 0


# ----------------------------------------------------------------------------- the bits


@pytest.mark.parametrize("G", [1, 2, 5, 64, 700])
def test_cell_frames_have_the_bits_of_the_numpy_einsums(hand, G):
    """The kernel's world cell centres and rotations are those of the einsums of
    ``hand_hits_points_numpy`` to the bit, for hands taken from a pool's array as it does."""
    rng = np.random.default_rng(G)
    big = _poses(rng, 3 * G + 1, spread=2.0)
    T = big[rng.permutation(len(big))[:G]]  # a fancy-indexed copy, as T_world_hand[sel]
    k = collision_kernels.kernels()
    for gt in TYPES:
        Tc, _ = link_cells(hand, hand.preshape(gt), 0.003)
        centres = np.einsum("gij,cj->gci", T[:, :3, :3], Tc[:, :3, 3])
        centres += T[:, None, :3, 3]
        R = np.einsum("gij,cjk->gcik", T[:, :3, :3], Tc[:, :3, :3])
        kc, kR = k.frames(T, Tc)
        assert kc.tobytes() == centres.tobytes()
        assert kR.tobytes() == R.tobytes()


@pytest.mark.parametrize("M", [1, 2, 3, 17, 5000])
def test_cell_coordinates_have_the_bits_of_the_numpy_einsum(M):
    """(p - centre) @ R as the numpy version's einsum over (point, cell) pairs computes it."""
    rng = np.random.default_rng(M)
    R = Rotation.random(1, random_state=M).as_matrix()[0]
    centre = rng.uniform(-1.0, 1.0, 3)
    p = centre + rng.normal(scale=10.0 ** rng.uniform(-4, 0, (M, 1)), size=(M, 3))
    ref = np.einsum("mj,mjk->mk", p - centre[None], np.tile(R, (M, 1, 1)))
    got = collision_kernels.kernels().local(p, centre, R)
    assert got.tobytes() == ref.tobytes()


def test_the_einsum_order_matters_so_the_bit_tests_can_fail():
    """Another order of the same sum gives other bits on such data (what the two tests above
    would see if the kernel summed in another order)."""
    rng = np.random.default_rng(0)
    a, b = rng.normal(size=(1000, 3)), rng.normal(size=(1000, 3))
    seq = (a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1]) + a[:, 2] * b[:, 2]
    other = (a[:, 0] * b[:, 0] + a[:, 2] * b[:, 2]) + a[:, 1] * b[:, 1]
    assert not np.array_equal(seq, other)


# ----------------------------------------------------------------------------- the answers


@pytest.mark.parametrize("margin", [0.0, 0.004, 0.02])
def test_random_poses_give_the_hand_models_answer(hand, margin):
    rng = np.random.default_rng(1)
    pts = rng.uniform(-0.1, 0.1, (2500, 3))
    G = 300
    T = _poses(rng, G)
    for gt in TYPES:
        q = np.tile(hand.preshape(gt), (G, 1))
        ours = hand_hits_points(hand, T, np.full(G, gt), q, pts, margin=margin)
        assert np.array_equal(ours, hand.hands_hit_points(pts, T, q[0], margin))
        assert np.array_equal(ours, hand_hits_points_numpy(hand, T, np.full(G, gt), q, pts, margin))
        assert 20 < ours.sum() < G - 20


def test_many_preshapes_give_the_hand_models_answer_hand_by_hand(hand):
    rng = np.random.default_rng(2)
    pts = rng.uniform(-0.1, 0.1, (3000, 3))
    G = 150
    T = _poses(rng, G)
    base = np.stack([hand.preshape(g) for g in TYPES])
    shapes = base[rng.integers(0, 4, 20)] + rng.uniform(-0.2, 0.2, (20, base.shape[1]))
    shapes = np.stack([hand.clamp(s) for s in shapes])
    q = shapes[rng.integers(0, 20, G)]
    ref = np.array([hand.hands_hit_points(pts, T[i : i + 1], q[i], 0.004)[0] for i in range(G)])
    ours = hand_hits_points(hand, T, np.full(G, "spherical"), q, pts, margin=0.004)
    assert np.array_equal(ours, ref) and 10 < ours.sum() < G - 10
    old = hand_hits_points_numpy(hand, T, np.full(G, "spherical"), q, pts, margin=0.004)
    assert np.array_equal(ours, old)


def test_no_hands_no_points_one_point(hand):
    q = np.tile(hand.preshape("spherical"), (3, 1))
    T = np.tile(np.eye(4), (3, 1, 1))
    T[1, :3, 3] = 5.0  # far away
    gts = np.full(3, "spherical")
    assert hand_hits_points(hand, T[:0], gts[:0], q[:0], np.zeros((4, 3))).shape == (0,)
    none = hand_hits_points(hand, T, gts, q, np.zeros((0, 3)))
    assert none.dtype == bool and not none.any() and none.shape == (3,)
    # one point at the centre of the first link box of the hands at the origin
    Tb = hand.box_poses(q[0])
    p = Tb[0, :3, 3][None]
    assert hand_hits_points(hand, T, gts, q, p).tolist() == [True, False, True]
    assert hand.hands_hit_points(p, T, q[0]).tolist() == [True, False, True]


def _box_points(hand, q, margin, T, rng, n_per_box: int, offsets) -> np.ndarray:
    """Points (N, 3) in the world near the grown link boxes of the hand at ``T`` (4, 4): on each
    box face (one coordinate at half + offset, the others inside) and on the seams between the
    box's cells (one coordinate exactly on a seam, the others inside)."""
    Tb = hand.box_poses(q)
    halves = np.asarray(hand.link_box_half, dtype=np.float64) + margin
    out = []
    for l, half in enumerate(halves):  # loop over the links
        n = np.maximum(np.ceil(half / max(half.min(), 1e-12) - 1e-9), 1).astype(int)
        for a in range(3):
            u = rng.uniform(-0.9, 0.9, (n_per_box, 3)) * half
            off = rng.choice(np.asarray(offsets), n_per_box)
            side = rng.choice([-1.0, 1.0], n_per_box)
            u[:, a] = side * (half[a] + off)
            out.append(u @ Tb[l, :3, :3].T + Tb[l, :3, 3])
            if n[a] > 1:  # the seams of the cells along axis a
                seams = -half[a] + np.arange(1, n[a]) * (2 * half[a] / n[a])
                u = rng.uniform(-0.9, 0.9, (n_per_box, 3)) * half
                u[:, a] = rng.choice(seams, n_per_box)
                out.append(u @ Tb[l, :3, :3].T + Tb[l, :3, 3])
    p = np.concatenate(out)
    return p @ T[:3, :3].T + T[:3, 3]


@pytest.mark.parametrize("margin", [0.0, 0.003])
def test_points_on_and_beside_faces_and_seams_give_the_hand_models_answer(hand, margin):
    """One point at a time (so each answer is that point's): points 1e-9 inside or outside the
    link boxes' faces and exactly on the seams between their cells. (A point exactly on a face
    is inside the box to within round-off: the hand model's own arithmetic puts about a third of
    them outside, the cells grown by CELL_SEAM all inside; the next test takes them.)"""
    rng = np.random.default_rng(3)
    for gt in TYPES:
        q = hand.preshape(gt)
        T = _poses(rng, 2, spread=0.5)
        pts = np.concatenate(
            [_box_points(hand, q, margin, T[i], rng, 2, (-1e-9, 1e-9)) for i in range(2)]
        )
        Q = np.tile(q, (2, 1))
        for p in pts:  # loop over the points (about 150)
            ours = hand_hits_points(hand, T, np.full(2, gt), Q, p[None], margin=margin)
            ref = hand.hands_hit_points(p[None], T, q, margin)
            assert np.array_equal(ours, ref)


def test_points_within_the_seam_tolerance_give_the_all_pairs_answer(hand):
    """Points within a few CELL_SEAM of the boxes' faces and on the cells' seams: the kernel
    decides as the plain numpy all-pairs test with the same expressions, point by point, and
    the numpy version it replaced agrees."""
    rng = np.random.default_rng(4)
    offsets = (-3e-12, -1e-12, -5e-13, 0.0, 5e-13, 1e-12, 1.5e-12, 3e-12)
    seen = set()
    for gt in TYPES:
        q = hand.preshape(gt)
        T = _poses(rng, 3, spread=0.3)
        pts = np.concatenate([_box_points(hand, q, 0.0, T[i], rng, 2, offsets) for i in range(3)])
        Q = np.tile(q, (3, 1))
        for p in pts:  # loop over the points
            ours = hand_hits_points(hand, T, np.full(3, gt), Q, p[None])
            ref = _all_pairs(hand, T, q, p[None], 0.0)
            assert np.array_equal(ours, ref)
            old = hand_hits_points_numpy(hand, T, np.full(3, gt), Q, p[None])
            assert np.array_equal(ours, old)
            seen.add(bool(ours.any()))
    assert seen == {True, False}


def test_clouds_around_random_hands_give_the_all_pairs_answer(hand):
    """Dense small clouds around random hands (many points in and near the cells)."""
    rng = np.random.default_rng(5)
    for gt in TYPES:
        q = hand.preshape(gt)
        T = _poses(rng, 40, spread=0.08)
        pts = rng.normal(scale=0.04, size=(60, 3))
        ours = hand_hits_points(hand, T, np.full(40, gt), np.tile(q, (40, 1)), pts, margin=0.001)
        ref = _all_pairs(hand, T, q, pts, 0.001)
        assert np.array_equal(ours, ref) and 0 < ours.sum() < 40


def test_the_answers_do_not_depend_on_the_voxel(hand, monkeypatch):
    rng = np.random.default_rng(6)
    pts = rng.normal(scale=0.05, size=(4000, 3))
    G = 200
    T = _poses(rng, G, spread=0.15)
    q = np.tile(hand.preshape("cylindrical"), (G, 1))
    gts = np.full(G, "cylindrical")
    answers = []
    for voxel in (0.0005, 0.003, 0.005, 0.02, 1.0):
        monkeypatch.setattr(collision, "VOXEL", voxel)
        answers.append(hand_hits_points(hand, T, gts, q, pts, margin=0.002))
    assert all(np.array_equal(a, answers[0]) for a in answers)
    assert np.array_equal(answers[0], hand.hands_hit_points(pts, T, q[0], 0.002))


def test_a_sparse_cloud_gets_a_bounded_grid():
    """Two points a kilometre apart: the voxel grows until the grid has at most 4,096 voxels."""
    pts = np.array([[0.0, 0.0, 0.0], [1000.0, 1000.0, 1000.0]])
    g = collision_kernels.point_grid(pts, 0.005)
    assert int(np.prod(g.dims)) <= 4096 and g.start[-1] == 2
    assert sorted(map(tuple, g.pts)) == sorted(map(tuple, pts))


# ----------------------------------------------------------------------------- the pools


@pytest.mark.parametrize("path", demo_objects(), ids=lambda p: p.stem)
def test_demo_pools_get_the_answers_of_the_numpy_version(hand, monkeypatch, path):
    """Every collision test of the pool stage of each demo object (4,000 points): the kernel's
    answer equals the numpy version's, call by call (and the pool is built on them)."""
    calls = []

    def both(*args, **kwargs):
        ours = hand_hits_points(*args, **kwargs)
        old = hand_hits_points_numpy(*args, **kwargs)
        calls.append((len(ours), int(ours.sum()), bool(np.array_equal(ours, old))))
        return ours

    monkeypatch.setattr(build, "hand_hits_points", both)
    cloud = load_point_cloud(path, n_points=4000, seed=0)
    run_pipeline(cloud, PipelineParams(), hand, until="pool")
    assert calls and all(same for _, _, same in calls), calls
    if path == DEFAULT_OBJECT:
        assert sum(h for _, h, _ in calls) > 0 and sum(n - h for n, h, _ in calls) > 0


def test_warm_up_compiles_every_kernel_for_the_pools_arrays(hand):
    """warm_up compiles every kernel; a pool on the pipeline's (read-only) cloud then compiles
    nothing more (numba would compile again for another array type)."""
    assert collision_kernels.warm_up() > 0.0
    k = collision_kernels.kernels()
    for name in k._fields:
        assert getattr(k, name).signatures, f"{name} was not compiled by warm_up"
    before = {name: len(getattr(k, name).signatures) for name in ("bounds", "grid", "hits")}
    cloud = load_point_cloud(DEFAULT_OBJECT, n_points=2000, seed=0)
    assert not cloud.points.flags.writeable
    run_pipeline(cloud, PipelineParams(), hand, until="pool")
    after = {name: len(getattr(k, name).signatures) for name in ("bounds", "grid", "hits")}
    assert after == before


def test_a_grid_given_once_gives_the_answers_of_a_grid_built_per_call(hand):
    """The pool builds the cloud's grid once (``cloud_grid``) and passes it to every call: the
    answers are those of a call that builds its own, and of the hand model, on two clouds."""
    rng = np.random.default_rng(7)
    a, b = rng.uniform(-0.1, 0.1, (2000, 3)), rng.uniform(-0.1, 0.1, (2000, 3)) + 0.02
    G = 100
    T = _poses(rng, G, spread=0.2)
    q = np.tile(hand.preshape("spherical"), (G, 1))
    gts = np.full(G, "spherical")
    for pts in (a, b):
        grid = collision.cloud_grid(pts)
        ours = hand_hits_points(hand, T, gts, q, pts, grid=grid)
        assert np.array_equal(ours, hand_hits_points(hand, T, gts, q, pts))
        assert np.array_equal(ours, hand.hands_hit_points(pts, T, q[0]))
        assert 10 < ours.sum() < G - 10


def test_preshape_groups_are_those_of_the_numpy_version():
    rng = np.random.default_rng(8)
    shapes = rng.normal(size=(6, 16))
    for q in (np.tile(shapes[0], (50, 1)), shapes[rng.integers(0, 6, 300)], shapes[:1]):
        part, first = collision._preshape_parts(q)
        groups = {tuple(np.flatnonzero(part == k)) for k in range(len(first))}
        assert groups == {tuple(g) for g in collision._by_preshape(q)}
        assert all(np.array_equal(q[first[part[i]]], q[i]) for i in range(len(q)))


def test_points_at_the_cells_corners_give_the_all_pairs_answer(hand):
    """Points on the cells' corners and up to 1.5 CELL_SEAM beyond them (diagonally): the
    kernel decides as the all-pairs test. (The numpy version asked its k-d tree for the points
    of each cell's circumscribed sphere first, which leaves out some of the points of this band:
    on such a point, exactly on a box's surface to within 1e-12 m, it can say free where the
    exact test says hit; the hand model's own answer there is round-off. Nowhere else, and on
    no demo pool, do the two differ.)"""
    rng = np.random.default_rng(9)
    signs = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)
    seen = set()
    for gt in ("spherical", "two_finger_tip"):
        q = hand.preshape(gt)
        Tc, half = link_cells(hand, q, 0.0)
        for _ in range(8):  # loop over hand poses
            T = _poses(rng, 1, spread=0.3)
            c = rng.integers(0, len(Tc), 25)
            u = signs[rng.integers(0, 8, 25)] * (
                half[c] + rng.choice([0.0, 0.5, 0.9, 1.5], 25)[:, None] * 1e-12
            )
            p = np.einsum("cij,cj->ci", Tc[c, :3, :3], u) + Tc[c, :3, 3]
            p = p @ T[0, :3, :3].T + T[0, :3, 3]
            for pt in p:  # loop over the points
                ours = hand_hits_points(hand, T, np.array([gt]), q[None], pt[None])
                assert np.array_equal(ours, _all_pairs(hand, T, q, pt[None], 0.0))
                seen.add(bool(ours[0]))
    assert seen == {True, False}
