"""The scene's lights as a browser receives them: no shadow maps and no environment map (in
software WebGL they were most of every frame, docs/benchmarks.md "Viewer: frame cost of the
first screen"), and fill lights in their place so that no face is unlit."""

from __future__ import annotations

import time

import numpy as np
from test_security import Browser


def _messages_of(browser: Browser, kind: str) -> list[dict]:
    return [m for m in list(browser.messages) if m["type"] == kind]


def test_a_browser_gets_lights_without_shadows_or_environment_map(app):
    b = Browser(app.server.get_port())  # joins after the app is built, as a new tab does
    try:
        t0 = time.monotonic()
        while not _messages_of(b, "AmbientLightMessage"):
            assert time.monotonic() - t0 < 30, "the scene never reached the browser"
            time.sleep(0.02)
        lights = _messages_of(b, "EnableLightsMessage")
        assert lights and lights[-1]["enabled"] and not lights[-1]["cast_shadow"]
        env = _messages_of(b, "EnvironmentMapMessage")
        assert env and env[-1]["hdri_data"] is None
        (hemi,) = _messages_of(b, "HemisphereLightMessage")
        (ambient,) = _messages_of(b, "AmbientLightMessage")
        assert hemi["props"]["intensity"] > 0 and ambient["props"]["intensity"] > 0
        # the hemisphere's sky (three.js' +y in the node's frame) turned to the world's +z
        turns = [m for m in _messages_of(b, "SetOrientationMessage") if m["name"] == hemi["name"]]
        w, x, y, z = turns[-1]["wxyz"]
        sky = np.array([2 * (x * y - w * z), 1 - 2 * (x * x + z * z), 2 * (y * z + w * x)])
        assert np.allclose(sky, [0.0, 0.0, 1.0], atol=1e-9)
    finally:
        b.close()
