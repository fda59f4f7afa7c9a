"""Face masks, support plane and sub-faces (docs/design.md section 5, docs/conventions.md)."""

from __future__ import annotations

import time
import tracemalloc

import fcl
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from pregrasp_core import facemask
from pregrasp_core.box import OrientedBox
from pregrasp_core.decomposition import BoxNode, BoxTree
from pregrasp_core.errors import WorkLimitError
from pregrasp_core.facemask import (
    ADJACENT,
    FACE_NORMAL,
    FACE_RIGHT,
    FACE_UP,
    FaceMaskParams,
    SupportPlane,
    blocked_by_support,
    compute_face_masks,
    face_coverage,
    face_mask_matrix,
    face_slabs,
    obb_penetration,
    subface_rectangles,
    subface_scheme,
    support_plane,
    tree_intervals,
    usable_subfaces,
)
from pregrasp_core.limits import WorkLimits

UP = np.array([0.0, 0.0, 1.0])
TABLE = SupportPlane(UP, 0.0)


def aabb(lo, hi) -> OrientedBox:
    """An axis-aligned box from its corners, canonicalised like every box of the code."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    return OrientedBox.from_points_in_frame(np.stack([lo, hi]), np.eye(3))


def tree_of(root: OrientedBox, *children: OrientedBox) -> BoxTree:
    """A root with 0 or 2 leaf children (point indices are irrelevant to face masks)."""
    idx = np.arange(1, dtype=np.int64)
    kids = tuple(range(1, len(children) + 1))
    nodes = [BoxNode(0, -1, kids, 0, idx, root, 0)]
    nodes += [BoxNode(k, 0, (), 1, idx, b, 1) for k, b in zip(kids, children, strict=True)]
    return BoxTree(tuple(nodes), 1)


def face_toward(box: OrientedBox, world_dir) -> int:
    """Index of the face of ``box`` whose outward normal is ``world_dir``."""
    normals = FACE_NORMAL @ box.rotation.T  # (6, 3) world
    f = int(np.argmax(normals @ np.asarray(world_dir, float)))
    assert normals[f] @ world_dir > 0.999
    return f


def blocked_dirs(box: OrientedBox, blocked: np.ndarray) -> set[tuple[int, int, int]]:
    """World normals (rounded) of the blocked faces: comparable across box frames."""
    normals = FACE_NORMAL @ box.rotation.T
    return {tuple(np.rint(n).astype(int)) for n in normals[np.asarray(blocked, bool)]}


# ----------------------------------------------------------------------------- conventions


def test_face_frames_are_right_handed_and_adjacency_matches_the_documented_table():
    assert np.allclose(np.cross(FACE_RIGHT, FACE_UP), FACE_NORMAL)
    # the table printed in docs/conventions.md
    assert ADJACENT.tolist() == [
        [3, 5, 2, 4],
        [2, 5, 3, 4],
        [0, 5, 1, 4],
        [1, 5, 0, 4],
        [1, 3, 0, 2],
        [1, 2, 0, 3],
    ]
    for f in range(6):  # the four neighbours are the faces that are neither f nor its opposite
        assert sorted(ADJACENT[f]) == sorted(set(range(6)) - {f, f ^ 1})
        # l/r and d/u are opposite faces
        assert ADJACENT[f][0] ^ 1 == ADJACENT[f][2] and ADJACENT[f][1] ^ 1 == ADJACENT[f][3]


def test_mask_rows_are_face_then_l_d_r_u():
    blocked = np.array([0, 0, 0, 0, 1, 1], bool)  # +z and -z blocked
    m = face_mask_matrix(blocked)
    assert m.shape == (6, 5) and m.dtype == np.int8
    assert m[0].tolist() == [0, 0, 1, 0, 1]  # +x: d = -z, u = +z
    assert m[4].tolist() == [1, 0, 0, 0, 0]  # +z itself blocked, neighbours free
    with pytest.raises(ValueError, match=r"shape \(\.\.\., 6\)"):
        face_mask_matrix(np.zeros(5, bool))


# ----------------------------------------------------------------------------- SAT


def _fcl_box(box: OrientedBox) -> fcl.CollisionObject:
    return fcl.CollisionObject(fcl.Box(*box.extents), fcl.Transform(box.rotation, box.center))


def test_obb_penetration_agrees_with_fcl_on_random_boxes():
    rng = np.random.default_rng(3)
    depths, fcl_hit = [], []
    for _ in range(300):
        a = OrientedBox(
            rng.normal(0, 0.03, 3),
            Rotation.random(random_state=rng).as_matrix(),
            np.sort(rng.uniform(0.01, 0.08, 3))[::-1],
        )
        b = OrientedBox(
            rng.normal(0, 0.03, 3),
            Rotation.random(random_state=rng).as_matrix(),
            np.sort(rng.uniform(0.01, 0.08, 3))[::-1],
        )
        d = obb_penetration(
            a.center, a.rotation, a.half_extents, b.center, b.rotation, b.half_extents
        )
        depths.append(float(d))
        res = fcl.CollisionResult()
        fcl_hit.append(fcl.collide(_fcl_box(a), _fcl_box(b), fcl.CollisionRequest(), res) > 0)
    depths = np.array(depths)
    clear = np.abs(depths) > 1e-6
    assert np.array_equal((depths > 0)[clear], np.array(fcl_hit)[clear])
    assert 30 < np.count_nonzero(depths > 0) < 270  # both outcomes are exercised


def test_obb_penetration_of_axis_aligned_boxes_is_the_smallest_interval_overlap():
    a, b = aabb([0, 0, 0], [0.1, 0.1, 0.1]), aabb([0.08, 0.05, -0.2], [0.3, 0.3, 0.3])
    d = obb_penetration(a.center, a.rotation, a.half_extents, b.center, b.rotation, b.half_extents)
    assert d == pytest.approx(0.02)  # overlaps 0.02 in x, 0.05 in y, 0.1 in z
    c = aabb([0.15, 0, 0], [0.2, 0.1, 0.1])  # 0.05 apart in x
    d = obb_penetration(a.center, a.rotation, a.half_extents, c.center, c.rotation, c.half_extents)
    assert d == pytest.approx(-0.05)


# ----------------------------------------------------------------------------- masks


def l_shape() -> tuple[BoxTree, OrientedBox, OrientedBox]:
    """A horizontal bar on the table and an upright bar standing on its +x end, flush with it."""
    bar = aabb([0, -0.025, 0], [0.2, 0.025, 0.04])
    post = aabb([0.16, -0.02, 0.04], [0.2, 0.02, 0.16])
    root = aabb([0, -0.025, 0], [0.2, 0.025, 0.16])
    return tree_of(root, bar, post), bar, post


def test_l_shape_blocks_exactly_the_shared_faces_and_the_table():
    tree, bar, post = l_shape()
    fm = compute_face_masks(tree, TABLE)
    # bar: top shared with the post, bottom on the table; its +x end is flush under the post
    # (touching, not in front) and stays free
    assert blocked_dirs(bar, fm.blocked[1]) == {(0, 0, 1), (0, 0, -1)}
    assert fm.blockers[1][face_toward(bar, [0, 0, 1])] == (2,)
    assert fm.by_support[1].tolist() == [f == face_toward(bar, [0, 0, -1]) for f in range(6)]
    # post: only its bottom, on the bar (the table is 0.04 m below it, beyond the clearance)
    assert blocked_dirs(post, fm.blocked[2]) == {(0, 0, -1)}
    assert fm.blockers[2][face_toward(post, [0, 0, -1])] == (1,)
    assert not fm.by_support[2].any()
    # root: its own descendants never block it; only the table
    assert blocked_dirs(tree.root.box, fm.blocked[0]) == {(0, 0, -1)}
    # the bar's +x face row: [f, l, d, r, u] with d = bottom (table) and u = top (post)
    fx = face_toward(bar, [1, 0, 0])
    row = fm.mask(1)[fx]
    nbr_dirs = (FACE_NORMAL[ADJACENT[fx]] @ bar.rotation.T).round().astype(int).tolist()
    expected = [0] + [int(d in ([0, 0, 1], [0, 0, -1])) for d in nbr_dirs]
    assert row.tolist() == expected and sum(expected) == 2
    assert fm.masks.shape == (3, 6, 5)


def test_box_stacked_on_a_box():
    bottom = aabb([-0.05, -0.04, 0], [0.05, 0.04, 0.06])
    top = aabb([-0.03, -0.025, 0.06], [0.03, 0.025, 0.1])
    tree = tree_of(aabb([-0.05, -0.04, 0], [0.05, 0.04, 0.1]), bottom, top)
    fm = compute_face_masks(tree, TABLE)
    assert blocked_dirs(bottom, fm.blocked[1]) == {(0, 0, 1), (0, 0, -1)}
    assert blocked_dirs(top, fm.blocked[2]) == {(0, 0, -1)}
    # the wider bottom box does not block the top box's sides (it is below them, not in front)
    ftop = face_toward(top, [0, 0, -1])
    assert fm.mask(2)[ftop].tolist() == [1, 0, 0, 0, 0]
    for d in ([1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0]):
        row = fm.mask(2)[face_toward(top, d)]
        assert row[0] == 0 and row.sum() == 1  # its 'down' neighbour is the blocked bottom


def test_masks_are_invariant_under_rigid_motions():
    tree, *_ = l_shape()
    ref = compute_face_masks(tree, TABLE)
    rng = np.random.default_rng(7)
    for _ in range(5):
        R = Rotation.random(random_state=rng).as_matrix()
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R, rng.normal(0, 0.5, 3)
        moved = BoxTree(
            tuple(
                BoxNode(
                    n.id,
                    n.parent,
                    n.children,
                    n.depth,
                    n.indices,
                    n.box.transformed(T),
                    n.split_order,
                )
                for n in tree.nodes
            ),
            1,
        )
        plane = SupportPlane(R @ UP, float((R @ UP) @ T[:3, 3]))
        fm = compute_face_masks(moved, plane)
        for k, n in enumerate(tree.nodes):
            # world normals of the blocked faces, mapped back by R^T
            got = {
                tuple(np.rint(R.T @ (FACE_NORMAL[f] @ moved.nodes[k].box.rotation.T)).astype(int))
                for f in np.flatnonzero(fm.blocked[k])
            }
            assert got == blocked_dirs(n.box, ref.blocked[k])


def test_gap_within_clearance_blocks_and_beyond_does_not():
    a = aabb([0, 0, 0], [0.1, 0.06, 0.05])
    for gap, expect in ((0.01, True), (0.02, True), (0.03, False)):
        b = aabb([0.1 + gap, 0, 0], [0.2, 0.06, 0.05])
        tree = tree_of(aabb([0, 0, 0], [0.2, 0.06, 0.05]), a, b)
        fm = compute_face_masks(tree, None, FaceMaskParams(clearance=0.025))
        assert fm.blocked[1][face_toward(a, [1, 0, 0])] == expect
        assert fm.blocked[1].sum() == int(expect)


def test_a_blocker_grazing_a_corner_of_the_slab_leaves_the_face_free():
    a = aabb([0, 0, 0], [0.2, 0.1, 0.05])
    # in front of the +x face, covering 0.01 x 0.02 of its 0.1 x 0.05 (4 %) or 0.03 x 0.05 (30 %)
    for hi, cover in (([0.21, 0.01, 0.02], 0.04), ([0.21, 0.03, 0.05], 0.3)):
        b = aabb([0.2, 0, 0], hi)
        tree = tree_of(aabb([0, 0, 0], [0.21, 0.1, 0.05]), a, b)
        fm = compute_face_masks(tree, None)
        f = face_toward(a, [1, 0, 0])
        assert fm.blockers[1][f] == (2,)  # in front of it either way
        assert fm.blocked[1][f] == (cover >= 0.05)
        # with a coverage threshold below it, the small one blocks too
        fm = compute_face_masks(tree, None, FaceMaskParams(min_coverage=0.02))
        assert fm.blocked[1][f]


def test_support_plane_default_off_and_explicit():
    pts = np.array([[0, 0, 0.0], [0.1, 0.06, 0.05]])
    assert support_plane(pts, FaceMaskParams()).height == 0.0
    assert support_plane(pts, FaceMaskParams(support=False)) is None
    side = support_plane(pts, FaceMaskParams(up=(1, 0, 0), support_height=-0.5))
    assert np.allclose(side.normal, [1, 0, 0]) and side.height == -0.5
    box = aabb(pts[0], pts[1])
    tree = tree_of(box)
    assert blocked_dirs(
        box, compute_face_masks(tree, support_plane(pts, FaceMaskParams())).blocked[0]
    ) == {(0, 0, -1)}
    assert not compute_face_masks(tree, None).blocked.any()
    # a table 0.1 m below: beyond the clearance, nothing blocked
    low = SupportPlane(UP, -0.1)
    assert not compute_face_masks(tree, low).blocked.any()
    # a plane cutting the box at mid height: only the face looking at it (the box's part below
    # the plane is not an obstacle for its own side faces)
    mid = SupportPlane(UP, 0.025)
    assert blocked_dirs(box, compute_face_masks(tree, mid).blocked[0]) == {(0, 0, -1)}
    # the plane along +x at the box's -x face blocks that face
    wall = SupportPlane(np.array([1.0, 0, 0]), 0.0)
    assert blocked_dirs(box, compute_face_masks(tree, wall).blocked[0]) == {(-1, 0, 0)}


def test_a_tilted_box_on_the_table_blocks_only_the_faces_looking_at_it():
    for tilt in (0.05, 0.2):  # radians about a horizontal axis
        R = Rotation.from_rotvec([tilt, 0, 0]).as_matrix()
        box = OrientedBox(np.zeros(3), R, np.array([0.2, 0.1, 0.06]))
        box = OrientedBox(box.center - [0, 0, box.corners()[:, 2].min()], R, box.extents)
        fm = compute_face_masks(tree_of(box), TABLE)
        normals = FACE_NORMAL @ box.rotation.T
        assert fm.blocked[0][np.argmin(normals[:, 2])]  # the bottom face
        # side faces tilted by 0.05 rad stay free; at 0.2 rad the one turned down is blocked
        expected = normals[:, 2] < (-0.5 if tilt < 0.1 else -0.1)
        assert fm.blocked[0].tolist() == expected.tolist()


def test_cut_limits_the_blockers_to_the_current_decomposition():
    tree, bar, post = l_shape()
    fm = compute_face_masks(tree, None, cut=[0])  # the root alone: nothing blocks anything
    assert not fm.blocked.any() and fm.cut == (0,)
    with pytest.raises(IndexError):
        compute_face_masks(tree, None, cut=[9])


def test_params_validation_names_the_field_and_its_bounds():
    p = FaceMaskParams()  # the documented defaults
    assert (p.clearance, p.overlap_tolerance, p.min_coverage, p.support_tolerance) == (
        0.025,
        0.002,
        0.05,
        0.002,
    )
    assert (p.support, p.up, p.support_height) == (True, (0.0, 0.0, 1.0), None)
    for name in ("clearance", "overlap_tolerance", "support_tolerance"):
        for bad in (-1.0, 10.5, float("nan"), float("inf"), "0.02", True, None):
            with pytest.raises(ValueError, match=rf"^{name} must be a length in \[0, 10\] m, got"):
                FaceMaskParams(**{name: bad})
    for bad in (0.0, 1.5, float("nan"), "x"):
        with pytest.raises(ValueError, match=r"^min_coverage must be a fraction in \(0, 1\]"):
            FaceMaskParams(min_coverage=bad)
    for bad in ((0, 0, 0), (1e308, 1e308, 0.0), (0, 0, float("nan")), "abc", (0, 1), None):
        with pytest.raises(ValueError, match="^up must be a non-zero finite 3-vector"):
            FaceMaskParams(up=bad)
    for bad in (float("nan"), 2e6, "0"):
        with pytest.raises(ValueError, match=r"^support_height must be a height \(or None\)"):
            FaceMaskParams(support_height=bad)
    for bad in ("yes", 2, None):
        with pytest.raises(ValueError, match="^support must be True or False"):
            FaceMaskParams(support=bad)
    assert FaceMaskParams(clearance=10, up=[0, 0, 2], support=np.bool_(False)).clearance == 10.0


# ----------------------------------------------------------------------------- bounded work


def reference_face_masks(tree: BoxTree, support, params: FaceMaskParams, cut=None):
    """The face masks by the plain algorithm (every (node, blocker) pair through the
    separating-axis test at once, O(pairs) memory): the reference for the chunked stage."""
    cut_ids = tuple(tree.leaves() if cut is None else cut)
    K = len(tree.nodes)
    pairs = [(nd.id, c) for nd in tree.nodes for c in cut_ids if not tree.is_related(nd.id, c)]
    blocked = np.zeros((K, 6), dtype=bool)
    hits = [[[] for _ in range(6)] for _ in range(K)]
    if pairs:
        pn, pb = (np.array(x) for x in zip(*pairs, strict=True))
        slabs = [face_slabs(nd.box, params.clearance) for nd in tree.nodes]
        slab_c = np.stack([c for c, _ in slabs])
        slab_h = np.stack([h for _, h in slabs])
        R = np.stack([nd.box.rotation for nd in tree.nodes])
        C = np.stack([nd.box.center for nd in tree.nodes])
        H = np.stack([nd.box.half_extents for nd in tree.nodes])
        depth = obb_penetration(
            slab_c[pn], R[pn][:, None], slab_h[pn], C[pb][:, None], R[pb][:, None], H[pb][:, None]
        )
        hit = depth > params.overlap_tolerance
        for n, f in sorted({(int(pn[p]), int(f)) for p, f in zip(*np.nonzero(hit), strict=True)}):
            cands = [int(pb[p]) for p in np.flatnonzero((pn == n) & hit[:, f])]
            cov = face_coverage(
                tree.nodes[n].box, f, [tree.nodes[c].box for c in cands], params.clearance
            )
            hits[n][f] = [c for c, v in zip(cands, cov[:-1], strict=True) if v > 0]
            blocked[n, f] = cov[-1] >= params.min_coverage
    by_support = (
        blocked_by_support([nd.box for nd in tree.nodes], support, params)
        if support is not None
        else np.zeros((K, 6), dtype=bool)
    )
    return blocked | by_support, tuple(tuple(tuple(sorted(h)) for h in nh) for nh in hits)


def random_tree(rng: np.random.Generator, n_leaves: int, spread: float = 0.3) -> BoxTree:
    """A tree grown by splitting random leaves, with random boxes (0.01-0.12 m sides, random
    orientations) in a cube of side ``spread``: many of them touch, overlap or nearly touch."""
    parent, depth, kids = [-1], [0], [[]]
    leaves = [0]
    while len(leaves) < n_leaves:
        k = leaves.pop(int(rng.integers(len(leaves))))
        for _ in range(2):
            kids[k].append(len(parent))
            leaves.append(len(parent))
            parent.append(k)
            depth.append(depth[k] + 1)
            kids.append([])
    K = len(parent)
    idx = np.arange(1, dtype=np.int64)
    Rs = Rotation.random(K, random_state=int(rng.integers(1 << 31))).as_matrix()  # (K, 3, 3)
    corners = rng.uniform(0, spread, (K, 1, 3)) + rng.uniform(-0.06, 0.06, (K, 2, 3))
    nodes = [
        BoxNode(i, parent[i], tuple(kids[i]), depth[i], idx, box, 0)
        for i, box in enumerate(
            OrientedBox.from_points_in_frame(corners[i] @ Rs[i].T, Rs[i]) for i in range(K)
        )
    ]
    return BoxTree(tuple(nodes), 1)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_chunked_masks_equal_the_all_pairs_reference(seed, monkeypatch):
    """Screening and chunking change nothing: blocked faces and blockers are those of the
    all-pairs algorithm, for the leaves and for another cut, with chunks of a few pairs."""
    rng = np.random.default_rng(seed)
    tree = random_tree(rng, 40)
    params = FaceMaskParams(  # the whole-face rule (the sub-face rule is test_coverage.py)
        clearance=0.03, overlap_tolerance=[0.0, 0.002, 0.01][seed], rule="face"
    )
    cuts = [None, sorted(rng.choice(len(tree.nodes), 15, replace=False).tolist())]
    for cut in cuts:
        ref_blocked, ref_blockers = reference_face_masks(tree, TABLE, params, cut)
        assert ref_blocked.sum() > 20  # the random boxes do block each other
        for pair_chunk, sat_chunk in ((16_384, 1024), (7, 3), (1, 1)):
            monkeypatch.setattr(facemask.masks, "PAIR_CHUNK", pair_chunk)
            monkeypatch.setattr(facemask.masks, "SAT_CHUNK", sat_chunk)
            fm = compute_face_masks(tree, TABLE, params, cut=cut)
            assert np.array_equal(fm.blocked, ref_blocked)
            assert fm.blockers == ref_blockers


def test_tree_intervals_agree_with_is_related():
    tree = random_tree(np.random.default_rng(5), 30)
    tin, tout = tree_intervals(tree)
    K = len(tree.nodes)
    fast = (tin[:, None] <= tin[None]) & (tin[None] < tout[:, None])  # a is b or its ancestor
    fast |= fast.T
    slow = np.array([[tree.is_related(a, b) for b in range(K)] for a in range(K)])
    assert np.array_equal(fast, slow)


def test_too_many_pairs_are_refused_before_any_work():
    """The 2,135 parts (4,269 nodes) of issue 16 would be 9.1 million (node, blocker) pairs:
    refused at once with the limit's name, without allocating for them."""
    tree = random_tree(np.random.default_rng(3), 2135, spread=3.0)
    assert len(tree.nodes) == 4269
    tracemalloc.start()
    t0 = time.perf_counter()
    with pytest.raises(WorkLimitError, match=r"9,114,315 pairs, more than the limit 4,000,000 "):
        compute_face_masks(tree, TABLE)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert time.perf_counter() - t0 < 1.0 and peak < 2**20
    small = tree_of(aabb([0] * 3, [2] * 3), aabb([0] * 3, [1] * 3), aabb([1] * 3, [2] * 3))
    with pytest.raises(WorkLimitError, match=r"\(max_face_mask_pairs\): decompose into fewer"):
        compute_face_masks(small, None, limits=WorkLimits(max_face_mask_pairs=5))  # 3 x 2 = 6
    assert compute_face_masks(small, None, limits=WorkLimits(max_face_mask_pairs=6)).cut == (1, 2)


def test_memory_does_not_grow_with_the_pairs():
    """600 parts (719,400 pairs): the all-pairs algorithm's separating-axis arrays alone would
    take 720k x 6 x 15 x 3 floats x several temporaries (gigabytes); the chunked stage stays
    within tens of megabytes."""
    tree = random_tree(np.random.default_rng(4), 600, spread=1.0)
    pairs = len(tree.nodes) * 600
    tracemalloc.start()
    fm = compute_face_masks(tree, TABLE)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert pairs == 719_400 and fm.blocked.any()
    assert peak < 48 * 2**20, f"peak {peak / 2**20:.1f} MiB"


# ----------------------------------------------------------------------------- sub-faces


def test_subfaces_next_to_a_blocked_face_are_unused():
    blocked = np.zeros(6, bool)
    blocked[4] = True  # +z blocked: it is 'u' of faces 0..3 and the +z face itself
    use = usable_subfaces(blocked, "spherical")
    for f in range(4):  # 3 x 3 grid: the top row (cells 6, 7, 8) borders u
        assert use[f].tolist() == [True] * 6 + [False] * 3
    assert not use[4].any()  # the blocked face itself
    # face 5 (-z) does not border +z: all usable
    assert use[5].all()
    # face 0 with its 'l' (face 3) blocked too: the left column goes as well
    blocked[3] = True
    assert usable_subfaces(blocked, "spherical")[0].reshape(3, 3).tolist() == [
        [False, True, True],
        [False, True, True],
        [False, False, False],
    ]


def test_subface_schemes_per_grasp_type():
    cyl = subface_scheme("cylindrical")
    # side faces: three strips along axis 0 (= 'right' of the side faces), caps: one sub-face
    assert cyl.grid == ((1, 1), (1, 1), (3, 1), (3, 1), (3, 1), (3, 1))
    assert np.allclose(np.abs(FACE_RIGHT[2:]), [1, 0, 0])
    blocked = np.zeros(6, bool)
    blocked[0] = True  # +x cap blocked: the strips at the +x end of the side faces go
    use = usable_subfaces(blocked, "cylindrical")
    for f in range(2, 6):
        end = 2 if FACE_RIGHT[f][0] > 0 else 0  # the column at the +x end
        assert use[f].tolist() == [i != end for i in range(3)]
    assert use[0].tolist() == [False]  # the blocked cap itself
    # the -x cap (face 1) borders the four side faces only, so it stays usable
    assert use[1].tolist() == [True]
    tip = subface_scheme("three_finger_tip")
    assert tip.n_subfaces.tolist() == [9, 9, 9, 9, 0, 0]
    blocked = np.zeros(6, bool)
    blocked[5] = True  # a flat face (-z, 'd' of the rim faces): the bottom rows go
    use = usable_subfaces(blocked, "three_finger_tip")
    for f in range(4):
        assert use[f].tolist() == [False] * 3 + [True] * 6
    blocked[2] = True  # rim face +y: blocked itself, and the ends of its neighbours' rows
    use = usable_subfaces(blocked, "three_finger_tip")
    assert not use[2].any()
    assert use[0].reshape(3, 3)[1].tolist() == [True, True, False]  # +y is r of face 0
    with pytest.raises(ValueError, match="unknown grasp type"):
        subface_scheme("fist")


def test_subface_rectangles_tile_each_face():
    box = OrientedBox(
        np.array([0.3, -0.2, 0.1]),
        Rotation.from_euler("xyz", [0.3, -0.5, 1.0]).as_matrix(),
        np.array([0.12, 0.08, 0.05]),
    )
    for gt in ("spherical", "cylindrical", "three_finger_tip", "two_finger_tip"):
        rects = subface_rectangles(box, gt)
        n = subface_scheme(gt).n_subfaces
        for f in range(6):
            assert rects[f].shape == (n[f], 4, 3)
            if n[f] == 0:
                continue
            # corners on the face's plane and the areas add up to the face's area
            normal = box.rotation @ FACE_NORMAL[f]
            offset = box.half_extents[f // 2]
            assert np.allclose((rects[f] - box.center) @ normal, offset)
            e1 = rects[f][:, 1] - rects[f][:, 0]
            e2 = rects[f][:, 3] - rects[f][:, 0]
            area = np.linalg.norm(np.cross(e1, e2), axis=1).sum()
            sides = np.delete(box.extents, f // 2)
            assert area == pytest.approx(sides[0] * sides[1])
            # counter-clockwise seen from outside
            assert np.all(np.cross(e1, e2) @ normal > 0)


@settings(max_examples=60, deadline=None)
@given(
    blocked=st.lists(st.booleans(), min_size=6, max_size=6),
    grasp_type=st.sampled_from(["spherical", "cylindrical", "three_finger_tip", "two_finger_tip"]),
)
def test_usable_subfaces_match_the_geometry_of_the_rectangles(blocked, grasp_type):
    """Oracle from geometry alone: a sub-face borders face g when two of its corners lie on g's
    plane (the edge it shares with g); it is usable when its face and those faces are free."""
    box = OrientedBox(np.zeros(3), np.eye(3), np.array([0.3, 0.2, 0.1]))
    blocked = np.array(blocked)
    use = usable_subfaces(blocked, grasp_type)
    for f, rects in enumerate(subface_rectangles(box, grasp_type)):
        for s, corners in enumerate(rects):  # (4, 3)
            on_plane = np.isclose(corners @ FACE_NORMAL.T, box.half_extents[np.arange(6) // 2])
            borders = [g for g in range(6) if g != f and on_plane[:, g].sum() == 2]
            assert use[f][s] == (not blocked[f] and not any(blocked[g] for g in borders))


@settings(max_examples=60, deadline=None)
@given(
    st.sampled_from(["spherical", "cylindrical", "three_finger_tip", "two_finger_tip"]),
    st.integers(0, 2**32 - 1),
    st.floats(0.0, 0.8),
    st.sampled_from([0.0, 0.1, 0.25, 0.5, 1.0]),
)
def test_usable_subfaces_by_cells_counts_every_region_of_every_subface(gt, seed, fill, min_cov):
    """The sub-face test (its regions tabled once per grasp type) says what its definition
    says: a sub-face is usable when each of its regions (``subface_regions``) has fewer than
    ``min_coverage`` of its cells covered."""
    from pregrasp_core.facemask.cells import subface_regions, usable_subfaces_by_cells

    cov = np.random.default_rng(seed).uniform(size=(6, 12, 12)) < fill
    got = usable_subfaces_by_cells(cov, gt, min_cov)
    regions = subface_regions(gt)
    assert len(got) == 6
    for f in range(6):
        want = [
            all((r & cov).sum() < min_cov * max(int(r.sum()), 1) for r in reg) for reg in regions[f]
        ]
        assert got[f].dtype == bool and got[f].tolist() == want
