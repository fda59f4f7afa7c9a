"""``pregrasp`` on depth-camera input: the demo depth image planned end to end, ``--pick`` and
``--no-scene`` on a rendered scene, millimetre clouds, and the messages of bad intrinsics.

The scene is rendered by ray casting (``pregrasp_core.sensor.synthetic``) from two trimesh
boxes on the table z = 0, so which points belong to which box is known outside the CLI.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import trimesh

from app.cli import main
from pregrasp_core.io import load_point_cloud
from pregrasp_core.paths import OBJECTS_DIR
from pregrasp_core.sensor import Intrinsics
from pregrasp_core.sensor.synthetic import orbit_camera, render_view
from tests.core.test_depth_input import write_scene_pcd

DEMO = OBJECTS_DIR / "mug_depth.png"


def test_plan_the_demo_depth_image(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "mug.json"
    assert main(["plan", str(DEMO), "-o", str(out)]) == 0
    doc = json.loads(out.read_text())
    inp = doc["input"]
    assert inp["format"] == "png" and inp["kind"] == "depth"
    sc = inp["scene"]
    assert sc["n_visible"] + sc["n_assumed"] == inp["n_points"] and sc["n_assumed"] > 0
    # the table is the support plane and the camera orients the normals
    fm = doc["parameters"]["facemask"]
    assert fm["support"] and fm["up"][2] > 0.9998 and abs(fm["support_height"]) < 1e-3
    assert doc["parameters"]["planner"]["normals"]["viewpoint"] == pytest.approx(sc["viewpoint"])
    assert doc["best"] is not None and doc["best_reason"].startswith("force closure")
    best = doc["grasps"]["items"][doc["best"]]
    # --occluded auto (the default): the hidden back is an obstacle and the best grasp keeps
    # out of it (measured epsilon 0.020); planned with the back completed instead, the best
    # grasp wraps the assumed back (measured 0.153)
    assert "occluded" not in doc["parameters"] and doc["parameters"]["occluded_used"] == "occupied"
    assert best["epsilon"] > 0.0 and "unseen back occupied" in capsys.readouterr().out
    assert main(["plan", str(DEMO), "--occluded", "completed", "-o", str(out)]) == 0
    doc = json.loads(out.read_text())
    assert doc["parameters"]["occluded"] == doc["parameters"]["occluded_used"] == "completed"
    assert doc["grasps"]["items"][doc["best"]]["epsilon"] > 0.05


def test_pick_and_no_scene_on_a_rendered_scene(tmp_path: Path) -> None:
    big = trimesh.creation.box((0.08, 0.06, 0.12))
    big.apply_translation((0.0, 0.0, 0.06))
    small = trimesh.creation.box((0.04, 0.04, 0.05))
    small.apply_translation((0.0, 0.15, 0.025))
    mesh = trimesh.util.concatenate([big, small])
    T = orbit_camera(np.array([0.0, 0.07, 0.05]), 0.7, np.radians(20.0), np.radians(40.0))
    view = render_view(mesh.vertices, mesh.faces, T, Intrinsics(300, 300, 159.5, 119.5), 320,
                       240, table_half=0.4)  # fmt: skip
    pts, _ = view.points_world()
    pcd = tmp_path / "scene.pcd"
    write_scene_pcd(pcd, pts, T)
    out = tmp_path / "small.json"
    assert main(["decompose", str(pcd), "--pick", "0", "0.15", "0.02", "-o", str(out)]) == 0
    lo, hi = np.asarray(json.loads(out.read_text())["input"]["bounds"])
    assert lo[1] > 0.12 and hi[2] < 0.06  # the small box (and its completion), not the big one
    out = tmp_path / "all.json"
    assert main(["decompose", str(pcd), "--no-scene", "-o", str(out)]) == 0
    inp = json.loads(out.read_text())["input"]
    assert "scene" not in inp and inp["bounds"][1][0] - inp["bounds"][0][0] > 0.7  # the table


def test_millimetre_cloud_gets_the_notice(tmp_path: Path, capsys: pytest.CaptureFixture[str]):
    cloud = load_point_cloud(OBJECTS_DIR / "bottle.obj", n_points=3000)
    path = tmp_path / "bottle_mm.xyz"
    np.savetxt(path, np.asarray(cloud.points) * 1000.0)
    out = tmp_path / "b.json"
    assert main(["decompose", str(path), "-o", str(out)]) == 0
    inp = json.loads(out.read_text())["input"]
    assert inp["scale"] == 0.001
    assert any("read as millimetres" in w and "--scale 1" in w for w in inp["warnings"])
    np.testing.assert_allclose(np.ptp(np.asarray(inp["bounds"]), axis=0), cloud.extents,
                               atol=1e-6)  # fmt: skip


def test_bad_intrinsics_name_the_flag_or_file(tmp_path: Path, capsys) -> None:
    png = tmp_path / "frame.png"
    shutil.copy(DEMO, png)
    assert main(["decompose", str(png)]) != 0
    assert "--intrinsics FX FY CX CY" in capsys.readouterr().err
    assert main(["decompose", str(png), "--intrinsics", "420", "420", "239.5"]) != 0
    assert "--intrinsics: give four numbers" in capsys.readouterr().err
    assert main(["decompose", str(png), "--intrinsics", str(tmp_path / "none.json")]) != 0
    assert "none.json: intrinsics file not found" in capsys.readouterr().err
