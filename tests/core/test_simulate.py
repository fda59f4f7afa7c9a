"""The MuJoCo lift test (``pregrasp_core.simulate``, ``docs/simulation.md``).

References from outside the code under test: a 6 cm cylinder (trimesh's primitive, analytic
volume pi r^2 h), the hand's closing model (``Hand.close_finger``) for the wrap, and the
planner's own grasp of a demo can.
"""

from __future__ import annotations

import json
import math
from unittest.mock import ANY

import numpy as np
import pytest
import trimesh

from pregrasp_core.errors import InputError
from pregrasp_core.facemask import SupportPlane
from pregrasp_core.hand import Hand
from pregrasp_core.io import load_point_cloud
from pregrasp_core.paths import OBJECTS_DIR
from pregrasp_core.pipeline import run_pipeline
from pregrasp_core.simulate import (
    OUTCOMES,
    LiftSimulator,
    SimulationParams,
    grasp_spec,
    object_from_cloud,
    object_from_mesh,
    simulate_grasp,
    simulate_grasps,
    simulate_playback,
)

RADIUS, HEIGHT = 0.03, 0.12
AXIS_DEPTH = 0.062  # cylinder axis in front of the palm face (hand z), clear of the knuckles
PALM_HEIGHT = 0.065  # world height of the hand origin (its x axis is world up)


@pytest.fixture(scope="module")
def hand() -> Hand:
    return Hand.load()


@pytest.fixture(scope="module")
def cylinder() -> trimesh.Trimesh:
    mesh = trimesh.creation.cylinder(radius=RADIUS, height=HEIGHT, sections=64)
    mesh.apply_translation([0.0, 0.0, HEIGHT / 2])  # standing on z = 0
    return mesh


@pytest.fixture(scope="module")
def support() -> SupportPlane:
    return SupportPlane(normal=np.array([0.0, 0.0, 1.0]), height=0.0)


@pytest.fixture(scope="module")
def sim(hand, cylinder, support) -> LiftSimulator:
    return LiftSimulator(hand, object_from_mesh(cylinder), support, friction=0.5)


def _side_pose(depth_back: float = 0.0) -> np.ndarray:
    """Hand approaching the cylinder from -x, its x axis up (f1 on top), thumb towards +y."""
    T = np.eye(4)
    T[:3, :3] = np.array([[0.0, 0.0, 1.0], [0.0, -1.0, 0.0], [1.0, 0.0, 0.0]])
    T[:3, 3] = [-AXIS_DEPTH - depth_back, 0.0, PALM_HEIGHT]
    return T


def _wrap(hand: Hand) -> tuple[np.ndarray, np.ndarray]:
    """(preshape, closed q) of the cylindrical grasp around the cylinder: each finger closed by
    the hand's planar closing model on the cylinder's circular section in its flexion plane."""
    q0 = hand.preshape("cylindrical")
    q = q0.copy()
    t = np.linspace(0.0, 2.0 * np.pi, 720, endpoint=False)
    for f in hand.fingers_for("cylindrical"):
        plane = hand.flexion_plane(f, hand.spread_for("cylindrical"))
        x = plane.origin[0]  # the planes are x = const in the hand frame at spread 0
        ring = np.stack(
            [np.full_like(t, x), RADIUS * np.cos(t), AXIS_DEPTH + RADIUS * np.sin(t)], axis=1
        )
        p2d, _ = plane.to_plane(ring)
        closing = hand.close_finger(f, p2d, q0[list(f.flex_index)], margin=0.001)
        assert not closing.start_in_contact
        assert closing.contact_link is not None  # the model says the finger touches
        q = hand.with_flexion(q, f, closing.q)
    return q0, q


def _spec(hand, depth_back=0.0, closed=True, start_back=0.03):
    q0, q = _wrap(hand)
    T = _side_pose(depth_back)
    T0 = _side_pose(depth_back + start_back)
    if closed:
        return grasp_spec(hand, T, q, q0, T0, closing=("thumb", "f1", "f2"))
    return grasp_spec(hand, T, q0, q0, T0, closing=())


def test_wrapped_cylinder_lifts(sim, hand):
    res, _ = sim.run(_spec(hand))
    assert res.outcome == "lifted" and res.success
    assert res.rise > 0.09  # rose with the hand (10 cm)
    assert res.slip < 0.005
    assert res.initial_penetration == 0.0
    assert res.planned_penetration < 0.002
    assert {"thumb_middle", "f1_middle", "f2_middle"} & set(res.contact_links)
    assert res.n_steps == round(res.sim_time / sim.params.timestep)


def test_open_hand_does_not_lift(sim, hand):
    res, _ = sim.run(_spec(hand, closed=False))
    assert not res.success and res.outcome == "dropped"
    assert abs(res.rise) < 0.005  # the cylinder stayed on the table


def test_hand_10cm_away_does_not_lift(sim, hand):
    res, _ = sim.run(_spec(hand, depth_back=0.10))
    assert not res.success and res.outcome == "dropped"
    assert res.contact_links == ()
    assert res.push < 1e-4  # never touched


def test_same_grasp_twice_is_bit_identical(sim, hand, cylinder, support):
    a, fa = sim.run(_spec(hand), record_fps=25)
    b, fb = sim.run(_spec(hand), record_fps=25)
    da, db = a.to_dict(), b.to_dict()
    da.pop("cpu_time"), db.pop("cpu_time")
    assert da == db
    assert len(fa) == len(fb) and all(
        np.array_equal(x.T_world_object, y.T_world_object) and np.array_equal(x.q, y.q)
        for x, y in zip(fa, fb, strict=True)
    )
    # a freshly built scene (object model and MuJoCo model rebuilt) gives the same outcome too
    q0, q = _wrap(hand)
    c = simulate_grasp(
        object_from_mesh(cylinder),
        hand,
        _side_pose(),
        q,
        q0,
        _side_pose(0.03),
        ("thumb", "f1", "f2"),
        support,
        SimulationParams(friction=0.5),
    ).to_dict()
    c.pop("cpu_time")
    assert c == da


def test_playback_frames(sim, hand):
    res, frames = sim.run(_spec(hand), record_fps=20)
    assert len(frames) == 1 + math.floor(res.n_steps * sim.params.timestep * 20 + 1e-9)
    t = np.array([f.t for f in frames])
    assert t[0] == 0.0 and np.all(np.diff(t) > 0)
    first, last = frames[0], frames[-1]
    np.testing.assert_allclose(first.T_world_hand, _side_pose(0.03), atol=1e-9)
    np.testing.assert_allclose(first.T_world_object[:3, :3], np.eye(3), atol=1e-3)
    assert abs(first.T_world_object[2, 3]) < 1e-3  # resting where the file put it
    assert last.T_world_hand[2, 3] - first.T_world_hand[2, 3] == pytest.approx(0.10, abs=2e-3)
    assert last.T_world_object[2, 3] > 0.09  # the object went up with the hand
    assert first.q.shape == (hand.n_joints,)


def test_result_to_dict_is_json(sim, hand):
    res, _ = sim.run(_spec(hand, closed=False))
    doc = json.loads(json.dumps(res.to_dict()))
    assert doc["outcome"] in OUTCOMES
    assert set(doc) >= {"success", "rise", "slip", "push", "initial_penetration", "cpu_time"}
    assert len(doc["q_closed"]) == hand.n_joints


def test_collision_model_of_the_cylinder(cylinder):
    obj = object_from_mesh(cylinder)
    assert obj.source == "mesh"
    assert obj.volume == pytest.approx(math.pi * RADIUS**2 * HEIGHT, rel=0.01)  # 64-gon
    assert obj.mass == pytest.approx(500.0 * obj.volume)
    np.testing.assert_allclose(obj.com, [0.0, 0.0, HEIGHT / 2], atol=1e-6)
    verts = np.concatenate(obj.pieces)
    r = np.hypot(verts[:, 0], verts[:, 1])
    assert r.max() <= RADIUS + 1e-9 and verts[:, 2].min() >= -1e-9
    # from the surface samples as a cloud (no mesh): the same solid within the grid's error
    cloud = object_from_cloud(obj.samples, _cylinder_normals(obj.samples))
    assert cloud.source == "cloud"
    assert cloud.volume == pytest.approx(obj.volume, rel=0.1)
    np.testing.assert_allclose(cloud.com, obj.com, atol=2e-3)


def _cylinder_normals(p: np.ndarray) -> np.ndarray:
    n = np.zeros_like(p)
    side = (p[:, 2] > 1e-6) & (p[:, 2] < HEIGHT - 1e-6)
    n[side, :2] = p[side, :2] / np.hypot(p[side, 0], p[side, 1])[:, None]
    n[~side & (p[:, 2] >= HEIGHT / 2), 2] = 1.0
    n[~side & (p[:, 2] < HEIGHT / 2), 2] = -1.0
    return n


def test_planned_best_grasp_of_the_can_lifts(hand):
    cloud = load_point_cloud(OBJECTS_DIR / "can_soda.obj")
    result = run_pipeline(cloud, until="grasps", hand=hand)
    best = result.grasps.best
    assert best is not None
    (res,) = simulate_grasps(result, [best], hand)
    assert res.success, res.to_dict()
    assert res.initial_penetration == 0.0
    # the playback is the same run
    again, frames = simulate_playback(result, best, hand, fps=10)
    a, b = res.to_dict(), again.to_dict()
    a.pop("cpu_time"), b.pop("cpu_time")
    assert a == b and len(frames) > 10


def test_grasp_index_without_a_plan_is_refused(hand):
    cloud = load_point_cloud(OBJECTS_DIR / "can_soda.obj")
    with pytest.raises(InputError, match="bare cloud has no planned grasps"):
        simulate_grasps(cloud, [0], hand)


def test_params_are_checked():
    with pytest.raises(ValueError, match="SimulationParams.timestep must be"):
        SimulationParams(timestep=0.0)
    with pytest.raises(ValueError, match="base_timeconst .* at least two timesteps"):
        SimulationParams(timestep=0.01, base_timeconst=0.01, contact_timeconst=0.02)
    with pytest.raises(ValueError, match="finger_torque must be two torques"):
        SimulationParams(finger_torque=(0.5, -1.0))


def test_synchronous_closing_reaches_every_planned_contact_at_once(hand, cylinder, support):
    """``SimulationParams.synchronous``: the closing commands bring every closing joint to its
    planned closed angle at the same step (each at its own rate, the farthest at
    ``closing_speed``), then squeeze; the default protocol moves every joint at
    ``closing_speed``, so the ones with less way arrive first. Both end at the same targets
    and both lift the wrapped cylinder."""
    spec = _spec(hand)
    arrivals, finals = {}, []
    for sync in (False, True):
        params = SimulationParams(synchronous=sync)
        s = LiftSimulator(hand, object_from_mesh(cylinder), support, params, friction=0.5)
        _, ctrl, ends = s._commands(spec)
        q0, q1 = np.asarray(spec.q_start), np.asarray(spec.q_closed)
        moving = np.flatnonzero(q1 - q0 > 1e-3)
        assert len(moving) >= 4
        arrivals[sync] = [int(np.argmax(ctrl[:, j] >= q1[j] - 1e-12)) for j in moving]
        assert np.all(ctrl[ends["approach"] - 1, moving] == q0[moving])  # closing starts after
        finals.append(ctrl[-1])
        res, _ = s.run(spec)
        assert res.success, res.to_dict()
    assert np.allclose(finals[0], finals[1])  # the same targets, squeeze included
    assert max(arrivals[True]) - min(arrivals[True]) <= 1
    assert max(arrivals[False]) - min(arrivals[False]) > 10


def test_a_pinch_is_simulated_from_its_own_preshape(hand):
    """A 30 mm ball on the table, planned from its cloud: its grasps are tripod pinches, whose
    preshape the pool adapts to the ball (each finger opened just wider than it). The lift test
    starts from that preshape (``pool.q``), the one the planner closed the fingers from, and
    lifts the true sphere with little push. Before, it started every grasp from its type's
    fixed preshape (the tripod opened wide): the fingers then swept far, the first to touch
    rolled the ball away (pushed more than 5 cm) and it dropped. MuJoCo is the reference."""
    from pregrasp_core.io import PointCloud

    r = 0.015
    mesh = trimesh.creation.icosphere(4, r)
    mesh.apply_translation([0.0, 0.0, r])
    pts, face = trimesh.sample.sample_surface(mesh, 8000, seed=0)
    cloud = PointCloud(points=np.asarray(pts), normals=mesh.face_normals[face], source="ball")
    result = run_pipeline(cloud, until="grasps", hand=hand)
    best = result.grasps.best
    assert best is not None
    g = result.grasps.grasps[best]
    own = grasp_spec_of(hand, g, result, pool=True)
    typed = grasp_spec_of(hand, g, result, pool=False)
    assert np.array_equal(own.q_start, result.pool.q[g.pregrasp])
    assert np.array_equal(typed.q_start, hand.preshape(g.grasp_type))
    assert not np.allclose(own.q_start, typed.q_start)
    (lift,) = simulate_grasps(result, [best], hand, mesh=mesh)
    assert lift.success and lift.push < 0.01, lift.to_dict()
    sim = LiftSimulator(hand, object_from_mesh(mesh), result.masks.support, friction=0.5)
    assert sim.run(own)[0].to_dict() == {**lift.to_dict(), "cpu_time": ANY}
    wide, _ = sim.run(typed)
    assert not wide.success and wide.push > 0.05, wide.to_dict()


def grasp_spec_of(hand, g, result, pool: bool):
    """The simulator's spec of grasp ``g`` of ``result``, from the pre-grasp's own preshape
    (``pool``) or from its type's."""
    from pregrasp_core.simulate import grasp_specs

    return grasp_specs(hand, [g], result.grasps, result.pool if pool else None)[0]
