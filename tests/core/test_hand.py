"""The three-finger hand (docs/design.md section 7, docs/hand.md).

References from outside the code under test: fingertip positions worked out by hand from the
dimensions in docs/hand.md (palm face z = 0, Lk = 0.03, Lm = 0.05, Ld = 0.04, spread axes at
(+-0.028, 0.03), flexion planes offset 0.012 m from the spread axes, thumb at (0.012, -0.03));
yourdfpy's own forward kinematics; python-fcl's box collision; analytic contact angles.
"""

from __future__ import annotations

import math

import fcl
import numpy as np
import pytest
import yourdfpy
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp
from scipy.optimize import brentq

from pregrasp_core.errors import HandModelError
from pregrasp_core.hand import GRASP_TYPES, Hand, load_hand
from pregrasp_core.paths import HAND_URDF
from pregrasp_core.shape import GraspType

LK, LM, LD, H = 0.03, 0.05, 0.04, 0.01  # knuckle, middle, distal lengths; half thickness


@pytest.fixture(scope="module")
def hand() -> Hand:
    return load_hand()


def _q(hand: Hand, **values: float) -> np.ndarray:
    q = np.zeros(hand.n_joints)
    for name, v in values.items():
        q[hand.joint_names.index(name)] = v
    return q


# ------------------------------------------------------------------------------ the URDF


def test_urdf_loads_and_validates_with_yourdfpy():
    urdf = yourdfpy.URDF.load(str(HAND_URDF), build_scene_graph=True, load_meshes=True)
    assert urdf.validate(), urdf.errors
    assert urdf.base_link == "palm"
    assert urdf.actuated_joint_names == [
        "thumb_j1",
        "thumb_j2",
        "f1_spread",
        "f1_j1",
        "f1_j2",
        "f2_j1",
        "f2_j2",
    ]
    joints = {j.name: j for j in urdf.robot.joints}
    assert joints["f2_spread"].mimic.joint == "f1_spread"
    assert joints["thumb_base"].type == "fixed"
    # every link has visual meshes that loaded and one primitive collision box
    for link in urdf.robot.links:
        assert len(link.collisions) == 1 and link.collisions[0].geometry.box is not None
        assert len(link.visuals) == 1
    assert len(urdf.scene.geometry) == len(urdf.robot.links)


def test_hand_model_joint_order_limits(hand):
    assert hand.joint_names == tuple(hand.urdf.actuated_joint_names)
    assert hand.lower.shape == hand.upper.shape == (7,)
    i1 = hand.joint_names.index("f1_j1")
    # opens beyond straight, closes past 90 degrees; spread reaches pi/2
    assert hand.lower[i1] < 0 and hand.upper[i1] > math.pi / 2
    assert hand.upper[hand.spread_index] == pytest.approx(math.pi / 2)
    assert [f.name for f in hand.fingers] == ["thumb", "f1", "f2"]
    assert hand.finger("thumb").spread_joint is None
    assert hand.finger("f2").spread_joint == "f2_spread"


def test_missing_or_invalid_urdf_raises(tmp_path):
    with pytest.raises(HandModelError, match="does not exist"):
        Hand.load(tmp_path / "nope.urdf")
    bad = tmp_path / "bad.urdf"
    bad.write_text(HAND_URDF.read_text().replace('effort="5.0" ', ""))
    with pytest.raises(HandModelError, match="validation"):
        Hand.load(bad)
    nomesh = tmp_path / "nomesh.urdf"
    nomesh.write_text(HAND_URDF.read_text())
    with pytest.raises(HandModelError, match="make_hand_meshes"):
        Hand.load(nomesh)


# ------------------------------------------------------------------------------ kinematics


def _tip_by_hand(base, v, a1, a2):
    """Fingertip centre from the flexion-plane origin, closing direction and two angles."""
    base, v, z = np.asarray(base), np.asarray(v, dtype=float), np.array([0.0, 0.0, 1.0])
    return (
        base
        + LM * (math.sin(a1) * v + math.cos(a1) * z)
        + LD * (math.sin(a1 + a2) * v + math.cos(a1 + a2) * z)
    )


def test_fingertips_match_hand_worked_positions(hand):
    cases = [
        # (q, finger, expected tip centre)
        (_q(hand), "thumb", [0.012, -0.03, 0.12]),
        (_q(hand), "f1", [0.040, 0.03, 0.12]),
        (_q(hand), "f2", [-0.016, 0.03, 0.12]),
        (_q(hand, thumb_j1=math.pi / 2), "thumb", [0.012, 0.06, 0.03]),
        (_q(hand, thumb_j1=math.pi / 2, thumb_j2=math.pi / 2), "thumb", [0.012, 0.02, -0.01]),
        (_q(hand, f1_spread=math.pi / 2, f1_j1=math.pi / 2), "f1", [-0.062, 0.018, 0.03]),
        (_q(hand, f1_spread=math.pi / 2, f2_j1=math.pi / 2), "f2", [0.062, 0.042, 0.03]),
        (
            _q(hand, f1_spread=math.pi / 3, f2_j1=math.pi / 6, f2_j2=math.pi / 6),
            "f2",
            _tip_by_hand(
                [-0.028 + 0.012 * math.cos(math.pi / 3), 0.03 + 0.012 * math.sin(math.pi / 3), LK],
                [math.sin(math.pi / 3), -math.cos(math.pi / 3), 0.0],
                math.pi / 6,
                math.pi / 6,
            ),
        ),
        (
            _q(hand, f1_spread=0.4, f1_j1=-0.3, f1_j2=1.2),
            "f1",
            _tip_by_hand(
                [0.028 + 0.012 * math.cos(0.4), 0.03 - 0.012 * math.sin(0.4), LK],
                [-math.sin(0.4), -math.cos(0.4), 0.0],
                -0.3,
                1.2,
            ),
        ),
    ]
    for q, finger, expected in cases:
        np.testing.assert_allclose(hand.fingertips(q)[finger], expected, atol=1e-12)
    # batched call gives the same as the single calls
    Q = np.stack([c[0] for c in cases])
    tips = hand.fingertips(Q)
    for b, (_, finger, expected) in enumerate(cases):
        np.testing.assert_allclose(tips[finger][b], expected, atol=1e-12)


def test_batch_fk_equals_yourdfpy_per_configuration(hand):
    rng = np.random.default_rng(3)
    Q = rng.uniform(hand.lower, hand.upper, size=(40, hand.n_joints))
    T = hand.fk(Q)
    urdf = yourdfpy.URDF.load(str(HAND_URDF), build_scene_graph=True, load_meshes=False)
    for b in range(Q.shape[0]):
        urdf.update_cfg(Q[b])
        for name in hand.link_names:
            np.testing.assert_allclose(T[name][b], urdf.get_transform(name), atol=1e-12)
    single = hand.fk(Q[7])
    for name in hand.link_names:
        assert single[name].shape == (4, 4)
        np.testing.assert_allclose(single[name], T[name][7], atol=1e-15)


def test_fk_rejects_bad_shapes(hand):
    with pytest.raises(ValueError, match=r"q must have shape \(7,\) or \(B, 7\), got \(6,\)"):
        hand.fk(np.zeros(6))
    with pytest.raises(ValueError, match=r"got \(2, 3, 7\)"):
        hand.fk(np.zeros((2, 3, 7)))


def test_single_configuration_calls_reject_batches(hand):
    # every call that takes one configuration (J,): a batch (1, J) or a wrong length is refused
    # with the shape in the message; a list of 7 numbers is taken as float64
    q = hand.preshape(GRASP_TYPES[0])
    calls = {
        "one_q": hand.one_q,
        "with_flexion": lambda x: hand.with_flexion(x, "f1", np.zeros(2)),
        "points_in_links": lambda x: hand.points_in_links(np.zeros((1, 3)), x),
        "collision_objects": hand.collision_objects,
        "self_collisions": hand.self_collisions,
        "hand_mesh": hand.hand_mesh,
        "collision_mesh": hand.collision_mesh,
    }
    for call in calls.values():
        with pytest.raises(ValueError, match=r"q must have shape \(7,\), got \(1, 7\)"):
            call(q[None])
        with pytest.raises(ValueError, match=r"q must have shape \(7,\) or \(B, 7\), got \(6,\)"):
            call(q[:6])
        call(list(q))  # accepted
    one = hand.one_q(list(q))
    assert one.dtype == np.float64 and one.shape == (7,) and np.array_equal(one, q)


def test_mimic_spread_is_synchronous_and_mirrored(hand):
    for s in (0.0, 0.3, math.pi / 3, math.pi / 2):
        q = _q(hand, f1_spread=s)
        cfg = hand.full_cfg(q)
        assert cfg["f2_spread"] == pytest.approx(s)
        T = hand.fk(q)
        # closing directions (x axis of the knuckle frames): f1 turns by -s, f2 by +s from -y
        np.testing.assert_allclose(
            T["f1_knuckle"][:3, 0], [-math.sin(s), -math.cos(s), 0], atol=1e-12
        )
        np.testing.assert_allclose(
            T["f2_knuckle"][:3, 0], [math.sin(s), -math.cos(s), 0], atol=1e-12
        )
        # yourdfpy agrees when given only the actuated joints
        hand.urdf.update_cfg({n: v for n, v in cfg.items() if n != "f2_spread"})
        np.testing.assert_allclose(
            hand.urdf.get_transform("f2_knuckle"), T["f2_knuckle"], atol=1e-12
        )


def test_flexion_planes(hand):
    for s in (0.0, 0.7, math.pi / 2):
        for f in hand.fingers:
            plane = hand.flexion_plane(f, s)
            np.testing.assert_allclose(plane.u, [0, 0, 1], atol=1e-12)
            np.testing.assert_allclose(np.cross(plane.u, plane.v), plane.normal, atol=1e-12)
            # the finger's links stay in the plane whatever the flexion
            q = _q(hand, f1_spread=s)
            rng = np.random.default_rng(1)
            for _ in range(5):
                q[list(f.flex_index)] = rng.uniform(f.lower, f.upper)
                T = hand.fk(q)
                for link in f.links[1:]:
                    assert abs((T[link][:3, 3] - plane.origin) @ plane.normal) < 1e-12
                tip = hand.fingertips(q)[f.name]
                p2d, off = plane.to_plane(tip[None])
                assert abs(off[0]) < 1e-12
                a1, a2 = q[f.flex_index[0]], q[f.flex_index[1]]
                expected = LM * np.array([math.cos(a1), math.sin(a1)]) + LD * np.array(
                    [math.cos(a1 + a2), math.sin(a1 + a2)]
                )
                np.testing.assert_allclose(p2d[0], expected, atol=1e-12)
                np.testing.assert_allclose(plane.to_hand(p2d), tip[None], atol=1e-12)
    # at spread pi/2 the two spreading fingers close in parallel planes a finger width apart
    p1, p2 = hand.flexion_plane("f1", math.pi / 2), hand.flexion_plane("f2", math.pi / 2)
    assert abs(p1.normal @ p2.normal) == pytest.approx(1.0)
    assert abs((p2.origin - p1.origin) @ p1.normal) == pytest.approx(0.024)


def test_flexion_planes_are_computed_once_and_each_call_gets_a_copy(hand):
    from pregrasp_core.hand import kinematics

    for s in (0.0, -0.0, 0.3, math.pi / 3):
        for f in hand.fingers:
            want = kinematics.flexion_plane(hand, f, s)  # forward kinematics, no cache
            for name in (f, f.name):
                got = hand.flexion_plane(name, s)
                for a in ("origin", "u", "v", "normal"):
                    assert getattr(got, a).tobytes() == getattr(want, a).tobytes()
            got.origin[:] = 9.0  # a caller's change stays with its copy
            assert hand.flexion_plane(f, s).origin.tobytes() == want.origin.tobytes()


# ------------------------------------------------------------------------------ grasp types


def _closing_dirs(hand, grasp_type):
    s = hand.spread_for(grasp_type)
    return {f.name: hand.flexion_plane(f, s).v for f in hand.fingers}


def test_preshape_directions(hand):
    d = _closing_dirs(hand, "cylindrical")
    assert d["thumb"] @ d["f1"] == pytest.approx(-1.0) and d["thumb"] @ d["f2"] == pytest.approx(
        -1.0
    )
    d = _closing_dirs(hand, "three_finger_tip")
    assert d["thumb"] @ d["f1"] == pytest.approx(-1.0) and d["thumb"] @ d["f2"] == pytest.approx(
        -1.0
    )
    d = _closing_dirs(hand, GraspType.SPHERICAL)
    for a, b in (("thumb", "f1"), ("thumb", "f2"), ("f1", "f2")):
        assert d[a] @ d[b] == pytest.approx(math.cos(2 * math.pi / 3))
    d = _closing_dirs(hand, "two_finger_tip")
    assert d["f1"] @ d["f2"] == pytest.approx(-1.0)
    np.testing.assert_allclose(d["f1"], [-1, 0, 0], atol=1e-12)
    assert [f.name for f in hand.fingers_for("two_finger_tip")] == ["f1", "f2"]
    assert [f.name for f in hand.fingers_for(GraspType.CYLINDRICAL)] == ["thumb", "f1", "f2"]
    # the thumb is opened out of the way (tilted away from the fingers) for two-finger tips
    q = hand.preshape("two_finger_tip")
    assert q[hand.joint_names.index("thumb_j1")] == pytest.approx(hand.lower[0])
    assert hand.fingertips(q)["thumb"][1] < -0.07


def test_preshapes_within_limits_and_free(hand):
    for g in GRASP_TYPES:
        q = hand.preshape(g)
        assert hand.within_limits(q)
        assert q[hand.spread_index] == pytest.approx(hand.spread_for(g))
        assert not hand.self_collision(q)
        assert np.array_equal(q, hand.preshape(GraspType(g)))
    with pytest.raises(ValueError, match="unknown grasp type 'pinch'"):
        hand.preshape("pinch")


def test_apertures_worked_by_hand(hand):
    c30, s30, s15 = math.cos(math.pi / 6), math.sin(math.pi / 6), math.sin(math.pi / 12)
    # cylindrical: proximal opened 30 deg, distal straight: pads at y = +-(0.03 + 0.09 s30 - H c30)
    assert hand.aperture("cylindrical") == pytest.approx(2 * (0.03 + 0.09 * s30 - H * c30))
    # tip preshapes: middle tilted out 15 deg, distal parallel to z
    assert hand.aperture("three_finger_tip") == pytest.approx(2 * (0.03 + LM * s15 - H))
    assert hand.aperture(GraspType.TWO_FINGER_TIP) == pytest.approx(2 * (0.028 + LM * s15 - H))
    np.testing.assert_allclose(hand.grasp_center("two_finger_tip"), [0, 0.03, 0], atol=1e-12)
    np.testing.assert_allclose(hand.grasp_center("cylindrical"), [0.012, 0, 0], atol=1e-12)
    # spherical: the circle through the three pads; each pad is that far from the centre
    ap = hand.aperture("spherical")
    c = hand.grasp_center("spherical")
    pads = hand.tip_pads(hand.preshape("spherical"))
    for p in pads.values():
        assert np.linalg.norm(p[:2] - c[:2]) == pytest.approx(ap / 2)
    assert 0.12 < ap < 0.16  # "objects up to about 0.13 m"


def test_clamp(hand):
    q = np.array([-2.0, 3.0, 2.0, 0.1, -1.0, 5.0, 0.0])
    c = hand.clamp(q)
    np.testing.assert_allclose(c, np.clip(q, hand.lower, hand.upper))
    assert hand.within_limits(c) and not hand.within_limits(q)
    assert hand.clamp(np.stack([q, q])).shape == (2, 7)


# ------------------------------------------------------------------------------ collision


def test_fcl_agrees_with_points_in_links(hand):
    rng = np.random.default_rng(7)
    probe = fcl.Sphere(1e-9)
    req = fcl.CollisionRequest()
    for _ in range(4):
        q = rng.uniform(hand.lower, hand.upper)
        pts = rng.uniform([-0.08, -0.08, -0.04], [0.08, 0.08, 0.14], size=(400, 3))
        inside = hand.points_in_links(pts, q)
        objs = hand.collision_objects(q)
        ref = np.zeros_like(inside)
        for n, p in enumerate(pts):
            o = fcl.CollisionObject(probe, fcl.Transform(p))
            for li, name in enumerate(hand.link_names):
                ref[n, li] = fcl.collide(o, objs[name], req, fcl.CollisionResult()) > 0
        assert inside.any()
        np.testing.assert_array_equal(inside, ref)
        np.testing.assert_array_equal(hand.points_in_hand(pts, q), ref.any(axis=1))


def test_points_in_links_margin_matches_grown_fcl_boxes(hand):
    rng = np.random.default_rng(8)
    q = hand.preshape("spherical")
    pts = rng.uniform([-0.08, -0.08, -0.04], [0.08, 0.08, 0.14], size=(300, 3))
    m = 0.004
    inside = hand.points_in_links(pts, q, margin=m)
    Tb = hand.box_poses(q)
    probe = fcl.Sphere(1e-9)
    for li in range(len(hand.link_names)):
        box = fcl.CollisionObject(
            fcl.Box(*(2 * hand.link_box_half[li] + 2 * m)),
            fcl.Transform(Tb[li, :3, :3], Tb[li, :3, 3]),
        )
        for n, p in enumerate(pts):
            hit = (
                fcl.collide(
                    fcl.CollisionObject(probe, fcl.Transform(p)),
                    box,
                    fcl.CollisionRequest(),
                    fcl.CollisionResult(),
                )
                > 0
            )
            assert inside[n, li] == hit
    assert inside.sum() > hand.points_in_links(pts, q).sum()


def _random_poses(rng, G):
    from scipy.spatial.transform import Rotation

    T = np.tile(np.eye(4), (G, 1, 1))
    T[:, :3, :3] = Rotation.random(G, random_state=rng.integers(1 << 31)).as_matrix()
    T[:, :3, 3] = rng.uniform(-0.05, 0.05, size=(G, 3))
    return T


def test_batched_counts_equal_per_pose_queries(hand):
    rng = np.random.default_rng(11)
    G = 24
    T = _random_poses(rng, G)
    Q = rng.uniform(hand.lower, hand.upper, size=(G, hand.n_joints))  # all distinct
    Q4 = np.stack([hand.preshape(g) for g in GRASP_TYPES] * (G // 4))  # a pool: 4 preshapes
    # points spread around the hands plus points right at the link box surfaces (+-0.1 mm)
    near = [
        T[g, :3, :3] @ hand.collision_mesh(Q4[g]).sample(300, seed=g).T + T[g, :3, 3:4]
        for g in range(0, G, 5)
    ]
    pts = np.concatenate(
        [rng.uniform(-0.12, 0.12, size=(3000, 3))]
        + [p.T + rng.normal(0, 1e-4, size=p.T.shape) for p in near]
    )
    for q_arg in (Q, Q[0], Q4):
        for margin in (0.0, 0.002):
            counts = hand.link_point_counts(pts, T, q_arg, margin=margin)
            for g in range(G):
                qg = q_arg[g] if q_arg.ndim == 2 else q_arg
                p_hand = (pts - T[g, :3, 3]) @ T[g, :3, :3]  # world -> hand
                ref = hand.points_in_links(p_hand, qg, margin=margin).sum(axis=0)
                np.testing.assert_array_equal(counts[g], ref)
            assert counts.sum() > 0
    hits = hand.hands_hit_points(pts, T, Q)
    assert hits.dtype == bool and hits.shape == (G,)
    np.testing.assert_array_equal(hits, hand.link_point_counts(pts, T, Q).sum(axis=1) > 0)
    with pytest.raises(ValueError, match=r"T_world_hand must have shape \(G, 4, 4\)"):
        hand.link_point_counts(pts, T[0], Q[0])


def test_self_collision_detects_overlap(hand):
    # at spread pi/3 the fingers' planes cross: fully closed thumb and f2 meet
    q = hand.clamp(_q(hand, f1_spread=0.7, thumb_j1=1.3, f2_j1=1.3))
    assert hand.self_collision(q)
    assert not hand.self_collision(hand.preshape("spherical"))


def test_self_collisions_with_given_box_poses_match_python_fcl_pairs(hand):
    """Passing the box poses (as the planner does) gives the same pairs; each pair agrees with
    python-fcl on the link objects of ``collision_objects``; a wrong shape is refused."""
    import fcl

    rng = np.random.default_rng(11)
    Q = hand.clamp(rng.uniform(hand.lower, hand.upper, size=(40, hand.n_joints)))
    n_hit = 0
    for q in Q:  # loop over 40 configurations
        pairs = hand.self_collisions(q, hand.box_poses(q))
        assert pairs == hand.self_collisions(q)
        objs = hand.collision_objects(q)
        for a, b in hand.self_collision_pairs_checked:
            hit = fcl.collide(objs[a], objs[b], fcl.CollisionRequest(), fcl.CollisionResult())
            assert ((a, b) in pairs) == (hit > 0)
        n_hit += bool(pairs)
    assert 0 < n_hit < len(Q)  # both outcomes occur
    with pytest.raises(ValueError, match=r"box_poses must have shape"):
        hand.self_collisions(Q[0], np.eye(4))


def test_no_self_collision_when_closing_at_spread_pi_over_2(hand):
    """Every configuration the closing model produces for f1 and f2 at spread pi/2 (thumb open)
    is free of self-collision, with and without objects between the fingers."""
    rng = np.random.default_rng(5)
    base = hand.preshape("two_finger_tip")
    s = hand.spread_for("two_finger_tip")
    scenes = [np.zeros((0, 3))] + [
        rng.normal([0.0, 0.03, 0.08], 0.02, size=(200, 3)) for _ in range(6)
    ]
    n_checked = 0
    for cloud in scenes:
        q = base.copy()
        paths = {}
        for f in hand.fingers_for("two_finger_tip"):
            plane = hand.flexion_plane(f, s)
            p2d, off = plane.to_plane(cloud)
            closing = hand.close_finger(f, p2d[np.abs(off) <= f.width / 2], q[list(f.flex_index)])
            paths[f.name] = closing.path
        # every pair of intermediate configurations along the two paths
        for a in paths["f1"][:: max(1, len(paths["f1"]) // 8)].tolist() + [paths["f1"][-1]]:
            for b in paths["f2"][:: max(1, len(paths["f2"]) // 8)].tolist() + [paths["f2"][-1]]:
                qq = hand.with_flexion(hand.with_flexion(q, "f1", a), "f2", b)
                assert hand.within_limits(qq)
                assert not hand.self_collision(qq), hand.self_collisions(qq)
                n_checked += 1
    # with the fingers fully closed and nothing in between, still no collision
    full = hand.with_flexion(hand.with_flexion(base, "f1", hand.upper[3:5]), "f2", hand.upper[5:7])
    assert not any("f1" in a and "f2" in b for a, b in hand.self_collisions(full))
    assert n_checked > 100


# ------------------------------------------------------------------------------ closing model


def test_closing_without_points_stops_at_palm_or_limits(hand):
    f = hand.finger("thumb")
    c = hand.close_finger(f, np.zeros((0, 2)), np.zeros(2), palm=False)
    np.testing.assert_allclose(c.q, f.upper)
    assert c.at_limits and c.contact_link is None and c.contacts == ()
    c = hand.close_finger(f, np.zeros((0, 2)), np.zeros(2))
    assert c.palm_stop and not c.at_limits
    # coupled: both joints closed equally, and the distal tip's corner just reaches the palm
    assert c.q[0] == pytest.approx(c.q[1])
    a1, a = c.q[0], c.q[0] + c.q[1]
    low = LM * math.cos(a1) + LD * math.cos(a) - H * abs(math.sin(a))
    assert low == pytest.approx(-LK, abs=1e-4)


def test_middle_contact_then_distal_closes_alone(hand):
    f = hand.finger("f1")
    p = np.array([[0.025, 0.03]])  # in reach of the middle link's inner face
    c = hand.close_finger(f, p, np.zeros(2), palm=False)
    # the middle link's inner face (at +H) reaches the point: -x sin t + y cos t = H
    R, phi = math.hypot(0.025, 0.03), math.atan2(0.025, 0.03)
    theta = math.acos(H / R) - phi
    assert c.stopped_middle and c.contacts[0].link == "f1_middle" and c.contacts[0].index == 0
    assert c.q[0] == pytest.approx(theta, abs=2e-4)
    # with nothing else to touch the distal closes on alone to its limit
    assert c.q[1] == pytest.approx(f.upper[1])
    assert c.contact_link == "f1_middle" and not c.stopped_distal


def test_distal_contact_stops_the_finger(hand):
    f = hand.finger("f2")
    p = np.array([[0.075, 0.045]])
    c = hand.close_finger(f, p, np.zeros(2))

    def gap(t):  # distal inner face to the point, both joints at t (coupling 1)
        o2 = LM * np.array([math.cos(t), math.sin(t)])
        n2 = np.array([-math.sin(2 * t), math.cos(2 * t)])
        return (p[0] - o2) @ n2 - H

    t = brentq(gap, 0.0, 1.0)
    assert c.stopped_distal and not c.stopped_middle
    assert c.contact_link == "f2_distal" and c.contact_index == 0
    np.testing.assert_allclose(c.q, [t, t], atol=2e-4)
    np.testing.assert_allclose(c.contact_point, p[0])


def test_coupling_and_joint_limit_handoff(hand):
    f = hand.finger("thumb")
    c = hand.close_finger(f, np.zeros((0, 2)), np.array([0.0, 1.5]), coupling=2.0, palm=False)
    # the distal reaches its limit first and waits; the proximal goes on to its limit
    assert np.all(np.diff(c.path[:, 0]) >= 0) and np.all(np.diff(c.path[:, 1]) >= 0)
    np.testing.assert_allclose(c.path[-1], f.upper)
    k = np.argmax(c.path[:, 1] >= f.upper[1] - 1e-12)
    assert c.path[k, 0] < f.upper[0]
    steps = np.diff(c.path[: k + 1], axis=0)
    np.testing.assert_allclose(steps[:-1, 1], 2.0 * steps[:-1, 0])


def test_closing_result_agrees_with_3d_boxes(hand):
    """Random slices: the final configuration leaves no point inside a moving link (3D boxes),
    respects the limits, and the contact point touches its link (within the refinement)."""
    rng = np.random.default_rng(21)
    for trial in range(30):
        f = hand.fingers[trial % 3]
        s = rng.uniform(0, math.pi / 2)
        plane = hand.flexion_plane(f, s)
        p2d = rng.uniform([-0.01, -0.02], [0.1, 0.1], size=(60, 2))
        q0 = rng.uniform(f.lower, f.lower + 0.3)
        c = hand.close_finger(f, p2d, q0)
        assert np.all(c.q >= f.lower - 1e-12) and np.all(c.q <= f.upper + 1e-12)
        if c.start_in_contact:
            continue
        q = hand.with_flexion(_q(hand, f1_spread=s), f, c.q)
        p_hand = plane.to_hand(p2d)
        inside = hand.points_in_links(p_hand, q)
        cols = [hand.link_names.index(n) for n in f.links[1:]]
        assert not inside[:, cols].any()
        for contact in c.contacts:
            li = hand.link_names.index(contact.link)
            near = hand.points_in_links(p_hand[[contact.index]], q, margin=1e-3)[0, li]
            assert near, (trial, contact)


def test_closing_keeps_the_margin(hand):
    rng = np.random.default_rng(4)
    f = hand.finger("thumb")
    plane = hand.flexion_plane(f)
    m = 0.003
    for _ in range(10):
        p2d = rng.uniform([0.0, 0.0], [0.1, 0.1], size=(40, 2))
        c = hand.close_finger(f, p2d, f.lower.copy(), margin=m)
        if c.start_in_contact or not c.contacts:
            continue
        q = hand.with_flexion(np.zeros(hand.n_joints), f, c.q)
        cols = [hand.link_names.index(n) for n in f.links[1:]]
        inside = hand.points_in_links(plane.to_hand(p2d), q, margin=m - 1e-6)[:, cols]
        assert not inside.any()  # every point stays (just) outside the grown links
        for contact in c.contacts:
            li = hand.link_names.index(contact.link)
            grown = hand.points_in_links(plane.to_hand(p2d[[contact.index]]), q, margin=m + 1e-3)
            assert grown[0, li]


def test_closing_starting_in_contact(hand):
    f = hand.finger("f1")
    # a point inside the middle link at q_start = 0: the middle is stopped at once
    c = hand.close_finger(f, np.array([[0.02, 0.0]]), np.zeros(2), palm=False)
    assert c.start_in_contact and c.stopped_middle
    assert c.q[0] == 0.0 and c.q[1] == pytest.approx(f.upper[1])
    # a point inside the distal link at q_start: the finger does not move
    c = hand.close_finger(f, np.array([[0.07, 0.0]]), np.zeros(2))
    assert c.start_in_contact and c.stopped_distal
    np.testing.assert_array_equal(c.q, [0.0, 0.0])


@settings(max_examples=40, deadline=None)
@given(
    pts=hnp.arrays(np.float64, (12, 2), elements=st.floats(-0.05, 0.12)),
    q0=hnp.arrays(np.float64, (2,), elements=st.floats(-1.0, 2.0)),
    coupling=st.floats(0.3, 3.0),
)
def test_closing_invariants_hypothesis(hand, pts, q0, coupling):
    f = hand.finger("f2")
    c = hand.close_finger(f, pts, q0, n_steps=16, coupling=coupling)
    assert np.all(c.q >= f.lower) and np.all(c.q <= f.upper)
    start = np.clip(q0, f.lower, f.upper)
    assert np.all(c.q >= start - 1e-12)  # closing never opens a joint
    assert np.all(np.diff(c.path, axis=0) >= -1e-12)
    np.testing.assert_allclose(c.path[0], start)
    np.testing.assert_allclose(c.path[-1], c.q)
    if not c.start_in_contact:
        q = hand.with_flexion(np.zeros(hand.n_joints), f, c.q)
        cols = [hand.link_names.index(n) for n in f.links[1:]]
        p_hand = hand.flexion_plane(f).to_hand(pts)
        # no point deeper than 1e-9 m inside a moving link (points exactly on a face, e.g. at
        # the joint, are on the boundary in either test)
        assert not hand.points_in_links(p_hand, q, margin=-1e-9)[:, cols].any()
        assert (c.contact_link is None) == (len(c.contacts) == 0)


def test_closing_rejects_bad_input(hand):
    with pytest.raises(ValueError, match=r"points_2d must have shape \(M, 2\), got \(4, 3\)"):
        hand.close_finger("f1", np.zeros((4, 3)), np.zeros(2))
    with pytest.raises(ValueError, match=r"q_start must have shape \(2,\)"):
        hand.close_finger("f1", np.zeros((4, 2)), np.zeros(3))
    with pytest.raises(ValueError, match="unknown finger 'f3'"):
        hand.close_finger("f3", np.zeros((4, 2)), np.zeros(2))


# ------------------------------------------------------------------------------ meshes


def test_visual_mesh_lies_inside_collision_boxes(hand):
    rng = np.random.default_rng(2)
    for q in [hand.preshape(g) for g in GRASP_TYPES] + [rng.uniform(hand.lower, hand.upper)]:
        mesh = hand.hand_mesh(q)
        assert len(mesh.faces) > 1000
        assert hand.points_in_hand(mesh.vertices, q, margin=1e-9).all()
        assert mesh.visual.face_colors.shape == (len(mesh.faces), 4)
    box = hand.palm_box
    np.testing.assert_allclose(box.center, [0, 0, -0.015])
    np.testing.assert_allclose(box.extents, [0.1, 0.1, 0.03])


def test_committed_meshes_match_the_generator(tmp_path):
    """assets/meshes are what scripts/make_hand_meshes.py makes from the URDF's boxes."""
    import importlib.util
    import shutil

    import trimesh

    script = HAND_URDF.parents[1] / "scripts" / "make_hand_meshes.py"
    assert script.is_file(), f"run the tests from a checkout: {script} is missing"
    spec = importlib.util.spec_from_file_location("make_hand_meshes", script)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    urdf = tmp_path / "hand.urdf"
    shutil.copy(HAND_URDF, urdf)
    module.main(["--urdf", str(urdf)])
    for name in ("palm.stl", "knuckle.stl", "middle.stl", "distal.stl"):
        new = trimesh.load(tmp_path / "meshes" / name, force="mesh")
        old = trimesh.load(HAND_URDF.parent / "meshes" / name, force="mesh")
        assert new.is_watertight and new.is_convex
        np.testing.assert_allclose(
            np.sort(new.vertices, axis=0), np.sort(old.vertices, axis=0), atol=1e-6
        )
        assert len(new.faces) == len(old.faces)
