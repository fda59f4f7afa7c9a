"""Full pipeline time against the number of points (docs/design.md, "Measured, not asserted").

For one object (default: the mug with a handle) sampled at 10^3 to 10^6 points, the time of
every stage of the whole pipeline (load, decompose, classify, facemask, pool, normals, grasps),
the pool size, the planner's throughput and its phases, and the best grasp's epsilon. One core:
BLAS on one thread, the process pinned to one CPU, the planner without a thread pool. Times are
wall-clock seconds of one run per size (the large sizes take long), after a warm-up at 1,000
points.

Usage::

    .venv/bin/python benchmarks/bench_pipeline.py [--sizes 1000 3000 10000 20000 100000 300000
        1000000] [--object assets/objects/mug_handle.obj]
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import platform  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import scipy  # noqa: E402
from _timing import pin_one_core  # noqa: E402

from pregrasp_core.hand import load_hand  # noqa: E402
from pregrasp_core.io import load_point_cloud  # noqa: E402
from pregrasp_core.paths import DEFAULT_OBJECT  # noqa: E402
from pregrasp_core.pipeline import PipelineParams, run_pipeline  # noqa: E402
from pregrasp_core.planner import PlannerParams  # noqa: E402

STAGES = ("load", "decompose", "classify", "facemask", "pool", "normals", "grasps")
PHASES = ("approach_slicing", "closing", "verification", "quality")


def run_once(path: Path, n: int, hand) -> dict:
    """The whole pipeline on ``path`` at ``n`` points: stage times and the planner's figures."""
    t0 = time.perf_counter()
    cloud = load_point_cloud(path, n_points=n, seed=0)
    t_load = time.perf_counter() - t0
    params = PipelineParams(planner=PlannerParams(threads=1))
    result = run_pipeline(cloud, params=params, hand=hand, until="grasps")
    total = time.perf_counter() - t0
    gs = result.grasps
    P = len(result.pool)
    best = gs.grasps[gs.best] if gs.best is not None else None
    return {
        "n": n,
        "times": {"load": t_load, **result.timings},
        "total": total,
        "pool": P,
        "parts": len(result.tree.leaves()),
        "rate": P / result.timings["grasps"] if result.timings["grasps"] > 0 else 0.0,
        "phases": {k: gs.phase_seconds.get(k, 0.0) / max(P, 1) for k in PHASES},
        "eps": best.epsilon if best is not None else 0.0,
        "best_type": best.grasp_type if best is not None else "-",
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument(
        "--sizes", type=int, nargs="+", default=[1000, 3000, 10000, 20000, 100000, 300000, 1000000]
    )
    ap.add_argument("--object", type=Path, default=DEFAULT_OBJECT)
    args = ap.parse_args()
    pinned = pin_one_core()
    hand = load_hand()
    print(
        f"# bench_pipeline: {args.object.name}, {platform.machine()}, Python "
        f"{platform.python_version()}, numpy {np.__version__}, scipy {scipy.__version__}, "
        f"{pinned}, {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}"
    )
    run_once(args.object, 1000, hand)  # warm-up (imports, caches)
    rows = []
    for n in args.sizes:  # loop over cloud sizes
        rows.append(run_once(args.object, n, hand))
        r = rows[-1]
        print(f"  {n} points: {r['total']:.2f} s", flush=True)

    print("\n## Full pipeline against the number of points (seconds, one core)\n")
    print("| points | " + " | ".join(STAGES) + " | total | parts | pool | pre-grasps/s | best |")
    print("|---:|" + "---:|" * (len(STAGES) + 4) + "---|")
    for r in rows:
        cells = " | ".join(f"{r['times'][s]:.3f}" for s in STAGES)
        print(
            f"| {r['n']:,} | {cells} | {r['total']:.2f} | {r['parts']} | {r['pool']} | "
            f"{r['rate']:.0f} | {r['best_type']} {r['eps']:.4f} |"
        )
    print("\n## Planner phases per pre-grasp (ms)\n")
    print("| points | " + " | ".join(PHASES) + " |")
    print("|---:|" + "---:|" * len(PHASES))
    for r in rows:
        print(f"| {r['n']:,} | " + " | ".join(f"{r['phases'][k] * 1e3:.2f}" for k in PHASES) + " |")


if __name__ == "__main__":
    main()
