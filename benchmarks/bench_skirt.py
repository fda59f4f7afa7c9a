"""Time of the skirt (``completion.add_skirt``) against the whole completion, per view.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/bench_skirt.py [--objects A,B]

Each demo mesh is rendered from ``bench_odd_views.py``'s ``top85`` camera (a view from above:
a skirt) and its ``low12`` camera (a side view: the early return), its table segmented
(``segment_table``) and its object completed (``complete_view``, once, timed); then
``add_skirt`` is timed alone on the same range image (mean of 3 calls). Columns: seen object
points, skirt points, the completion's time and the skirt's, in milliseconds of one core.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # one BLAS thread, before numpy loads

import argparse  # noqa: E402
import platform  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import trimesh  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # this checkout's pregrasp_core, not an installed one
sys.path.insert(0, str(ROOT / "benchmarks"))

import bench_odd_views as odd  # noqa: E402

from pregrasp_core.paths import OBJECTS_DIR, demo_objects  # noqa: E402
from pregrasp_core.sensor import completion, segment_table  # noqa: E402

REPEAT: int = 3
"""Calls of ``add_skirt`` averaged per view."""


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--objects", default=None, help="comma-separated demo objects (default all)")
    args = ap.parse_args()
    names = args.objects.split(",") if args.objects else [p.stem for p in demo_objects()]
    mv = odd.MAKE_VIEWS
    print(f"# {platform.machine()}, {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, "
          f"load {os.getloadavg()[0]:.2f}")  # fmt: skip
    print("| object | camera | seen | skirt points | completion (ms) | skirt (ms) |")
    print("|---|---|---:|---:|---:|---:|")
    times: dict[str, list[tuple[float, float]]] = {"top85": [], "low12": []}
    for name in names:  # loop over the demo objects
        mesh = trimesh.load(OBJECTS_DIR / f"{name}.obj", force="mesh")
        _, _, table_half = mv.view_setup(mesh)
        for case in times:  # loop over the two cameras
            elevation, factor, border, noise = odd.CAMERAS[case]
            T = odd.camera(mesh, elevation, factor, border)
            view = odd.render_view(mesh.vertices, mesh.faces, T, mv.INTRINSICS, mv.WIDTH,
                                   mv.HEIGHT, table_half=table_half, noise=noise,
                                   rng=np.random.default_rng(3))  # fmt: skip
            pts, _ = view.points_world()
            seg = segment_table(pts, viewpoint=T[:3, 3])
            obj = seg.object_points
            t0 = time.perf_counter()
            done = completion.complete_view(obj, T[:3, 3], seg.plane)
            t_done = time.perf_counter() - t0
            vis = completion.RangeImage(obj, T[:3, 3], seg.plane)
            rest = done.points[~done.skirt]
            t0 = time.perf_counter()
            for _ in range(REPEAT):  # loop over a few repeats
                completion.add_skirt(obj, rest, vis, completion.CompletionParams())
            t_skirt = (time.perf_counter() - t0) / REPEAT
            times[case].append((t_done, t_skirt))
            print(f"| {name} | {case} | {len(obj)} | {int(done.skirt.sum())} | "
                  f"{1e3 * t_done:.0f} | {1e3 * t_skirt:.1f} |", flush=True)  # fmt: skip
    print("\n| camera | views | completion median (ms) | skirt median (ms) | skirt max (ms) |")
    print("|---|---:|---:|---:|---:|")
    for case, tt in times.items():
        a = np.array(tt)
        print(f"| {case} | {len(a)} | {1e3 * np.median(a[:, 0]):.0f} | "
              f"{1e3 * np.median(a[:, 1]):.1f} | {1e3 * a[:, 1].max():.1f} |")  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
