"""An animated picture of a simulated lift in the real app (``docs/screenshots/lift.gif``).

Starts the app on a free port (default object unless INPUT is given), opens it in Debian's
Chromium through Python playwright, plans, presses the page's **simulate lift** button on the
best grasp (and on the next ones until one lifts), then steps the lift's playback clock frame by
frame through the controller (the same clock the animator advances), screenshots the page at
each frame and writes them as a looping GIF at the recorded frame rate (real time).

    .venv/bin/python scripts/capture_lift.py [INPUT] [--out docs/screenshots/lift.gif]
        [--points 20000] [--width 720]
"""

from __future__ import annotations

import argparse
import io
import re
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from app.headless import CHROMIUM, launch  # noqa: E402 (the repository on the path first)

VIEWPORT = {"width": 1500, "height": 760}
"""Browser window of the capture (the picture is scaled down to ``--width``)."""
ZOOM = 2.3
"""The camera this many times as far from the object as the app frames it at load, so that the
hand's approach and the 10 cm lift stay in view."""


def _frames_drawn(page, n: int = 3) -> None:
    for _ in range(n):
        page.evaluate(
            "() => new Promise(r => requestAnimationFrame(() => requestAnimationFrame(r)))"
        )


def _close_notifications(page, timeout_s: float = 60.0) -> None:
    """Close the browser's notifications ('software WebGL') so they do not cover the view."""
    deadline = time.monotonic() + timeout_s
    while page.locator(".mantine-Notification-root").count():
        if time.monotonic() > deadline:
            texts = page.locator(".mantine-Notification-root").all_inner_texts()
            print(f"a notification does not close: {texts}", file=sys.stderr)
            return
        for btn in page.locator(".mantine-Notification-closeButton").all():
            try:
                btn.click(timeout=2000, force=True)
            except Exception:  # noqa: BLE001 - it may close by itself meanwhile
                pass
        page.wait_for_timeout(500)


def _wait(pred, what: str, timeout_s: float = 180.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not pred():
        if time.monotonic() > deadline:
            raise TimeoutError(what)
        time.sleep(0.05)


def main() -> int:
    ap = argparse.ArgumentParser(description="animated picture of a simulated lift in the app")
    ap.add_argument("input", nargs="?", type=Path, help="object to show (default: the mug)")
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "screenshots" / "lift.gif")
    ap.add_argument("--points", type=int, default=20000)
    ap.add_argument("--width", type=int, default=720, help="width of the picture (pixels)")
    ap.add_argument("--tries", type=int, default=5, help="grasps tried until one lifts")
    ap.add_argument("--chromium", default=CHROMIUM)
    args = ap.parse_args()

    import numpy as np
    import viser
    from PIL import Image
    from playwright.sync_api import sync_playwright

    from app.scene_data import ranked_grasps
    from app.server import ViewerConfig, run
    from app.simulate_view import shown_playback

    args.out.parent.mkdir(parents=True, exist_ok=True)
    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    app = run(ViewerConfig(input=args.input, n_points=args.points), server)
    c = app.controller
    try:
        with sync_playwright() as p:
            ctx = launch(p, tempfile.mkdtemp(prefix="pregrasp-lift-"), args.chromium,
                         viewport=VIEWPORT)  # fmt: skip
            page = ctx.new_page()
            page.set_default_timeout(180_000)
            page.goto(f"http://127.0.0.1:{server.get_port()}")
            page.get_by_text(re.compile(r"^boxes: \d+$")).wait_for()
            _close_notifications(page)
            c.set_face_masks_visible(False)
            c.plan()
            ranked = ranked_grasps(c.state.result)
            button = page.get_by_role("button", name="simulate lift")
            outcome = re.compile(r"^lift of grasp #\d+: (lifted|slipped|dropped|unstable)$")
            for k in range(min(args.tries, len(ranked))):
                c.select_grasp(k)
                _wait(lambda: button.is_enabled(), "the simulate button stays disabled")
                button.click()
                page.get_by_text(outcome).wait_for()
                _wait(lambda: not c.lift.running, "the lift does not finish")
                pb = shown_playback(c.state)
                print(f"grasp #{k + 1}: {pb.outcome.outcome}")
                if pb.outcome.success:
                    break
            else:
                print("no grasp lifted: the picture shows the last one", file=sys.stderr)
            c.lift.seek(0.0)
            # frame the lift: the object and the space above it, a little farther than at load
            up = np.array([0.0, 0.0, 0.02])
            for client in server.get_clients().values():
                cam = client.camera
                target = np.asarray(cam.look_at) + up
                cam.look_at, cam.position = target, target + ZOOM * (cam.position - cam.look_at)
            page.get_by_text(outcome).scroll_into_view_if_needed()
            _close_notifications(page)
            pb = shown_playback(c.state)
            images = []
            for t in pb.times:
                c.lift.seek(float(t))
                _wait(lambda: app.scene.rendered is c.state, "the scene does not draw the frame")
                page.wait_for_timeout(150)  # the poses reach the page
                _frames_drawn(page)
                png = page.screenshot(timeout=180_000)
                img = Image.open(io.BytesIO(png)).convert("RGB")
                h = round(img.height * args.width / img.width)
                images.append(img.resize((args.width, h), Image.LANCZOS))
            ctx.close()
    finally:
        app.close()
        server.stop()
    palette = images[len(images) // 2].quantize(colors=128, method=Image.Quantize.MEDIANCUT)
    frames = [im.quantize(palette=palette, dither=Image.Dither.NONE) for im in images]
    ms = [round(1000 * float(d)) for d in np.diff(pb.times)] + [1500]  # real time, then a rest
    frames[0].save(args.out, save_all=True, append_images=frames[1:], duration=ms, loop=0,
                   optimize=True, disposal=1)  # fmt: skip
    size = args.out.stat().st_size
    shown = args.out.relative_to(ROOT) if args.out.is_relative_to(ROOT) else args.out
    print(f"wrote {shown}: {len(frames)} frames, {size / 1e6:.2f} MB, {pb.outcome.outcome}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
