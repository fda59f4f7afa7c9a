"""Quality of the planner's grasps: exact hull for every kept grasp (``--exact-all``) against
bounds with exact scores only where they decide the ranking (issue 15), side by side.

For each object (default: the default object, the mug with a handle) the planner runs once;
then, on its kept grasps (the same contacts for both), interleaved ``--repeats`` times:

* exact-all: :func:`~pregrasp_core.planner.rank.score_grasp` at the exact level for every kept
  grasp (what the planner did before issue 15 and does with ``exact_all``);
* bounded: the cheapest level for every kept grasp, then
  :func:`~pregrasp_core.planner.rank.settle_exact` (exact for the best ``exact_top`` and the best
  of each type);

and the whole ``plan_grasps`` both ways. CPU time of this process (one BLAS thread, pinned to
one CPU when the OS allows it, no thread pool), median of the repeats. It also checks that both
give the same top ``exact_top`` and the same best grasp per type. Usage::

    .venv/bin/python benchmarks/bench_quality.py [--repeats 5] [--objects mug_handle ...]
        [--points 20000] [--all]
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import platform  # noqa: E402
import statistics  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402
import scipy  # noqa: E402
from _timing import pin_one_core  # noqa: E402

from pregrasp_core.hand import load_hand  # noqa: E402
from pregrasp_core.io import load_point_cloud  # noqa: E402
from pregrasp_core.paths import DEFAULT_OBJECT, demo_objects  # noqa: E402
from pregrasp_core.pipeline import PipelineParams, run_pipeline  # noqa: E402
from pregrasp_core.planner import PlannerParams, plan_grasps, rank_grasps  # noqa: E402
from pregrasp_core.planner.rank import (  # noqa: E402
    first_level,
    quality_frame,
    score_grasp,
    settle_exact,
)
from pregrasp_core.quality import LEVEL_EXACT, QualityParams  # noqa: E402


def cpu(fn):
    t0 = time.process_time()
    out = fn()
    return time.process_time() - t0, out


def best_per_type(grasps, ranking) -> dict[str, int]:
    best: dict[str, int] = {}
    for i in ranking:
        best.setdefault(grasps[i].grasp_type, int(i))
    return best


def bench_object(path, n_points: int, repeats: int, hand) -> dict[str, object]:
    cloud = load_point_cloud(path, n_points=n_points, seed=0)
    exact_prm = PlannerParams(threads=1, quality=QualityParams(exact_all=True))
    bound_prm = PlannerParams(threads=1)
    res = run_pipeline(cloud, PipelineParams(planner=bound_prm), hand, until="grasps")
    gs = res.grasps
    q = bound_prm.quality
    frame = quality_frame(q, cloud.points)
    kept = [g for g in gs.grasps if g.kept]

    def exact_all():
        return [score_grasp(q, frame, LEVEL_EXACT, g) if g.kept else g for g in gs.grasps]

    def bounded():
        level = first_level(q, len(gs))
        first = [score_grasp(q, frame, level, g) if g.kept else g for g in gs.grasps]
        return settle_exact(first, q, frame)

    def plan(prm):
        return plan_grasps(
            cloud.points,
            res.normals,
            res.pool,
            hand,
            prm,
            support=res.masks.support if res.masks is not None else None,
        )

    t_ex, t_bd, t_pex, t_pbd = [], [], [], []
    for _ in range(repeats):  # interleaved: exact, bounded, exact plan, bounded plan
        t, ex = cpu(exact_all)
        t_ex.append(t)
        t, (bd, n_refined) = cpu(bounded)
        t_bd.append(t)
        t, _ = cpu(lambda: plan(exact_prm))
        t_pex.append(t)
        t, _ = cpu(lambda: plan(bound_prm))
        t_pbd.append(t)
    r_ex, r_bd = rank_grasps(ex), rank_grasps(bd)
    k = q.exact_top
    same = r_ex[:k].tolist() == r_bd[:k].tolist() and best_per_type(ex, r_ex) == best_per_type(
        bd, r_bd
    )
    levels = {"exact": 0, "half cones": 0, "directions": 0}
    for g in bd:
        if g.kept:
            levels[g.quality_bound or "exact"] += 1
    return {
        "object": path.stem,
        "pool": len(gs),
        "kept": len(kept),
        "hulls": sum(len(g.contacts) >= 3 for g in kept),
        "levels": levels,
        "refined": n_refined,
        "q_exact": statistics.median(t_ex),
        "q_bound": statistics.median(t_bd),
        "p_exact": statistics.median(t_pex),
        "p_bound": statistics.median(t_pbd),
        "same": same,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--points", type=int, default=20000)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--objects", nargs="*", default=None, help="object stems")
    ap.add_argument("--all", action="store_true", help="every demo object")
    args = ap.parse_args()
    pinned = pin_one_core()
    paths = [DEFAULT_OBJECT]
    if args.all:
        paths = demo_objects()
    elif args.objects:
        paths = [p for p in demo_objects() if p.stem in args.objects]
    print(
        f"# bench_quality: {platform.machine()}, Python {platform.python_version()}, numpy "
        f"{np.__version__}, scipy {scipy.__version__}, {pinned}, {args.points} points, "
        f"{args.repeats} interleaved repeats (median CPU s), "
        f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, load {os.getloadavg()[0]:.1f}"
    )
    print(
        "| object | pool | kept | hulls | exact / half cones / directions | refined | "
        "quality exact-all s | quality bounded s | speed-up | plan exact-all s | "
        "plan bounded s | same top and best per type |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    hand = load_hand()
    for path in paths:  # loop over objects
        r = bench_object(path, args.points, args.repeats, hand)
        lv = r["levels"]
        print(
            f"| {r['object']} | {r['pool']} | {r['kept']} | {r['hulls']} | "
            f"{lv['exact']} / {lv['half cones']} / {lv['directions']} | {r['refined']} | "
            f"{r['q_exact']:.3f} | {r['q_bound']:.3f} | {r['q_exact'] / r['q_bound']:.2f}x | "
            f"{r['p_exact']:.3f} | {r['p_bound']:.3f} | {'yes' if r['same'] else 'NO'} |",
            flush=True,
        )


if __name__ == "__main__":
    main()
