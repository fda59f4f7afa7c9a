"""The 'up (table normal)' dropdown in headless Chromium: choosing +y for a mesh that stands
along +y re-plans it standing (the server's state), and the page shows the new pool."""

from __future__ import annotations

import re
import time

import numpy as np

from tests.browser.conftest import app_on_server

LOAD_TIMEOUT_MS = 120_000
"""Generous: software WebGL."""


def test_choosing_up_y_in_the_browser_plans_the_y_up_mesh_standing(
    browser_context, tmp_path, shots_dir
):
    import trimesh

    from app.server import ViewerConfig
    from pregrasp_core.paths import DEFAULT_OBJECT

    mesh = trimesh.load(DEFAULT_OBJECT, force="mesh")
    mesh.apply_transform(trimesh.transformations.rotation_matrix(-np.pi / 2, [1.0, 0.0, 0.0]))
    path = tmp_path / "mug_y.obj"
    mesh.export(path)
    with app_on_server(ViewerConfig(input=path, n_points=3000)) as app:
        page = browser_context.new_page()
        page.set_default_timeout(LOAD_TIMEOUT_MS)
        try:
            page.goto(f"http://127.0.0.1:{app.server.get_port()}")
            page.get_by_text(re.compile(r"^boxes: \d+$")).wait_for()
            c = app.controller
            assert c.state.params.facemask.up == (0.0, 0.0, 1.0)
            pool_z = len(c.state.result.pool)
            page.get_by_label("up (table normal)", exact=True).click()
            page.get_by_role("option", name="+y", exact=True).click()
            deadline = time.monotonic() + 120
            while not (c.state.params.facemask.up == (0.0, 1.0, 0.0) and c.idle()):
                assert time.monotonic() < deadline, "the choice does not reach the server"
                time.sleep(0.1)
            s = c.state
            assert np.allclose(s.result.masks.support.normal, [0.0, 1.0, 0.0])
            assert len(s.result.pool) != pool_z
            page.wait_for_function(
                "() => [...document.querySelectorAll('input')].some(i => i.value === '+y')"
            )
            page.screenshot(path=str(shots_dir / "browser_up.png"))
        finally:
            page.close()
