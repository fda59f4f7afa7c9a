"""Every graspable object gets force-closure grasps (issue 12): small parts on the table,
handles beside bigger parts, big boxes across their thin side, thin parts; ``best`` is the best
force-closure grasp or ``None`` with its reason (docs/pregrasps.md sections 2b and 6b).

The objects are generated here from trimesh primitives standing on the table (z = 0); the
references (which points are the handle, which faces a box has) come from the primitives'
own geometry, not from the code under test."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import trimesh

from pregrasp_core.box import OrientedBox
from pregrasp_core.decomposition import BoxNode, BoxTree
from pregrasp_core.facemask import (
    FACE_NORMAL,
    FaceMaskParams,
    SupportPlane,
    compute_face_masks,
    usable_subfaces,
)
from pregrasp_core.hand import load_hand
from pregrasp_core.io import PointCloud, load_point_cloud
from pregrasp_core.paths import OBJECTS_DIR
from pregrasp_core.pipeline import PipelineParams, result_document, run_pipeline
from pregrasp_core.pregrasps import SURFACES, SamplingParams, hand_corners
from pregrasp_core.pregrasps.pinch import PINCH_MARGIN

UP = np.array([0.0, 0.0, 1.0])
PINCH = SURFACES.index("pinch")


@pytest.fixture(scope="module")
def hand():
    return load_hand()


def on_table(mesh: trimesh.Trimesh, n: int = 4000, seed: int = 0) -> PointCloud:
    """``n`` points sampled on ``mesh`` (with its face normals), moved to stand on z = 0."""
    mesh = mesh.copy()
    mesh.apply_translation([0.0, 0.0, -mesh.bounds[0, 2]])
    pts, face = trimesh.sample.sample_surface(mesh, n, seed=seed)
    return PointCloud(points=np.asarray(pts), normals=mesh.face_normals[face], source="generated")


def plan(cloud: PointCloud, hand, **sampling):
    params = PipelineParams(sampling=SamplingParams(**sampling))
    return run_pipeline(cloud, params, hand, until="grasps")


# ----------------------------------------------------------------------------- small parts


SMALL_PARTS = {
    "cube_3cm": trimesh.creation.box([0.03, 0.03, 0.03]),
    "brick_2x2x1cm": trimesh.creation.box([0.02, 0.02, 0.01]),
    "cap_1.5cm": trimesh.creation.cylinder(radius=0.0075, height=0.012, sections=48),
}


@pytest.mark.parametrize("name", sorted(SMALL_PARTS))
def test_small_parts_on_the_table_get_a_force_closure_pinch(hand, name):
    mesh = SMALL_PARTS[name]
    cloud = on_table(mesh)
    res = plan(cloud, hand)
    gs = res.grasps
    assert gs.best is not None, gs.best_reason
    best = gs.grasps[gs.best]
    assert best.epsilon > 0 and best.n_contacts >= 3
    assert gs.best_reason.startswith("force closure")
    # the paper's surfaces alone give nothing here (the open hand reaches below the table)
    assert len(plan(cloud, hand, pinch=False).pool) == 0
    # every contact is a point of the part, every finger link above the table
    pts = np.asarray(cloud.points)
    for c in best.contacts:
        assert np.min(np.linalg.norm(pts - c.point, axis=1)) < 1e-12
    z = hand_corners(hand, best.q) @ best.T_world_hand[:3, :3].T + best.T_world_hand[:3, 3]
    assert z[:, 2].min() > -1e-9


@pytest.mark.parametrize("name", sorted(SMALL_PARTS))
def test_the_pinch_preshape_fits_the_part(hand, name):
    """Aperture just wider than the part, fingertips at the part's height, the hand that will
    close above the table and clear of the part."""
    mesh = SMALL_PARTS[name]
    cloud = on_table(mesh)
    pool = run_pipeline(cloud, PipelineParams(), hand, until="pool").pool
    pinch = pool.select(pool.surface == PINCH)
    assert len(pinch) >= 2
    height = float(mesh.extents[2])
    pts = np.asarray(cloud.points)
    for g in pinch:
        assert np.allclose(g.approach, -UP)  # straight down
        pads = np.stack(list(hand.tip_pads(g.q).values()))  # (3, 3) hand frame
        pads = pads @ g.T_world_hand[:3, :3].T + g.T_world_hand[:3, 3]
        # the three fingertips at one height, within the part's height
        assert np.ptp(pads[:, 2]) < 1e-9
        assert 0.0 < pads[0, 2] <= height
        # each fingertip outside the part, by at least the margin and at most a finger width
        gap = np.min(np.linalg.norm(pts[None, :, :2] - pads[:, None, :2], axis=2), axis=1)
        assert np.all(gap >= PINCH_MARGIN - 1e-3) and np.all(gap <= PINCH_MARGIN + 0.02)
        corners = hand_corners(hand, g.q) @ g.T_world_hand[:3, :3].T + g.T_world_hand[:3, 3]
        assert corners[:, 2].min() >= -1e-9  # the closing hand's links above the table
        assert not hand.hands_hit_points(pts, g.T_world_hand[None], g.q)[0]


# ----------------------------------------------------------------------------- big boxes


def test_big_box_is_held_across_its_6cm_side(hand):
    # a 20 x 30 x 6 cm box standing on its 30 x 6 cm face: too big for every grasp type but
    # across the 6 cm (y); the contacts must be on its two big faces y = +-0.03
    cloud = on_table(trimesh.creation.box([0.30, 0.06, 0.20]), n=8000)
    gs = plan(cloud, hand).grasps
    across = []
    for g in gs.ranked:
        p = np.array([c.point for c in g.contacts])
        n = np.array([c.normal for c in g.contacts])
        on_big = np.abs(np.abs(p[:, 1]) - 0.03) < 1e-9
        if g.epsilon > 0 and (n[on_big, 1] > 0.99).any() and (n[on_big, 1] < -0.99).any():
            across.append(g)
    assert across, gs.best_reason
    assert gs.best is not None and gs.grasps[gs.best].epsilon >= across[0].epsilon


# ----------------------------------------------------------------------------- handles

BODY_R, BODY_H = 0.04, 0.10
BAR_X, BAR_R, BAR_Z = 0.072, 0.006, (0.02, 0.09)


def generated_mug(n: int = 8000, seed: int = 0) -> PointCloud:
    """A 8 cm x 10 cm cylinder with a handle: a vertical bar (1.2 cm thick, 7 cm long, 2.6 cm
    from the wall) on two arms; surface points only (what lies inside another primitive is
    dropped)."""
    body = trimesh.creation.cylinder(radius=BODY_R, height=BODY_H, sections=64)
    body.apply_translation([0.0, 0.0, BODY_H / 2])
    z0, z1 = BAR_Z
    bar = trimesh.creation.cylinder(radius=BAR_R, height=z1 - z0, sections=24)
    bar.apply_translation([BAR_X, 0.0, (z0 + z1) / 2])
    parts = [body, bar]
    for z in (z0 + BAR_R, z1 - BAR_R):
        arm = trimesh.creation.cylinder(radius=BAR_R, height=BAR_X - BODY_R + 0.004, sections=24)
        arm.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [0, 1, 0]))
        arm.apply_translation([(BODY_R - 0.004 + BAR_X) / 2, 0.0, z])
        parts.append(arm)
    areas = np.array([p.area for p in parts])
    pts, nrm = [], []
    for k, (p, m) in enumerate(
        zip(parts, np.round(n * areas / areas.sum()).astype(int), strict=True)
    ):
        s, face = trimesh.sample.sample_surface(p, int(m), seed=seed + k)
        keep = np.ones(len(s), dtype=bool)
        for j, other in enumerate(parts):
            if j != k:
                keep &= ~other.contains(s)
        pts.append(s[keep])
        nrm.append(p.face_normals[face][keep])
    return PointCloud(
        points=np.concatenate(pts), normals=np.concatenate(nrm), source="generated mug"
    )


def handle_pregrasps(res, on_handle) -> np.ndarray:
    """Indices of the pre-grasps sampled for nodes whose points are (90 %) on the handle."""
    pts = np.asarray(res.cloud.points)
    nodes = [nd.id for nd in res.tree.nodes if on_handle(pts[nd.indices]).mean() > 0.9]
    assert nodes
    return np.flatnonzero(np.isin(res.pool.node, nodes))


def test_generated_mug_handle_gets_pregrasps_and_a_force_closure_grasp_on_it(hand):
    res = plan(generated_mug(), hand)

    def on_handle(p):  # outside the body's wall (the primitives' geometry)
        return np.hypot(p[..., 0], p[..., 1]) > BODY_R + 0.001

    assert len(handle_pregrasps(res, on_handle)) >= 5
    held = [
        g
        for g in res.grasps.ranked
        if g.epsilon > 0 and all(on_handle(c.point) for c in g.contacts)
    ]
    assert held, res.grasps.best_reason
    # the paper's whole-face rule without pinches: fewer pre-grasps on the handle, none on it
    paper = run_pipeline(
        generated_mug(),
        PipelineParams(facemask=FaceMaskParams(rule="face"), sampling=SamplingParams(pinch=False)),
        hand,
        until="grasps",
    )
    assert len(handle_pregrasps(paper, on_handle)) < len(handle_pregrasps(res, on_handle))
    assert not any(
        g.epsilon > 0 and all(on_handle(c.point) for c in g.contacts) for g in paper.grasps
    )


def test_mug_handle_asset_gets_at_least_5_pregrasps_on_its_handle(hand):
    cloud = load_point_cloud(OBJECTS_DIR / "mug_handle.obj")  # 20,000 points: 2 parts
    res = run_pipeline(cloud, PipelineParams(), hand, until="pool")

    def on_handle(p):  # scripts/make_mug_handle.py: the body's axis at x = -0.0155, r 0.04
        return np.hypot(p[..., 0] + 0.0155, p[..., 1]) > 0.041

    assert len(handle_pregrasps(res, on_handle)) >= 5
    paper = run_pipeline(
        cloud, PipelineParams(facemask=FaceMaskParams(rule="face")), hand, until="pool"
    )
    assert len(handle_pregrasps(paper, on_handle)) < 5  # the issue: 1 with whole-face masks


# ----------------------------------------------------------------------------- sub-face rule


def cylinder_points(n: int, rng) -> np.ndarray:
    """Points on the side of a vertical cylinder of radius 0.04, z in [0, 0.1]."""
    t, z = rng.uniform(0, 2 * np.pi, n), rng.uniform(0.0, 0.1, n)
    return np.column_stack([0.04 * np.cos(t), 0.04 * np.sin(t), z])


def test_a_handle_in_the_corner_of_the_body_box_keeps_its_outer_subfaces():
    """The body's box is turned 45 degrees about z (a valid box of the cylinder); its corner
    reaches into the handle's box. Whole faces: every face of the handle but the outer one is
    blocked, one sub-face is left. Per sub-face (the body's points): only the inner face and
    the cells next to it are blocked."""
    rng = np.random.default_rng(0)
    body = cylinder_points(4000, rng)
    lo, hi = np.array([0.04, -0.005, 0.03]), np.array([0.07, 0.005, 0.08])
    handle = lo + rng.uniform(size=(1500, 3)) * (hi - lo)
    ax = rng.integers(0, 3, 1500)
    handle[np.arange(1500), ax] = np.where(rng.uniform(size=1500) < 0.5, lo[ax], hi[ax])
    handle = handle[np.hypot(handle[:, 0], handle[:, 1]) > 0.04]
    pts = np.concatenate([body, handle])
    c, s = np.cos(np.pi / 4), np.sin(np.pi / 4)
    R45 = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    body_box = OrientedBox.from_points_in_frame(body, R45)
    handle_box = OrientedBox.from_points_in_frame(handle, np.eye(3))
    idx = np.arange(len(pts), dtype=np.int64)
    nodes = (
        BoxNode(0, -1, (1, 2), 0, idx, OrientedBox.from_points_in_frame(pts, np.eye(3)), 0),
        BoxNode(1, 0, (), 1, idx[: len(body)], body_box, 1),
        BoxNode(2, 0, (), 1, idx[len(body) :], handle_box, 1),
    )
    tree = BoxTree(nodes, len(pts))
    normals = FACE_NORMAL @ handle_box.rotation.T  # (6, 3) world
    outer = int(np.argmax(normals @ [1.0, 0.0, 0.0]))
    inner = int(np.argmax(normals @ [-1.0, 0.0, 0.0]))

    paper = compute_face_masks(tree, None, FaceMaskParams(rule="face"), points=pts)
    assert paper.covered is None
    assert paper.blocked[2].tolist() == [f != outer for f in range(6)]
    use = paper.usable(2, "spherical")
    assert sum(int(u.sum()) for u in use) == 1 and use[outer][4]  # the centre of the outer face
    assert all(
        np.array_equal(a, b)
        for a, b in zip(use, usable_subfaces(paper.blocked[2], "spherical"), strict=True)
    )

    ours = compute_face_masks(tree, None, FaceMaskParams(), points=pts)
    assert ours.blocked[2].tolist() == [f == inner for f in range(6)]
    use = ours.usable(2, "spherical")
    assert use[outer].all()  # the whole outer face
    assert not use[inner].any()
    for f in set(range(6)) - {outer, inner}:  # the other faces: all but the cells at the body
        assert 3 <= int(use[f].sum()) <= 6


def test_on_a_lone_box_the_subface_rule_is_the_paper_rule():
    """Nothing in front of a box on the table but the table: both rules give the same usable
    sub-faces for every grasp type (the bottom face and the cells next to it blocked)."""
    rng = np.random.default_rng(1)
    lo, hi = np.array([-0.04, -0.03, 0.0]), np.array([0.04, 0.03, 0.05])
    pts = lo + rng.uniform(size=(3000, 3)) * (hi - lo)
    ax = rng.integers(0, 3, 3000)
    pts[np.arange(3000), ax] = np.where(rng.uniform(size=3000) < 0.5, lo[ax], hi[ax])
    box = OrientedBox.from_points_in_frame(pts, np.eye(3))
    tree = BoxTree((BoxNode(0, -1, (), 0, np.arange(3000), box, 0),), 3000)
    table = SupportPlane(UP, 0.0)
    a = compute_face_masks(tree, table, FaceMaskParams(rule="face"), points=pts)
    b = compute_face_masks(tree, table, FaceMaskParams(), points=pts)
    assert np.array_equal(a.blocked, b.blocked)
    for gt in ("spherical", "cylindrical", "three_finger_tip", "two_finger_tip"):
        for u, v in zip(a.usable(0, gt), b.usable(0, gt), strict=True):
            assert np.array_equal(u, v)


def test_face_rule_must_be_known():
    with pytest.raises(ValueError, match="rule must be one of"):
        FaceMaskParams(rule="faces")


# ----------------------------------------------------------------------------- best


def test_no_force_closure_grasp_gives_best_none_with_the_reason(hand):
    # the paper's surfaces alone on a 2 cm brick: an empty pool
    res = plan(on_table(SMALL_PARTS["brick_2x2x1cm"]), hand, pinch=False)
    gs = res.grasps
    assert gs.best is None
    assert gs.best_reason == "no force-closure grasp: the pre-grasp pool is empty"
    doc = result_document(res)
    assert doc["best"] is None and doc["best_reason"] == gs.best_reason
    # kept grasps, every one with epsilon 0: best is None too (the ranking keeps them)
    gs = plan(on_table(SMALL_PARTS["cube_3cm"]), hand).grasps
    kept = gs.grasps[gs.best]
    flat = replace(gs, grasps=(replace(kept, pregrasp=0, epsilon=0.0),), ranking=np.array([0]))
    assert flat.best is None and flat.n_force_closure == 0 and len(flat.ranked) == 1
    assert flat.best_reason.startswith("no force-closure grasp: all 1 kept grasps have epsilon 0")


@pytest.mark.parametrize("name", ["bowl", "toy_car"])
def test_demo_objects_without_one_before_get_a_force_closure_best_grasp(hand, name):
    """The two demo objects whose best grasp had epsilon 0 (docs/benchmarks.md, "Coverage"),
    at default settings (20,000 points); the others are checked by `pregrasp plan
    assets/objects --report`."""
    res = run_pipeline(load_point_cloud(OBJECTS_DIR / f"{name}.obj"), None, hand, until="grasps")
    gs = res.grasps
    assert gs.best is not None, gs.best_reason
    assert gs.grasps[gs.best].epsilon > 0 and gs.n_force_closure >= 1


def test_the_pinch_preshapes_are_computed_once_per_hand_and_equal_fresh_ones(hand):
    """The pool's cache of pinch preshapes (the same part widths come back for both rolls and
    every re-plan) gives what ``pinch_preshape`` computes afresh, read-only."""
    from pregrasp_core.pregrasps import pinch

    for kind in pinch.KINDS:
        for half in (0.004, 0.01, 0.02, 0.035, 0.2):
            fresh = pinch.pinch_preshape(hand, kind, half)
            got = pinch._preshape(hand, kind, half)
            assert pinch._preshape(hand, kind, half) is got
            if fresh is None:
                assert got is None
                continue
            assert got is not None and got[0].tobytes() == fresh[0].tobytes()
            assert got[1] == fresh[1] and not got[0].flags.writeable
        c = pinch._center(hand, kind)
        assert c.tobytes() == pinch.pinch_center(hand, kind).tobytes() and not c.flags.writeable


# ------------------------------------------------------- rings wider than the hand's pinch


def test_rim_bar_is_the_material_between_the_fingers_end_and_the_hole():
    """Analytic: a ring's cross-section under the thumb is two intervals with the hole between
    them; the fingers' slices see more material (they lie off the ring's centre line)."""
    from pregrasp_core.pregrasps.pinch import RIM_MIN_GAP, rim_bar

    thumb = np.concatenate([np.linspace(-0.065, -0.035, 31), np.linspace(0.035, 0.065, 31)])
    fingers = np.concatenate([np.linspace(-0.065, -0.02, 46), np.linspace(0.02, 0.065, 46)])
    every = np.concatenate([thumb, fingers])
    # thumb on the + side: it goes into the hole, f1 and f2 close on the - end from outside
    centre, half = rim_bar(every, thumb, 1.0)
    assert centre == pytest.approx(-0.05) and half == pytest.approx(0.015)
    centre, half = rim_bar(every, thumb, -1.0)
    assert centre == pytest.approx(0.05) and half == pytest.approx(0.015)
    # a solid disc, or a hole too narrow for the thumb: no bar
    disc = np.linspace(-0.065, 0.065, 131)
    assert rim_bar(disc, disc, 1.0) is None
    narrow = np.concatenate([np.linspace(-0.065, -0.01, 56), np.linspace(0.01, 0.065, 56)])
    assert 0.02 < RIM_MIN_GAP and rim_bar(narrow, narrow, 1.0) is None


def _torus_surface_distance(p: np.ndarray, R: float, r: float) -> np.ndarray:
    """Distance of points (N, 3) to the surface of a torus about the z axis through (0, 0, r)
    (major radius R, tube radius r)."""
    rho = np.hypot(p[:, 0], p[:, 1])
    return np.abs(np.hypot(rho - R, p[:, 2] - r) - r)


@pytest.mark.parametrize("yaw", [0.0, 0.7])
def test_a_ring_wider_than_the_pinch_is_lifted_by_its_tube(hand, yaw):
    """A torus 130 mm across and 30 mm high lying on the table (one part: no split halves its
    box): no preshape opens across it, so the pinch from above closes on its tube, the thumb in
    the hole and f1 and f2 outside (docs/pregrasps.md, 6b). The best grasp is force closure,
    its contacts lie on the true torus (the analytic surface), the thumb's inside the tube's
    centre circle and the others' outside, and MuJoCo lifts the true mesh with it; under a turn
    about the vertical too."""
    from pregrasp_core.pregrasps.pinch import pinch_preshape
    from pregrasp_core.simulate import simulate_grasps

    R, r = 0.05, 0.015
    assert pinch_preshape(hand, "tip", R + r) is None  # the whole-ring pinch is out of reach
    mesh = trimesh.creation.torus(R, r, major_sections=64, minor_sections=24)
    mesh.apply_transform(trimesh.transformations.rotation_matrix(yaw, UP))
    cloud = on_table(mesh, n=8000)
    res = plan(cloud, hand)
    gs = res.grasps
    assert gs.best is not None, gs.best_reason
    best = gs.grasps[gs.best]
    assert best.epsilon > 0 and best.n_contacts >= 3
    assert res.pool.surface[best.pregrasp] == PINCH
    pts = np.array([c.point for c in best.contacts])
    assert _torus_surface_distance(pts, R, r).max() < 1e-3
    rho = {c.link: float(np.hypot(*c.point[:2])) for c in best.contacts}
    assert [k for k in rho if k.startswith("thumb")] and [k for k in rho if k.startswith("f")]
    assert all(v < R for k, v in rho.items() if k.startswith("thumb"))
    assert all(v > R for k, v in rho.items() if k.startswith("f"))
    on_plane = mesh.copy()
    on_plane.apply_translation([0.0, 0.0, -on_plane.bounds[0, 2]])
    (sim,) = simulate_grasps(res, [best], hand, mesh=on_plane)
    assert sim.success, sim.to_dict()


# ----------------------------------------------------------------------------- tilted boxes


def _top_face_tilt(box: OrientedBox) -> float:
    """Degrees between ``UP`` and the box face that faces up the most."""
    return float(np.degrees(np.arccos(np.abs(box.rotation.T @ UP).max())))


@pytest.mark.parametrize("yaw", [0.0, 1.1])
def test_a_ball_whose_box_stands_on_an_edge_is_pinched_from_above(hand, yaw):
    """A 45 mm ball on the table: its minimum box is a cube in any orientation, here one whose
    most level face is tilted past the 30 degrees of the pinch from above, so the pinch used to
    be skipped and the ball had no force-closure grasp (the enclosing surfaces reach below the
    table). The pinch now goes across the part's upright box (``mvbb.upright_box``): the best
    grasp is force closure, its contacts lie on the true sphere and around its middle, and
    MuJoCo lifts the true mesh with it; under a turn about the vertical too."""
    from pregrasp_core.simulate import simulate_grasps

    r = 0.0225
    mesh = trimesh.creation.icosphere(4, r)
    mesh.apply_transform(trimesh.transformations.rotation_matrix(yaw, UP))
    cloud = on_table(mesh, n=8000)
    res = plan(cloud, hand)
    assert _top_face_tilt(res.tree.nodes[0].box) > 30.0  # the case this test is about
    gs = res.grasps
    assert gs.best is not None, gs.best_reason
    best = gs.grasps[gs.best]
    assert best.epsilon > 0.05 and best.n_contacts >= 3
    assert res.pool.surface[best.pregrasp] == PINCH
    centre = np.array([0.0, 0.0, r])
    pts = np.array([c.point for c in best.contacts])
    assert np.abs(np.linalg.norm(pts - centre, axis=1) - r).max() < 1e-3
    assert np.abs(pts[:, 2] - r).max() < 0.6 * r  # around the middle, not on the top
    on_plane = mesh.copy()
    on_plane.apply_translation([0.0, 0.0, -on_plane.bounds[0, 2]])
    (sim,) = simulate_grasps(res, [best], hand, mesh=on_plane)
    assert sim.success, sim.to_dict()


def test_upright_box_is_the_minimum_area_rectangle_extruded():
    """``upright_box``: one axis along up, the other two those of the minimum-area rectangle of
    the projected points, against trimesh's rotating calipers (``oriented_bounds_2D``), on
    random clouds under random tilts of up; it holds every point."""
    from pregrasp_core.mvbb import upright_box

    rng = np.random.default_rng(3)
    for _ in range(20):
        pts = rng.normal(size=(200, 3)) * rng.uniform(0.01, 0.1, size=3)
        up = rng.normal(size=3)
        up /= np.linalg.norm(up)
        box = upright_box(pts, up)
        k = int(np.argmax(np.abs(box.rotation.T @ up)))
        assert abs(abs(box.rotation[:, k] @ up) - 1.0) < 1e-12
        e1 = np.cross(up, [1.0, 0.0, 0.0])
        e1 /= np.linalg.norm(e1)
        q2 = pts @ np.stack([e1, np.cross(up, e1)], axis=1)
        _, size = trimesh.bounds.oriented_bounds_2D(q2)
        area = float(np.prod(np.delete(box.extents, k)))
        assert area == pytest.approx(float(np.prod(size)), rel=1e-9)
        assert box.extents[k] == pytest.approx(float(np.ptp(pts @ up)), rel=1e-12)
        local = (pts - box.center) @ box.rotation
        assert np.all(np.abs(local) <= box.half_extents + 1e-12)
