"""The slicing contact planner on analytic objects: a cylinder in a cylindrical grasp, a flat box
pinched with the three fingertips, penetration and contact checks with the hand's own
point-in-link query (an implementation independent of the planner's box distances), rigid-motion
invariance, rejections, ranking and the result-file sections."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from pregrasp_core.facemask import SupportPlane
from pregrasp_core.hand import load_hand
from pregrasp_core.normals import estimate_normals
from pregrasp_core.planner import (
    REJECTION_REASONS,
    PlannerParams,
    box_signed_distance,
    grasps_sections,
    plan_grasps,
    rank_grasps,
    sweep_hit,
)
from pregrasp_core.pregrasps import PreGraspPool
from pregrasp_core.quality import grasp_quality


@pytest.fixture(scope="module")
def hand():
    return load_hand()


def _cloud(mesh: trimesh.Trimesh, n: int = 12000, seed: int = 0):
    pts, face = trimesh.sample.sample_surface(mesh, n, seed=seed)
    normals = estimate_normals(pts, reference=mesh.face_normals[face]).normals
    return np.asarray(pts), normals


def _pose(hand, gt, approach, closing, centre, back):
    """Hand pose whose +z is ``approach``, +y is ``closing`` (made orthogonal), with the
    preshape's grasp centre on the line through ``centre`` along the approach, ``back`` metres
    before it."""
    z = np.asarray(approach, float) / np.linalg.norm(approach)
    y = np.asarray(closing, float) - z * (z @ closing)
    y /= np.linalg.norm(y)
    x = np.cross(y, z)
    T = np.eye(4)
    T[:3, :3] = np.c_[x, y, z]
    T[:3, 3] = centre - T[:3, :3] @ hand.grasp_center(gt) - back * z
    return T


def _pool(hand, Ts, gt):
    P = len(Ts)
    Ts = np.asarray(Ts)
    return PreGraspPool(
        T_world_hand=Ts,
        approach=Ts[:, :3, 2].copy(),
        grasp_type=np.full(P, gt, dtype="<U16"),
        spread=np.full(P, hand.spread_for(gt)),
        q=np.tile(hand.preshape(gt), (P, 1)),
        node=np.zeros(P, dtype=np.int64),
        face=np.zeros(P, dtype=np.int64),
        subface=np.zeros(P, dtype=np.int64),
        surface=np.zeros(P, dtype=np.int64),
        joint_names=tuple(hand.joint_names),
    )


def _cylinder_scene(hand, n_dirs=6):
    """A 0.06 m x 0.15 m cylinder along z; side approaches, fingers closing across the axis."""
    mesh = trimesh.creation.cylinder(radius=0.03, height=0.15)
    angles = np.linspace(0.0, 2 * np.pi, n_dirs, endpoint=False)
    Ts = [
        _pose(hand, "cylindrical", [np.cos(a), np.sin(a), 0.0], [-np.sin(a), np.cos(a), 0.0],
              np.array([0.0, 0.0, 0.01 * k]), 0.09)
        for k, a in enumerate(angles)
    ]  # fmt: skip
    return mesh, _pool(hand, Ts, "cylindrical")


def _flat_box_scene(hand, n_dirs=6):
    """A 0.16 x 0.16 x 0.02 m plate (thin along z, longer than the fingers); approaches in the
    xy plane, fingers closing along z (across the thin dimension)."""
    mesh = trimesh.creation.box(extents=[0.16, 0.16, 0.02])
    angles = np.linspace(0.0, 2 * np.pi, n_dirs, endpoint=False)
    Ts = [
        _pose(hand, "three_finger_tip", [np.cos(a), np.sin(a), 0.0], [0.0, 0.0, 1.0],
              -0.08 * np.array([np.cos(a), np.sin(a), 0.0]), 0.04)
        for a in angles
    ]  # fmt: skip
    return mesh, _pool(hand, Ts, "three_finger_tip")


@pytest.fixture(scope="module")
def cylinder_plan(hand):
    mesh, pool = _cylinder_scene(hand)
    pts, nrm = _cloud(mesh)
    return pts, nrm, pool, plan_grasps(pts, nrm, pool, hand)


@pytest.fixture(scope="module")
def box_plan(hand):
    mesh, pool = _flat_box_scene(hand)
    pts, nrm = _cloud(mesh)
    return pts, nrm, pool, plan_grasps(pts, nrm, pool, hand)


def test_cylinder_cylindrical_grasp_has_contacts_on_both_sides_and_positive_epsilon(
    hand, cylinder_plan
):
    pts, _, pool, gs = cylinder_plan
    assert len(gs) == len(pool)
    for g in gs.grasps:
        assert g.kept, (g.rejection, g.detail)
        assert g.epsilon > 0.0
        links = {c.link for c in g.contacts}
        assert links & {"thumb_middle", "thumb_distal"}
        assert links & {"f1_middle", "f1_distal"} and links & {"f2_middle", "f2_distal"}
        # the thumb pushes towards hand +y, f1/f2 towards -y: contacts on both sides of the axis
        y_hand = g.T_world_hand[:3, 1]
        for c in g.contacts:
            side = np.dot(c.point[:2], y_hand[:2])
            if c.link.startswith("thumb"):
                assert side < -0.01
            elif c.link.startswith(("f1", "f2")):
                assert side > 0.01
            # the force points into the cylinder: against the radial outward direction
            radial = c.point[:2] / np.linalg.norm(c.point[:2])
            if abs(c.point[2]) < 0.07:  # on the curved side, not a cap
                assert np.dot(c.normal[:2], radial) < -0.9


def test_flat_box_three_finger_tip_pinches_opposite_faces(hand, box_plan):
    _, _, pool, gs = box_plan
    for g in gs.grasps:
        assert g.kept, (g.rejection, g.detail)
        tips = {c.link: c for c in g.contacts if c.link.endswith("_distal")}
        assert set(tips) == {"thumb_distal", "f1_distal", "f2_distal"}
        # the thumb tip on the bottom face z = -0.01, the two finger tips on the top face
        assert tips["thumb_distal"].point[2] == pytest.approx(-0.01, abs=1e-6)
        assert tips["f1_distal"].point[2] == pytest.approx(0.01, abs=1e-6)
        assert tips["f2_distal"].point[2] == pytest.approx(0.01, abs=1e-6)
        assert np.allclose(tips["thumb_distal"].normal, [0, 0, 1], atol=0.05)
        assert np.allclose(tips["f1_distal"].normal, [0, 0, -1], atol=0.05)


@pytest.mark.parametrize("scene", ["cylinder_plan", "box_plan"])
def test_final_hand_holds_no_point_deeper_than_tolerance(hand, scene, request):
    pts, _, _, gs = request.getfixturevalue(scene)
    tol = PlannerParams().penetration_tol
    for g in gs.grasps:
        if not g.kept:
            continue
        p_hand = (pts - g.T_world_hand[:3, 3]) @ g.T_world_hand[:3, :3]
        # the hand's own query, boxes shrunk by the tolerance: nothing inside
        assert not hand.points_in_hand(p_hand, g.q, margin=-tol).any()
        assert hand.within_limits(g.q)
        assert not hand.self_collision(g.q)


@pytest.mark.parametrize("scene", ["cylinder_plan", "box_plan"])
def test_every_contact_is_a_cloud_point_within_contact_distance_of_its_link(hand, scene, request):
    pts, nrm, _, gs = request.getfixturevalue(scene)
    d_max = PlannerParams().contact_distance
    n_contacts = 0
    for g in gs.grasps:
        for c in g.contacts:
            n_contacts += 1
            assert np.array_equal(c.point, pts[c.point_index])
            assert np.allclose(c.normal, -nrm[c.point_index])
            p_hand = (c.point - g.T_world_hand[:3, 3]) @ g.T_world_hand[:3, :3]
            inside = hand.points_in_links(p_hand[None], g.q, margin=d_max + 1e-9)[0]
            assert inside[hand.link_names.index(c.link)]
            assert -PlannerParams().penetration_tol <= c.distance <= d_max
    assert n_contacts >= 4 * len(gs)


def test_scores_and_contacts_unchanged_by_a_rigid_motion(hand):
    mesh, pool = _cylinder_scene(hand, n_dirs=3)
    pts, nrm = _cloud(mesh, n=8000)
    base = plan_grasps(pts, nrm, pool, hand)
    rng = np.random.default_rng(8)
    M = np.eye(4)
    M[:3, :3] = Rotation.random(random_state=rng).as_matrix()
    M[:3, 3] = rng.uniform(-0.5, 0.5, size=3)
    moved_pool = _pool(hand, M @ pool.T_world_hand, "cylindrical")
    moved = plan_grasps(pts @ M[:3, :3].T + M[:3, 3], nrm @ M[:3, :3].T, moved_pool, hand)
    for a, b in zip(base.grasps, moved.grasps, strict=True):
        assert a.rejection == b.rejection
        assert a.epsilon == pytest.approx(b.epsilon, abs=1e-6)
        assert a.volume == pytest.approx(b.volume, rel=1e-6, abs=1e-12)
        assert [(c.link, c.point_index) for c in a.contacts] == [
            (c.link, c.point_index) for c in b.contacts
        ]
        assert np.allclose(M @ a.T_world_hand, b.T_world_hand, atol=1e-9)
        assert np.allclose(a.q, b.q, atol=1e-6)


def test_rejections_and_support_stop(hand):
    mesh = trimesh.creation.box(extents=[0.05, 0.08, 0.02])
    pts, nrm = _cloud(mesh, n=4000)
    gt = "three_finger_tip"
    away = _pose(hand, gt, [1.0, 0.0, 0.0], [0, 0, 1.0], np.array([0.0, 0.3, 0.0]), 0.06)
    towards = _pose(hand, gt, [1.0, 0.0, 0.0], [0, 0, 1.0], np.zeros(3), 0.06)
    gs = plan_grasps(pts, nrm, _pool(hand, [away, towards], gt), hand)
    assert gs.grasps[0].rejection == "nothing_ahead" and gs.grasps[0].rank is None
    assert gs.grasps[1].kept and gs.best == 1 and gs.grasps[1].rank == 0
    assert gs.rejected == {**{k: 0 for k in REJECTION_REASONS}, "nothing_ahead": 1}
    # top-down over the box standing on a table at its bottom face: the open fingers reach
    # the table before the palm reaches the box, so the table stops the approach; the fingers
    # then close on the table, so the hand retreats (max_lift) until they reach the box
    down = _pose(hand, "cylindrical", [0, 0, -1.0], [0, 1.0, 0], np.zeros(3), 0.15)
    support = SupportPlane(normal=np.array([0.0, 0.0, 1.0]), height=-0.01)
    tol = PlannerParams().penetration_tol
    clearance = PlannerParams().approach_clearance
    pool = _pool(hand, [down], "cylindrical")

    def lowest(g, q):
        v = hand.collision_mesh(q).vertices @ g.T_world_hand[:3, :3].T + g.T_world_hand[:3, 3]
        return v[:, 2].min()

    stiff = plan_grasps(pts, nrm, pool, hand, PlannerParams(max_lift=0.0), support=support)
    g = stiff.grasps[0]
    assert g.approach_stop == "support"
    assert lowest(g, hand.preshape("cylindrical")) == pytest.approx(-0.01 + clearance, abs=1e-9)
    # closing lowers the open fingertips: the table (in every slice) stops them on it
    assert all(f.support_stop for f in g.fingers)
    assert lowest(g, g.q) >= -0.01 - tol
    assert g.rejection == "no_contact"

    lifted = plan_grasps(pts, nrm, pool, hand, support=support).grasps[0]
    assert lifted.approach_stop == "support_lifted"
    up = g.approach_distance - lifted.approach_distance
    assert 0.0 < up <= PlannerParams().max_lift + 1e-12
    assert up / 0.005 == pytest.approx(round(up / 0.005), abs=1e-9)
    assert lowest(lifted, lifted.q) >= -0.01 - tol
    assert lifted.kept and lifted.n_contacts >= 2
    assert {c.link.split("_")[0] for c in lifted.contacts} == {"thumb", "f1", "f2"}


def test_support_collision_check_uses_fcl_half_space(hand):
    """The closed hand's boxes against the table: fcl's box/half-space test (the last line of
    defence: the closing model already stops links on the table)."""
    from pregrasp_core.planner.context import Context
    from pregrasp_core.planner.verify import support_collision

    q = hand.preshape("cylindrical")
    lowest = hand.collision_mesh(q).vertices[:, 2].min()  # hand frame = world here
    tol = PlannerParams().penetration_tol
    pts = np.zeros((20, 3))
    for height, expect in ((lowest + tol - 1e-4, None), (lowest + tol + 1e-4, "some link")):
        ctx = Context(
            pts,
            pts,
            hand,
            PlannerParams(),
            SupportPlane(normal=np.array([0.0, 0.0, 1.0]), height=height),
        )
        got = support_collision(ctx, np.eye(4), q)
        assert (got is None) == (expect is None)
        if got is not None:
            assert got in hand.link_names


def test_support_collision_pretest_gives_what_fcl_gives_for_every_link(hand):
    """The pre-test (boxes clearly above the plane skip fcl) changes no answer: the first link
    fcl finds below the plane, over random poses, tilted planes and heights at each box's
    lowest point (within 1e-7 m, on both sides of it)."""
    import fcl

    from pregrasp_core.planner.context import Context
    from pregrasp_core.planner.verify import support_collision

    rng = np.random.default_rng(5)
    pts = np.zeros((20, 3))
    prm = PlannerParams()
    q = hand.preshape("cylindrical")
    n_hit = n_free = 0
    for trial in range(40):
        a = rng.normal(size=3)
        T = np.eye(4)
        T[:3, :3] = np.linalg.qr(rng.normal(size=(3, 3)))[0] * np.sign(rng.uniform(-1, 1))
        if np.linalg.det(T[:3, :3]) < 0:
            T[:3, :3] *= -1.0
        T[:3, 3] = rng.normal(scale=0.05, size=3)
        n = a / np.linalg.norm(a)
        ctx0 = Context(pts, pts, hand, prm, None)
        Tb = T @ ctx0.boxes(q)[0]
        # each box's lowest point along n (only to put the plane near one of them)
        low = [
            Tb[k, :3, 3] @ n - np.abs(Tb[k, :3, :3].T @ n) @ ctx0.half[k] for k in range(len(Tb))
        ]
        i = int(np.argmin(low)) if trial % 2 else int(rng.integers(len(Tb)))
        height = low[i] + prm.penetration_tol + rng.uniform(-1e-7, 1e-7)
        ctx = Context(pts, pts, hand, prm, SupportPlane(normal=n, height=height))
        table = fcl.CollisionObject(fcl.Halfspace(n, height - prm.penetration_tol), fcl.Transform())
        want = None
        for k, name in enumerate(hand.link_names):
            box = fcl.CollisionObject(
                fcl.Box(*(2.0 * ctx.half[k])), fcl.Transform(Tb[k, :3, :3], Tb[k, :3, 3])
            )
            if fcl.collide(box, table, fcl.CollisionRequest(), fcl.CollisionResult()) > 0:
                want = name
                break
        assert support_collision(ctx, T, q) == want
        n_hit, n_free = n_hit + (want is not None), n_free + (want is None)
    assert n_hit > 5 and n_free > 5


def test_ranking_by_epsilon_then_volume(cylinder_plan, box_plan):
    for _, _, _, gs in (cylinder_plan, box_plan):
        eps = [gs.grasps[k].epsilon for k in gs.ranking]
        assert eps == sorted(eps, reverse=True)
        assert [gs.grasps[k].rank for k in gs.ranking] == list(range(len(gs.ranking)))
        assert gs.best == gs.ranking[0]
        assert np.array_equal(rank_grasps(gs.grasps), gs.ranking)


def test_result_sections_are_json_ready(hand, box_plan):
    _, _, pool, gs = box_plan
    sec = grasps_sections(gs, hand)
    doc = json.loads(json.dumps(sec))
    assert doc["best"] == gs.best
    items = doc["grasps"]["items"]
    assert len(items) == len(pool)
    best = items[gs.best]
    assert best["rank"] == 0 and best["status"] == "kept"
    assert set(best["joints"]) >= set(hand.joint_names)
    assert best["contacts"][0].keys() >= {"link", "point", "normal", "point_index", "distance"}
    assert np.asarray(best["T_world_hand"]).shape == (4, 4)


def test_sweep_hit_against_stepping():
    """First touch of moving oriented boxes, against a brute-force march in 0.1 mm steps."""
    rng = np.random.default_rng(4)
    for _ in range(5):
        T = np.tile(np.eye(4), (2, 1, 1))
        T[:, :3, :3] = Rotation.random(2, random_state=rng).as_matrix()
        T[:, :3, 3] = rng.uniform(-0.02, 0.02, size=(2, 3))
        half = rng.uniform(0.005, 0.02, size=(2, 3))
        d = rng.normal(size=3) + [0.0, 0.0, 2.0]
        d /= np.linalg.norm(d)
        p = rng.uniform(-0.04, 0.04, size=(200, 3)) + 0.06 * d
        s, box = sweep_hit(p, T, half, d)
        steps = np.arange(0.0, 0.2, 1e-4)
        first = None
        for st in steps:  # brute force over steps (test only)
            Ts = T.copy()
            Ts[:, :3, 3] += st * d
            if (box_signed_distance(p, Ts, half) <= 0).any():
                first = st
                break
        if first is None:
            assert not np.isfinite(s)
        else:
            assert s == pytest.approx(first, abs=1.1e-4)
            assert box in (0, 1)


def test_box_signed_distance_matches_trimesh():
    rng = np.random.default_rng(6)
    T = np.eye(4)
    T[:3, :3] = Rotation.random(random_state=rng).as_matrix()
    T[:3, 3] = [0.01, -0.02, 0.03]
    half = np.array([0.03, 0.02, 0.01])
    mesh = trimesh.creation.box(extents=2 * half, transform=T)
    p = rng.normal(scale=0.04, size=(300, 3)) + T[:3, 3]
    ours = box_signed_distance(p, T[None], half[None])[:, 0]
    theirs = -trimesh.proximity.signed_distance(mesh, p)  # trimesh: positive inside
    assert np.allclose(ours, theirs, atol=1e-9)


def test_box_push_direction_is_the_gradient_of_the_exact_distance():
    """The direction a link's box pushes a point is the gradient of the box's signed distance
    (central differences of trimesh's exact distance), outside and inside, for rotated boxes."""
    from pregrasp_core.planner.boxes import box_push_direction

    rng = np.random.default_rng(11)
    M = 60
    T = np.tile(np.eye(4), (M, 1, 1))
    T[:, :3, :3] = Rotation.random(M, random_state=rng).as_matrix()
    T[:, :3, 3] = rng.normal(scale=0.05, size=(M, 3))
    half = rng.uniform(0.005, 0.03, size=(M, 3))
    p = T[:, :3, 3] + rng.normal(scale=0.03, size=(M, 3))
    ours = box_push_direction(p, T, half)
    h = 1e-6
    for k in range(M):  # loop over the boxes: one trimesh box each
        mesh = trimesh.creation.box(extents=2 * half[k], transform=T[k])
        probes = p[k] + h * np.vstack([np.eye(3), -np.eye(3)])
        d = -trimesh.proximity.signed_distance(mesh, probes)  # trimesh: positive inside
        grad = (d[:3] - d[3:]) / (2 * h)
        assert np.allclose(ours[k], grad / np.linalg.norm(grad), atol=1e-4), k
    assert np.allclose(np.linalg.norm(ours, axis=1), 1.0)
    # analytic: beyond a face, beyond an edge (the diagonal), on the face itself
    box = np.eye(4)[None]
    unit = np.array([[0.01, 0.01, 0.01]])
    got = box_push_direction(
        np.array([[0.0, 0.0, 0.02], [0.02, 0.0, 0.02], [0.005, 0.0, 0.01]]),
        np.repeat(box, 3, axis=0),
        np.repeat(unit, 3, axis=0),
    )
    assert np.allclose(got, [[0, 0, 1], [2**-0.5, 0, 2**-0.5], [0, 0, 1]])


def test_parameter_and_shape_checks(hand):
    with pytest.raises(ValueError, match="contact_distance"):
        PlannerParams(contact_distance=0.0005, closing_margin=0.001)
    with pytest.raises(ValueError, match="max_approach"):
        PlannerParams(max_approach=0.0)
    with pytest.raises(ValueError, match="slice_resolution .* sqrt"):
        PlannerParams(slice_resolution=0.001, closing_margin=0.001)
    mesh, pool = _flat_box_scene(hand, n_dirs=1)
    with pytest.raises(ValueError, match=r"normals must have shape \(10, 3\)"):
        plan_grasps(np.zeros((10, 3)), np.zeros((9, 3)), pool, hand)


@pytest.mark.parametrize("scene", ["cylinder_plan", "box_plan"])
def test_approach_stops_exactly_at_the_clearance(hand, scene, request):
    """At the approach pose the open hand's boxes, grown by the clearance, touch the cloud and
    hold no point: the smallest Chebyshev box distance of the cloud is the clearance."""
    pts, _, pool, gs = request.getfixturevalue(scene)
    c = PlannerParams().approach_clearance
    for g in gs.grasps:
        assert g.approach_stop == "object"
        q0 = pool.q[g.pregrasp]
        Tb = hand.box_poses(q0)
        p_h = (pts - g.T_world_hand[:3, 3]) @ g.T_world_hand[:3, :3]
        local = np.einsum("nlj,ljk->nlk", p_h[:, None, :] - Tb[None, :, :3, 3], Tb[:, :3, :3])
        cheb = (np.abs(local) - hand.link_box_half[None]).max(axis=2)  # (N, L)
        assert cheb.min() == pytest.approx(c, abs=1e-9)
        # and it got there by moving straight along its approach from the pre-grasp pose
        T0 = pool.T_world_hand[g.pregrasp]
        assert np.allclose(g.T_world_hand[:3, :3], T0[:3, :3])
        assert np.allclose(g.T_world_hand[:3, 3], T0[:3, 3] + g.approach_distance * T0[:3, 2])


def test_empty_pool_and_determinism(hand, box_plan):
    pts, nrm, pool, gs = box_plan
    empty = plan_grasps(pts, nrm, PreGraspPool.empty(hand.joint_names), hand)
    assert len(empty) == 0 and empty.best is None and empty.ranking.shape == (0,)
    assert grasps_sections(empty, hand)["best"] is None
    again = plan_grasps(pts, nrm, pool, hand)
    for a, b in zip(gs.grasps, again.grasps, strict=True):
        assert a.epsilon == b.epsilon and a.rank == b.rank
        assert np.array_equal(a.q, b.q) and np.array_equal(a.T_world_hand, b.T_world_hand)


def test_threads_change_no_result(hand):
    """More pre-grasps than one chunk (64): the per-pre-grasp phases on 3 threads give exactly
    the grasps of the single-thread run; progress ends at the pool size; every kept grasp's
    scores are those of grasp_quality on its own contacts with the object's centroid and
    radius."""
    mesh = trimesh.creation.cylinder(radius=0.03, height=0.15)
    angles = np.linspace(0.0, 2 * np.pi, 70, endpoint=False)
    Ts = [
        _pose(hand, "cylindrical", [np.cos(a), np.sin(a), 0.0], [-np.sin(a), np.cos(a), 0.0],
              np.array([0.0, 0.0, 0.01 * (k % 7) - 0.03]), 0.09)
        for k, a in enumerate(angles)
    ]  # fmt: skip
    pool = _pool(hand, Ts, "cylindrical")
    pts, nrm = _cloud(mesh, n=6000)
    seen = []
    one = plan_grasps(pts, nrm, pool, hand, PlannerParams(threads=1))
    three = plan_grasps(
        pts, nrm, pool, hand, PlannerParams(threads=3), progress=lambda d, n: seen.append((d, n))
    )
    assert seen == sorted(seen) and seen[-1] == (70, 70)
    assert np.array_equal(one.ranking, three.ranking) and one.n_force_closure > 0
    assert len(one.ranking) > 64  # kept grasps in both chunks
    prm = PlannerParams()
    center, radius = pts.mean(axis=0), np.linalg.norm(pts - pts.mean(axis=0), axis=1).max()
    for a, b in zip(one.grasps, three.grasps, strict=True):
        assert (a.epsilon, a.volume, a.rank, a.rejection, a.detail) == (
            b.epsilon, b.volume, b.rank, b.rejection, b.detail,
        )  # fmt: skip
        assert np.array_equal(a.q, b.q) and [c.point_index for c in a.contacts] == [
            c.point_index for c in b.contacts
        ]
        if a.kept:
            ref = grasp_quality(
                np.array([c.point for c in a.contacts]),
                np.array([c.normal for c in a.contacts]),
                prm.quality,
                tangents=np.array([c.tangent for c in a.contacts]),
                center=center,  # GraspIt: torques about the object's centroid, rho its radius
                radius=radius,
            )
            if a.epsilon_exact and a.volume_exact:
                assert (a.epsilon, a.volume) == pytest.approx((ref.epsilon, ref.volume), rel=1e-12)
            else:  # an upper bound (docs/quality.md): same force closure, never below the exact
                assert (a.epsilon > 0.0) == (ref.epsilon > 0.0)
                assert a.epsilon >= ref.epsilon and a.volume >= ref.volume
    assert set(three.phase_seconds) == {"approach_slicing", "closing", "verification", "quality"}
    with pytest.raises(ValueError, match=r"threads must be an integer in \[0, 1,024\], got -1"):
        PlannerParams(threads=-1)


def _seventy_cylinder_pregrasps(hand):
    """A cylinder and 70 cylindrical pre-grasps about it (two chunks of the planner)."""
    mesh = trimesh.creation.cylinder(radius=0.03, height=0.15)
    angles = np.linspace(0.0, 2 * np.pi, 70, endpoint=False)
    Ts = [
        _pose(hand, "cylindrical", [np.cos(a), np.sin(a), 0.0], [-np.sin(a), np.cos(a), 0.0],
              np.array([0.0, 0.0, 0.01 * (k % 7) - 0.03]), 0.09)
        for k, a in enumerate(angles)
    ]  # fmt: skip
    pts, nrm = _cloud(mesh, n=6000)
    return pts, nrm, _pool(hand, Ts, "cylindrical")


def _same_grasps(a, b):
    assert np.array_equal(a.ranking, b.ranking)
    for x, y in zip(a.grasps, b.grasps, strict=True):
        assert (x.pregrasp, x.epsilon, x.volume, x.rank, x.rejection, x.detail) == (
            y.pregrasp, y.epsilon, y.volume, y.rank, y.rejection, y.detail,
        )  # fmt: skip
        assert x.q.tobytes() == y.q.tobytes()
        assert x.T_world_hand.tobytes() == y.T_world_hand.tobytes()
        assert [
            (c.link, c.point_index, c.point.tobytes(), c.normal.tobytes()) for c in x.contacts
        ] == [(c.link, c.point_index, c.point.tobytes(), c.normal.tobytes()) for c in y.contacts]
        assert [f.q.tobytes() for f in x.fingers] == [f.q.tobytes() for f in y.fingers]


def test_forked_processes_threads_and_one_thread_give_the_same_grasps():
    """From a process running one thread, threads > 1 plans the chunks in forked copies of the
    process; with another thread alive it uses a thread pool: both give the grasps of one
    thread bit for bit. A copy that dies has its chunks planned by the parent; an exception
    in a copy is raised in the parent. Run in a fresh interpreter: in a long pytest run other
    tests' threads (servers, clusters) may still be alive, and then the planner never forks."""
    import subprocess
    import sys
    from pathlib import Path

    script = (
        "import sys; sys.path.insert(0, 'tests/core'); import pytest, test_planner as t; "
        "mp = pytest.MonkeyPatch(); t.check_fork_paths(t.load_hand(), mp); mp.undo(); "
        "print('fork paths ok')"
    )
    proc = subprocess.run(
        [sys.executable, "-c", script],
        capture_output=True,
        text=True,
        timeout=600,
        cwd=Path(__file__).resolve().parents[2],
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert proc.stdout.strip().splitlines()[-1] == "fork paths ok"


def check_fork_paths(hand, monkeypatch) -> None:
    """The checks of the test above, in a process running one thread."""
    import os
    import threading
    import time
    from pathlib import Path

    from pregrasp_core.planner import plan as plan_mod

    pts, nrm, pool = _seventy_cylinder_pregrasps(hand)
    one = plan_grasps(pts, nrm, pool, hand, PlannerParams(threads=1))
    assert plan_mod._can_fork()  # (the test runs in a process with one thread)
    forks = []
    real_fork = os.fork

    def counting_fork():
        forks.append(1)
        return real_fork()

    monkeypatch.setattr(os, "fork", counting_fork)
    forked = plan_grasps(pts, nrm, pool, hand, PlannerParams(threads=2))
    assert len(forks) == 1
    _same_grasps(one, forked)
    stop = threading.Event()
    other = threading.Thread(target=stop.wait)
    other.start()
    try:
        assert not plan_mod._can_fork()
        threaded = plan_grasps(pts, nrm, pool, hand, PlannerParams(threads=2))
    finally:
        stop.set()
        other.join()
    assert len(forks) == 1  # no fork with a second thread alive
    _same_grasps(one, threaded)
    # the copy dies, then it raises: the parent plans its chunk, then raises the same error
    parent, real_chunks = os.getpid(), plan_mod._plan_chunks

    def dying(*args, **kwargs):
        if os.getpid() != parent:
            os._exit(3)
        return real_chunks(*args, **kwargs)

    monkeypatch.setattr(plan_mod, "_plan_chunks", dying)
    _same_grasps(one, plan_grasps(pts, nrm, pool, hand, PlannerParams(threads=2)))

    def raising(*args, **kwargs):
        if os.getpid() != parent:
            raise ValueError("from the copy")
        return real_chunks(*args, **kwargs)

    monkeypatch.setattr(plan_mod, "_plan_chunks", raising)
    with pytest.raises(ValueError, match="from the copy"):
        plan_grasps(pts, nrm, pool, hand, PlannerParams(threads=2))
    monkeypatch.setattr(plan_mod, "_plan_chunks", real_chunks)
    # the exact settling's quality jobs: shared with the copy (some of them scored there), the
    # same grasps when the copy dies on its first job, its error raised here
    real_job, scored_in = plan_mod.run_quality_job, []

    def counting_job(job):
        scored_in.append(os.getpid())
        if os.getpid() != parent:
            os.write(report_w, b"j")
        return real_job(job)

    report_r, report_w = os.pipe()
    monkeypatch.setattr(plan_mod, "run_quality_job", counting_job)
    _same_grasps(one, plan_grasps(pts, nrm, pool, hand, PlannerParams(threads=2)))
    os.close(report_w)
    with os.fdopen(report_r, "rb") as fh:
        assert len(fh.read()) > 0  # the copy scored jobs of the settling
    assert len(scored_in) > 0  # and so did this process

    def dying_job(job):
        if os.getpid() != parent:
            os._exit(3)
        return real_job(job)

    monkeypatch.setattr(plan_mod, "run_quality_job", dying_job)
    _same_grasps(one, plan_grasps(pts, nrm, pool, hand, PlannerParams(threads=2)))

    def raising_job(job):
        if os.getpid() != parent:
            raise ValueError("from a job of the copy")
        return real_job(job)

    monkeypatch.setattr(plan_mod, "run_quality_job", raising_job)
    with pytest.raises(ValueError, match="from a job of the copy"):
        plan_grasps(pts, nrm, pool, hand, PlannerParams(threads=2))
    monkeypatch.setattr(plan_mod, "run_quality_job", real_job)
    # the copy's end is not waited for: a copy slow to exit is still there when the plan has
    # returned (and a zombie is never left: reaped at the next plan's end, or at exit)
    pids, real_exit = [], os._exit

    def fork_pid():
        pid = real_fork()
        pids.append(pid)
        return pid

    def slow_exit(code):
        if os.getpid() != parent:
            time.sleep(1.0)
        real_exit(code)

    monkeypatch.setattr(os, "fork", fork_pid)
    monkeypatch.setattr(os, "_exit", slow_exit)
    _same_grasps(one, plan_grasps(pts, nrm, pool, hand, PlannerParams(threads=2)))
    state = Path(f"/proc/{pids[-1]}/stat").read_text().rsplit(")", 1)[1].split()[0]
    assert state != "Z" and pids[-1] in plan_mod._LEAVING  # alive, not waited for
    plan_mod._reap_leaving(True)
    assert not plan_mod._LEAVING
    with pytest.raises(ChildProcessError):  # no child of this process is left, not even a zombie
        os.waitpid(-1, os.WNOHANG)


@pytest.mark.parametrize("P, n_proc", [(1, 2), (70, 2), (276, 2), (1000, 3), (5000, 2)])
def test_fork_chunks_cover_the_pool_in_order_large_first(P, n_proc):
    """The chunks of a forked plan: every pre-grasp once, in pool order, none larger than a
    chunk of one process nor smaller than the minimum (but the last), never growing."""
    from pregrasp_core.planner import plan as plan_mod

    chunks = plan_mod._fork_chunks(P, n_proc)
    assert [c for c0, c1 in chunks for c in range(c0, c1)] == list(range(P))
    sizes = [c1 - c0 for c0, c1 in chunks]
    assert max(sizes) <= plan_mod._CHUNK and min(sizes[:-1] or [8]) >= plan_mod._MIN_FORK_CHUNK
    assert sizes == sorted(sizes, reverse=True)


def test_pipeline_grasps_stage_reuses_normals_and_pool(hand):
    """The pipeline's planning stage: normals once per cloud, the pool reused when only the
    planner's parameters change, everything reused when nothing changes."""
    import dataclasses

    from pregrasp_core.io import load_point_cloud
    from pregrasp_core.paths import OBJECTS_DIR
    from pregrasp_core.pipeline import ALL_STAGES, PipelineParams, run_pipeline
    from pregrasp_core.quality import QualityParams

    cloud = load_point_cloud(OBJECTS_DIR / "fruit_lemon.obj", n_points=2500)
    fractions = []
    first = run_pipeline(cloud, hand=hand, until="grasps", progress=fractions.append)
    assert ALL_STAGES[-1] == "grasps" and set(first.timings) >= set(ALL_STAGES) | {"normals"}
    assert fractions[-1] == pytest.approx(1.0) and fractions == sorted(fractions)
    assert len(first.grasps) == len(first.pool) and first.normals.shape == (2500, 3)
    same = run_pipeline(cloud, first.params, hand, until="grasps", previous=first)
    assert "grasps" in same.reused and same.grasps is first.grasps
    params = dataclasses.replace(
        first.params,
        planner=dataclasses.replace(first.params.planner, quality=QualityParams(mu=1.0)),
    )
    other = run_pipeline(cloud, params, hand, until="grasps", previous=first)
    assert "pool" in other.reused and "grasps" not in other.reused
    assert other.normals is first.normals and other.pool is first.pool
    # more friction can only enlarge every friction cone: no epsilon decreases
    for a, b in zip(first.grasps.grasps, other.grasps.grasps, strict=True):
        assert b.epsilon >= a.epsilon - 1e-9
    assert isinstance(PipelineParams().planner, PlannerParams)


def test_fingers_closed_into_each_other_are_opened_back_along_their_paths(hand):
    """Spherical preshape, the three fingers closed together along straight paths until two of
    them overlap: the correction leaves no self-collision and every finger on its own path."""
    from types import SimpleNamespace

    from pregrasp_core.planner.context import Context
    from pregrasp_core.planner.verify import open_self_collisions

    q0 = hand.preshape("spherical")
    t = np.linspace(0.0, 1.0, 60)
    paths = {
        f.name: q0[list(f.flex_index)] + t[:, None] * (f.upper - q0[list(f.flex_index)])
        for f in hand.fingers
    }

    def at(k):
        q = q0.copy()
        for f in hand.fingers:
            q[list(f.flex_index)] = paths[f.name][k]
        return q

    k = next(k for k in range(len(t)) if hand.self_collisions(at(k)))
    assert all("palm" not in pair for pair in hand.self_collisions(at(k)))
    closings = [(f, SimpleNamespace(path=paths[f.name][: k + 1]), 0, (), False)
                for f in hand.fingers]  # fmt: skip
    pts = np.zeros((20, 3))
    ctx = Context(pts, pts, hand, PlannerParams(), None)
    corrected = {f.name: False for f in hand.fingers}
    q, clean = open_self_collisions(ctx, at(k), closings, corrected)
    assert clean and hand.self_collisions(q) == []
    assert any(corrected.values())
    for f in hand.fingers:
        flex = q[list(f.flex_index)]
        assert np.min(np.abs(paths[f.name][: k + 1] - flex).sum(axis=1)) < 1e-12
        if not corrected[f.name]:
            assert np.array_equal(flex, paths[f.name][k])


class _BlindHand:
    """The real hand, except that its planar closing model sees no point: every finger closes
    through the object. The planner's 3D verification must catch and correct that."""

    def __init__(self, hand):
        self._hand = hand

    def __getattr__(self, name):
        return getattr(self._hand, name)

    def close_finger(self, finger, points_2d, q_start, **kw):
        return self._hand.close_finger(finger, np.zeros((0, 2)), q_start, **kw)

    def close_fingers(self, slices, **kw):  # the batched form the planner calls
        blind = [(f, np.zeros((0, 2)), q) for f, _, q in slices]
        return self._hand.close_fingers(blind, **kw)


def test_fingers_closed_into_the_object_are_opened_back_or_rejected(hand):
    mesh, pool = _cylinder_scene(hand, n_dirs=3)
    pts, nrm = _cloud(mesh, n=8000)
    gs = plan_grasps(pts, nrm, pool, _BlindHand(hand))
    tol = PlannerParams().penetration_tol
    n_corrected = 0
    for g in gs.grasps:
        assert g.kept or g.rejection in ("penetration", "self_collision")
        if not g.kept:
            continue
        n_corrected += sum(f.corrected for f in g.fingers)
        p_hand = (pts - g.T_world_hand[:3, 3]) @ g.T_world_hand[:3, :3]
        assert not hand.points_in_hand(p_hand, g.q, margin=-tol).any()
    assert n_corrected >= 3  # the blind closing went through the cylinder and was undone


@pytest.mark.slow
def test_invariants_on_the_default_object(hand):
    """The whole pipeline on the mug with a handle: every kept grasp holds no cloud point deeper
    than the tolerance, every contact is within contact_distance of its link, no link is below
    the table (all by the hand's own queries), and some grasp is force closure."""
    from pregrasp_core.io import load_point_cloud
    from pregrasp_core.paths import DEFAULT_OBJECT
    from pregrasp_core.pipeline import run_pipeline

    cloud = load_point_cloud(DEFAULT_OBJECT, n_points=6000)
    result = run_pipeline(cloud, hand=hand, until="grasps")
    prm = PlannerParams()
    support = result.masks.support
    ranked = result.grasps.ranked
    assert len(ranked) >= 10 and ranked[0].epsilon > 0.0
    for g in ranked:
        R, t = g.T_world_hand[:3, :3], g.T_world_hand[:3, 3]
        p_hand = (cloud.points - t) @ R
        assert not hand.points_in_hand(p_hand, g.q, margin=-prm.penetration_tol).any()
        for c in g.contacts:
            inside = hand.points_in_links(((c.point - t) @ R)[None], g.q, prm.contact_distance)
            assert inside[0, hand.link_names.index(c.link)]
        corners = hand.collision_mesh(g.q).vertices @ R.T + t
        assert (corners @ support.normal).min() >= support.height - prm.penetration_tol - 1e-9


def _grasp_rows(gs):
    """Every field of every grasp that the planner computes, as comparable Python values."""
    rows = []
    for g in gs.grasps:
        rows.append((
            g.T_world_hand.tobytes(), g.approach_distance, g.approach_stop, g.q.tobytes(),
            g.rejection, g.detail, g.epsilon, g.volume, g.rank,
            [(c.link, c.point_index, c.distance) for c in g.contacts],
            [(f.finger, f.n_slice, f.q.tobytes(), f.links_touched, f.corrected) for f in g.fingers],
        ))  # fmt: skip
    return rows


def test_cell_size_changes_no_result(hand, monkeypatch):
    """The cloud's cells only find candidates for exact tests: planning the default object (with
    its table: approach stops on the support, retreats, corrections) with cells of 2 mm, 1 cm
    and 8 cm gives the same grasps, field for field, bit for bit."""
    import pregrasp_core.planner.context as context
    from pregrasp_core.io import load_point_cloud
    from pregrasp_core.paths import DEFAULT_OBJECT
    from pregrasp_core.pipeline import run_pipeline
    from pregrasp_core.planner import cloud_normals

    cloud = load_point_cloud(DEFAULT_OBJECT, n_points=4000, seed=3)
    res = run_pipeline(cloud, hand=hand, until="pool")
    pool, support, normals = res.pool, res.masks.support, cloud_normals(cloud)
    rows = []
    for size in (0.002, 0.01, 0.08):
        monkeypatch.setattr(context, "CELL_SIZE", size)
        gs = plan_grasps(cloud.points, normals, pool, hand, PlannerParams(threads=1), support)
        rows.append(_grasp_rows(gs))
    assert rows[0] == rows[1] == rows[2]
    stops = {g.approach_stop for g in gs.grasps}
    assert len(gs.ranking) >= 10 and "object" in stops and len(stops) >= 2


def test_cells_hold_every_point_and_list_them_ascending():
    """Cells against brute force on a random cloud: every point lies in its cell's ball; the
    points of any set of cells come back exactly and in ascending order; a ball query through the
    cells misses no point that the brute-force query finds."""
    from pregrasp_core.planner.cells import Cells

    rng = np.random.default_rng(7)
    pts = rng.normal(scale=0.05, size=(3000, 3))
    cells = Cells(pts, 0.01)
    assert cells.count.sum() == len(pts) and np.array_equal(np.sort(cells.order), np.arange(3000))
    owner = np.repeat(np.arange(len(cells.count)), cells.count)  # cell of each row of order
    d = np.linalg.norm(pts[cells.order] - cells.centre[owner], axis=1)
    assert np.all(d <= cells.radius[owner])
    for _ in range(20):
        some = np.flatnonzero(rng.random(len(cells.count)) < 0.3)
        ref = np.sort(cells.order[np.isin(owner, some)])
        assert np.array_equal(cells.points_of(some), ref)
        c, r = rng.normal(scale=0.05, size=3), rng.uniform(0.005, 0.05)
        hit = np.flatnonzero(np.linalg.norm(cells.centre - c, axis=1) <= r + cells.radius)
        found = cells.points_of(hit)
        truth = np.flatnonzero(np.linalg.norm(pts - c, axis=1) <= r)
        assert np.all(np.isin(truth, found))
    empty = Cells(np.zeros((0, 3)), 0.01)
    assert len(empty.points_of(np.zeros(0, dtype=np.int64))) == 0


@pytest.mark.parametrize("spread", [0.004, 0.5])
def test_thin_2d_keeps_the_first_point_of_every_cell(spread):
    """thin_2d against a loop over the points with a set of the cells seen so far, on a dense
    patch (the grid branch) and on a sparse spread (the sorting branch)."""
    from pregrasp_core.planner.slicing import thin_2d

    rng = np.random.default_rng(1)
    p2 = rng.uniform(-spread, spread, size=(800, 2))
    p2[::7] = p2[1::7][: len(p2[::7])]  # exact duplicates
    seen, ref = set(), []
    for p in p2:  # the reference: one pass in order
        key = (int(np.floor(p[0] / 0.0007)), int(np.floor(p[1] / 0.0007)))
        if key not in seen:
            seen.add(key)
            ref.append(p)
    assert np.array_equal(thin_2d(p2, 0.0007), np.array(ref))
    assert np.array_equal(thin_2d(p2, 0.0), p2)
