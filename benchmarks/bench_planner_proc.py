"""The viewer's planner alone: ``plan_grasps`` on the server's threads against the planner
process (``app/planner_proc.py``), alternating in one run.

The default object (the mug with a handle) at each ``--points``, its pool and normals computed
once; then, ``--rounds`` times, one plan each way: "threads" = ``plan_grasps`` in this process
with another thread alive (as in the viewer's server, where it cannot fork and runs its chunks on
a thread pool), "process" = ``PlannerProcess.plan`` (the worker forks its copy and plans on two
processes; the inputs and the ``GraspSet`` go through pipes). Wall seconds of each plan as the
caller sees it, and CPU seconds of this process plus the worker and its forked copies
(``/proc/PID/stat``, the copies reaped by the worker); min and median. The grasps of both are
checked to be the same (ranking, scores).

``--cli``: instead, what ``pregrasp plan`` does in a process of one thread: "one" =
``plan_grasps`` with ``threads=1``, "forked" = ``threads=2`` (this process and a forked copy;
CPU with the copy's, ``os.times``), alternating; no planner process.

    .venv/bin/python benchmarks/bench_planner_proc.py [--points 20000 5000] [--rounds 7] [--cli]
"""

from __future__ import annotations

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse
import dataclasses
import functools
import platform
import statistics
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from app.planner_proc import PlannerProcess  # noqa: E402
from pregrasp_core import io as pio  # noqa: E402
from pregrasp_core import pipeline as ppl  # noqa: E402
from pregrasp_core.hand import Hand  # noqa: E402
from pregrasp_core.paths import DEFAULT_OBJECT  # noqa: E402
from pregrasp_core.planner import plan_grasps  # noqa: E402


def _cpu(pid: int | None) -> float:
    """Seconds of processor time of ``pid`` and its reaped children (0 for None)."""
    if pid is None:
        return 0.0
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return sum(int(f) for f in fields[11:15]) / os.sysconf("SC_CLK_TCK")


def _own_cpu() -> float:
    """Seconds of processor time of this process and its reaped children (forked copies)."""
    t = os.times()
    return t.user + t.system + t.children_user + t.children_system


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=int, nargs="+", default=[20000, 5000])
    ap.add_argument("--rounds", type=int, default=7)
    ap.add_argument("--cli", action="store_true", help="one process against the forked plan")
    args = ap.parse_args()
    print(
        f"# {platform.machine()}, Python {platform.python_version()}, numpy {np.__version__}, "
        f"{os.cpu_count()} CPUs, {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, "
        f"load {os.getloadavg()[0]:.1f}"
    )
    pp = None if args.cli else PlannerProcess()
    hand = Hand.load()
    alive = threading.Event()
    if not args.cli:  # a server thread: no fork here
        threading.Thread(target=alive.wait, daemon=True).start()
    print("| points | pool | way | wall min (s) | wall median (s) | CPU min (s) | CPU median (s) "
          "| load |")  # fmt: skip
    print("|---:|---:|---|---:|---:|---:|---:|---|")
    try:
        if pp is not None and not pp.wait_ready():
            raise SystemExit("the planner process did not start")
        for n in args.points:
            cloud = pio.load_point_cloud(DEFAULT_OBJECT, n_points=n)
            r = ppl.run_pipeline(cloud, hand=hand, until="pool")
            normals = ppl.view_normals(cloud, r.params.planner.normals)
            support = None if r.masks is None else r.masks.support
            prm = r.params.planner
            plan_args = (cloud.points, normals, r.pool, hand, prm, support)
            ways: dict[str, Any] = {}
            if pp is None:  # `pregrasp plan`: one thread, the planner forks when threads > 1
                for way, threads in (("one", 1), ("forked", 2)):
                    one = dataclasses.replace(prm, threads=threads)
                    ways[way] = functools.partial(plan_grasps, *plan_args[:4], one, support)
            else:
                ways = {
                    "threads": functools.partial(plan_grasps, *plan_args),
                    "process": functools.partial(pp.plan, *plan_args),
                }
            got: dict[str, list[tuple[float, float]]] = {w: [] for w in ways}
            load0 = os.getloadavg()[0]
            first = {}
            for k in range(args.rounds + 1):
                for way, fn in ways.items():
                    pid = None if pp is None else pp.pid
                    c0, w0, t0 = _own_cpu(), _cpu(pid), time.perf_counter()
                    gs = fn()
                    t1, c1, w1 = time.perf_counter(), _own_cpu(), _cpu(pid)
                    if k == 0:  # warm-up; the grasps of both ways compared
                        first[way] = gs
                        continue
                    got[way].append((t1 - t0, c1 - c0 + (w1 - w0)))
            a, b = first.values()
            assert np.array_equal(a.ranking, b.ranking)
            assert [g.epsilon for g in a.grasps] == [g.epsilon for g in b.grasps]
            for way, v in got.items():
                wall, cpu = [x[0] for x in v], [x[1] for x in v]
                print(
                    f"| {n:,} | {len(r.pool)} | {way} | {min(wall):.3f} | "
                    f"{statistics.median(wall):.3f} | {min(cpu):.3f} | "
                    f"{statistics.median(cpu):.3f} | {load0:.1f}-{os.getloadavg()[0]:.1f} |",
                    flush=True,
                )
        if pp is not None and pp.local_plans:
            print(f"# {pp.local_plans} plan(s) of the process way ran here (worker failed)")
    finally:
        if pp is not None:
            pp.close()
        alive.set()


if __name__ == "__main__":
    main()
