"""The frame cost of the viewer's hidden-space layer (``--occluded occupied``) in headless
Chromium (software WebGL), at several point sizes and shapes, interleaved.

The real app is opened on INPUT (default: the depth demo ``assets/objects/mug_depth.png``)
planned with ``--occluded occupied``, as ``benchmarks/bench_frames.py`` opens it (1400 x 900,
``?fixedDpr=1``). Per round and per variant (point size in voxels, point shape) the layer's
handle is restyled from Python (``--counts``: an even subsample of every boundary voxel, the
layer's cap left out), then the GPU process's CPU per frame is measured with the
layer shown and hidden (``bench_frames.frame_gpu_cpu_ms``: SwiftShader's work, steadier than
the wall time on a shared machine); reported: per variant the median over the rounds of the
difference, and its range.

    .venv/bin/python benchmarks/bench_hidden_layer.py [INPUT] [--rounds 4] [--frames 8]
        [--sizes 0.4 0.25] [--shapes rounded square] [--counts 0 3000]
"""

from __future__ import annotations

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse
import itertools
import platform
import re
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_frames import frame_gpu_cpu_ms, gpu_processes, set_visible  # noqa: E402

from app.headless import CHROMIUM, launch  # noqa: E402
from app.scene_data import hidden_space_points  # noqa: E402
from app.server import ViewerConfig, run  # noqa: E402
from pregrasp_core.paths import OBJECTS_DIR  # noqa: E402
from pregrasp_core.pipeline import PipelineParams  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("input", nargs="?", type=Path, default=OBJECTS_DIR / "mug_depth.png")
    ap.add_argument("--points", type=int, default=20000)
    ap.add_argument("--rounds", type=int, default=4)
    ap.add_argument("--frames", type=int, default=8)
    ap.add_argument("--sizes", type=float, nargs="+", default=[0.4, 0.25])
    ap.add_argument("--shapes", nargs="+", default=["rounded", "square"])
    ap.add_argument("--counts", type=int, nargs="+", default=[0],
                    help="points drawn (an even subsample of the layer's; 0 = all)")  # fmt: skip
    args = ap.parse_args()
    import viser
    from playwright.sync_api import sync_playwright

    print(f"# {platform.node()} {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())} "
          f"load {os.getloadavg()[0]:.1f}, {args.input.name}")  # fmt: skip
    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    config = ViewerConfig(
        input=args.input,
        n_points=args.points,
        params=PipelineParams(occluded="occupied"),
        plan_on_start=True,
    )
    app = run(config, server)
    profile = tempfile.mkdtemp(prefix="pregrasp-hidden-")
    try:
        for _ in range(1200):
            if app.controller.idle() and app.controller.state.planned:
                break
            time.sleep(0.1)
        h = app.scene.handle("hidden")
        if h is None:
            print("no hidden-space layer drawn (not a depth view?)")
            return
        voxel = float(app.controller.state.result.occupied.voxel)
        print(f"hidden-space points {app.scene.n_hidden_points_shown}, voxel {voxel * 1e3:.1f} mm")
        with sync_playwright() as p:
            ctx = launch(p, profile, CHROMIUM, viewport={"width": 1400, "height": 900})
            page = ctx.new_page()
            page.set_default_timeout(300_000)
            page.goto(f"http://127.0.0.1:{server.get_port()}/?fixedDpr=1")
            page.get_by_text(re.compile(r"^\d+ force-closure of \d+ kept$")).wait_for()
            page.wait_for_function("() => window.__viserMutable && __viserMutable.syncCanvasSize")
            gpu = gpu_processes(profile)
            # every boundary voxel (the layer's cap left out), so that a count may exceed it
            occ = app.controller.state.result.occupied
            full = hidden_space_points(occ, max_points=10**9).astype(np.float32)
            variants = list(itertools.product(args.sizes, args.shapes, args.counts))
            diffs: dict[tuple[float, str, int], list[float]] = {v: [] for v in variants}
            for _ in range(args.rounds):  # interleaved: a drift of the load touches every variant
                for size, shape, count in variants:
                    n = len(full) if count <= 0 else min(count, len(full))
                    with app.server.atomic():
                        h.point_size = size * voxel
                        h.point_shape = shape
                        h.points = full[np.linspace(0, len(full) - 1, n).astype(np.int64)]
                    with_it = frame_gpu_cpu_ms(page, gpu, args.frames)
                    set_visible(app, [h], False)
                    without = frame_gpu_cpu_ms(page, gpu, args.frames)
                    set_visible(app, [h], True)
                    diffs[(size, shape, count)].append(with_it - without)
            for (size, shape, count), d in diffs.items():
                n = len(full) if count <= 0 else min(count, len(full))
                print(f"size {size:.2f} voxel, {shape:<8} {n:6d} points "
                      f"{statistics.median(d):+6.0f} ms a frame "
                      f"(GPU CPU; rounds {', '.join(f'{x:+.0f}' for x in d)})")  # fmt: skip
            print(f"# end load {os.getloadavg()[0]:.1f}")
            ctx.close()
    finally:
        app.close()
        server.stop()
        shutil.rmtree(profile, ignore_errors=True)


if __name__ == "__main__":
    main()
