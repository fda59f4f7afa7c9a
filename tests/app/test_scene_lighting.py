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


def test_the_drawn_hand_is_non_metallic_in_its_urdf_colours():
    """Without an environment map a metallic surface has no diffuse light (its faces turned
    away from the lights are black); the hand's meshes carry only a colour, which glTF would
    draw fully metallic. Reference: the URDF's own materials, read from the XML."""
    import xml.etree.ElementTree as ET

    from app.scene import display_urdf
    from pregrasp_core.paths import HAND_URDF

    root = ET.parse(HAND_URDF).getroot()
    rgba = {m.get("name"): m.find("color").get("rgba") for m in root.iter("material")
            if m.find("color") is not None}  # fmt: skip
    want = sorted(
        tuple(round(float(v) * 255) for v in rgba[v.find("material").get("name")].split())
        for v in root.iter("visual")
    )
    meshes = list(display_urdf(HAND_URDF).scene.geometry.values())
    got = sorted(tuple(int(c) for c in m.visual.material.baseColorFactor) for m in meshes)
    # one mesh per visual, each in its link's colour (to the 8-bit step: 0.32 -> 81 or 82)
    assert len(got) == len(want) and np.abs(np.array(got) - np.array(want)).max() <= 1
    assert all(m.visual.material.metallicFactor == 0.0 for m in meshes)
