"""Planner throughput and the full pipeline per object (issue 5).

Prints, for every object of ``assets/objects`` at ``--points`` points (default 20,000):

1. the full pipeline time (load, decompose, classify, facemask, pool, normals, grasps) and the
   planner's throughput (pre-grasps planned per second: approach, slicing, closing, 3D
   verification, contacts and quality, every pre-grasp of the pool);
2. the best grasp per object (type, contacts, epsilon) and whether it is force closure, with
   the count over the objects;
3. for the default object (the mug with a handle), the best grasp of each grasp type, i.e. why
   the best grasp has its type;
4. the cost of the quality measure alone (6D qhull) against the number of contacts.

Runs on one core (BLAS pinned to 1 thread, the process pinned to one CPU when the OS allows
it, no thread pool); ``--threads T`` instead runs unpinned with the planner's per-pre-grasp
phases on T threads (``PlannerParams.threads``). Usage::

    .venv/bin/python benchmarks/bench_planner.py [--points 20000] [--repeats 1] [--objects a b]
        [--threads 1] [--edges 8]
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import platform  # noqa: E402
import statistics  # noqa: E402
import time  # noqa: E402
from collections import defaultdict  # noqa: E402

import numpy as np  # noqa: E402
import scipy  # noqa: E402
from _timing import pin_one_core  # noqa: E402

from pregrasp_core.hand import load_hand  # noqa: E402
from pregrasp_core.io import load_point_cloud  # noqa: E402
from pregrasp_core.paths import DEFAULT_OBJECT, demo_objects  # noqa: E402
from pregrasp_core.pipeline import PipelineParams, run_pipeline  # noqa: E402
from pregrasp_core.planner import PlannerParams  # noqa: E402
from pregrasp_core.quality import QualityParams, grasp_quality  # noqa: E402


def bench_objects(paths, n_points: int, repeats: int, threads: int = 1, edges: int = 8):
    hand = load_hand()
    rows = []
    mug = None
    for path in paths:  # loop over objects
        best_run = None
        for _ in range(repeats):
            t0 = time.perf_counter()
            cloud = load_point_cloud(path, n_points=n_points, seed=0)
            t_load = time.perf_counter() - t0
            quality = QualityParams(n_edges=edges)
            params = PipelineParams(planner=PlannerParams(threads=threads, quality=quality))
            result = run_pipeline(cloud, params=params, hand=hand, until="grasps")
            total = time.perf_counter() - t0
            timings = {"load": t_load, **result.timings}
            if best_run is None or total < best_run[0]:
                best_run = (total, timings, result)
        total, timings, result = best_run
        gs = result.grasps
        best = gs.grasps[gs.best] if gs.best is not None else None
        rows.append(
            {
                "object": path.stem,
                "parts": len(result.tree.leaves()),
                "pool": len(result.pool),
                "kept": len(gs.ranking),
                "fc": gs.n_force_closure,
                "t_pool": sum(timings[k] for k in ("decompose", "classify", "facemask", "pool")),
                "t_normals": timings["normals"],
                "t_grasps": timings["grasps"],
                "total": total,
                "rate": len(result.pool) / timings["grasps"] if timings["grasps"] > 0 else 0.0,
                "best_type": best.grasp_type if best else "-",
                "best_contacts": best.n_contacts if best else 0,
                "best_eps": best.epsilon if best else 0.0,
                "rejected": {k: v for k, v in gs.rejected.items() if v},
                "phases": dict(gs.phase_seconds),
                "kept_contacts": [g.n_contacts for g in gs.ranked],
            }
        )
        if path.resolve() == DEFAULT_OBJECT.resolve():
            mug = result
    return rows, mug


def bench_quality(repeats: int = 30, edges: tuple[int, ...] = (4, 6, 8)):
    """Median time of grasp_quality for 2 to 7 random contacts on a sphere, per cone edges m."""
    rng = np.random.default_rng(0)
    out = []
    for k in (2, 3, 4, 5, 6, 7):
        times: dict[int, list[float]] = {m: [] for m in edges}
        for _ in range(repeats):
            p = rng.normal(size=(k, 3))
            p /= np.linalg.norm(p, axis=1, keepdims=True)
            p *= 0.04
            n = -p / 0.04 + rng.normal(scale=0.2, size=(k, 3))
            for m in edges:  # the same contacts for every m
                prm = QualityParams(n_edges=m)
                t0 = time.perf_counter()
                grasp_quality(p, n, prm)
                times[m].append(time.perf_counter() - t0)
        out.append((k, [statistics.median(times[m]) for m in edges]))
    return edges, out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--points", type=int, default=20000)
    ap.add_argument("--repeats", type=int, default=1, help="runs per object (the fastest kept)")
    ap.add_argument("--objects", nargs="*", default=None, help="object stems (default: all)")
    ap.add_argument(
        "--threads",
        type=int,
        default=1,
        help="1 (default): one CPU, no thread pool (the one-core figure); T > 1: not pinned, "
        "the per-pre-grasp phases on T threads (PlannerParams.threads)",
    )
    ap.add_argument(
        "--edges", type=int, default=8, help="friction cone edges m (default 8, docs/quality.md)"
    )
    args = ap.parse_args()
    pinned = pin_one_core() if args.threads == 1 else f"not pinned, {args.threads} threads"
    paths = demo_objects()
    if args.objects:
        paths = [p for p in paths if p.stem in args.objects]
    print(
        f"# bench_planner: {platform.machine()}, Python {platform.python_version()}, numpy "
        f"{np.__version__}, scipy {scipy.__version__}, {pinned}, {args.points} points, "
        f"m = {args.edges}, "
        f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}"
    )
    rows, mug = bench_objects(paths, args.points, args.repeats, args.threads, args.edges)

    print("\n## Full pipeline and planner throughput per object\n")
    print(
        "| object | parts | pool | kept | force closure | pool stages s | normals s | "
        "planner s | pre-grasps/s | total s |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(
            f"| {r['object']} | {r['parts']} | {r['pool']} | {r['kept']} | {r['fc']} | "
            f"{r['t_pool']:.3f} | {r['t_normals']:.3f} | {r['t_grasps']:.3f} | "
            f"{r['rate']:.0f} | {r['total']:.3f} |"
        )
    n_pre = sum(r["pool"] for r in rows)
    t_plan = sum(r["t_grasps"] for r in rows)
    totals = [r["total"] for r in rows]
    print(
        f"\nall objects: {n_pre} pre-grasps planned in {t_plan:.2f} s = "
        f"{n_pre / max(t_plan, 1e-9):.0f} pre-grasps/s; full pipeline per object: median "
        f"{statistics.median(totals):.2f} s, max {max(totals):.2f} s"
    )

    print("\n## Where the planner's time goes (all objects)\n")
    phases = defaultdict(float)
    for r in rows:
        for k, v in r["phases"].items():
            phases[k] += v
    total_ph = sum(phases.values())
    print("| phase | s | ms per pre-grasp | share |")
    print("|---|---|---|---|")
    for k, v in phases.items():
        print(f"| {k} | {v:.2f} | {v / n_pre * 1e3:.2f} | {v / max(total_ph, 1e-9):.0%} |")
    if args.threads == 1:
        t_noq = total_ph - phases.get("quality", 0.0)
        n_kept = sum(len(r["kept_contacts"]) for r in rows)
        t_q = phases.get("quality", 0.0)
        print(
            f"\nwithout the quality measure: {n_pre / max(t_noq, 1e-9):.0f} pre-grasps/s; the 6D "
            f"hull alone ({n_kept} kept grasps, {t_q / max(n_kept, 1) * 1e3:.2f} ms each on "
            f"average) caps the planner at {n_pre / max(t_q, 1e-9):.0f} pre-grasps/s on one core"
        )

    print("\n## Best grasp per object\n")
    print("| object | best type | contacts | epsilon | force closure | rejected |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        rej = ", ".join(f"{k} {v}" for k, v in r["rejected"].items()) or "-"
        print(
            f"| {r['object']} | {r['best_type']} | {r['best_contacts']} | {r['best_eps']:.4f} | "
            f"{'yes' if r['best_eps'] > 0 else 'no'} | {rej} |"
        )
    n_fc = sum(r["best_eps"] > 0 for r in rows)
    print(f"\nbest grasp force closure on {n_fc} of {len(rows)} objects")

    if mug is not None:
        print(f"\n## {DEFAULT_OBJECT.stem}: best grasp of each type\n")
        per_type: dict[str, list] = defaultdict(list)
        for g in mug.grasps.ranked:
            per_type[g.grasp_type].append(g)
        pool_types = dict(zip(*np.unique(mug.pool.grasp_type, return_counts=True), strict=True))
        print("| type | pre-grasps | kept | force closure | best epsilon | contacts | links |")
        print("|---|---|---|---|---|---|---|")
        for t in sorted(pool_types, key=lambda t: -(per_type[t][0].epsilon if per_type[t] else 0)):
            gl = per_type[t]
            b = gl[0] if gl else None
            print(
                f"| {t} | {pool_types[t]} | {len(gl)} | {sum(g.epsilon > 0 for g in gl)} | "
                f"{b.epsilon if b else 0:.4f} | {b.n_contacts if b else 0} | "
                f"{', '.join(c.link for c in b.contacts) if b else '-'} |"
            )
        nodes = sorted(set(int(n) for n in mug.pool.node))
        print(
            f"\npool nodes: {nodes}; node grasp types: "
            + ", ".join(f"{i}: {mug.shapes[i].grasp_type.value}" for i in nodes)
        )

    edges, rows = bench_quality()
    print("\n## Quality measure alone (6D qhull; median ms per grasp; m = cone edges)\n")
    print("| contacts | " + " | ".join(f"m = {m}" for m in edges) + " |")
    print("|---|" + "---|" * len(edges))
    for k, ts in rows:
        print(f"| {k} | " + " | ".join(f"{t * 1e3:.2f}" for t in ts) + " |")


if __name__ == "__main__":
    main()
