"""The viewer's "simulate lift" button without a browser: the MuJoCo lift of the chosen grasp
runs on a worker thread, its frames pose the cloud and the URDF hand in the scene, the outcome
reaches the panel and the grasp table.

Reference: ``pregrasp plan --simulate`` (the CLI's lift test through ``simulate_grasps``) on
the same object, points and seed: the app's playback must give the same outcome for the same
grasp, and its frames must carry the object up 10 cm with the hand."""

from __future__ import annotations

import json
import time

import numpy as np
import pytest

from app.cli import main
from app.scene import NAMES
from app.scene_data import ranked_grasps
from app.simulate_view import rank_of
from pregrasp_core.paths import DEFAULT_OBJECT

APP_POINTS = 3000  # the app fixture's points (tests/app/conftest.py)

K = 3
"""Grasps the CLI simulates (the planner's best K)."""


def _wait_rendered(app, pred, timeout: float = 60.0):
    deadline = time.monotonic() + timeout
    while True:
        s = app.controller.state
        if pred(s) and app.scene.rendered is s:
            return s
        assert time.monotonic() < deadline, "the app does not reach the expected state"
        time.sleep(0.05)


@pytest.fixture(scope="module")
def cli_doc(tmp_path_factory):
    out = tmp_path_factory.mktemp("lift") / "mug.json"
    argv = ["plan", str(DEFAULT_OBJECT), "--points", str(APP_POINTS), "--simulate", str(K)]
    assert main([*argv, "-o", str(out)]) == 0
    return json.loads(out.read_text())


def test_simulate_needs_a_planned_grasp(app):
    c = app.controller
    assert app.gui.simulate.disabled  # nothing planned yet
    assert c.act(None, c.simulate, None) is None
    assert "plan the grasps first" in c.state.error
    assert not c.lift.running and c.state.lift is None
    assert "Plan the grasps" in app.gui.lift_info.content


def test_simulate_plays_the_lift_the_cli_reports(app, cli_doc):
    c = app.controller
    items = cli_doc["grasps"]["items"]
    lifted = [g for g in items if g["simulation"] is not None and g["simulation"]["success"]]
    assert lifted, "the CLI's best grasps of the mug should include one that lifts"
    ref = lifted[0]
    c.plan()
    s = c.state
    assert len(s.cloud.points) == APP_POINTS
    k = rank_of(s, ref["pregrasp"])
    assert k is not None, "the app plans the same grasps as the CLI"
    g = ranked_grasps(s.result)[k]
    np.testing.assert_allclose(g.T_world_hand, ref["T_world_hand"], atol=1e-9)
    c.select_grasp(k)
    assert not app.gui.simulate.disabled

    c.simulate()
    # the lift runs on its worker thread, outside the lock: the app keeps serving meanwhile
    c.set_face_masks_visible(False)
    assert c.lift.running, "the view action should return while the lift is simulated"
    assert app.gui.simulate.disabled and "Simulating the lift of grasp" in app.gui.lift_info.content
    assert c.lift.wait(120)
    s = _wait_rendered(app, lambda s: s.lift is not None and s.lift.running is None)
    assert s.error == ""
    pb = s.lift.playback
    sim = ref["simulation"]
    assert pb.pregrasp == ref["pregrasp"] and pb.outcome.outcome == sim["outcome"] == "lifted"
    for key in ("rise", "slip", "push", "initial_penetration"):  # the same run as the CLI's
        assert getattr(pb.outcome, key) == pytest.approx(sim[key], abs=1e-9), key

    # the frames: the cloud carried up 10 cm with the hand, not moving in it
    pts = np.asarray(s.cloud.points)
    centre = pts.mean(axis=0)

    def at(T, p):
        return T[:3, :3] @ p + T[:3, 3]

    lift0 = pb.frame_index(pb.duration - sum(sim["phase_times"][p] for p in ("lift", "hold")))
    hand_rise = pb.T_world_hand[-1][2, 3] - pb.T_world_hand[lift0][2, 3]
    obj_rise = at(pb.T_world_object[-1], centre)[2] - at(pb.T_world_object[lift0], centre)[2]
    assert hand_rise == pytest.approx(0.10, abs=2e-3)
    assert obj_rise == pytest.approx(0.10, abs=0.02)
    np.testing.assert_allclose(at(pb.T_world_object[0], centre), centre, atol=5e-3)  # at rest

    def in_hand(i):
        return np.linalg.solve(pb.T_world_hand[i], np.r_[at(pb.T_world_object[i], centre), 1.0])

    assert np.linalg.norm(in_hand(-1) - in_hand(lift0)) < 0.02
    assert pb.q.shape == (len(pb.times), c.hand.n_joints)
    assert np.all(np.diff(pb.times) > 0) and pb.duration == pytest.approx(sim["sim_time"], abs=0.1)

    # it plays by itself (the animator) and stops on the last frame, drawn in the scene
    s = _wait_rendered(app, lambda s: not s.view.playing and s.view.lift_t >= pb.duration)
    assert s.view.show_lift
    cloud = app.server.scene.get_handle_by_name(NAMES["cloud"])
    np.testing.assert_allclose(cloud.position, pb.T_world_object[-1][:3, 3], atol=1e-6)
    p_shown = _rotate(cloud.wxyz, centre) + cloud.position
    np.testing.assert_allclose(p_shown, at(pb.T_world_object[-1], centre), atol=1e-6)
    frame = app.scene.handle("hand_frame")
    np.testing.assert_allclose(frame.position, pb.T_world_hand[-1][:3, 3], atol=1e-6)
    assert all(not h.visible for h in app.scene._boxes.values())
    assert not app.scene.handle("contacts").visible

    # the outcome in the panel and in the table's lift column
    assert "**lift of grasp" in app.gui.lift_info.content and "lifted" in app.gui.lift_info.content
    row = next(r for r in app.gui.table.content.splitlines() if r.startswith(f"| {k + 1} |"))
    assert row.endswith(" |") and "lifted" in row.split("|")[-2]

    # choosing a grasp again: the planned animation, the object back where it rests
    c.select_grasp(k)
    s = _wait_rendered(app, lambda s: not s.view.show_lift)
    np.testing.assert_allclose(cloud.position, 0.0, atol=1e-12)
    assert all(h.visible for h in app.scene._boxes.values())
    assert "lifted" in app.gui.table.content  # the outcome stays in the table
    # a second press reuses the compiled scene; play replays a lift that has ended
    c.simulate()
    assert c.lift.wait(120)
    s = _wait_rendered(app, lambda s: s.lift.running is None)
    assert s.lift.playback is not pb and s.lift.playback.build_cpu == 0.0
    assert s.lift.playback.outcome.rise == pb.outcome.rise  # deterministic
    app.close()  # stop the animator: the clock moves only by hand below
    c.lift.seek(1e9)
    assert c.state.view.lift_t == s.lift.playback.duration and not c.state.view.playing
    c.play()
    assert c.state.view.lift_t == 0.0 and c.state.view.playing and c.state.view.show_lift
    c.tick(0.5)
    assert c.state.view.lift_t == pytest.approx(0.5)  # real time at speed 1


def _rotate(wxyz, p):
    w, x, y, z = wxyz
    R = np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )
    return R @ p


def test_an_upload_is_simulated_from_its_cloud_never_from_a_file_by_its_name(app):
    """An upload's name is the browser's: even when it names a mesh file on the server (here
    the demo can, relative to the working directory), the collision model comes from the
    uploaded cloud."""
    from pathlib import Path

    from pregrasp_core.paths import OBJECTS_DIR

    c = app.controller
    name = "assets/objects/can_soda.obj"
    assert Path(name).is_file(), "the test runs from the repository root"
    c.load_upload(name, (OBJECTS_DIR / "can_soda.obj").read_bytes())
    c.plan()
    assert ranked_grasps(c.state.result), "the can gets grasps"
    c.select_grasp(0)
    c.simulate()
    assert c.lift.wait(120)
    s = _wait_rendered(app, lambda s: s.lift is not None and s.lift.running is None)
    assert s.error == "" and s.lift.playback.model == "cloud"
    assert s.lift.playback.outcome.outcome in ("lifted", "slipped", "dropped", "unstable")
    assert f"model from the cloud ({s.lift.playback.n_pieces} pieces" in app.gui.lift_info.content
