"""The hidden space of a single depth view in headless Chromium: the depth demo (the mug on a
table, one view) opened with ``--occluded occupied`` draws the space behind the seen surface in
its own pale blue (``app.scene_data.HIDDEN_RGB``); unticking "hidden space" removes it from the
canvas without re-planning. The pale-blue pixels are counted on the canvas as displayed, and
the first composited frame without them is on screen within 2 s (in the best of three tries,
as in ``test_app_browser.py``).
"""

from __future__ import annotations

import re
import time
from collections.abc import Iterator

import numpy as np
import pytest

from app.scene_data import HIDDEN_RGB
from pregrasp_core.paths import OBJECTS_DIR
from tests.browser.conftest import app_on_server, look_from
from tests.browser.test_app_browser import (
    ACTION_S,
    _canvas_clip,
    _canvas_png,
    _Screencast,
    _shown_within,
)

LOAD_TIMEOUT_MS = 180_000
"""Generous: headless Chromium renders WebGL in software, on a shared machine."""


@pytest.fixture(scope="module")
def occupied_app() -> Iterator:
    from app.server import ViewerConfig
    from pregrasp_core.pipeline import PipelineParams

    cfg = ViewerConfig(
        input=OBJECTS_DIR / "mug_depth.png",
        params=PipelineParams(occluded="occupied"),
        planner_process=False,  # the pool alone: nothing is planned here
    )
    with app_on_server(cfg) as app:
        yield app


def _pale_blue(img: np.ndarray) -> int:
    """Pixels of ``img`` (H, W, 3) within 16 of :data:`HIDDEN_RGB` in every channel (no part
    colour, face mask or the table's grey comes that close: 0 pixels once the layer is off)."""
    return int((np.abs(img - np.asarray(HIDDEN_RGB)).max(axis=2) <= 16).sum())


def test_the_hidden_space_shows_in_its_colour_and_hides(browser_context, occupied_app, shots_dir):
    app = occupied_app
    c = app.controller
    occ = c.state.result.occupied
    assert occ is not None and app.scene.n_hidden_points_shown > 0
    page = browser_context.new_page()
    page.set_default_timeout(LOAD_TIMEOUT_MS)
    try:
        page.goto(f"http://127.0.0.1:{app.server.get_port()}")
        page.get_by_text(re.compile(r"^boxes: \d+$")).wait_for(timeout=LOAD_TIMEOUT_MS)
        page.get_by_text(re.compile(r"hidden space \(occupied\): \d+ cm\^3")).wait_for()
        box = page.get_by_label("hidden space", exact=True)
        assert box.is_checked() and box.is_enabled()
        # the hidden space is behind the mug as the depth camera saw it: look from behind, with
        # the face masks (translucent quads over it) off
        c.set_face_masks_visible(False)
        deadline = time.monotonic() + LOAD_TIMEOUT_MS / 1000
        (client,) = app.server.get_clients().values()
        centre = occ.points.mean(axis=0)
        camera = np.asarray(c.state.cloud.viewpoint)
        behind = centre + 0.4 * (centre - camera)  # as far on the other side, closer in
        behind[2] = max(behind[2], centre[2] + 0.2 * np.linalg.norm(centre - camera))
        look_from(client, behind, centre, deadline)
        clip = _canvas_clip(page)
        shown = _pale_blue(_canvas_png(page, clip=clip))
        page.screenshot(path=str(shots_dir / "browser_hidden_space.png"))
        runs = []
        real = c._run
        c._run = lambda *a, **k: runs.append(1) or real(*a, **k)  # no pipeline run may follow
        cast = _Screencast(page)

        def hide(i: int) -> float:
            if i:  # the layer back on screen for another try
                box.check()
                while _pale_blue(_canvas_png(page, frames=0, clip=clip)) < shown // 2:
                    assert time.monotonic() < deadline, "the pale blue did not come back"
                page.wait_for_timeout(1000)
            page.wait_for_timeout(300)  # the frame on screen before the action
            t0 = time.perf_counter()
            box.uncheck()
            while app.scene.handle("hidden") is not None or app.scene.n_hidden_points_shown:
                assert time.monotonic() < deadline, "the server kept the hidden-space layer"
                page.wait_for_timeout(20)
            server_s = time.perf_counter() - t0
            while _pale_blue(_canvas_png(page, frames=0, clip=clip)) > shown // 20:
                assert time.monotonic() < deadline, "the pale blue stayed on the canvas"
            on_screen = time.perf_counter() - t0
            frame = cast.first_change(t0, clip)
            first = "" if frame is None else f", first frame with it {frame:.2f} s"
            print(  # noqa: T201 - figures for the log
                f"hidden space hidden: on screen {on_screen:.2f} s{first}, server {server_s:.2f} s"
            )
            assert server_s < ACTION_S, f"the server took {server_s:.2f} s to drop the layer"
            return on_screen if frame is None else frame

        _shown_within("hidden space hidden", hide)
        cast.stop()
        hidden = _pale_blue(_canvas_png(page, clip=clip))
        print(f"pale-blue pixels {shown} -> {hidden}")  # noqa: T201 - figures for the log
        c._run = real
        assert shown >= 500, f"only {shown} pale-blue pixels with the layer on"
        assert hidden <= shown // 20
        assert not runs and not c.state.view.show_hidden_space
        assert c.state.result.occupied is occ  # the same hidden space, not computed again
    finally:
        page.close()
