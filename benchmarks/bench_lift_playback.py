"""The viewer's "simulate lift" button in the real app (issue 11; ``docs/benchmarks.md``).

Builds the app on a real ``ViserServer`` (no browser) as ``pregrasp view`` does (default object,
20,000 points), plans, then presses simulate (``Controller.simulate``, what the button calls) on
each of the best ``--top`` grasps in turn. Per press: the seconds from the press until the
scene has drawn the lift's first frame (``SceneRenderer.rendered`` shows it: the poses are then
on their way to the browsers), the CPU seconds of the worker thread building the object's
scene (the first press only: it is kept for the next) and of the simulated run, the frames
recorded and the outcome. One core: BLAS on one thread, the process pinned to one CPU.

Usage::

    .venv/bin/python benchmarks/bench_lift_playback.py [INPUT] [--top 5] [--points 20000]
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import datetime  # noqa: E402
import platform  # noqa: E402
import statistics  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

from _timing import pin_one_core  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from app.scene_data import ranked_grasps  # noqa: E402
from app.server import ViewerConfig, run  # noqa: E402
from app.simulate_view import lift_frame  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("input", nargs="?", type=Path)
    ap.add_argument("--top", type=int, default=5)
    ap.add_argument("--points", type=int, default=20000)
    args = ap.parse_args()
    pin_one_core()
    import viser

    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    app = run(ViewerConfig(input=args.input, n_points=args.points), server)
    c = app.controller
    rows = []
    try:
        c.plan()
        name = c.state.source.name
        n = min(args.top, len(ranked_grasps(c.state.result)))
        for k in range(n):
            c.select_grasp(k)
            t0 = time.perf_counter()
            c.simulate()
            while True:
                f = lift_frame(app.scene.rendered) if app.scene.rendered is not None else None
                if f is not None and f.playback.rank == k:
                    break
                if not c.lift.running and c.state.error:
                    raise SystemExit(f"grasp #{k + 1}: {c.state.error}")
                time.sleep(0.002)
            first = time.perf_counter() - t0
            c.lift.wait()
            pb = f.playback
            rows.append((k, first, pb, pb.outcome))
    finally:
        app.close()
        server.stop()
    now = datetime.datetime.now(datetime.UTC)
    cpu = platform.processor() or platform.machine()
    print(
        f"# {now:%Y-%m-%d %H:%M} UTC, {cpu}, Python {platform.python_version()}, object "
        f"{name}, {args.points} points, one core, load average {os.getloadavg()[0]:.1f}"
    )
    print(
        "| grasp | outcome | press to first frame (s) | build CPU (s) | run CPU (s) | frames "
        "| simulated (s) |"
    )
    print("|---|---|---|---|---|---|---|")
    for k, first, pb, res in rows:
        print(
            f"| #{k + 1} | {res.outcome} | {first:.2f} | {pb.build_cpu:.2f} | {pb.run_cpu:.3f} | "
            f"{len(pb.times)} | {pb.duration:.2f} |"
        )
    warm = [first for _, first, pb, _ in rows if pb.build_cpu == 0.0]
    runs = [pb.run_cpu for _, _, pb, _ in rows]
    if warm:
        med, top = statistics.median(warm), max(warm)
        print(f"\nwarm press to first frame: median {med:.2f} s, max {top:.2f} s")
    print(f"run CPU per grasp: median {statistics.median(runs):.3f} s, max {max(runs):.3f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
