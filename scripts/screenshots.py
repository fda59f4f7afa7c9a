"""Take the documentation screenshots from the real app in headless Chromium.

Starts the app on a free port (default object unless INPUT is given), opens it in Debian's
Chromium through Python playwright, sets up each view through the app's controller (the same
actions the GUI runs) and saves ``docs/screenshots/{decomposition,face_masks,pregrasps,
grasp}.png``, then ``depth_demo.png``: the depth-camera demo (``assets/objects/mug_depth.png``
opened as ``pregrasp view`` opens it, planned on start with ``--occluded auto``: its hidden
space drawn) with its best grasp closed (:func:`depth_demo_shot`; ``--depth`` takes only that
one), and ``depth_completed.png``: the same planned with ``--occluded completed``, the back
completed and no hidden space (``--completed`` takes only that one). ``--rim`` takes only
``rim_pinch.png``: a torus 130 mm across, its best grasp a rim pinch (:func:`rim_pinch_shot`).
``--flying`` takes only ``flying_pixels.png``: the depth demo's view with every edge pixel
mixed, opened with ``--flying-pixels`` (:func:`flying_pixels_shot`). ``--up`` takes only
``up_lying.png`` and ``up_standing.png``: a Y-up bottle read z-up, then with up +y
(:func:`up_shots`). ``--clutter`` takes only ``clutter_obstacles.png``: a ball picked among a
can, a box and a pen, the space hidden behind them drawn (:func:`clutter_shot`). ``--above``
takes only ``ramekin_above.png``: the ramekin seen from 85 degrees, its skirt among the assumed
points (:func:`above_shot`).

    .venv/bin/python scripts/screenshots.py [INPUT] [--out docs/screenshots] [--points 20000]
    .venv/bin/python scripts/screenshots.py --depth
    .venv/bin/python scripts/screenshots.py --completed
    .venv/bin/python scripts/screenshots.py --rim
    .venv/bin/python scripts/screenshots.py --flying
    .venv/bin/python scripts/screenshots.py --up
    .venv/bin/python scripts/screenshots.py --clutter
    .venv/bin/python scripts/screenshots.py --above
"""

from __future__ import annotations

import argparse
import contextlib
import re
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from app.headless import CHROMIUM, launch  # noqa: E402 (the repository on the path first)


def _settle(page, app) -> None:
    """Wait until the page shows the scene's box count and two frames have been drawn."""
    page.get_by_text(f"boxes: {app.scene.n_boxes}", exact=True).wait_for(timeout=120_000)
    ghosts = f"{app.scene.n_ghosts_shown} ghosts drawn"
    page.get_by_text(re.compile(re.escape(ghosts))).wait_for(timeout=120_000)
    page.wait_for_load_state("networkidle")
    for _ in range(3):
        page.evaluate(
            "() => new Promise(r => requestAnimationFrame(() => requestAnimationFrame(r)))"
        )


def _close_notifications(page, timeout_s: float = 60.0) -> None:
    """Close the browser's notifications (e.g. 'software WebGL') so they do not cover the view."""
    deadline = time.monotonic() + timeout_s
    roots = page.locator(".mantine-Notification-root")
    while roots.count():
        if time.monotonic() > deadline:
            raise TimeoutError("a notification does not close")
        for btn in page.locator(".mantine-Notification-closeButton").all():
            try:
                btn.click(timeout=2000, force=True)
            except Exception:  # noqa: BLE001 - a notification may close by itself meanwhile
                pass
        page.wait_for_timeout(500)


def _zoom(server, factor: float) -> None:
    """Move every browser's camera ``factor`` times as far from its target (docs framing)."""
    for client in server.get_clients().values():
        cam = client.camera
        target = cam.look_at.copy()
        cam.position = target + factor * (cam.position - target)
        cam.look_at = target  # a client camera's position setter moves its look_at along


def _wait_idle(controller, timeout_s: float = 300.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not controller.idle():
        if time.monotonic() > deadline:
            raise TimeoutError("the app did not finish planning")
        time.sleep(0.1)


def _view_behind_the_hand(server, state, elevation: float = 0.75) -> None:
    """Aim every camera at the object from the side away from the chosen grasp's hand (the
    hand would hide the object), ``elevation`` radians above the horizontal, at the framing
    distance the app uses, 1.4 times."""
    import numpy as np

    from app.scene import camera_offset, support_of
    from app.scene_data import selected_grasp

    pts = np.asarray(state.cloud.points)
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    center = (lo + hi) / 2.0
    up = support_of(state, pts)[0]  # above the table the object stands on
    away = center - np.asarray(selected_grasp(state).T_world_hand)[:3, 3]
    away -= (away @ up) * up
    away /= max(float(np.linalg.norm(away)), 1e-9)
    diag, fov = float(np.linalg.norm(hi - lo)), float(server.initial_camera.fov)
    dist = 1.4 * float(np.linalg.norm(camera_offset(diag, fov)))
    d = np.cos(elevation) * away + np.sin(elevation) * up
    for client in server.get_clients().values():  # position first: it moves look_at along
        client.camera.position = center + dist * d
        client.camera.look_at = center


DEPTH_SHOTS: dict[str, str] = {
    "auto": "depth_demo.png",
    "completed": "depth_completed.png",
    "occupied": "depth_hidden.png",
}
"""The file :func:`depth_demo_shot` writes per ``--occluded`` setting."""


@contextlib.contextmanager
def _closed_grasp_page(
    server, app, chromium: str, what: str, elevation: float = 0.75, scroll: bool = False
):
    """A browser page on ``app`` once its plan is done, showing the chosen grasp closed, the
    face masks hidden and the notifications hidden (under load a software-WebGL page may not
    take clicks for minutes), seen from behind the hand, the grasp table drawn; ``None`` (and a
    message naming ``what``) when no grasp was planned."""
    from playwright.sync_api import sync_playwright

    c = app.controller
    _wait_idle(c)
    if c.state.view.selected_grasp is None:
        print(f"no grasp was planned on {what}: no picture written", file=sys.stderr)
        yield None
        return
    c.set_face_masks_visible(False)
    c.set_anim_t(1.0)  # the closed hand
    with sync_playwright() as p:
        ctx = launch(
            p,
            tempfile.mkdtemp(prefix="pregrasp-shots-"),
            chromium,
            viewport={"width": 1600, "height": 900},
        )
        page = ctx.new_page()
        page.goto(f"http://127.0.0.1:{server.get_port()}")
        page.get_by_text(re.compile(r"^boxes: \d+$")).wait_for(timeout=120_000)
        page.add_style_tag(content=".mantine-Notification-root { display: none !important; }")
        _view_behind_the_hand(server, c.state, elevation=elevation)
        fc = re.compile(r"^\d+ force-closure of \d+ kept$")
        page.get_by_text(fc).wait_for(timeout=120_000)
        if scroll:  # the grasp table in view
            page.get_by_text(fc).scroll_into_view_if_needed()
        _settle(page, app)
        yield page
        ctx.close()


def depth_demo_shot(out: Path, chromium: str, occluded: str = "auto") -> int:
    """``out/depth_demo.png``: the depth demo in the viewer as ``pregrasp view
    assets/objects/mug_depth.png`` starts it (the table found and removed, drawn grey behind the
    mug, the completed back in dark slate, the hidden space the hand kept out of in pale blue,
    the best grasp planned on start), the hand closed, seen from the side away from the hand,
    the Object panel and the legend open. Another ``occluded``: the same planned with that
    ``--occluded`` setting, in :data:`DEPTH_SHOTS`'s file."""
    import viser

    from app.server import ViewerConfig, run
    from pregrasp_core.paths import OBJECTS_DIR
    from pregrasp_core.pipeline import PipelineParams

    name = DEPTH_SHOTS[occluded]
    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    params = PipelineParams(occluded=occluded)
    config = ViewerConfig(input=OBJECTS_DIR / "mug_depth.png", params=params, plan_on_start=True)
    return _legend_shot(server, run(config, server), chromium, "the depth demo",
                        "dark slate points", out / name)  # fmt: skip


def _legend_shot(server, app, chromium: str, what: str, legend_row: str, path: Path) -> int:
    """Save ``path``: ``app`` (on ``server``) with its chosen grasp closed
    (:func:`_closed_grasp_page`), the long panels folded and the legend open (its row
    ``legend_row`` shown); 1 when no grasp was planned on ``what``. Closes the app and server."""
    try:
        with _closed_grasp_page(server, app, chromium, what) as page:
            if page is None:
                return 1
            for folder in ("Decomposition", "Face masks and pre-grasps", "Planner", "Legend"):
                # fold the long panels, open the legend (the scene's colours)
                page.get_by_text(folder, exact=True).click(timeout=300_000)
            page.get_by_text(legend_row, exact=True).wait_for(timeout=300_000)
            page.wait_for_load_state("networkidle")
            for _ in range(3):
                page.evaluate(
                    "() => new Promise(r => requestAnimationFrame(() => requestAnimationFrame(r)))"
                )
            _screenshot(page, path)
    finally:
        app.close()
        server.stop()
    return 0


def flying_pixels_shot(out: Path, chromium: str) -> int:
    """``out/flying_pixels.png``: the depth demo's view (``scripts/make_views.py --demo``: the
    mug with a handle, azimuth 300 degrees, 1 mm of noise) with every pixel at a depth jump of
    more than 2 cm mixed (``add_mixed_pixels``, the time-of-flight model), written as a PCD scene
    and opened as ``pregrasp view SCENE.pcd --flying-pixels`` opens it: the dropped points in
    magenta behind the mug's outline, its best grasp planned on start and closed."""
    import numpy as np
    import trimesh
    import viser

    from app.server import ViewerConfig, run
    from pregrasp_core.io import SensorOptions
    from pregrasp_core.paths import OBJECTS_DIR
    from pregrasp_core.sensor.synthetic import add_mixed_pixels

    mv = _make_views()
    name, azimuth, noise = mv.DEMO
    mesh = trimesh.load(OBJECTS_DIR / f"{name}.obj", force="mesh")
    view = mv.make_view(mesh, azimuth, noise, mv.view_seed(name, 0, noise))
    view = add_mixed_pixels(view, 1.0, 0.02, np.random.default_rng(0))
    pts, lab = view.points_world()
    path = Path(tempfile.mkdtemp(prefix="pregrasp-veiled-")) / "mug_handle_veiled.pcd"
    path.write_bytes(mv.pcd_bytes(pts, lab, view.T_world_camera))
    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    config = ViewerConfig(input=path, sensor=SensorOptions(flying_pixels=True), plan_on_start=True)
    return _legend_shot(server, run(config, server), chromium, "the veiled view",
                        "magenta points", out / "flying_pixels.png")  # fmt: skip


def clutter_shot(out: Path, chromium: str) -> int:
    """``out/clutter_obstacles.png``: a depth view (1 mm of noise, camera at 150 degrees and 40
    up) of a soda-can cylinder, a 4 cm ball, a small box and a pen lying down, 4-5 cm apart,
    written as a PCD scene and opened with the ball picked and ``--occluded completed``: the
    other objects brown, the space hidden behind them in pale blue (the hand's obstacles with
    their points, ``docs/limits.md``), the ball's best grasp planned on start and closed."""
    import numpy as np
    import trimesh
    import viser

    from app.server import ViewerConfig, run
    from pregrasp_core.io import SensorOptions
    from pregrasp_core.pipeline import PipelineParams
    from pregrasp_core.sensor import Intrinsics
    from pregrasp_core.sensor.synthetic import (
        LABEL_OBJECT,
        clutter_meshes,
        orbit_camera,
        render_view,
    )

    mesh = trimesh.util.concatenate(list(clutter_meshes().values()))
    T = orbit_camera(np.zeros(3), 0.55, np.radians(150.0), np.radians(40.0))
    view = render_view(mesh.vertices, mesh.faces, T, Intrinsics(420.0, 420.0, 239.5, 179.5),
                       480, 360, table_half=0.35, noise=0.001,
                       rng=np.random.default_rng(1))  # fmt: skip
    pts, lab = view.points_world()
    mv = _make_views()
    path = Path(tempfile.mkdtemp(prefix="pregrasp-clutter-")) / "clutter.pcd"
    path.write_bytes(mv.pcd_bytes(pts, np.where(lab == LABEL_OBJECT, 2, 1), T))
    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    pick = SensorOptions(pick=(0.09, 0.02, 0.02))
    params = PipelineParams(occluded="completed")
    config = ViewerConfig(input=path, sensor=pick, params=params, plan_on_start=True)
    return _legend_shot(server, run(config, server), chromium, "the clutter scene",
                        "pale blue points", out / "clutter_obstacles.png")  # fmt: skip


def above_shot(out: Path, chromium: str) -> int:
    """``out/ramekin_above.png``: the demo ramekin on a table seen from 85 degrees of elevation
    (a camera over the table, 1 mm of noise), written as a PCD scene and opened as ``pregrasp
    view`` opens it: its outer wall out of sight, the skirt below its outline among the dark
    slate assumed points (``docs/partial-views.md``, "Views from above"), its best grasp planned
    on start and closed on that wall."""
    import numpy as np
    import trimesh
    import viser

    from app.server import ViewerConfig, run
    from pregrasp_core.paths import OBJECTS_DIR
    from pregrasp_core.sensor.synthetic import orbit_camera, render_view

    mv = _make_views()
    mesh = trimesh.load(OBJECTS_DIR / "ramekin.obj", force="mesh")
    target, dist, table_half = mv.view_setup(mesh)
    T = orbit_camera(target, dist, np.radians(60.0), np.radians(85.0))
    # bench_odd_views' top85 view at azimuth 60 degrees
    rng = np.random.default_rng(3)
    view = render_view(mesh.vertices, mesh.faces, T, mv.INTRINSICS, mv.WIDTH, mv.HEIGHT,
                       table_half=table_half, noise=0.001, rng=rng)  # fmt: skip
    pts, lab = view.points_world()
    path = Path(tempfile.mkdtemp(prefix="pregrasp-above-")) / "ramekin_above.pcd"
    path.write_bytes(mv.pcd_bytes(pts, lab, T))
    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    config = ViewerConfig(input=path, plan_on_start=True)
    return _legend_shot(server, run(config, server), chromium, "the ramekin from above",
                        "dark slate points", out / "ramekin_above.png")  # fmt: skip


def _make_views():
    """``scripts/make_views.py`` as a module (its PCD writer and the demo view)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("make_views", ROOT / "scripts" / "make_views.py")
    assert spec is not None and spec.loader is not None
    mv = importlib.util.module_from_spec(spec)
    sys.modules["make_views"] = mv
    spec.loader.exec_module(mv)
    return mv


def rim_pinch_shot(out: Path, chromium: str) -> int:
    """``out/rim_pinch.png``: a torus 130 mm across lying on the table (too wide for the pinch
    across it, ``docs/pregrasps.md`` "Rim pinches"), opened in the viewer with its best grasp
    planned on start, the hand closed with the thumb in the hole, seen from the side away
    from the hand."""
    import trimesh
    import viser

    from app.server import ViewerConfig, run

    torus = trimesh.creation.torus(0.05, 0.015, major_sections=64, minor_sections=24)
    torus.apply_translation([0.0, 0.0, 0.015])
    path = Path(tempfile.mkdtemp(prefix="pregrasp-torus-")) / "torus_130mm.stl"
    torus.export(path)
    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    app = run(ViewerConfig(input=path, plan_on_start=True), server)
    try:
        with _closed_grasp_page(server, app, chromium, "the torus", 1.0, scroll=True) as page:
            if page is None:
                return 1
            shot = out / "rim_pinch.png"
            _screenshot(page, shot)
    finally:
        app.close()
        server.stop()
    return 0


def up_shots(out: Path, chromium: str) -> int:
    """``out/up_lying.png`` and ``out/up_standing.png``: the bottle turned to stand along +y
    (as a glTF file is) and saved as GLB, opened in the viewer with its best grasp planned on
    start: first as every file is read (up +z: the bottle lies on its side), then with 'up
    (table normal)' +y (standing, the view turned with it), each with its best grasp closed."""
    import numpy as np
    import trimesh
    import viser

    from app.server import ViewerConfig, run
    from pregrasp_core.paths import OBJECTS_DIR

    mesh = trimesh.load(OBJECTS_DIR / "bottle.obj", force="mesh")
    mesh.apply_transform(trimesh.transformations.rotation_matrix(-np.pi / 2, [1.0, 0.0, 0.0]))
    path = Path(tempfile.mkdtemp(prefix="pregrasp-up-")) / "bottle_y_up.glb"
    path.write_bytes(mesh.export(file_type="glb"))
    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    app = run(ViewerConfig(input=path, plan_on_start=True), server)
    c = app.controller
    try:
        with _closed_grasp_page(server, app, chromium, "the Y-up bottle") as page:
            if page is None:
                return 1
            for name, up in (("up_lying", None), ("up_standing", "+y")):
                if up is not None:
                    c.set_up(up)
                    _wait_idle(c)
                    c.set_face_masks_visible(False)
                    c.set_anim_t(1.0)
                    _view_behind_the_hand(server, c.state)
                    page.get_by_text(re.compile(r"^\d+ force-closure of \d+ kept$")).wait_for(
                        timeout=120_000
                    )
                    _settle(page, app)
                shot = out / f"{name}.png"
                _screenshot(page, shot)
    finally:
        app.close()
        server.stop()
    return 0


def _screenshot(page: Any, path: Path) -> None:
    """Write the page's screenshot to ``path`` and say so."""
    page.screenshot(path=str(path), timeout=180_000)
    print(f"wrote {path.relative_to(ROOT) if path.is_relative_to(ROOT) else path}")


def main() -> int:
    ap = argparse.ArgumentParser(description="documentation screenshots of the real app")
    ap.add_argument("input", nargs="?", type=Path, help="object to show (default: the mug)")
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "screenshots")
    ap.add_argument("--points", type=int, default=20000)
    ap.add_argument("--chromium", default=CHROMIUM)
    ap.add_argument("--depth", action="store_true", help="only the depth demo (depth_demo.png)")
    completed_help = "only the depth demo with --occluded completed (depth_completed.png)"
    ap.add_argument("--completed", action="store_true", help=completed_help)
    rim_help = "only the rim pinch on a torus 130 mm across (rim_pinch.png)"
    ap.add_argument("--rim", action="store_true", help=rim_help)
    flying_help = "only the depth demo's view with flying pixels, dropped (flying_pixels.png)"
    ap.add_argument("--flying", action="store_true", help=flying_help)
    up_help = "only a Y-up bottle (GLB) read z-up, then with up +y (up_lying/up_standing.png)"
    ap.add_argument("--up", action="store_true", help=up_help)
    clutter_help = "only a ball picked in clutter, its neighbours' hidden space drawn"
    ap.add_argument("--clutter", action="store_true", help=clutter_help)
    above_help = "only the ramekin seen from above, its skirt drawn (ramekin_above.png)"
    ap.add_argument("--above", action="store_true", help=above_help)
    args = ap.parse_args()
    if args.above:
        args.out.mkdir(parents=True, exist_ok=True)
        return above_shot(args.out, args.chromium)
    if args.clutter:
        args.out.mkdir(parents=True, exist_ok=True)
        return clutter_shot(args.out, args.chromium)
    if args.up:
        args.out.mkdir(parents=True, exist_ok=True)
        return up_shots(args.out, args.chromium)
    if args.flying:
        args.out.mkdir(parents=True, exist_ok=True)
        return flying_pixels_shot(args.out, args.chromium)
    if args.rim:
        args.out.mkdir(parents=True, exist_ok=True)
        return rim_pinch_shot(args.out, args.chromium)
    if args.depth or args.completed:
        args.out.mkdir(parents=True, exist_ok=True)
        rc = depth_demo_shot(args.out, args.chromium) if args.depth else 0
        if args.completed:
            rc = rc or depth_demo_shot(args.out, args.chromium, "completed")
        return rc

    import viser
    from playwright.sync_api import sync_playwright

    from app.server import ViewerConfig, run

    args.out.mkdir(parents=True, exist_ok=True)
    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    # as `pregrasp view` starts (ghosts off); the plan runs below, where its picture is taken
    app = run(ViewerConfig(input=args.input, n_points=args.points), server)
    c = app.controller
    try:
        with sync_playwright() as p:
            ctx = launch(
                p,
                tempfile.mkdtemp(prefix="pregrasp-shots-"),
                args.chromium,
                viewport={"width": 1600, "height": 900},
            )
            page = ctx.new_page()
            page.goto(f"http://127.0.0.1:{server.get_port()}")
            page.get_by_text(re.compile(r"^boxes: \d+$")).wait_for(timeout=120_000)
            _close_notifications(page)
            _zoom(server, 0.9)

            def shot(name: str) -> None:
                _settle(page, app)
                _close_notifications(page)
                path = args.out / f"{name}.png"
                _screenshot(page, path)

            c.set_ghosts_visible(False)
            c.set_face_masks_visible(False)
            shot("decomposition")

            c.set_face_masks_visible(True)
            s = c.state
            c.select_node(max(s.tree.leaves(), key=lambda i: len(s.tree.node(i).indices)))
            shot("face_masks")

            c.set_face_masks_visible(False)
            c.select_node(None)
            # the app's own ghost cap: an even subsample of 24 of the pool
            c.set_ghosts_visible(True)
            shot("pregrasps")

            c.set_ghosts_visible(False)
            c.plan()
            if c.state.view.selected_grasp is None:
                print("no grasp was planned: grasp.png not written", file=sys.stderr)
                return 1
            c.set_anim_t(1.0)  # the closed hand (pauses the animation the plan started)
            fc = re.compile(r"^\d+ force-closure of \d+ kept$")
            page.get_by_text(fc).scroll_into_view_if_needed()
            shot("grasp")
            ctx.close()
    finally:
        app.close()
        server.stop()
    return depth_demo_shot(args.out, args.chromium) or depth_demo_shot(
        args.out, args.chromium, "completed"
    )


if __name__ == "__main__":
    sys.exit(main())
