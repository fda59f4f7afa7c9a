"""The page's cost of drawing the viewer's scene in headless Chromium (software WebGL), layer by
layer, and chromium's CPU time while it is idle and while a grasp is chosen.

The real app (as the browser tests start it: plan on start, ghosts off) is opened in headless
Chromium (``app.headless``, 1400 x 900, at a fixed pixel ratio of 1: ``?fixedDpr=1``, since
viser otherwise lowers the resolution while frames are slow). A frame is drawn synchronously in
the page with viser's ``window.__viserMutable.syncCanvasSize`` followed by a 1-pixel
``readPixels``, so that SwiftShader has finished it when the clock stops. Reported: the median
of ``--frames`` such frames on the first screen; per layer, the median over ``--pairs`` of the
difference between a frame with it and one without it (hidden from Python through the scene's
handles; in pairs, so that a change of the machine's load cancels); the frame with every layer
hidden; the GPU process's CPU time per frame of the first screen (SwiftShader's work, steadier
than the wall time on a shared machine). Chromium's CPU time is the sum of utime + stime of
the processes started with the run's own profile directory (``/proc`` via psutil), idle and
while a grasp is chosen.

    .venv/bin/python benchmarks/bench_frames.py [INPUT] [--occluded occupied] [--points 5000]
        [--frames 5] [--idle 10] [--animate-hz HZ] [--shot first_screen.png]

INPUT: the object to open (default: the mug); a depth view with ``--occluded occupied`` adds
the ``hidden`` layer (the hidden space, ``app/scene.py``).
"""

from __future__ import annotations

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse
import platform
import re
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

import psutil

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from app.headless import CHROMIUM, launch  # noqa: E402
from app.server import ViewerConfig, run  # noqa: E402

FRAME_JS = """() => {
  const m = window.__viserMutable;
  const c = [...document.querySelectorAll('canvas')].sort((a, b) => b.width - a.width)[0];
  const gl = c.getContext('webgl2') || c.getContext('webgl');
  const px = new Uint8Array(4);
  const t0 = performance.now();
  m.syncCanvasSize(c.clientWidth, c.clientHeight);
  gl.readPixels(0, 0, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, px);
  return [performance.now() - t0, c.width, c.height];
}"""
"""One frame drawn synchronously and finished (ms), and the drawing buffer's size."""

LAYERS = ("cloud", "boxes", "box_edges", "faces_free", "faces_blocked", "subfaces", "hand_frame",
          "contacts", "cones", "table", "scene", "hidden")  # fmt: skip
"""Scene layers toggled one by one (``boxes``: every box node)."""


def chromium_cpu(profile: str) -> float:
    """CPU seconds (user + system) of every process started with this profile directory."""
    total = 0.0
    for p in psutil.process_iter(["cmdline"]):
        try:
            cmd = p.info["cmdline"] or []
            if any(profile in a for a in cmd) or _parent_has(p, profile):
                t = p.cpu_times()
                total += t.user + t.system
        except (psutil.NoSuchProcess, psutil.AccessDenied):
            continue
    return total


def _parent_has(p: psutil.Process, profile: str) -> bool:
    try:
        for parent in p.parents():
            if any(profile in a for a in (parent.cmdline() or [])):
                return "chrom" in (p.name() or "")
    except (psutil.NoSuchProcess, psutil.AccessDenied):
        pass
    return False


def handles(app, layer: str) -> list:
    if layer == "boxes":
        return list(app.scene._boxes.values())
    h = app.scene.handle(layer)
    return [] if h is None else [h]


def set_visible(app, hs, visible: bool) -> None:
    with app.server.atomic():
        for h in hs:
            h.visible = visible


def gpu_processes(profile: str) -> list[psutil.Process]:
    """Chromium's GPU process(es) of this profile (where SwiftShader draws the WebGL frames)."""
    out = []
    for p in psutil.process_iter(["cmdline"]):
        try:
            cmd = p.info["cmdline"] or []
            if any("--type=gpu-process" in a for a in cmd) and _parent_has(p, profile):
                out.append(p)
        except (psutil.NoSuchProcess, psutil.AccessDenied):
            continue
    return out


def frame_ms(page, n: int) -> float:
    page.wait_for_timeout(1000)  # the visibility messages arrive and are applied
    ms = [page.evaluate(FRAME_JS)[0] for _ in range(n)]
    return statistics.median(ms)


def frame_gpu_cpu_ms(page, gpu: list[psutil.Process], n: int) -> float:
    """CPU milliseconds of the GPU process per frame, over ``n`` frames drawn back to back:
    the frame's work, which other jobs on a busy machine change far less than its wall time
    (docs/benchmarks.md, "Session 8: viewer")."""

    def cpu() -> float:
        return sum(t.user + t.system for t in (p.cpu_times() for p in gpu))

    page.wait_for_timeout(1000)
    c0 = cpu()
    for _ in range(n):
        page.evaluate(FRAME_JS)
    return (cpu() - c0) / n * 1000.0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument(
        "input",
        nargs="?",
        type=Path,
        default=None,
        help="object to open (default: the mug); e.g. assets/objects/mug_depth.png",
    )
    ap.add_argument(
        "--occluded",
        choices=("auto", "completed", "occupied"),
        default="auto",
        help="a single view's hidden space (auto, the default, or occupied: drawn as the "
        "'hidden' layer when the plan kept the hand out of it)",
    )
    ap.add_argument("--points", type=int, default=5000)
    ap.add_argument("--frames", type=int, default=5)
    ap.add_argument("--pairs", type=int, default=3, help="with/without pairs per layer")
    ap.add_argument("--idle", type=float, default=10.0, help="seconds of idle CPU measured")
    ap.add_argument("--gpu-layers", nargs="*", default=(), metavar="LAYER",
                    help="layers whose cost is also measured as the GPU process's CPU per frame "
                    "(e.g. hidden cloud)")  # fmt: skip
    ap.add_argument("--animate-hz", type=float, default=None, help="the animation clock's rate")
    ap.add_argument("--shot", type=Path, default=None, help="save the first screen as PNG")
    args = ap.parse_args()
    import viser
    from playwright.sync_api import sync_playwright

    print(f"# {platform.node()} {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())} "
          f"load {os.getloadavg()[0]:.1f}, {args.points} points")  # fmt: skip
    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    extra = {} if args.animate_hz is None else {"animate_hz": args.animate_hz}
    from pregrasp_core.pipeline import PipelineParams

    params = PipelineParams(occluded=args.occluded)
    app = run(ViewerConfig(input=args.input, n_points=args.points, params=params,
                           plan_on_start=True, **extra), server)  # fmt: skip
    profile = tempfile.mkdtemp(prefix="pregrasp-frames-")
    try:
        for _ in range(1200):
            if app.controller.idle() and app.controller.state.planned:
                break
            time.sleep(0.1)
        with sync_playwright() as p:
            ctx = launch(p, profile, CHROMIUM, viewport={"width": 1400, "height": 900})
            page = ctx.new_page()
            page.set_default_timeout(300_000)
            t0, c0 = time.perf_counter(), chromium_cpu(profile)
            # a fixed pixel ratio: viser's adaptive one lowers the resolution of slow frames
            page.goto(f"http://127.0.0.1:{server.get_port()}/?fixedDpr=1")
            page.get_by_text(re.compile(r"^\d+ force-closure of \d+ kept$")).wait_for()
            page.wait_for_function("() => window.__viserMutable && __viserMutable.syncCanvasSize")
            print(f"page to the first screen's text: {time.perf_counter() - t0:.1f} s, "
                  f"chromium CPU {chromium_cpu(profile) - c0:.1f} s")  # fmt: skip
            size = page.evaluate(FRAME_JS)[1:]
            s = app.scene
            n_cloud = len(app.controller.state.cloud.points)
            print(f"canvas {size[0]} x {size[1]}; boxes {s.n_boxes}, faces {s.n_faces_shown}, "
                  f"points {n_cloud}, scene points {s.n_scene_points_shown}, "
                  f"hidden-space points {s.n_hidden_points_shown}")  # fmt: skip
            full = frame_ms(page, args.frames)
            if args.shot is not None:
                page.screenshot(path=str(args.shot))
            print(f"{'first screen':<24} {full:8.0f} ms")
            gpu = gpu_processes(profile)
            if gpu:
                cpus = [frame_gpu_cpu_ms(page, gpu, 2 * args.frames) for _ in range(3)]
                print(f"{'first screen, GPU CPU':<24} {statistics.median(cpus):8.0f} ms a frame "
                      f"(runs {', '.join(f'{c:.0f}' for c in cpus)})")  # fmt: skip
            for layer in LAYERS:
                hs = handles(app, layer)
                if not hs:
                    print(f"{layer:<24} (not drawn)")
                    continue
                diffs = []  # pairs with and without, so that a drift of the load cancels
                for _ in range(args.pairs):
                    with_it = frame_ms(page, args.frames)
                    set_visible(app, hs, False)
                    diffs.append(with_it - frame_ms(page, args.frames))
                    set_visible(app, hs, True)
                print(f"{layer:<24} {statistics.median(diffs):+8.0f} ms  "
                      f"(pairs {', '.join(f'{d:+.0f}' for d in diffs)})")  # fmt: skip
                if gpu and layer in args.gpu_layers:  # the GPU process's CPU, in pairs too
                    cd = []
                    for _ in range(args.pairs):
                        with_it = frame_gpu_cpu_ms(page, gpu, 2 * args.frames)
                        set_visible(app, hs, False)
                        cd.append(with_it - frame_gpu_cpu_ms(page, gpu, 2 * args.frames))
                        set_visible(app, hs, True)
                    print(f"{layer + ', GPU CPU':<24} {statistics.median(cd):+8.0f} ms a frame "
                          f"(pairs {', '.join(f'{d:+.0f}' for d in cd)})")  # fmt: skip
            every = [h for layer in LAYERS for h in handles(app, layer)]
            set_visible(app, every, False)
            print(f"{'every layer hidden':<24} {frame_ms(page, args.frames):8.0f} ms")
            set_visible(app, every, True)
            page.wait_for_timeout(2000)
            c0 = chromium_cpu(profile)
            page.wait_for_timeout(args.idle * 1000)
            idle = (chromium_cpu(profile) - c0) / args.idle
            print(f"idle page: chromium CPU {idle:.2f} s per s")
            c0, t0 = chromium_cpu(profile), time.perf_counter()
            app.controller.select_grasp(1)
            for _ in range(600):
                st = app.controller.state
                if not st.view.playing and app.scene.rendered is st:
                    break
                time.sleep(0.05)
            page.evaluate("() => 0")
            page.wait_for_timeout(3000)
            print(f"grasp choice + 3 s: chromium CPU {chromium_cpu(profile) - c0:.1f} s "
                  f"(wall {time.perf_counter() - t0:.1f} s)")  # fmt: skip
            ctx.close()
    finally:
        app.close()
        server.stop()
        shutil.rmtree(profile, ignore_errors=True)


if __name__ == "__main__":
    main()
