"""Traversal, enclosing-surface sampling and the pre-grasp pool (`pregrasp_core.pregrasps`)."""

from __future__ import annotations

import json
import re
import time
import tracemalloc
from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from pregrasp_core.box import OrientedBox
from pregrasp_core.decomposition import BoxNode, BoxTree
from pregrasp_core.errors import PregraspError
from pregrasp_core.facemask import (
    FACE_NORMAL,
    FaceMaskParams,
    SupportPlane,
    compute_face_masks,
    subface_scheme,
    usable_subfaces,
)
from pregrasp_core.hand import load_hand
from pregrasp_core.io import load_point_cloud
from pregrasp_core.paths import DEFAULT_OBJECT
from pregrasp_core.pipeline import PipelineParams, run_pipeline
from pregrasp_core.pregrasps import (
    MAX_POOL_SAMPLES,
    SAMPLING_BOUNDS,
    SURFACES,
    PreGraspPool,
    SamplingParams,
    TraversalPolicy,
    build_pool,
    check_pool_size,
    collision,
    count_samples,
    estimate_pool_bytes,
    grip_width,
    hand_corners,
    hand_hits_points,
    sample_node,
    total_samples,
    traverse,
)
from pregrasp_core.shape import GRASP_TYPE_OF_CLASS, NodeShape, ShapeClass, ShapeParams

UP = np.array([0.0, 0.0, 1.0])
TYPES = ("cylindrical", "spherical", "three_finger_tip", "two_finger_tip")
BOX = OrientedBox(
    np.array([0.1, -0.2, 0.3]),
    Rotation.from_euler("xyz", [0.4, -0.3, 1.1]).as_matrix(),
    np.array([0.12, 0.07, 0.04]),
)


@pytest.fixture(scope="module")
def hand():
    return load_hand()


def shape_of(cls: ShapeClass) -> NodeShape:
    return NodeShape(np.array([3.0, 2.0, 1.0]), cls, GRASP_TYPE_OF_CLASS[cls])


def box_surface_points(lo, hi, n: int, rng) -> np.ndarray:
    """``n`` points uniformly on the surface of the axis-aligned box [lo, hi]."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    e = hi - lo
    areas = np.array([e[1] * e[2], e[1] * e[2], e[0] * e[2], e[0] * e[2], e[0] * e[1], e[0] * e[1]])
    face = rng.choice(6, size=n, p=areas / areas.sum())
    p = lo + rng.uniform(size=(n, 3)) * e
    axis, side = face // 2, face % 2
    p[np.arange(n), axis] = np.where(side == 0, hi[axis], lo[axis])
    return p


def tree_from_parts(parts, rng, n_per_part=1500):
    """A root over axis-aligned parts (given as (lo, hi)); two parts -> two leaf children.
    Returns (tree, points)."""
    pts = [box_surface_points(lo, hi, n_per_part, rng) for lo, hi in parts]
    points = np.concatenate(pts)
    idx = np.arange(len(points), dtype=np.int64)
    root = OrientedBox.from_points_in_frame(points, np.eye(3))
    kids = tuple(range(1, len(parts) + 1)) if len(parts) > 1 else ()
    nodes = [BoxNode(0, -1, kids, 0, idx, root, 0)]
    start = 0
    for k, p in enumerate(pts if kids else []):
        sub = idx[start : start + len(p)]
        start += len(p)
        nodes.append(
            BoxNode(k + 1, 0, (), 1, sub, OrientedBox.from_points_in_frame(p, np.eye(3)), 1)
        )
    return BoxTree(tuple(nodes), len(points)), points


# ----------------------------------------------------------------------------- sample_node


@pytest.mark.parametrize("gt", TYPES)
def test_every_approach_points_at_its_aim_and_starts_on_the_enclosing_surface(gt):
    params = SamplingParams(interval=0.02, standoff=0.01)
    s = sample_node(BOX, gt, params)
    T = s.T_box_grasp
    assert len(T) > 8
    R = T[:, :3, :3]
    assert np.allclose(np.einsum("nji,njk->nik", R, R), np.eye(3), atol=1e-12)
    assert np.allclose(np.linalg.det(R), 1.0)
    p, a = T[:, :3, 3], T[:, :3, 2]
    to_aim = s.aim - p
    # the approach line passes through the aim and the aim is ahead of the hand
    assert np.allclose(np.cross(to_aim, a), 0.0, atol=1e-12)
    assert np.all(np.einsum("ij,ij->i", to_aim, a) > 0)
    h = BOX.half_extents
    surf = np.array(["sphere", "cylinder_side", "cylinder_cap", "circle"])[s.surface]
    if gt in ("spherical", "two_finger_tip"):
        assert np.all(surf == "sphere") and np.allclose(s.aim, 0.0)
        assert np.allclose(np.linalg.norm(p, axis=1), np.linalg.norm(h) + 0.01)
    elif gt == "three_finger_tip":
        assert np.all(surf == "circle") and np.allclose(p[:, 2], 0.0)
        assert np.allclose(np.linalg.norm(p, axis=1), np.hypot(h[0], h[1]) + 0.01)
        assert np.allclose(np.abs(T[:, :3, 1] @ [0, 0, 1]), 1.0)  # closes across the thickness
    else:
        side = surf == "cylinder_side"
        assert side.sum() > 0 and (surf == "cylinder_cap").sum() == 8  # 2 caps x 4 rolls
        # radial: perpendicular to the cylinder axis (box axis 0), aimed at the axis
        assert np.allclose(a[side, 0], 0.0) and np.allclose(s.aim[side, 1:], 0.0)
        assert np.allclose(np.hypot(p[side, 1], p[side, 2]), np.hypot(h[1], h[2]) + 0.01)
        assert np.all(np.abs(p[side, 0]) <= h[0])
        assert np.allclose(np.abs(T[side, 0, 0]), 1.0)  # hand x along the axis
        # caps: axial approach through the centre
        cap = ~side
        assert np.allclose(np.abs(a[cap, 0]), 1.0) and np.allclose(s.aim[cap], 0.0)
        assert np.allclose(np.abs(p[cap, 0]), h[0] + 0.01)


def _exit_face_and_point(origin: np.ndarray, direction: np.ndarray, h: np.ndarray):
    """Independent ray-box exit: the face hit leaving the box [-h, h] from ``origin``."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(direction != 0, (np.sign(direction) * h - origin) / direction, np.inf)
    axis = np.argmin(t, axis=1)
    tmin = t[np.arange(len(t)), axis]
    side = direction[np.arange(len(t)), axis] < 0
    return 2 * axis + side, origin + tmin[:, None] * direction


@pytest.mark.parametrize("gt", ("spherical", "cylindrical", "three_finger_tip"))
def test_face_and_subface_are_where_the_sample_projects_onto_the_box(gt):
    s = sample_node(BOX, gt, SamplingParams(interval=0.015))
    a = s.T_box_grasp[:, :3, 2]
    face, hitp = _exit_face_and_point(s.aim, -a, BOX.half_extents)
    assert np.array_equal(face, s.face)
    scheme = subface_scheme(gt)
    from pregrasp_core.facemask import FACE_RIGHT, FACE_UP

    for f in np.unique(s.face):
        m = s.face == f
        hr = np.abs(FACE_RIGHT[f]) @ BOX.half_extents
        hu = np.abs(FACE_UP[f]) @ BOX.half_extents
        cell = scheme.cell(f, hitp[m] @ FACE_RIGHT[f], hitp[m] @ FACE_UP[f], hr, hu)
        assert np.array_equal(cell, s.subface[m])


def test_samples_are_spaced_at_the_interval():
    big = OrientedBox(np.zeros(3), np.eye(3), np.array([0.3, 0.25, 0.2]))
    for interval in (0.03, 0.05):
        s = sample_node(big, "spherical", SamplingParams(interval=interval, standoff=0.0))
        p = np.unique(s.T_box_grasp[:, :3, 3].round(12), axis=0)  # both rolls share positions
        d = np.linalg.norm(p[:, None] - p[None], axis=2)
        np.fill_diagonal(d, np.inf)
        nn = d.min(axis=1)
        assert 0.6 * interval < np.median(nn) < 1.2 * interval
        assert nn.max() < 1.6 * interval


@pytest.mark.parametrize("gt", TYPES)
def test_samples_do_not_depend_on_the_signs_of_the_box_axes(gt):
    """The same box given with two of its axes flipped yields the same world poses (as a set)."""
    params = SamplingParams(interval=0.02)
    flipped = OrientedBox(BOX.center, BOX.rotation @ np.diag([-1.0, -1.0, 1.0]), BOX.extents)
    A = BOX.T_world_box @ sample_node(BOX, gt, params).T_box_grasp
    B = flipped.T_world_box @ sample_node(flipped, gt, params).T_box_grasp
    assert len(A) == len(B)
    key = lambda T: np.round(T[:, :3, :].reshape(len(T), -1), 9)  # noqa: E731
    assert np.array_equal(np.unique(key(A), axis=0), np.unique(key(B), axis=0))


def test_only_usable_subfaces_are_sampled():
    blocked = np.zeros(6, bool)
    blocked[[4, 3]] = True
    use = usable_subfaces(blocked, "spherical")
    s = sample_node(BOX, "spherical", SamplingParams(interval=0.01), use)
    every = sample_node(BOX, "spherical", SamplingParams(interval=0.01))
    assert 0 < len(s.face) < len(every.face)
    assert all(use[f][k] for f, k in zip(s.face, s.subface, strict=True))
    assert not np.isin(s.face, [3, 4]).any()
    # what was left out is exactly the samples on unusable sub-faces
    unusable = [not use[f][k] for f, k in zip(every.face, every.subface, strict=True)]
    assert len(every.face) - len(s.face) == sum(unusable)


# ----------------------------------------------------------------------------- traversal


def hand_built(root_ext, child_exts, classes):
    root = OrientedBox(np.zeros(3), np.eye(3), np.asarray(root_ext, float))
    idx = np.arange(1, dtype=np.int64)
    kids = tuple(range(1, len(child_exts) + 1))
    nodes = [BoxNode(0, -1, kids, 0, idx, root, 0)]
    for k, e in zip(kids, child_exts, strict=True):
        b = OrientedBox(np.array([0.1 * k, 0, 0]), np.eye(3), np.asarray(e, float))
        nodes.append(BoxNode(k, 0, (), 1, idx, b, 1))
    return BoxTree(tuple(nodes), 1), tuple(shape_of(c) for c in classes)


def test_big_box_with_two_small_children_passes_them_on(hand):
    tree, shapes = hand_built(
        [0.3, 0.3, 0.3],
        [[0.05, 0.05, 0.05]] * 2,
        [ShapeClass.THREE_D_LARGE, ShapeClass.THREE_D_SMALL, ShapeClass.THREE_D_SMALL],
    )
    t = traverse(tree, shapes, hand)
    assert t.candidates == (1, 2)
    assert t.reasons[0].startswith("too big: spherical width 0.300 m")


def test_a_small_child_makes_its_parent_a_candidate(hand):
    classes = [ShapeClass.THREE_D_LARGE, ShapeClass.THREE_D_LARGE, ShapeClass.THREE_D_SMALL]
    tree, shapes = hand_built([0.1, 0.08, 0.06], [[0.07, 0.06, 0.06], [0.04, 0.03, 0.03]], classes)
    assert traverse(tree, shapes, hand).candidates == (0, 1, 2)
    # no small child: the parent is not a candidate, the leaves are
    classes = [ShapeClass.THREE_D_LARGE] * 3
    tree, shapes = hand_built([0.1, 0.08, 0.06], [[0.07, 0.06, 0.06]] * 2, classes)
    t = traverse(tree, shapes, hand)
    assert t.candidates == (1, 2) and t.reasons[0] == "no small child"
    # small_size decides what is small
    t = traverse(tree, shapes, hand, shape_params=ShapeParams(small_size=0.07))
    assert t.candidates == (0, 1, 2)


def test_policies_and_aperture_scale(hand):
    classes = [ShapeClass.THREE_D_LARGE, ShapeClass.THREE_D_LARGE, ShapeClass.THREE_D_SMALL]
    tree, shapes = hand_built([0.3, 0.3, 0.3], [[0.14, 0.1, 0.1], [0.04, 0.03, 0.03]], classes)
    assert traverse(tree, shapes, hand, SamplingParams(policy="all")).candidates == (0, 1, 2)
    leaves = traverse(tree, shapes, hand, SamplingParams(policy=TraversalPolicy.LEAVES))
    assert leaves.candidates == (1, 2) and leaves.reasons[0] == "not a leaf"
    # a 0.14 m part fits the spherical aperture (0.148 m) only at full scale
    assert traverse(tree, shapes, hand, SamplingParams(aperture_scale=0.9)).candidates == (2,)
    with pytest.raises(ValueError, match="policy must be one of"):
        SamplingParams(policy="random")


def test_grip_width_per_type():
    assert grip_width(BOX, "cylindrical") == pytest.approx(0.07)
    assert grip_width(BOX, "spherical") == pytest.approx(0.12)
    assert grip_width(BOX, "two_finger_tip") == pytest.approx(0.12)
    assert grip_width(BOX, "three_finger_tip") == pytest.approx(0.04)


# ----------------------------------------------------------------------------- the pool


def _random_hand_poses(rng, n: int, random_state: int) -> np.ndarray:
    """``n`` hand poses: random rotations, positions within 0.25 m of the origin on each axis
    (around the random clouds of the collision tests)."""
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = Rotation.random(n, random_state=random_state).as_matrix()
    T[:, :3, 3] = rng.uniform(-0.25, 0.25, (n, 3))
    return T


def test_batched_hand_collision_matches_the_hand_model(hand):
    rng = np.random.default_rng(0)
    pts = rng.uniform(-0.1, 0.1, (2000, 3))
    G = 200
    T = _random_hand_poses(rng, G, random_state=1)
    for gt in TYPES:
        q = np.tile(hand.preshape(gt), (G, 1))
        for margin in (0.0, 0.004):
            ours = hand_hits_points(hand, T, np.full(G, gt), q, pts, margin=margin)
            ref = hand.hands_hit_points(pts, T, q[0], margin)
            assert np.array_equal(ours, ref)
            assert 20 < ours.sum() < G - 20


def test_link_cells_kept_with_the_hand_equal_fresh_ones_and_serve_every_pool(hand):
    """The pool's link cells are kept per hand (a new threshold reuses them): each entry
    equals link_cells of its preshape and margin, and the hits found with the kept cells equal
    those of an empty cache."""
    rng = np.random.default_rng(2)
    pts = rng.uniform(-0.1, 0.1, (1500, 3))
    G = 60
    T = np.tile(np.eye(4), (G, 1, 1))
    T[:, :3, :3] = Rotation.random(G, random_state=3).as_matrix()
    T[:, :3, 3] = rng.uniform(-0.25, 0.25, (G, 3))
    kept = collision.hand_cell_cache(hand)
    assert collision.hand_cell_cache(hand) is kept
    for gt in TYPES:
        q = np.tile(hand.preshape(gt), (G, 1))
        fresh = hand_hits_points(hand, T, np.full(G, gt), q, pts, margin=0.002, cells={})
        again = hand_hits_points(hand, T, np.full(G, gt), q, pts, margin=0.002, cells=kept)
        assert np.array_equal(fresh, again)
        Tc, half = kept[(q[0].tobytes(), 0.002)]
        Tf, hf = collision.link_cells(hand, q[0], 0.002)
        assert Tc.tobytes() == Tf.tobytes() and half.tobytes() == hf.tobytes()
    box_on_table_pool(hand)  # a pool fills the hand's cache with its preshapes
    assert len(collision.hand_cell_cache(hand)) >= 1


def box_on_table_pool(hand, **kw):
    rng = np.random.default_rng(5)
    tree, pts = tree_from_parts([([-0.04, -0.03, 0.0], [0.04, 0.03, 0.05])], rng, 3000)
    shapes = (shape_of(ShapeClass.THREE_D_LARGE),)
    masks = compute_face_masks(tree, SupportPlane(UP, 0.0), FaceMaskParams())
    return tree, pts, masks, build_pool(pts, tree, shapes, masks, hand, SamplingParams(**kw))


def test_box_on_the_table_gets_no_pregrasp_from_below_and_all_are_collision_free(hand):
    tree, pts, masks, pool = box_on_table_pool(hand)
    bottom = int(np.argmin(FACE_NORMAL @ tree.root.box.rotation.T @ UP))
    assert masks.blocked[0].tolist() == [f == bottom for f in range(6)]
    assert len(pool) > 0
    assert bottom not in pool.face
    assert np.all(pool.approach @ UP < 0.5)  # nothing approaches upwards from under the box
    # nothing below the support plane: every corner of every link box above z = 0 (pinches
    # from above adapt their preshape: one check per distinct preshape)
    for q in np.unique(pool.q, axis=0):
        sel = np.all(pool.q == q, axis=1)
        c = hand_corners(hand, q)  # (C, 3)
        z = np.einsum("pij,cj->pci", pool.T_world_hand[sel, :3, :3], c)[..., 2]
        assert (z + pool.T_world_hand[sel, None, 2, 3]).min() >= -1e-12
        # no cloud point inside the open hand (the hand model's own query)
        assert not hand.hands_hit_points(pts, pool.T_world_hand[sel], q).any()
    # the drops were counted; the enclosing-surface samples have the hand's preshape
    assert pool.dropped["blocked_subface"] > 0 and pool.dropped["support"] > 0
    paper = pool.surface != SURFACES.index("pinch")
    assert paper.sum() > 0
    assert np.allclose(pool.q[paper], hand.preshape("spherical"))
    assert np.allclose(pool.spread[paper], hand.spread_for("spherical"))
    assert np.all(hand.within_limits(pool.q))
    assert np.all((pool.backoff >= 0) & (pool.backoff <= 0.06 + 1e-12))


def test_every_pregrasp_of_the_pool_aims_at_its_box_centre(hand):
    # the enclosing-surface samples (pinches from above aim at their own positions along the
    # part: tests/core/test_coverage.py)
    tree, _, _, pool = box_on_table_pool(hand, pinch=False)
    c = tree.root.box.center
    # the line from the hand's grasp centre along the approach passes through the box centre
    g = pool.T_world_hand[:, :3, :3] @ hand.grasp_center("spherical") + pool.T_world_hand[:, :3, 3]
    to_c = c - g
    assert np.allclose(np.cross(to_c, pool.approach), 0.0, atol=1e-12)
    assert np.all(np.einsum("ij,ij->i", to_c, pool.approach) > 0)
    assert np.allclose(np.linalg.norm(pool.approach, axis=1), 1.0)


def test_back_off_is_the_smallest_clear_step(hand):
    tree, pts, masks, pool = box_on_table_pool(hand)
    moved = pool.backoff > 0
    assert moved.any() and np.allclose(pool.backoff / 0.01, np.round(pool.backoff / 0.01))
    # one step closer, the open hand is below the table or holds a cloud point
    T = pool.T_world_hand[moved].copy()
    T[:, :3, 3] += 0.01 * pool.approach[moved]
    c = hand_corners(hand, hand.preshape("spherical"))
    below = (np.einsum("pij,cj->pci", T[:, :3, :3], c)[..., 2] + T[:, None, 2, 3]).min(1) < 0
    hits = hand.hands_hit_points(pts, T, hand.preshape("spherical"))
    assert np.all(below | hits)


def test_without_back_off_the_hand_is_dropped_rather_than_moved(hand):
    *_, moved = box_on_table_pool(hand)
    *_, strict = box_on_table_pool(hand, max_backoff=0.0)
    assert len(strict) < len(moved)
    assert np.all(strict.backoff == 0)
    assert sum(strict.dropped.values()) > sum(moved.dropped.values())


def test_pool_only_on_the_small_children_of_a_big_box(hand):
    rng = np.random.default_rng(1)
    parts = [([0.0, 0.0, 0.0], [0.05, 0.05, 0.05]), ([0.25, 0.25, 0.25], [0.3, 0.3, 0.3])]
    tree, pts = tree_from_parts(parts, rng, 1500)
    assert np.allclose(tree.root.box.extents, 0.3 * np.sqrt([1, 1, 1]) * [1, 1, 1])
    shapes = (
        shape_of(ShapeClass.THREE_D_LARGE),
        shape_of(ShapeClass.THREE_D_SMALL),
        shape_of(ShapeClass.THREE_D_SMALL),
    )
    masks = compute_face_masks(tree, None)
    pool = build_pool(pts, tree, shapes, masks, hand)
    assert pool.candidates == (1, 2)
    assert set(np.unique(pool.node)) == {1, 2}
    assert set(np.unique(pool.grasp_type)) == {"two_finger_tip"}
    assert pool.fallback == {}


def test_pool_is_deterministic_and_moves_with_the_cloud(hand):
    rng = np.random.default_rng(2)
    # irregular sizes: no link face lands exactly on a face of the cloud (a knife edge)
    parts = [
        ([0.0, -0.0313, 0.0], [0.1217, 0.0291, 0.0407]),
        ([0.0803, -0.0219, 0.0407], [0.1217, 0.0187, 0.1433]),
    ]
    tree, pts = tree_from_parts(parts, rng, 1500)
    shapes = tuple(
        shape_of(c) for c in (ShapeClass.THREE_D_LARGE, ShapeClass.ONE_D, ShapeClass.ONE_D)
    )
    params = SamplingParams(interval=0.02)
    plane = SupportPlane(UP, 0.0)
    masks = compute_face_masks(tree, plane)
    a = build_pool(pts, tree, shapes, masks, hand, params)
    b = build_pool(pts.copy(), tree, shapes, compute_face_masks(tree, plane), hand, params)
    assert len(a) > 10
    for name in ("T_world_hand", "approach", "q", "node", "face", "subface", "backoff"):
        assert np.array_equal(getattr(a, name), getattr(b, name))
    assert a.dropped == b.dropped
    # a rigid motion of the cloud, its boxes and its table moves the pool with it
    rot = Rotation.from_euler("xyz", [0.7, -0.4, 2.0]).as_matrix()
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = rot, [0.3, -1.2, 0.5]
    moved = BoxTree(
        tuple(
            BoxNode(n.id, n.parent, n.children, n.depth, n.indices, n.box.transformed(T), 0)
            for n in tree.nodes
        ),
        tree.n_points,
    )
    mplane = SupportPlane(rot @ UP, float((rot @ UP) @ T[:3, 3]))
    c = build_pool(
        pts @ rot.T + T[:3, 3], moved, shapes, compute_face_masks(moved, mplane), hand, params
    )
    assert len(c) == len(a) and c.dropped == a.dropped

    # same set of (pose, node): every moved pre-grasp of a has exactly one match in c
    fa = np.concatenate([(T @ a.T_world_hand)[:, :3, :].reshape(len(a), -1), a.node[:, None]], 1)
    fc = np.concatenate([c.T_world_hand[:, :3, :].reshape(len(c), -1), c.node[:, None]], 1)
    d = np.abs(fa[:, None, :] - fc[None, :, :]).max(axis=2)  # (P, P)
    match = d.argmin(axis=1)
    assert np.all(d.min(axis=1) < 1e-9) and len(set(match.tolist())) == len(a)


def test_fallback_type_when_the_own_type_gives_nothing(hand):
    rng = np.random.default_rng(3)
    # a flat plate lying on the table: three-finger tip cannot get under it
    tree, pts = tree_from_parts([([-0.05, -0.03, 0.0], [0.05, 0.03, 0.012])], rng, 3000)
    shapes = (shape_of(ShapeClass.TWO_D),)
    masks = compute_face_masks(tree, SupportPlane(UP, 0.0))
    # the paper's enclosing surfaces only (the pinches from above are extra: test_coverage.py)
    strict = build_pool(pts, tree, shapes, masks, hand, SamplingParams(fallback=False, pinch=False))
    assert len(strict) == 0 and strict.dropped["support"] > 0
    pool = build_pool(pts, tree, shapes, masks, hand, SamplingParams(pinch=False))
    assert len(pool) > 0
    assert pool.fallback == {0: str(pool.grasp_type[0])}
    assert pool.grasp_type[0] != "three_finger_tip"


def test_a_part_too_big_for_its_own_type_is_grasped_by_a_type_that_fits(hand):
    """The traversal's last resort: a 3 x 14 x 20 cm board standing on the table, given the
    spherical type (as the PCA of an unevenly sampled view gave a cereal box) whose grip, its
    longest side, is wider than the hand opens (20 cm > 14.8 cm): no candidate with the paper's
    fixed types; with the fallback (the default) the board is a candidate for the types whose
    grip fits by its box sides (docs/pregrasps.md: cylindrical spans the middle side, 14 cm >
    13.3 cm: no; the three-finger tip the 3 cm thickness: yes), and every pre-grasp is of
    those types, none spherical."""
    from pregrasp_core.pregrasps.traversal import fitting_types

    rng = np.random.default_rng(4)
    tree, pts = tree_from_parts([([-0.015, -0.07, 0.0], [0.015, 0.07, 0.20])], rng, 4000)
    shapes = (shape_of(ShapeClass.THREE_D_LARGE),)
    masks = compute_face_masks(tree, SupportPlane(UP, 0.0))
    strict = SamplingParams(fallback=False)
    t = traverse(tree, shapes, hand, strict)
    assert t.candidates == () and t.reasons[0].startswith("too big: spherical width 0.200 m")
    assert len(build_pool(pts, tree, shapes, masks, hand, strict, t)) == 0
    t = traverse(tree, shapes, hand)
    assert t.candidates == (0,) and t.reasons[0].endswith("candidate by fallback (no part fits "
                                                          "its own type)")  # fmt: skip
    e = np.array([0.20, 0.14, 0.03])  # the box's sides, longest first
    fits = {g for g, w in zip(["spherical", "cylindrical", "three_finger_tip", "two_finger_tip"],
                              [e[0], e[1], e[2], e[0]], strict=True)
            if w <= hand.aperture(g)}  # fmt: skip
    assert fits == {"three_finger_tip"}
    assert set(fitting_types(tree.nodes[0].box, hand, SamplingParams())) == fits
    pool = build_pool(pts, tree, shapes, masks, hand, SamplingParams(pinch=False), t)
    assert len(pool) > 0 and set(pool.grasp_type.tolist()) <= fits
    assert pool.fallback == {0: "three_finger_tip"}
    with_pinches = build_pool(pts, tree, shapes, masks, hand, SamplingParams(), t)
    assert "spherical" not in set(with_pinches.grasp_type.tolist())


def test_pool_container(hand):
    *_, pool = box_on_table_pool(hand, pinch=False)
    P = len(pool)
    g = pool[P - 1]
    assert np.array_equal(g.T_world_hand, pool.T_world_hand[-1]) and g.node == 0
    assert g.grasp_type == "spherical" and g.q.shape == (len(hand.joint_names),)
    assert len(list(pool)) == P
    sub = pool.filter(grasp_type="spherical", node=0)
    assert len(sub) == P and len(pool.filter(node=5)) == 0
    assert len(pool.filter(grasp_type="cylindrical")) == 0
    with pytest.raises(IndexError, match="out of range"):
        pool[P]
    with pytest.raises(ValueError, match="unknown grasp type"):
        pool.filter(grasp_type="fist")
    d = json.loads(json.dumps(pool.to_dict()))
    assert d["count"] == P and len(d["pregrasps"]) == P
    assert set(d["pregrasps"][0]["preshape"]) == set(hand.joint_names)
    assert d["per_type"] == {"spherical": P} and d["dropped"] == pool.dropped
    empty = PreGraspPool.empty(hand.joint_names)
    assert len(empty) == 0 and empty.to_dict()["count"] == 0
    with pytest.raises(ValueError, match=r"PreGraspPool.q must have shape"):
        PreGraspPool(
            pool.T_world_hand,
            pool.approach,
            pool.grasp_type,
            pool.spread,
            pool.q[:, :2],
            pool.node,
            pool.face,
            pool.subface,
            pool.surface,
            pool.joint_names,
        )


def test_params_validation():
    with pytest.raises(ValueError, match="interval must be > 0"):
        SamplingParams(interval=0.0)
    with pytest.raises(ValueError, match="max_backoff must be >= 0"):
        SamplingParams(max_backoff=-0.1)
    with pytest.raises(ValueError, match="unknown grasp type"):
        sample_node(BOX, "fist")


# ----------------------------------------------------------------------------- bounded work


@pytest.mark.parametrize("name", sorted(SAMPLING_BOUNDS))
def test_every_field_is_bounded_and_the_bounds_themselves_are_accepted(name):
    lo, hi = SAMPLING_BOUNDS[name]
    assert SamplingParams(**{name: lo}) and SamplingParams(**{name: hi, "max_backoff": 0.0})
    outside = [hi * 1.01 + 1e-9, lo - 1e-9 if lo <= 0 else lo * 0.99]
    for v in outside:
        with pytest.raises(ValueError, match=rf"^{name} must be"):
            SamplingParams(**{name: v})
    with pytest.raises(ValueError, match=rf"^{name} must be"):
        SamplingParams(**{name: float("inf")})


def test_bad_sampling_values_name_the_field():
    with pytest.raises(ValueError, match=r"interval must be between 0.001 and 1, got 1e-06"):
        SamplingParams(interval=1e-6)  # the CLI's --interval 1e-6 (25.9 GiB before the bound)
    with pytest.raises(ValueError, match=r"interval must be between 0.001 and 1, got 0.0002"):
        SamplingParams(interval=0.0002)  # the value sent over the viewer protocol (7.1 GB)
    with pytest.raises(ValueError, match=r"collision_margin must be between 0 and 0.02"):
        SamplingParams(collision_margin=0.05)  # 9.5 GB and 93 s before the batches and bound
    with pytest.raises(ValueError, match=r"max_backoff / backoff_step must give at most 100"):
        SamplingParams(max_backoff=0.5, backoff_step=0.001)
    assert SamplingParams(max_backoff=0.5, backoff_step=0.005)  # exactly 100 levels
    with pytest.raises(ValueError, match=r"fallback must be True or False, got 'no'"):
        SamplingParams(fallback="no")
    with pytest.raises(ValueError, match=r"interval must be a number > 0, got '0.02'"):
        SamplingParams(interval="0.02")


@pytest.mark.parametrize("gt", TYPES)
def test_sample_counts_are_those_sample_node_makes(gt):
    rng = np.random.default_rng(11)
    for _ in range(20):
        ext = np.sort(rng.uniform(0.002, 0.3, 3))[::-1]
        box = OrientedBox(rng.normal(size=3), Rotation.random(random_state=rng).as_matrix(), ext)
        interval = float(rng.uniform(0.004, 0.05))
        s = sample_node(box, gt, SamplingParams(interval=interval))
        made = np.bincount(s.surface, minlength=len(SURFACES))
        assert count_samples(box, gt, interval) == dict(zip(SURFACES, made.tolist(), strict=True))


def test_total_samples_over_many_jobs_and_intervals_is_the_sum_of_the_counts():
    rng = np.random.default_rng(12)
    jobs = []
    for k in range(40):
        ext = np.sort(rng.uniform(0.002, 0.5, 3))[::-1]
        jobs.append((OrientedBox(np.zeros(3), np.eye(3), ext), TYPES[k % 4]))
    intervals = [0.001, 0.0013, 0.004, 0.02, 0.25, 1.0]
    want = [sum(sum(count_samples(b, gt, iv).values()) for b, gt in jobs) for iv in intervals]
    assert total_samples(jobs, intervals).tolist() == want
    assert total_samples([], [0.02]).tolist() == [0.0]


def test_sample_node_refuses_a_box_past_the_limit_before_allocating():
    box = OrientedBox(np.zeros(3), np.eye(3), np.array([2.0, 1.5, 1.0]))
    n = sum(count_samples(box, "spherical", 0.001).values())
    assert n > MAX_POOL_SAMPLES  # a 2 m box at 1 mm: about 40 million samples
    tracemalloc.start()
    try:
        with pytest.raises(PregraspError, match=rf"would make {n:,} samples.*raise the interval"):
            sample_node(box, "spherical", SamplingParams(interval=0.001))
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 2**20


@pytest.fixture(scope="module")
def default_object(hand):
    cloud = load_point_cloud(DEFAULT_OBJECT)
    return run_pipeline(cloud, PipelineParams(), hand, until="facemask")


def test_a_tiny_interval_on_the_default_object_is_a_clear_error_within_a_second(
    hand, default_object
):
    r = default_object
    params = SamplingParams(interval=0.001)  # the smallest allowed: 376,400 samples
    tracemalloc.start()
    t0 = time.perf_counter()
    try:
        with pytest.raises(PregraspError, match=r"--interval\) to at least") as err:
            build_pool(r.cloud.points, r.tree, r.shapes, r.masks, hand, params)
        seconds = time.perf_counter() - t0
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert seconds < 1.0 and peak < 4 * 2**20  # nothing of the 0.7 GiB was allocated
    msg = str(err.value)
    assert "more than the limit of 200,000" in msg and "GiB" in msg
    # the interval it suggests fits, and one a little smaller does not
    fit = float(re.search(r"to at least ([0-9.e-]+) m", msg).group(1))
    trav = traverse(r.tree, r.shapes, hand, params)
    jobs = [(r.tree.nodes[i].box, r.shapes[i].grasp_type.value) for i in trav.candidates]
    assert check_pool_size(jobs, SamplingParams(interval=fit)) <= MAX_POOL_SAMPLES
    with pytest.raises(PregraspError):
        check_pool_size(jobs, SamplingParams(interval=fit / 1.2))
    # a lower limit is honoured the same way (build_pool's max_samples)
    with pytest.raises(PregraspError, match="more than the limit of 500"):
        build_pool(r.cloud.points, r.tree, r.shapes, r.masks, hand, max_samples=500)


def test_the_memory_estimate_bounds_the_measured_peak(hand, default_object, monkeypatch):
    """Peak memory (tracemalloc) of whole pool runs against the estimate, with small collision
    batches so that the per-sample part of the estimate is what is tested."""
    monkeypatch.setattr(collision, "HAND_BATCH", 64)
    monkeypatch.setattr(collision, "PAIR_BATCH", 4096)
    r = default_object
    for params in (SamplingParams(interval=0.012), SamplingParams(collision_margin=0.01)):
        trav = traverse(r.tree, r.shapes, hand, params)
        jobs = [(r.tree.nodes[i].box, r.shapes[i].grasp_type.value) for i in trav.candidates]
        n = check_pool_size(jobs, params)
        tracemalloc.start()
        try:
            pool = build_pool(r.cloud.points, r.tree, r.shapes, r.masks, hand, params, trav)
            peak = tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()
        estimate = estimate_pool_bytes(n, len(r.cloud.points))
        assert len(pool) > 0 and 0.3 * estimate < peak <= estimate


def test_collision_memory_is_bounded_by_its_batches(hand, monkeypatch):
    """The numpy version, many hands at the largest margin: the peak stays under one batch's
    bound, far below what the same hands take in one batch."""
    rng = np.random.default_rng(8)
    pts = rng.normal(scale=0.03, size=(20000, 3))
    G = 2048
    T = np.tile(np.eye(4), (G, 1, 1))
    T[:, :3, :3] = Rotation.random(G, random_state=9).as_matrix()
    T[:, :3, 3] = rng.uniform(-0.15, 0.15, (G, 3))
    gts, q = np.full(G, "spherical"), np.tile(hand.preshape("spherical"), (G, 1))
    kd = cKDTree(pts)
    peaks, hits = [], []
    # one batch of everything, then small batches (32 hands: the cells' rotations are built
    # only for the hands with an undecided cell, so one batch of 2,048 takes about 3 MB)
    for hb, pb in ((G, 1 << 30), (32, 2048)):
        monkeypatch.setattr(collision, "HAND_BATCH", hb)
        monkeypatch.setattr(collision, "PAIR_BATCH", pb)
        tracemalloc.start()
        try:
            hits.append(collision.hand_hits_points_numpy(hand, T, gts, q, pts, margin=0.02, kd=kd))
            peaks.append(tracemalloc.get_traced_memory()[1])
        finally:
            tracemalloc.stop()
    assert np.array_equal(hits[0], hits[1]) and 0 < hits[0].sum() < G
    assert peaks[1] <= collision.collision_batch_bytes() < peaks[0] / 2


@pytest.mark.parametrize("margin", [0.0, 0.004, 0.02])
def test_collision_batches_give_the_unbatched_answer(hand, monkeypatch, margin):
    """Tiny hand and pair batches (many of each, hands hit in an earlier pair batch skipped)
    give the answer of the hand model's own test."""
    rng = np.random.default_rng(3)
    pts = rng.uniform(-0.1, 0.1, (2000, 3))
    G = 150
    T = np.tile(np.eye(4), (G, 1, 1))
    T[:, :3, :3] = Rotation.random(G, random_state=4).as_matrix()
    T[:, :3, 3] = rng.uniform(-0.25, 0.25, (G, 3))
    gts = np.array(TYPES)[rng.integers(0, 4, G)]
    q = np.stack([hand.preshape(g) for g in gts])
    ref = np.zeros(G, dtype=bool)
    for gt in TYPES:
        sel = gts == gt
        ref[sel] = hand.hands_hit_points(pts, T[sel], hand.preshape(gt), margin)
    monkeypatch.setattr(collision, "HAND_BATCH", 16)
    monkeypatch.setattr(collision, "PAIR_BATCH", 64)
    ours = hand_hits_points(hand, T, gts, q, pts, margin=margin)
    assert np.array_equal(ours, ref) and 10 < ours.sum() < G - 10
    assert np.array_equal(
        collision.hand_hits_points_numpy(hand, T, gts, q, pts, margin=margin), ref
    )


@pytest.mark.parametrize(
    "extents",
    [(0.03, 0.03, 0.03), (0.02, 0.02, 0.01), (0.12, 0.02, 0.025), (0.10, 0.06, 0.004)],
    ids=["cube", "brick", "bar", "plate"],
)
def test_pinch_count_bound_bounds_the_pinches_made(hand, extents):
    """The pool's size check counts pinches by a bound: never fewer than pinch_samples makes,
    on parts standing on the table at several turns and intervals (a plate is a thin part:
    pinches around its rim too), and on boxes tilted past 30 degrees, whose pinches from above
    go across the upright box of the part's points (wider than the box along the table)."""
    from pregrasp_core.pregrasps.pinch import pinch_count_bound, pinch_samples

    ext = np.asarray(extents, dtype=np.float64)
    rng = np.random.default_rng(5)
    for yaw, roll in ((0.0, 0.0), (0.7, 0.0), (0.3, 0.8), (1.0, 0.6)):
        R = Rotation.from_euler("zx", [yaw, roll]).as_matrix()
        local = rng.uniform(-0.5, 0.5, size=(2000, 3)) * ext
        local[np.arange(2000), rng.integers(0, 3, 2000)] = 0.5 * ext[rng.integers(0, 3, 2000)]
        pts = local @ R.T
        lift = -pts[:, 2].min()
        box = OrientedBox(np.array([0.0, 0.0, lift]), R, ext)
        pts = pts + box.center
        for interval in (0.004, 0.01, 0.02):
            got = pinch_samples(
                hand, box, SupportPlane(UP, 0.0), SamplingParams(interval=interval), pts
            )
            made = 0 if got is None else len(got.T_world_hand)
            bound = float(pinch_count_bound([box], [interval])[0])
            assert made <= bound
            if roll == 0.0:  # a bound, not a blanket: 8 kinds and rolls per position, and the
                # positions counted along the box's diagonal (the upright box's run) add at
                # most one either end on these parts
                assert bound <= 9 * max(made, 1)


def test_the_pool_size_check_counts_pinches(hand, default_object):
    """With pinches on, the limit applies to surfaces plus pinches."""
    r = default_object
    params = SamplingParams()
    trav = traverse(r.tree, r.shapes, hand, params)
    jobs = [(r.tree.nodes[i].box, r.shapes[i].grasp_type.value) for i in trav.candidates]
    boxes = [r.tree.nodes[i].box for i in trav.candidates]
    surfaces = check_pool_size(jobs, replace(params, pinch=False), pinch_boxes=boxes)
    both = check_pool_size(jobs, replace(params, pinch=True), pinch_boxes=boxes)
    assert both > surfaces
    with pytest.raises(PregraspError, match="more than the limit"):
        check_pool_size(jobs, replace(params, pinch=True), both - 1, boxes)


@pytest.mark.parametrize("hand_batch", [7, 4096])
def test_collision_of_many_preshapes_in_one_batch_gives_the_hand_models_answer(
    hand, monkeypatch, hand_batch
):
    """Hands of many preshapes (as the pinches, which adapt theirs to the part) tested in shared
    batches (a batch holds several preshapes, a preshape spans several batches) give the answer
    of the hand model's own test, hand by hand."""
    rng = np.random.default_rng(11)
    pts = rng.uniform(-0.1, 0.1, (3000, 3))
    G = 120
    T = _random_hand_poses(rng, G, random_state=12)
    base = np.stack([hand.preshape(g) for g in TYPES])
    shapes = base[rng.integers(0, 4, 15)] + rng.uniform(-0.2, 0.2, (15, base.shape[1]))
    shapes = np.stack([hand.clamp(s) for s in shapes])
    q = shapes[rng.integers(0, 15, G)]  # 15 preshapes, in no order
    ref = np.array([hand.hands_hit_points(pts, T[i : i + 1], q[i], 0.004)[0] for i in range(G)])
    monkeypatch.setattr(collision, "HAND_BATCH", hand_batch)
    monkeypatch.setattr(collision, "PAIR_BATCH", 256)
    gts = np.full(G, "spherical")
    ours = hand_hits_points(hand, T, gts, q, pts, margin=0.004)
    assert np.array_equal(ours, ref) and 10 < ours.sum() < G - 10
    assert np.array_equal(collision.hand_hits_points_numpy(hand, T, gts, q, pts, margin=0.004), ref)
