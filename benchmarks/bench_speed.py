"""Interactive speed (issue 15): the planner and ``pregrasp plan`` of the default object, side by
side with the code before issue 15 (commit ``fe74cdf``, checked out into a ``git worktree``).

For each code tree, interleaved round by round (so that the load of a shared machine hits both
alike), in a fresh process per round:

* ``cli wall``: ``python -m app.cli plan <default object> -o OUT.json``, the whole command in a
  fresh process (interpreter start, imports, hand, load, pipeline, JSON);
* inside one process, after a warm-up plan (numba's kernels loaded or compiled):
  ``in-process``: from the loaded cloud to the written result file, what the command does after
  its imports (``plan_loaded`` + ``result_doc`` + ``write_result``, default threads);
  ``planner 1 core``: ``plan_grasps`` on the pool with ``threads=1``, the process pinned to one
  CPU; ``planner 2 workers``: with ``threads=2`` on both CPUs (forked processes since session 6
  of issue 15, threads before); wall-clock seconds, and the pre-grasps per second that gives;
  the CPU times count the process and its waited-for children (the forked planners);
* the planner's phases at ``threads=1`` (``GraspSet.phase_seconds``), ms per pre-grasp;
* ``first plan``: the warm-up plan of each process (numba imported and its cached kernels
  loaded: the first plan of a process pays it);
* the in-process run's parts: the stages around the planner (``plan_loaded`` less its
  ``grasps`` stage: decomposition to pool, and the normals, on a thread of their own since
  ``85eaa04``), each stage's seconds, the result document and the writing of the file.

A digest of the result file (without timings) and of the grasps at 1 and 2 threads says, per
tree, that the results do not depend on the round or the threads. Usage::

    OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/bench_speed.py \\
        [--rounds 5] [--old fe74cdf]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

CHILD = r"""
import time
t_start = time.perf_counter()
import hashlib, json, os, sys
from pathlib import Path
from app.commands.plan import plan_loaded, result_doc
from pregrasp_core.hand import load_hand
from pregrasp_core.io import load_point_cloud
from pregrasp_core.paths import DEFAULT_OBJECT
from pregrasp_core.pipeline import PipelineParams
from pregrasp_core.planner import PlannerParams, plan_grasps
from pregrasp_core.result import write_result
t_imports = time.perf_counter() - t_start
cpus = sorted(os.sched_getaffinity(0))
hand = load_hand()
out = Path(sys.argv[1])
cloud = load_point_cloud(DEFAULT_OBJECT, n_points=20000, seed=0)
params = PipelineParams()
t0 = time.perf_counter()
result, timings, lift = plan_loaded(cloud, 0.0, params, hand)
t_first = time.perf_counter() - t0

def digest_file(path):
    doc = json.loads(path.read_text())
    doc.pop("timings", None)
    doc.get("generator", {}).pop("version", None)
    return hashlib.sha256(json.dumps(doc, sort_keys=True).encode()).hexdigest()[:16]

def digest_grasps(gs):
    rows = [(g.pregrasp, g.rejection, g.epsilon, g.volume, g.rank, g.q.tobytes(),
             g.T_world_hand.tobytes(), tuple((c.link, c.point_index) for c in g.contacts))
            for g in gs.grasps]
    return hashlib.sha256(repr(rows).encode()).hexdigest()[:16]

import resource

try:  # the forked copies are reaped without waiting since this session: reap them here
    from pregrasp_core.planner.plan import _reap_leaving
except ImportError:
    _reap_leaving = None

def cpu():  # CPU seconds of this process and of its waited-for children (forked planners)
    if _reap_leaving is not None:
        _reap_leaving(True)
    a, b = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return a.ru_utime + a.ru_stime + b.ru_utime + b.ru_stime

rec = {"imports": t_imports, "first_plan": t_first}
t0, c0 = time.perf_counter(), cpu()
result, timings, lift = plan_loaded(cloud, 0.0, params, hand)
t1 = time.perf_counter()
doc = result_doc(result, timings, False, lift)
t2 = time.perf_counter()
write_result(doc, out)
rec["in_process"] = time.perf_counter() - t0
rec["around"] = t1 - t0 - timings["grasps"]
rec["stages"] = {k: v for k, v in timings.items() if k != "load"}
rec["doc"], rec["write"] = t2 - t1, time.perf_counter() - t2
rec["in_process_cpu"] = cpu() - c0
rec["file"] = digest_file(out)
pool, support = result.pool, result.masks.support
rec["pool"] = len(pool)
for threads in (1, 2):
    os.sched_setaffinity(0, {cpus[0]} if threads == 1 else set(cpus))
    prm = PlannerParams(threads=threads)
    t0, c0 = time.perf_counter(), cpu()
    gs = plan_grasps(cloud.points, result.normals, pool, hand, prm, support)
    rec[f"planner_{threads}"] = time.perf_counter() - t0
    rec[f"planner_cpu_{threads}"] = cpu() - c0
    rec[f"grasps_{threads}"] = digest_grasps(gs)
    if threads == 1:
        rec["phases"] = {k: v * 1e3 / len(pool) for k, v in gs.phase_seconds.items()}
print("RESULT " + json.dumps(rec))
"""


def old_tree(commit: str) -> Path:
    """A detached ``git worktree`` of ``commit`` (made once, reused)."""
    path = Path(tempfile.gettempdir()) / f"pregrasp-bench-{commit}"
    if not (path / "app" / "cli.py").exists():
        subprocess.run(
            ["git", "-C", str(REPO), "worktree", "add", "--detach", str(path), commit],
            check=True,
            capture_output=True,
        )
    return path


def run_child(tree: Path, out: Path) -> dict:
    env = {**os.environ, "PYTHONPATH": str(tree), "OMP_NUM_THREADS": "1"}
    env["OPENBLAS_NUM_THREADS"] = "1"
    cmd = [sys.executable, "-c", CHILD, str(out)]
    p = subprocess.run(cmd, cwd=tree, env=env, capture_output=True, text=True, check=True)
    line = next(x for x in p.stdout.splitlines() if x.startswith("RESULT "))
    return json.loads(line[len("RESULT ") :])


def cli_wall(tree: Path, out: Path) -> float:
    env = {**os.environ, "PYTHONPATH": str(tree), "OMP_NUM_THREADS": "1"}
    env["OPENBLAS_NUM_THREADS"] = "1"
    obj = tree / "assets" / "objects" / "mug_handle.obj"
    t0 = time.perf_counter()
    subprocess.run(
        [sys.executable, "-m", "app.cli", "plan", str(obj), "-o", str(out)],
        cwd=tree,
        env=env,
        check=True,
        capture_output=True,
    )
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument(
        "--old", default="fe74cdf", help="the code to compare with (default: before issue 15)"
    )
    args = ap.parse_args()
    trees = {"before (" + args.old + ")": old_tree(args.old), "now": REPO}
    recs: dict[str, list[dict]] = {k: [] for k in trees}
    walls: dict[str, list[float]] = {k: [] for k in trees}
    load0 = os.getloadavg()
    with tempfile.TemporaryDirectory() as tmp:
        for _ in range(args.rounds):  # interleaved rounds
            for name, tree in trees.items():
                walls[name].append(cli_wall(tree, Path(tmp) / "cli.json"))
                recs[name].append(run_child(tree, Path(tmp) / "r.json"))
    load = os.getloadavg()
    print(f"# load average at the start {load0[0]:.1f}, at the end {load[0]:.1f}")
    print(
        f"# {platform.machine()} {os.cpu_count()} CPUs, Python {platform.python_version()}, "
        f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, load average "
        f"{load[0]:.1f} {load[1]:.1f} {load[2]:.1f}; medians of {args.rounds} interleaved rounds"
    )
    med = statistics.median
    pool = recs["now"][0]["pool"]
    print(f"\ndefault object (mug_handle, 20,000 points, seed 0): {pool} pre-grasps\n")
    print("| | " + " | ".join(trees) + " |")
    print("|---|" + "---:|" * len(trees))

    def row(label: str, values: list[str]) -> None:
        print(f"| {label} | " + " | ".join(values) + " |")

    row("`pregrasp plan` wall, fresh process (s)", [f"{med(walls[k]):.2f}" for k in trees])

    def col(key: str, fmt: str = ".3f") -> list[str]:
        return [format(med(r[key] for r in recs[k]), fmt) for k in trees]

    row("imports in that process (s)", col("imports", ".2f"))
    row("first plan of a process (s)", col("first_plan"))
    row(
        "in-process: loaded cloud to written file (s; median / min)",
        [
            f"{med(r['in_process'] for r in recs[k]):.3f} / "
            f"{min(r['in_process'] for r in recs[k]):.3f}"
            for k in trees
        ],
    )
    row(
        "in-process: the stages around the planner (plan_loaded less its grasps stage) (s)",
        col("around"),
    )
    for st in recs["now"][0]["stages"]:
        note = " (on its own thread beside the others since 85eaa04)" if st == "normals" else ""
        row(
            f"in-process: stage {st}{note} (s)",
            [format(med(r["stages"].get(st, float("nan")) for r in recs[k]), ".3f") for k in trees],
        )
    row("in-process: result document (s)", col("doc"))
    row("in-process: writing the file (s)", col("write"))
    for t in (1, 2):
        label = "planner, 1 core" if t == 1 else "planner, 2 workers"
        row(
            f"{label} (s median / min; pre-grasps/s of the min)",
            [
                f"{med(r[f'planner_{t}'] for r in recs[k]):.3f} / "
                f"{min(r[f'planner_{t}'] for r in recs[k]):.3f}; "
                f"{pool / min(r[f'planner_{t}'] for r in recs[k]):.0f}"
                for k in trees
            ],
        )
    row("in-process, CPU time of all its processes (s)", col("in_process_cpu"))
    for t in (1, 2):
        label = "1 core" if t == 1 else "2 workers, all processes"
        row(
            f"planner, {label}, CPU time (s; pre-grasps per CPU second)",
            [
                f"{med(r[f'planner_cpu_{t}'] for r in recs[k]):.3f}; "
                f"{pool / med(r[f'planner_cpu_{t}'] for r in recs[k]):.0f}"
                for k in trees
            ],
        )
    for ph in recs["now"][0]["phases"]:
        row(
            f"phase {ph}, 1 core (ms per pre-grasp)",
            [f"{med(r['phases'][ph] for r in recs[k]):.2f}" for k in trees],
        )
    for k in trees:  # the same results in every round and at 1 and 2 threads, per tree
        files = {r["file"] for r in recs[k]}
        grasps = {r[f"grasps_{t}"] for r in recs[k] for t in (1, 2)}
        print(
            f"\n{k}: result file the same in every round: {len(files) == 1}; grasps equal at 1 "
            f"and 2 threads: {len(grasps) == 1}"
        )
    print(
        "(the two trees' results differ where other work of issue 15 changed them, e.g. the "
        "bounded epsilons; scripts/compare_results.py compares trees that differ only by a change)"
    )


if __name__ == "__main__":
    main()
