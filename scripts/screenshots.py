"""Take the documentation screenshots from the real app in headless Chromium.

Starts the app on a free port (default object unless INPUT is given), opens it in Debian's
Chromium through Python playwright, sets up each view through the app's controller (the same
actions the GUI runs) and saves ``docs/screenshots/{decomposition,face_masks,pregrasps,
grasp}.png``.

    .venv/bin/python scripts/screenshots.py [INPUT] [--out docs/screenshots] [--points 20000]
"""

from __future__ import annotations

import argparse
import re
import sys
import tempfile
import time
from pathlib import Path

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
        cam.position = cam.look_at + factor * (cam.position - cam.look_at)


def main() -> int:
    ap = argparse.ArgumentParser(description="documentation screenshots of the real app")
    ap.add_argument("input", nargs="?", type=Path, help="object to show (default: the mug)")
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "screenshots")
    ap.add_argument("--points", type=int, default=20000)
    ap.add_argument("--chromium", default=CHROMIUM)
    args = ap.parse_args()

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
                page.screenshot(path=str(path), timeout=180_000)
                print(f"wrote {path.relative_to(ROOT) if path.is_relative_to(ROOT) else path}")

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
    return 0


if __name__ == "__main__":
    sys.exit(main())
