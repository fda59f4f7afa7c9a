"""The depth-camera workflow in the viewer, without a browser: ``pregrasp view`` takes the sensor
flags of ``pregrasp plan``, the demo depth image opens as the mug on its table, the scale field
(units, the one-click fix of the loader's unit hint, bounds), picking an object by a click, and
the assumed points and the contacts on them in their own colours.

The scene of the pick tests is rendered by ray casting (``pregrasp_core.sensor.synthetic``) from
two trimesh boxes on the table z = 0, so which points belong to which box is known outside the
app; the assumed points are checked against the depth image's own points.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree
from viser._gui_handles import GuiEvent
from viser._scene_handles import SceneClickEvent

from app.cli import build_parser, main
from app.commands import plan
from app.controller import is_camera_file
from app.gui import LEGEND, grasp_table
from app.scene import ASSUMED_CONTACT_RGB, CONTACT_RGB, NAMES
from app.scene_data import (
    ASSUMED_RGB,
    FLYING_RGB,
    OTHER_RGB,
    TABLE_RGB,
    assumed_contacts,
    neighbour_hidden_points,
    ranked_grasps,
    ray_pick,
    unit_fix,
)
from pregrasp_core.errors import InputError
from pregrasp_core.io import PointCloud, SensorOptions, load_point_cloud
from pregrasp_core.paths import OBJECTS_DIR
from pregrasp_core.sensor import Intrinsics, load_camera_pose, load_depth_image
from pregrasp_core.sensor.synthetic import add_mixed_pixels, orbit_camera, render_view
from tests.core.test_depth_input import two_boxes, write_scene_pcd

DEMO = OBJECTS_DIR / "mug_depth.png"


def _demo_world_points() -> np.ndarray:
    """The demo depth image's points in its world frame (the JSON's camera pose), read by the
    sensor package directly (not through the loader)."""
    depth = load_depth_image(DEMO, DEMO.with_suffix(".json"))
    T = load_camera_pose(DEMO.with_suffix(".json"))
    assert T is not None
    return depth.points @ T[:3, :3].T + T[:3, 3]


def _wait_idle(controller, timeout: float = 120.0) -> None:
    deadline = time.monotonic() + timeout
    while not controller.idle():
        assert time.monotonic() < deadline, "the app did not finish its work"
        time.sleep(0.05)


# ---------------------------------------------------------------------- command line
def test_view_takes_the_sensor_flags_of_plan(monkeypatch, tmp_path: Path) -> None:
    """`pregrasp view` builds the loader's SensorOptions from the same flags as `pregrasp plan`
    (one definition) and hands them to the viewer (the server is not started)."""
    import app.server

    seen: list[app.server.ViewerConfig] = []
    monkeypatch.setattr(app.server, "serve", seen.append)
    flags = ["--intrinsics", "420", "421", "239.5", "179.5", "--pick", "0", "0.15", "0.02",
             "--no-scene", "--viewpoint", "0.4", "-0.3", "0.5", "--scale", "0.5",
             "--scene-obstacles", "off"]  # fmt: skip
    assert main(["view", str(DEMO), "--port", "0", *flags]) == 0
    (config,) = seen
    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    planned = plan.plan_run(sub.choices["plan"].parse_args([str(DEMO), *flags])).input.sensor()
    assert config.sensor == planned
    assert config.sensor == SensorOptions(
        intrinsics=(420.0, 421.0, 239.5, 179.5),
        viewpoint=(0.4, -0.3, 0.5),
        scene=False,
        pick=(0.0, 0.15, 0.02),
        obstacles="off",
    )
    assert config.scale == 0.5 and config.input == DEMO


def test_view_plans_with_the_occluded_space_occupied(monkeypatch) -> None:
    """`pregrasp view --occluded occupied` hands the setting to the viewer (the same option as
    `pregrasp plan`), and the app plans the depth demo with it: the grasps are those of
    ``run_pipeline`` with that setting, their contacts on the cloud's own points."""
    import viser

    import app.server
    from app.server import ViewerConfig, run
    from pregrasp_core.pipeline import PipelineParams, run_pipeline

    seen: list[app.server.ViewerConfig] = []
    monkeypatch.setattr(app.server, "serve", seen.append)
    assert main(["view", str(DEMO), "--port", "0", "--occluded", "occupied"]) == 0
    (config,) = seen
    assert config.params.occluded == "occupied"
    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    viewer = run(ViewerConfig(input=DEMO, params=config.params, plan_on_start=True), server)
    try:
        _wait_idle(viewer.controller)
        s = viewer.controller.state
        assert s.error == "" and s.planned
        res = s.result
        assert res.params.occluded == "occupied"
        ref = run_pipeline(res.cloud, PipelineParams(occluded="occupied"), until="grasps")
        assert ref.grasps is not None and res.grasps is not None
        assert [g.pregrasp for g in res.grasps.ranked] == [g.pregrasp for g in ref.grasps.ranked]
        n = len(res.cloud.points)
        assert all(c.point_index < n for g in res.grasps.ranked for c in g.contacts)
    finally:
        viewer.close()
        server.stop()


def test_view_bad_sensor_flag_is_a_clean_error(capsys) -> None:
    assert main(["view", str(DEMO), "--intrinsics", "420", "420", "239.5"]) != 0
    assert "--intrinsics: give four numbers" in capsys.readouterr().err
    assert main(["view", str(DEMO), "--scale", "1e9"]) != 0
    assert "--scale: must be a positive factor in [1e-06, 1e+06]" in capsys.readouterr().err


# ---------------------------------------------------------------------- the depth demo
@pytest.fixture(scope="module")
def demo_app():
    """The app as `pregrasp view assets/objects/mug_depth.png` starts it (planned on start)."""
    import viser

    from app.server import ViewerConfig, run

    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    app = run(ViewerConfig(input=DEMO, plan_on_start=True), server)
    try:
        _wait_idle(app.controller)
        yield app
    finally:
        app.close()
        server.stop()


def test_depth_demo_opens_as_the_mug_without_its_table(demo_app) -> None:
    s = demo_app.controller.state
    assert s.error == "" and s.planned and s.view.selected_grasp == 0
    world = _demo_world_points()
    cloud = s.cloud
    # the table (z = 0 in the demo's world frame) is gone: every point of the object lies on
    # or above it, and the object is the mug_handle mesh's size (0.111 x 0.080 x 0.100 m)
    assert cloud.points[:, 2].min() > -0.003
    assert 0.095 < np.ptp(cloud.points[:, 2]) < 0.105
    assert np.ptp(cloud.points[:, :2], axis=0).max() < 0.13
    n_table = int(np.count_nonzero(np.abs(world[:, 2]) < 0.003))
    assert n_table > 0.9 * len(world)  # the frame is mostly table ...
    assert cloud.info["scene"]["n_table"] > 0.95 * n_table  # ... and the loader found it
    # the scene behind the object: the table in grey
    h = demo_app.server.scene.get_handle_by_name(NAMES["scene"])
    assert h is not None and demo_app.scene.n_scene_points_shown == len(h.points)
    cols = np.asarray(h.colors)
    on_table = np.abs(np.asarray(h.points, dtype=np.float64)[:, 2]) < 0.003
    assert np.mean(np.all(cols[on_table] == TABLE_RGB, axis=1)) > 0.99
    assert not np.any(np.all(cols == ASSUMED_RGB, axis=1))
    assert "mug_depth.png" in s.message or "planned" in s.message
    # planned with --occluded auto (the default): the demo's occupied plan has a force-closure
    # grasp, so the hidden space it kept the hand out of is the one drawn
    assert s.params.occluded == "auto" and s.result.occupied is not None
    assert s.result.occluded_used == "occupied" and s.result.fallback is None
    h = demo_app.server.scene.get_handle_by_name(NAMES["hidden"])
    assert h is not None and demo_app.scene.n_hidden_points_shown == len(h.points) > 0
    assert not demo_app.gui.show_hidden.disabled


def test_assumed_points_and_their_contacts_have_their_own_colours(demo_app) -> None:
    s = demo_app.controller.state
    cloud = s.cloud
    assumed = np.asarray(cloud.assumed)
    assert 0 < assumed.sum() < len(assumed)
    # the loader's contract: the object's points are the visible ones, then the assumed ones;
    # the visible ones are the depth image's (smoothed by at most 2 mm), its counts in info
    n_visible = cloud.info["scene"]["n_visible"]
    assert n_visible + cloud.info["scene"]["n_assumed"] == len(assumed)
    assert not assumed[:n_visible].any() and assumed[n_visible:].all()
    tree = cKDTree(_demo_world_points())
    d, _ = tree.query(cloud.points[:n_visible])
    assert d.max() < 0.002
    cols = np.asarray(demo_app.server.scene.get_handle_by_name(NAMES["cloud"]).colors)
    assert np.all(cols[assumed] == ASSUMED_RGB)
    assert not np.any(np.all(cols[~assumed] == ASSUMED_RGB, axis=1))
    # the shown grasp's contacts: orange where they touch an assumed point, as the planner
    # flags them itself (Contact.assumed)
    g = ranked_grasps(s.result)[s.view.selected_grasp]
    unseen = np.array([bool(c.assumed) for c in g.contacts])
    np.testing.assert_array_equal(assumed_contacts(g, cloud), unseen)
    assert unseen.any()  # the demo's best grasp wraps the mug: a finger on its back
    contacts = demo_app.server.scene.get_handle_by_name(NAMES["contacts"])
    ccols = np.asarray(contacts.colors)
    np.testing.assert_array_equal(ccols[unseen], np.tile(ASSUMED_CONTACT_RGB, (unseen.sum(), 1)))
    np.testing.assert_array_equal(ccols[~unseen], np.tile(CONTACT_RGB, ((~unseen).sum(), 1)))
    assert demo_app.scene.n_assumed_contacts_shown == int(unseen.sum())
    assert f"({int(unseen.sum())} assumed)" in grasp_table(s)
    colours = " ".join(a for a, _ in LEGEND)
    assert "dark slate points" in colours and "orange dots" in colours
    assert "light grey points" in colours and "brown points" in colours
    # the assumed colour is darker than every part's colour (so it reads as its own)
    from app.scene_data import node_colors

    assert node_colors(np.arange(500)).max(axis=1).min() > 2 * max(ASSUMED_RGB)


# ---------------------------------------------------------------------- picking
@pytest.fixture(scope="module")
def boxes_scene(tmp_path_factory) -> tuple[Path, np.ndarray, np.ndarray, np.ndarray]:
    """A PCD scene (VIEWPOINT = the camera) of two boxes on a table: (path, camera position,
    big box centre, small box centre)."""
    mesh, big_c, small_c = two_boxes()
    T = orbit_camera(np.array([0.0, 0.07, 0.05]), 0.7, np.radians(20.0), np.radians(40.0))
    view = render_view(mesh.vertices, mesh.faces, T, Intrinsics(300, 300, 159.5, 119.5), 320,
                       240, table_half=0.4)  # fmt: skip
    pts, _ = view.points_world()
    path = tmp_path_factory.mktemp("scene") / "two_boxes.pcd"
    write_scene_pcd(path, pts, T)
    return path, T[:3, 3].copy(), big_c, small_c


def _click(cam: np.ndarray, target: np.ndarray) -> SceneClickEvent:
    d = target - cam
    return SceneClickEvent(
        client=None,  # type: ignore[arg-type]
        client_id=0,
        ray_origin=tuple(cam),
        ray_direction=tuple(d / np.linalg.norm(d)),
        screen_pos=(0.5, 0.5),
        modifier=None,
    )


def test_a_click_picks_the_cluster_under_it_and_replans(make_app, boxes_scene) -> None:
    path, cam, big_c, small_c = boxes_scene
    app = make_app(input=path, n_points=3000)
    c, gui = app.controller, app.gui
    s0 = c.state
    assert s0.error == "" and s0.cloud.sensor is not None
    assert s0.cloud.points[:, 1].max() < 0.06  # the largest cluster: the big box
    assert not gui.pick_mode.disabled
    # the small box seen from the camera: brown behind the object (another object of the scene)
    cols = np.asarray(app.server.scene.get_handle_by_name(NAMES["scene"]).colors)
    pts = np.asarray(app.server.scene.get_handle_by_name(NAMES["scene"]).points)
    on_small = np.all(np.abs(pts - small_c) <= [0.021, 0.021, 0.026], axis=1)
    on_small &= pts[:, 2] > 0.005  # above the table's band (its foot lies in the band)
    assert on_small.sum() > 50 and np.all(cols[on_small] == OTHER_RGB)
    top = small_c + [0, 0, 0.025]  # the top face of the small box, which the camera sees
    gui._scene_click(_click(cam, top))  # pick mode off: a click only looks
    assert c.state.result is s0.result
    gui.pick_mode.value = True
    gui._scene_click(_click(cam, top))
    s = c.state
    assert s.error == "" and s.planned and s.result is not s0.result
    lo, hi = s.cloud.points.min(axis=0), s.cloud.points.max(axis=0)
    assert lo[1] > 0.12 and hi[2] < 0.06  # the small box (and its completion)
    assert np.allclose(s.source.sensor.pick, top, atol=0.01)
    assert "kept the cluster nearest" in s.message and "cluster 2 of" in s.message
    assert "planned" in s.message
    # the big box again, by a click on its front
    c.pick_ray(cam, (big_c + [0, 0, 0.06]) - cam)
    assert c.state.cloud.points[:, 1].max() < 0.06 and "cluster 1 of" in c.state.message


def test_a_click_beside_every_object_changes_nothing(make_app, boxes_scene) -> None:
    path, cam, _, _ = boxes_scene
    app = make_app(input=path, n_points=3000)
    c = app.controller
    s0 = c.state
    away = np.array([0.0, 0.07, 0.6]) - cam  # up into the empty air above the table
    with pytest.raises(InputError, match="no object of the scene under the click"):
        c.pick_ray(cam, away)
    with pytest.raises(InputError, match="no object"):  # the bare table is not an object
        c.pick_ray(cam, np.array([0.3, -0.3, 0.0]) - cam)
    assert c.state.result is s0.result


def test_picking_needs_a_scene(app) -> None:
    assert app.gui.pick_mode.disabled  # the default mug is a complete cloud
    with pytest.raises(InputError, match="picking needs a depth-camera scene"):
        app.controller.pick_ray((0.3, 0.3, 0.3), (-1, -1, -1))


def test_ray_pick_takes_the_nearest_point_along_the_ray() -> None:
    pts = np.array([[0, 0, 1.0], [0, 0, 2.0], [0.0, 0.5, 1.0], [0, 0, -1.0]])
    assert ray_pick(pts, (0, 0, 0), (0, 0, 5)) == 0  # front-most of the two on the ray
    assert ray_pick(pts, (0, 0, 0), (0, 0, 1), candidates=np.array([0, 1, 1, 1], bool)) == 1
    assert ray_pick(pts, (0, 0, 0), (0, 1, 2)) == 2  # 0.46 rad off the axis: only point 2
    assert ray_pick(pts, (0, 0, 0), (1, 0, 0)) is None
    assert ray_pick(pts, (0, 0, 0), (0, 0, 0)) is None
    assert ray_pick(pts, (0, 0, 0), (np.nan,) * 3) is None
    assert ray_pick(pts, (0, 0, 0), (0, 0, -1)) == 3  # behind the camera is never hit
    # the front surface (within 2 cm of the nearest hit): the point seen closest to the ray,
    # never one of an object behind it even when that one lies exactly on the ray
    front = np.array([[0.012, 0, 1.0], [0.004, 0, 1.015], [0, 0, 1.5]])
    assert ray_pick(front, (0, 0, 0), (0, 0, 1)) == 1


# ---------------------------------------------------------------------- scale
@pytest.fixture(scope="module")
def bottle_mm(tmp_path_factory) -> tuple[Path, PointCloud]:
    ref = load_point_cloud(OBJECTS_DIR / "bottle.obj", n_points=3000)
    path = tmp_path_factory.mktemp("mm") / "bottle_mm.xyz"
    np.savetxt(path, np.asarray(ref.points) * 1000.0, fmt="%.6f")
    return path, ref


def test_scale_field_units_and_the_one_click_fix(make_app, bottle_mm) -> None:
    path, ref = bottle_mm
    app = make_app(input=path, n_points=3000)
    c, gui = app.controller, app.gui
    s = c.state
    # the loader recognised millimetres: the fix reads the file as metres instead
    np.testing.assert_allclose(s.cloud.extents, ref.extents, atol=1e-6)
    assert (gui.units.value, gui.scale.value) == ("auto", 0.001)
    assert gui.units_fix.visible and gui.units_fix.label == "read as metres (scale 1)"
    for cb in gui.units_fix._impl.update_cb:  # what a click on the button runs
        cb(GuiEvent(client=None, client_id=None, target=gui.units_fix))
    s = c.state
    assert s.source.scale == 1.0 and s.error == ""
    np.testing.assert_allclose(s.cloud.extents, 1000 * ref.extents, rtol=1e-6)
    assert (gui.units.value, gui.scale.value, gui.units_fix.visible) == ("m", 1.0, False)
    gui.units.value = "cm"
    np.testing.assert_allclose(c.state.cloud.extents, 10 * ref.extents, rtol=1e-6)
    assert (gui.units.value, gui.scale.value) == ("cm", 0.01)
    gui.scale.value = 0.0005  # a factor of one's own
    np.testing.assert_allclose(c.state.cloud.extents, 0.5 * ref.extents, rtol=1e-6)
    assert gui.units.value == "custom"
    gui.units.value = "auto"  # the loader's rule again
    np.testing.assert_allclose(c.state.cloud.extents, ref.extents, atol=1e-6)
    assert c.state.source.scale is None


def test_scale_is_bounded_and_a_bad_value_keeps_the_object(make_app, bottle_mm) -> None:
    path, _ = bottle_mm
    app = make_app(input=path, n_points=3000)
    c = app.controller
    s0 = c.state
    with pytest.raises(ValueError, match=r"scale must be a positive factor in \[1e-06, 1e\+06\]"):
        c.set_scale(1e7)
    with pytest.raises(ValueError, match="scale must be"):
        c.set_scale(0.0)
    with pytest.raises(ValueError, match="scale must be a number or one of"):
        c.set_scale("furlong")
    c.act(None, c.set_scale, float("nan"))  # through the GUI's path: a notification
    assert "scale must be" in c.state.error and c.state.result is s0.result


def test_the_unit_fix_of_a_long_metre_cloud_reads_millimetres() -> None:
    """A 6-unit cloud sampled too densely for the millimetre rule keeps metres with the loader's
    hint (longer than MILLIMETRE_EXTENT): the fix offers millimetres."""
    rng = np.random.default_rng(0)
    pts = rng.random((20000, 3)) * [6.0, 0.5, 0.5]
    cloud = load_point_cloud_array(pts)
    assert any("looks like millimetres" in w for w in cloud.info["warnings"])
    assert unit_fix(cloud, None) == (0.001, "read as millimetres (scale 0.001)")
    assert unit_fix(cloud, 1.0) is None  # a scale given by the user is not second-guessed
    small = load_point_cloud_array(pts * 0.01)
    assert unit_fix(small, None) is None


def load_point_cloud_array(pts: np.ndarray) -> PointCloud:
    import io as _io

    from pregrasp_core.io import load_point_cloud_bytes

    buf = _io.BytesIO()
    np.save(buf, pts)
    return load_point_cloud_bytes(buf.getvalue(), "cloud.npy", n_points=None)


# ---------------------------------------------------------------------- the demo chooser
def _true_mug() -> cKDTree:
    """The true surface of the demo's object (``mug_handle.obj`` stands in the demo's world frame
    as ``scripts/make_views.py --demo`` rendered it): 300,000 samples, about 0.4 mm apart, so a
    distance to them is at most about 0.3 mm more than to the surface."""
    import trimesh

    mesh = trimesh.load(OBJECTS_DIR / "mug_handle.obj", force="mesh")
    samples, _ = trimesh.sample.sample_surface(mesh, 300_000, seed=0)
    return cKDTree(samples)


def _shown(markdown) -> str:
    """A markdown widget's text without its escapes."""
    return str(markdown.content).replace("\\", "")


def _press(button) -> None:
    """What a browser's click on ``button`` runs."""
    for cb in button._impl.update_cb:
        cb(GuiEvent(client=None, client_id=None, target=button))


def test_the_depth_demo_in_the_chooser_loads_the_mug_and_plans(app) -> None:
    c, gui = app.controller, app.gui
    assert "mug_depth" in gui.demo.options and c.state.source.name == "mug_handle"
    gui.demo.value = "mug_depth"
    s = c.state
    assert s.error == "" and s.source.name == "mug_depth" and gui.demo.value == "mug_depth"
    assert s.planned and s.view.selected_grasp == 0 and len(ranked_grasps(s.result)) > 0
    dep = s.cloud.info["depth"]
    assert dep["camera_file"] == str(DEMO.with_suffix(".json")) and dep["pose"]
    shown = "fx 420 fy 420 cx 239.5 cy 179.5 from mug_depth.json; camera pose"
    assert shown in _shown(gui.camera_info)
    # the object kept is the mug: its seen points lie on the true mesh ...
    truth = _true_mug()
    cloud = s.cloud
    d, _ = truth.query(cloud.points[~cloud.assumed], distance_upper_bound=0.01)
    assert np.mean(d < 0.003) >= 0.99
    # ... and the segmentation's object holds the depth image's mug points (those within 2 mm
    # of the true mesh, above the table's band), nearly nothing else
    seg = cloud.sensor.segmentation
    d_scene, _ = truth.query(seg.points, distance_upper_bound=0.01)  # inf beyond 1 cm
    on_mug = (d_scene < 0.002) & (seg.points[:, 2] > 0.005)
    assert on_mug.sum() > 3000 and np.mean(seg.object_mask[on_mug]) >= 0.99
    assert np.mean(d_scene[seg.object_mask] < 0.003) >= 0.99
    # the same object as `pregrasp view assets/objects/mug_depth.png` (the loader on the file)
    ref = load_point_cloud(DEMO, n_points=s.n_points)
    np.testing.assert_array_equal(cloud.points, ref.points)


# ---------------------------------------------------------------------- depth image uploads
def _cli_cloud(path: Path, *flags: str) -> PointCloud:
    """The cloud `pregrasp plan PATH FLAGS` plans on (its own parser builds the loader's
    options), at the app tests' point count."""
    from tests.app.conftest import APP_POINTS

    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    inp = plan.plan_run(sub.choices["plan"].parse_args([str(path), *flags])).input
    return load_point_cloud(path, n_points=APP_POINTS, seed=inp.seed, sensor=inp.sensor())


def test_an_uploaded_png_waits_for_its_intrinsics_then_matches_the_cli(app, tmp_path) -> None:
    c, gui = app.controller, app.gui
    s0 = c.state
    c.load_upload("frame.png", DEMO.read_bytes())
    s = c.state
    assert s.result is s0.result and s.waiting is not None  # the mug stays meanwhile
    assert "needs its camera's intrinsics" in s.message and "'use intrinsics'" in s.message
    assert "frame.json" in s.message and "frame.png waits" in _shown(gui.camera_info)
    gui.intrinsics.value = "420 420 239.5"  # three numbers: refused, nothing changes
    _press(gui.use_intrinsics)
    assert "give four numbers fx fy cx cy" in c.state.error and c.state.waiting is not None
    gui.intrinsics.value = "420, 420, 239.5, 179.5"
    _press(gui.use_intrinsics)
    s = c.state
    assert s.error == "" and s.waiting is None and s.source.name == "frame.png"
    assert s.cloud.info["depth"]["intrinsics_from"] == "--intrinsics"
    alone = tmp_path / "frame.png"  # the same image on disk, no sidecar beside it
    alone.write_bytes(DEMO.read_bytes())
    ref = _cli_cloud(alone, "--intrinsics", "420", "420", "239.5", "179.5")
    np.testing.assert_array_equal(s.cloud.points, ref.points)
    np.testing.assert_array_equal(s.cloud.assumed, ref.assumed)
    # its camera file uploaded next: read again with the pose, as the CLI reads the sidecar
    c.load_upload("frame.json", DEMO.with_suffix(".json").read_bytes())
    s = c.state
    assert s.error == "" and s.cloud.info["depth"]["pose"]
    (tmp_path / "frame.json").write_bytes(DEMO.with_suffix(".json").read_bytes())
    np.testing.assert_array_equal(s.cloud.points, _cli_cloud(alone).points)
    # the numbers typed over an uploaded camera file keep its pose (as --intrinsics over a
    # sidecar does)
    gui.intrinsics.value = "430 430 239.5 179.5"
    _press(gui.use_intrinsics)
    flags = ("--intrinsics", "430", "430", "239.5", "179.5")
    np.testing.assert_array_equal(c.state.cloud.points, _cli_cloud(alone, *flags).points)


def test_a_camera_file_uploaded_first_is_used_by_the_next_depth_upload(app) -> None:
    c = app.controller
    c.load_upload("cam.json", DEMO.with_suffix(".json").read_bytes())
    s = c.state
    assert s.source.name == "mug_handle" and s.camera is not None  # nothing to read yet
    assert "kept: the next depth image uploaded uses them" in s.message
    assert "next depth upload: fx 420" in _shown(app.gui.camera_info)
    c.load_upload("frame.png", DEMO.read_bytes())
    s = c.state
    assert (
        s.error == "" and s.waiting is None and s.cloud.info["depth"]["camera_file"] == "cam.json"
    )
    np.testing.assert_array_equal(s.cloud.points, load_point_cloud(DEMO, n_points=3000).points)
    # an NPY point cloud uploaded meanwhile is still a cloud (N x 3), not a depth map
    import io as _io

    buf = _io.BytesIO()
    np.save(buf, np.asarray(load_point_cloud(OBJECTS_DIR / "bottle.obj", n_points=2000).points))
    c.load_upload("bottle.npy", buf.getvalue())
    assert c.state.error == "" and c.state.cloud.info["kind"] == "cloud"
    # an empty field forgets the camera: the next depth image waits for its own
    app.gui.intrinsics.value = ""
    _press(app.gui.use_intrinsics)
    assert c.state.camera is None and "forgotten" in c.state.message
    c.load_upload("again.png", DEMO.read_bytes())
    assert c.state.waiting is not None and c.state.source.name == "bottle.npy"
    # a result file is still a result file, a camera file a camera file
    assert not is_camera_file(b'{"schema": "pregrasp/1", "fx": 1}')
    assert is_camera_file(b'{"fy": 1}') and not is_camera_file(b"[1, 2]")


def test_a_ros_camera_info_uploaded_is_a_camera_file(app) -> None:
    """A ROS CameraInfo (as JSON) uploaded before its depth image is kept as the camera file
    and gives the cloud of pregrasp's own camera file (``sensor/camera_layouts.py``)."""
    import json

    doc = json.loads(DEMO.with_suffix(".json").read_text())
    fx, fy, cx, cy = (doc[k] for k in ("fx", "fy", "cx", "cy"))
    info = {"header": {"frame_id": "depth"}, "height": doc["height"], "width": doc["width"],
            "distortion_model": "plumb_bob", "D": [0.0] * 5,
            "K": [fx, 0.0, cx, 0.0, fy, cy, 0.0, 0.0, 1.0],
            "T_world_camera": doc["T_world_camera"]}  # fmt: skip
    data = json.dumps(info).encode()
    assert is_camera_file(data)
    c = app.controller
    c.load_upload("camera_info.json", data)
    assert c.state.camera is not None and c.state.camera.layout == "ROS CameraInfo"
    c.load_upload("frame.png", DEMO.read_bytes())
    s = c.state
    assert s.error == "" and s.cloud.info["depth"]["camera_layout"] == "ROS CameraInfo"
    np.testing.assert_array_equal(s.cloud.points, load_point_cloud(DEMO, n_points=3000).points)


def test_a_bad_uploaded_camera_file_names_the_file_and_the_field(app) -> None:
    c = app.controller
    c.load_upload("frame.png", DEMO.read_bytes())
    s0 = c.state
    bad = b'{"fx": 420, "fy": 420, "cx": 239.5, "cy": 179.5, "depth_scale": 1000}'
    c.act(None, c.load_upload, "frame.json", bad)
    s = c.state
    assert s.error.startswith("frame.json: depth_scale is metres per stored depth unit")
    assert s.result is s0.result and s.waiting is not None  # the image still waits
    c.act(None, c.load_upload, "frame.json", b'{"fx": 420, "fy": -1, "cx": 0, "cy": 0}')
    assert (
        "frame.json: fx and fy must be positive focal lengths in pixels, got fy=-1" in c.state.error
    )


def _toggle(handle, value: bool) -> None:
    """Set a checkbox as a browser does: its value, then its update callbacks."""
    handle.value = value
    for cb in handle._impl.update_cb:
        cb(GuiEvent(client=None, client_id=None, target=handle))


@pytest.fixture(scope="module")
def veiled_boxes(tmp_path_factory) -> Path:
    """The two boxes' scene with every pixel at a depth jump of more than 2 cm mixed
    (``add_mixed_pixels``, the time-of-flight model): a PCD with VIEWPOINT = the camera."""
    mesh, _, _ = two_boxes()
    T = orbit_camera(np.array([0.0, 0.07, 0.05]), 0.7, np.radians(20.0), np.radians(40.0))
    view = render_view(mesh.vertices, mesh.faces, T, Intrinsics(300, 300, 159.5, 119.5), 320,
                       240, table_half=0.4)  # fmt: skip
    view = add_mixed_pixels(view, 1.0, 0.02, np.random.default_rng(0))
    pts, _ = view.points_world()
    path = tmp_path_factory.mktemp("veiled") / "two_boxes_veiled.pcd"
    write_scene_pcd(path, pts, T)
    return path


def test_the_flying_pixels_box_reads_the_scene_again(make_app, veiled_boxes) -> None:
    """The object panel's "drop flying pixels" reads the scene again with the flying-pixel test
    (the scene section then counts what it dropped, as `pregrasp plan --flying-pixels` does, and
    the dropped points are drawn in magenta) and without it; the box is off for a complete
    cloud, where there is nothing to drop."""
    path = veiled_boxes
    app = make_app(input=path, n_points=3000)
    c, gui = app.controller, app.gui
    assert not gui.flying.disabled and gui.flying.value is False
    assert "n_flying" not in c.state.cloud.info["scene"]
    _toggle(gui.flying, True)
    _wait_idle(c)
    s = c.state
    assert s.error == "" and s.source.sensor.flying_pixels
    expected = load_point_cloud(path, n_points=3000, sensor=SensorOptions(flying_pixels=True))
    assert s.cloud.info["scene"]["n_flying"] == expected.info["scene"]["n_flying"]
    assert np.array_equal(s.cloud.points, expected.points)
    handle = app.server.scene.get_handle_by_name(NAMES["scene"])
    magenta = np.all(np.asarray(handle.colors) == FLYING_RGB, axis=1)
    n_flying = s.cloud.info["scene"]["n_flying"]
    assert n_flying > 100 and np.count_nonzero(magenta) == n_flying  # (under the layer's cap)
    drawn = np.asarray(handle.points, dtype=np.float64)[magenta]
    np.testing.assert_allclose(drawn, s.cloud.sensor.flying, atol=1e-6)
    _toggle(gui.flying, False)
    _wait_idle(c)
    assert "n_flying" not in c.state.cloud.info["scene"] and gui.flying.value is False
    handle = app.server.scene.get_handle_by_name(NAMES["scene"])
    assert not np.all(np.asarray(handle.colors) == FLYING_RGB, axis=1).any()


def test_the_scene_obstacles_dropdown_reads_the_scene_again(make_app, boxes_scene) -> None:
    """The object panel's "scene obstacles" reads the scene again as ``--scene-obstacles``
    does: ``all`` (the other box and the space hidden behind it), ``seen`` (its seen points
    only: the hidden-space layer has nothing of the other box to draw), ``off`` (nothing, said
    in the pool panel); the object's cloud is the same in every setting."""
    path = boxes_scene[0]
    app = make_app(input=path, n_points=3000)
    c, gui = app.controller, app.gui
    s0 = c.state
    assert not gui.obstacles.disabled and gui.obstacles.value == "all"
    assert s0.cloud.info["scene"]["n_obstacles_hidden"] > 0 and not gui.show_hidden.disabled
    for which in ("seen", "off", "all"):
        _toggle(gui.obstacles, which)
        _wait_idle(c)
        s = c.state
        assert s.error == "" and s.source.sensor.obstacles == which
        expected = load_point_cloud(path, n_points=3000, sensor=SensorOptions(obstacles=which))
        np.testing.assert_array_equal(s.cloud.points, s0.cloud.points)
        if expected.obstacles is None:
            assert which == "off" and s.cloud.obstacles is None
        else:
            np.testing.assert_array_equal(s.cloud.obstacles, expected.obstacles)
        assert (len(neighbour_hidden_points(s.cloud)) > 0) == (which == "all")
        assert ("scene obstacles: off" in gui.pool_info.content) == (which == "off")
    np.testing.assert_array_equal(c.state.cloud.obstacles, s0.cloud.obstacles)


def test_flying_pixels_need_a_scene(app) -> None:
    assert app.gui.flying.disabled  # the default mug is a complete cloud
    with pytest.raises(InputError, match="flying pixels are dropped from a depth-camera scene"):
        app.controller.set_flying_pixels(True)
    assert app.gui.obstacles.disabled
    with pytest.raises(InputError, match="scene obstacles are the rest of a scene"):
        app.controller.set_scene_obstacles("seen")
    with pytest.raises(ValueError, match="expected one of all, seen, off"):
        app.controller.set_scene_obstacles("most")


def test_a_depth_image_in_its_camera_frame_is_shown_on_its_table(make_app, tmp_path) -> None:
    """The demo's depth image without its pose (the points in the camera frame, where the
    table is no horizontal plane): the view's up is the normal of the table the scene found
    (it points at the camera's side, about 55 degrees from the camera's -y here), and the table
    grid lies in that plane."""
    from scipy.spatial.transform import Rotation

    from pregrasp_core.io import SensorOptions

    png = tmp_path / "frame.png"
    png.write_bytes(DEMO.read_bytes())  # no frame.json beside it: intrinsics as numbers
    sensor = SensorOptions(intrinsics=(420.0, 420.0, 239.5, 179.5))
    app = make_app(input=png, n_points=3000, sensor=sensor)
    s = app.controller.state
    support = s.result.masks.support
    assert s.cloud.info["depth"]["pose"] is False
    assert float(support.normal @ [0.0, -1.0, 0.0]) > 0.5  # not +z: the camera frame's table
    np.testing.assert_allclose(app.scene._up, support.normal, atol=1e-12)
    grid = app.server.scene.get_handle_by_name("/table")
    normal = Rotation.from_quat(grid.wxyz, scalar_first=True).apply([0.0, 0.0, 1.0])
    np.testing.assert_allclose(normal, support.normal, atol=1e-9)
    assert float(np.asarray(grid.position) @ support.normal) == pytest.approx(support.height)
