"""The depth-camera workflow in headless Chromium: a scene of two boxes on a table opens with the
larger box as the object; ticking "click picks the object" and clicking the smaller box on the
canvas keeps that box instead (the click travels as a ray from the browser's camera).

The click's pixel is the small box's top face projected with the browser's own camera (pose and
field of view as the browser reports them to the server), so the test exercises the page's ray,
not a ray made up on the server.
"""

from __future__ import annotations

import re
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import viser.transforms as vtf

from pregrasp_core.sensor import Intrinsics
from pregrasp_core.sensor.synthetic import orbit_camera, render_view
from tests.browser.conftest import app_on_server, look_from
from tests.core.test_depth_input import two_boxes, write_scene_pcd

LOAD_TIMEOUT_MS = 180_000
"""Generous: headless Chromium renders WebGL in software, on a shared machine."""


@pytest.fixture(scope="module")
def scene_app(tmp_path_factory) -> Iterator:
    from app.server import ViewerConfig

    mesh, _, small_c = two_boxes()
    T = orbit_camera(np.array([0.0, 0.07, 0.05]), 0.7, np.radians(20.0), np.radians(40.0))
    view = render_view(mesh.vertices, mesh.faces, T, Intrinsics(300, 300, 159.5, 119.5), 320,
                       240, table_half=0.4)  # fmt: skip
    pts, _ = view.points_world()
    path: Path = tmp_path_factory.mktemp("scene") / "two_boxes.pcd"
    write_scene_pcd(path, pts, T)
    with app_on_server(ViewerConfig(input=path, n_points=3000)) as app:
        yield app, small_c


def _pixel(client, canvas_box: dict, point: np.ndarray) -> tuple[float, float]:
    """Page coordinates of world ``point`` in ``client``'s view (OpenCV camera: +z forward,
    +y down; ``fov`` vertical)."""
    cam = client.camera
    R = vtf.SO3(np.asarray(cam.wxyz)).as_matrix()
    p = R.T @ (np.asarray(point) - np.asarray(cam.position))
    assert p[2] > 0, "the point is behind the browser's camera"
    w, h = canvas_box["width"], canvas_box["height"]
    f = 0.5 * h / np.tan(0.5 * float(cam.fov))
    return canvas_box["x"] + 0.5 * w + f * p[0] / p[2], canvas_box["y"] + 0.5 * h + f * p[1] / p[2]


def test_click_on_the_canvas_picks_the_other_box(browser_context, scene_app, shots_dir):
    app, small_c = scene_app
    c = app.controller
    assert c.state.cloud.points[:, 1].max() < 0.06  # the largest cluster: the big box
    page = browser_context.new_page()
    page.set_default_timeout(LOAD_TIMEOUT_MS)
    try:
        page.goto(f"http://127.0.0.1:{app.server.get_port()}")
        page.get_by_text(re.compile(r"^boxes: \d+$")).wait_for(timeout=LOAD_TIMEOUT_MS)
        page.get_by_label("click picks the object", exact=True).check()
        deadline = time.monotonic() + LOAD_TIMEOUT_MS / 1000
        while not app.gui.pick_mode.value:  # the tick reaches the server
            assert time.monotonic() < deadline, "the checkbox did not reach the server"
            time.sleep(0.1)
        canvas = max(
            page.locator("canvas").all(), key=lambda h: (h.bounding_box() or {}).get("width", 0)
        )
        box = canvas.bounding_box()
        assert box is not None
        (client,) = app.server.get_clients().values()
        # the app frames the big box from -y, where it hides the small one: look from +y
        look_from(client, [0.05, 0.6, 0.35], [0.0, 0.07, 0.05], deadline)
        x, y = _pixel(client, box, small_c + [0.0, 0.0, 0.025])  # the small box's top face
        page.mouse.click(x, y)
        while c.state.cloud.points[:, 1].min() < 0.12 or not c.idle():
            assert time.monotonic() < deadline, f"no pick: {c.state.error or c.state.message}"
            time.sleep(0.2)
        s = c.state
        assert s.error == "" and s.planned and s.cloud.points[:, 2].max() < 0.06
        # the browser's camera is framed on the new object (it looks at its centre)
        lo, hi = s.cloud.points.min(axis=0), s.cloud.points.max(axis=0)
        while np.linalg.norm(np.asarray(client.camera.look_at) - (lo + hi) / 2) > 1e-3:
            assert time.monotonic() < deadline, f"camera looks at {client.camera.look_at}"
            time.sleep(0.1)
        page.get_by_text(re.compile(r"kept the cluster nearest")).first.wait_for()
        page.screenshot(path=str(shots_dir / "browser_depth_pick.png"))
    finally:
        page.close()
