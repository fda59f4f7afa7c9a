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


def _world_pose(server, name: str) -> np.ndarray:
    """4x4 pose of scene node ``name`` in the world: its own pose composed with its parents'
    (viser nests nodes by their ``/``-separated names)."""
    import viser.transforms as vtf

    T = np.eye(4)
    parts = name.strip("/").split("/")
    for k in range(1, len(parts) + 1):
        h = server.scene.get_handle_by_name("/" + "/".join(parts[:k]))
        if h is None:
            continue
        step = np.eye(4)
        step[:3, :3] = vtf.SO3(np.asarray(h.wxyz, dtype=np.float64)).as_matrix()
        step[:3, 3] = np.asarray(h.position, dtype=np.float64)
        T = T @ step
    return T


def test_the_drawn_hand_is_posed_as_the_urdf_forward_kinematics():
    """``scene.HandMeshes`` (the hand as simple meshes in the cheaper material): at a random
    joint configuration, under a hand frame at a random pose, each drawn mesh's vertices,
    carried to the world through the scene's nested frames, are the link's visual mesh placed
    by yourdfpy's own forward kinematics (reference: ``URDF.get_transform`` to the base link);
    each mesh has its URDF colour."""
    from functools import partial

    import viser
    import yourdfpy

    from app.scene import NAMES, HandMeshes, display_urdf
    from app.scene_data import wxyz_from_matrices
    from pregrasp_core.paths import HAND_URDF

    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    try:
        frame = server.scene.add_frame(NAMES["hand"], show_axes=False)
        rng = np.random.default_rng(3)
        A = np.linalg.qr(rng.normal(size=(3, 3)))[0]
        A *= np.sign(np.linalg.det(A))
        T_world_hand = np.eye(4)
        T_world_hand[:3, :3], T_world_hand[:3, 3] = A, rng.normal(size=3) * 0.1
        frame.wxyz = wxyz_from_matrices(A[None])[0]
        frame.position = T_world_hand[:3, 3]
        drawn = HandMeshes(server, display_urdf(HAND_URDF), NAMES["hand"])
        ref = yourdfpy.URDF.load(
            HAND_URDF,
            build_scene_graph=True,
            load_meshes=True,
            filename_handler=partial(yourdfpy.filename_handler_magic, dir=HAND_URDF.parent),
        )
        lo = np.array([j.limit.lower for j in ref.actuated_joints])
        hi = np.array([j.limit.upper for j in ref.actuated_joints])
        q = lo + rng.random(len(lo)) * (hi - lo)
        drawn.update_cfg(q)
        ref.update_cfg(q)
        assert len(drawn.meshes) == len(ref.scene.geometry) > 0
        base = ref.base_link
        for h in drawn.meshes:
            geom = h.name.rsplit("/", 1)[1]
            mesh = ref.scene.geometry[geom]
            want = (T_world_hand @ ref.get_transform(geom, base))[:3] @ np.c_[
                mesh.vertices, np.ones(len(mesh.vertices))
            ].T
            got = _world_pose(server, h.name)[:3] @ np.c_[h.vertices, np.ones(len(h.vertices))].T
            assert np.abs(got - want).max() < 1e-5, geom
            rgba = np.asarray(mesh.visual.face_colors, dtype=np.uint8)[0]
            assert tuple(h.color) == tuple(int(c) for c in rgba[:3])
    finally:
        server.stop()
