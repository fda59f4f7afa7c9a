"""The rest of a scene as obstacles: a wall behind the object, a neighbour in clutter.

A depth camera's view of an object on a table holds more than the object and the table; the
segmentation keeps the object and sets the rest aside (``pregrasp_core/sensor/table.py``), and
the rest near the object goes to the pool and the planner as points the hand must clear and
never touches (``PointCloud.obstacles``). Checked against the true geometry the views are
rendered from: the wall's plane and the neighbour's mesh."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import trimesh

from pregrasp_core.hand import Hand
from pregrasp_core.io import SensorOptions, load_point_cloud
from pregrasp_core.paths import OBJECTS_DIR
from pregrasp_core.pipeline import PipelineParams, run_pipeline, with_cloud
from pregrasp_core.sensor import Intrinsics
from pregrasp_core.sensor.synthetic import orbit_camera, render_view


def _view(
    meshes: list[trimesh.Trimesh], azimuth: float, seed: int
) -> tuple[np.ndarray, np.ndarray]:
    """World points and camera pose of a depth view of ``meshes`` on the table z = 0 at 35
    degrees of elevation, 1 mm of noise."""
    scene = trimesh.util.concatenate(meshes)
    T = orbit_camera(np.array([0.0, 0.0, 0.05]), 0.6, np.radians(azimuth), np.radians(35.0))
    view = render_view(scene.vertices, scene.faces, T, Intrinsics(420.0, 420.0, 239.5, 179.5),
                       480, 360, table_half=0.8, noise=0.001,
                       rng=np.random.default_rng(seed))  # fmt: skip
    return view.points_world()[0], T


def _hands(res, hand: Hand) -> list[np.ndarray]:
    """World points of the collision mesh of every kept grasp's hand: its vertices and 3,000
    points spread over its surface (a box may cross a cylinder with its corners outside)."""
    out = []
    for g in res.grasps:
        if g.rejection is None:
            m = hand.collision_mesh(g.q)
            p = np.concatenate([m.vertices, trimesh.sample.sample_surface(m, 3000, seed=0)[0]])
            out.append(p @ g.T_world_hand[:3, :3].T + g.T_world_hand[:3, 3])
    return out


@pytest.fixture(scope="module")
def hand() -> Hand:
    return Hand.load()


def test_a_wall_behind_the_object_keeps_every_grasp_out_of_it(tmp_path, hand, make_views) -> None:
    """The mug with a handle 4 cm in front of a wall (its back at y = 0.04, the wall at
    y = 0.08): with the wall as an obstacle no kept grasp's hand reaches more than 4 mm (the
    obstacle lattice) past the wall's plane and force closure remains; planned on the same
    cloud without the obstacle, grasps reach into the wall by centimetres."""
    mug = trimesh.load(OBJECTS_DIR / "mug_handle.obj", force="mesh")
    wall = trimesh.creation.box((3.0, 0.001, 1.7))
    wall.apply_translation((0.0, 0.0805, 0.65))
    pts, T = _view([mug, wall.subdivide_to_size(0.05)], 270.0, seed=3)
    path = tmp_path / "wall.pcd"
    path.write_bytes(make_views.pcd_bytes(pts, np.ones(len(pts), dtype=np.uint8), T))
    cloud = load_point_cloud(path, n_points=None)
    assert cloud.obstacles is not None and cloud.info["scene"]["n_obstacles"] > 1000
    assert np.all(np.abs(cloud.obstacles[:, 1] - 0.08) < 0.01)  # the wall, not the mug
    params = with_cloud(PipelineParams(), cloud)
    res = run_pipeline(cloud, params, hand, until="grasps")
    reach = [float(v[:, 1].max()) - 0.08 for v in _hands(res, hand)]
    assert reach and max(reach) < 0.004, max(reach)
    assert res.grasps.n_force_closure > 0
    bare = run_pipeline(dataclasses.replace(cloud, obstacles=None), params, hand, until="grasps")
    assert max(float(v[:, 1].max()) - 0.08 for v in _hands(bare, hand)) > 0.01


def test_a_neighbour_in_clutter_is_not_touched_by_the_grasps_of_the_object(
    tmp_path, hand, make_views
):
    """A soda can 3 cm beside a 7 cm ball on the table: picking the ball, the obstacles are the
    can's seen points and the space hidden behind them (its unseen back), none near the ball;
    no kept grasp's hand enters the can (by the true cylinder: at most 4 mm inside). With
    ``--scene-obstacles seen`` the obstacles are the can's seen front only and some grasp
    reaches through its unseen back; with ``off`` there are none (the object's cloud the
    same) and some grasp passes through the can."""
    ball = trimesh.creation.icosphere(subdivisions=3, radius=0.035)
    ball.apply_translation((0.0, 0.0, 0.035))
    can = trimesh.creation.cylinder(radius=0.033, height=0.12, sections=48)
    can.apply_translation((0.098, 0.0, 0.06))
    pts, T = _view([ball, can], 250.0, seed=4)
    path = tmp_path / "clutter.pcd"
    path.write_bytes(make_views.pcd_bytes(pts, np.ones(len(pts), dtype=np.uint8), T))
    pick = SensorOptions(pick=(0.0, 0.0, 0.035))
    cloud = load_point_cloud(path, n_points=None, sensor=pick)
    assert cloud.obstacles is not None and cloud.info["scene"]["obstacles"] == "all"
    obs = cloud.obstacles  # the can's seen points and the space hidden behind it
    assert np.all(obs[:, 0] > 0.098 - 0.033 - 0.005)
    assert np.all(np.linalg.norm(obs - [0.0, 0.0, 0.035], axis=1) > 0.035 + 0.005)
    assert np.sum(np.hypot(obs[:, 0] - 0.098, obs[:, 1]) < 0.02) > 50  # the can's inside
    assert np.all(np.linalg.norm(cloud.points - [0, 0, 0.035], axis=1) < 0.035 + 0.01)

    def inside_can(v: np.ndarray) -> float:
        r = 0.033 - np.hypot(v[:, 0] - 0.098, v[:, 1])  # depth inside the wall of the can
        return float(np.max(np.where((v[:, 2] > 0.0) & (v[:, 2] < 0.12), r, -1.0)))

    params = with_cloud(PipelineParams(), cloud)
    res = run_pipeline(cloud, params, hand, until="grasps")
    depths = [inside_can(v) for v in _hands(res, hand)]
    assert depths and max(depths) < 0.004, max(depths)

    seen = load_point_cloud(path, n_points=None, sensor=dataclasses.replace(pick, obstacles="seen"))
    assert seen.obstacles is not None and "n_obstacles_hidden" not in seen.info["scene"]
    n_hidden = cloud.info["scene"]["n_obstacles_hidden"]
    assert len(seen.obstacles) == len(obs) - n_hidden
    np.testing.assert_array_equal(seen.obstacles, obs[: len(seen.obstacles)])  # seen first
    radial = np.hypot(seen.obstacles[:, 0] - 0.098, seen.obstacles[:, 1])
    on_can = (np.abs(radial - 0.033) < 0.006) | (np.abs(seen.obstacles[:, 2] - 0.12) < 0.006)
    assert np.all(on_can)  # the can's seen wall and lid, nothing inside it
    res_seen = run_pipeline(seen, params, hand, until="grasps")
    assert max(inside_can(v) for v in _hands(res_seen, hand)) > 0.01

    off = load_point_cloud(path, n_points=None, sensor=dataclasses.replace(pick, obstacles="off"))
    assert off.obstacles is None and off.info["scene"]["obstacles"] == "off"
    assert "n_obstacles" not in off.info["scene"]
    np.testing.assert_array_equal(off.points, cloud.points)
    bare = run_pipeline(off, params, hand, until="grasps")
    assert max(inside_can(v) for v in _hands(bare, hand)) > 0.01


def test_scene_obstacles_setting_is_checked() -> None:
    with pytest.raises(ValueError, match="scene obstacles must be one of all, seen, off"):
        SensorOptions(obstacles="hidden")
