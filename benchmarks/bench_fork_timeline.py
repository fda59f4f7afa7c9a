"""Where a forked plan (``plan_grasps`` with ``threads=2`` from a process of one thread, what
``pregrasp plan`` does) loses against twice the speed of one core: a timeline per process.

The default object (the mug with a handle, 20,000 points), its pool and normals computed once,
one warm-up plan; then ``--plans`` plans forked and ``--plans`` on one core (``threads=1``, the
process pinned to one CPU), alternating. Each forked plan is timed by ``time.perf_counter``
stamps that the private functions of ``pregrasp_core/planner/plan.py`` are wrapped to write (in
the parent and in the forked copy; appended to a file, one JSON line each): the call, the fork,
each chunk's start and end, each pipe message (its wait and unpickling or pickling), each
quality job of the exact settling and the settling's start and end, the copies' end. Per plan:

* ``wall``: the call; ``cpu``: this process and its children (the copy reaped first);
* ``fork``: from the call to the parent's first chunk (the context, the fork);
* ``chunks``: until the last chunk of either process has ended, and each process's busy part
  (``P`` the parent, ``C`` the copy: wall and CPU of its chunk loop, minor page faults in it);
* ``tail``: the parent waiting for the copy's last chunk (or the copy for the parent's);
* ``settle``: the exact settling (``planner/rank.py``), its quality jobs' seconds in each
  process and the number of rounds handed to the copy;
* ``end``: after the settling until the call returns (ranking, the copies let go).

``--old COMMIT``: the same for that commit (a detached ``git worktree``), in fresh processes
alternating with this tree's, ``--rounds`` times; min and median per tree. ``--show`` prints the
full timeline of this tree's last forked plan.

    OPENBLAS_NUM_THREADS=1 PYTHONPATH=. .venv/bin/python benchmarks/bench_fork_timeline.py \\
        [--old 702618a] [--rounds 3] [--plans 3] [--show]
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
import json, os, resource, sys, time
import pregrasp_core.planner.plan as pm
from pregrasp_core.hand import load_hand
from pregrasp_core.io import load_point_cloud
from pregrasp_core.paths import DEFAULT_OBJECT
from pregrasp_core.pipeline import PipelineParams, run_pipeline
from pregrasp_core.planner import PlannerParams, plan_grasps

LOG, PLANS, SHOW = sys.argv[1], int(sys.argv[2]), sys.argv[3] == "1"
on = [False]

def stamp(ev, **kw):
    if on[0]:
        ru = resource.getrusage(resource.RUSAGE_SELF)
        rec = {"pid": os.getpid(), "t": time.perf_counter(), "cpu": time.process_time(),
               "flt": ru.ru_minflt, "ev": ev, **kw}
        with open(LOG, "a") as fh:
            fh.write(json.dumps(rec) + "\n")

real = {n: getattr(pm, n) for n in
        ("_plan_chunks", "_send", "_recv", "run_quality_job", "settle_exact", "_reap")}

def plan_chunks(ctx, pool, P, ex, grasps, progress, chunks=None):
    if chunks is None:
        return real["_plan_chunks"](ctx, pool, P, ex, grasps, progress, chunks)
    def stamped(it):
        for c in it:
            stamp("chunk", c=list(c))
            yield c
            stamp("chunk_end", c=list(c))
    stamp("chunks")
    try:
        return real["_plan_chunks"](ctx, pool, P, ex, grasps, progress, stamped(chunks))
    finally:
        stamp("chunks_end")

def send(fd, obj):
    t0 = time.perf_counter(); real["_send"](fd, obj)
    stamp("send", dt=time.perf_counter() - t0, kind=str(obj[0]) if type(obj) is tuple else "jobs")

def recv(fd):
    t0 = time.perf_counter(); msg = real["_recv"](fd)
    stamp("recv", dt=time.perf_counter() - t0, kind=str(msg[0]) if type(msg) is tuple else "-")
    return msg

def job(j):
    t0 = time.perf_counter(); q = real["run_quality_job"](j)
    stamp("job", dt=time.perf_counter() - t0, n=len(j[0]), level=j[3])
    return q

def settle(*a, **k):
    stamp("settle"); out = real["settle_exact"](*a, **k); stamp("settle_end"); return out

def reap(*a):
    stamp("reap"); real["_reap"](*a); stamp("reap_end")

pm._plan_chunks, pm._send, pm._recv = plan_chunks, send, recv
pm.run_quality_job, pm.settle_exact, pm._reap = job, settle, reap
leaving = getattr(pm, "_reap_leaving", None)

def cpu():
    if leaving is not None:
        leaving(True)
    a, b = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return a.ru_utime + a.ru_stime + b.ru_utime + b.ru_stime

hand = load_hand()
cloud = load_point_cloud(DEFAULT_OBJECT, n_points=20000, seed=0)
res = run_pipeline(cloud, PipelineParams(), hand, until="grasps")
pool, support, nrm = res.pool, res.masks.support, res.normals
cpus = sorted(os.sched_getaffinity(0))
plan_grasps(cloud.points, nrm, pool, hand, PlannerParams(threads=2), support)  # warm-up

def summary(ev):
    parent = ev[0]["pid"]
    t0 = ev[0]["t"]
    by = {}
    for e in ev:
        by.setdefault("P" if e["pid"] == parent else "C", []).append(e)
    out = {}
    first = min(e["t"] for e in by["P"] if e["ev"] == "chunk")
    out["fork"] = first - t0
    ends = {}
    for who, es in by.items():
        a = next(e for e in es if e["ev"] == "chunks")
        b = next(e for e in es if e["ev"] == "chunks_end")
        ends[who] = b["t"]
        out[f"chunks_{who}"] = b["t"] - a["t"]
        out[f"chunks_cpu_{who}"] = b["cpu"] - a["cpu"]
        out[f"faults_{who}"] = b["flt"] - a["flt"]
        out[f"jobs_{who}"] = sum(e["dt"] for e in es if e["ev"] == "job")
        out[f"pipe_{who}"] = sum(e["dt"] for e in es if e["ev"] in ("send", "recv")
                                 and e["kind"] == "chunk")
    out["chunks"] = max(ends.values()) - first
    out["tail"] = abs(ends.get("P", 0) - ends.get("C", 0)) if "C" in ends else 0.0
    s0 = next(e["t"] for e in by["P"] if e["ev"] == "settle")
    s1 = next(e["t"] for e in by["P"] if e["ev"] == "settle_end")
    out["settle"] = s1 - s0
    out["rounds_C"] = sum(1 for e in by.get("C", []) if e["ev"] == "recv" and e["kind"] == "-")
    out["end"] = ev[-1]["t"] - s1
    return out

recs = []
for k in range(PLANS):
    for threads in (2, 1):
        os.sched_setaffinity(0, set(cpus) if threads == 2 else {cpus[0]})
        if os.path.exists(LOG):
            os.remove(LOG)
        c0 = cpu()
        on[0] = threads == 2
        stamp("call")
        t0 = time.perf_counter()
        gs = plan_grasps(cloud.points, nrm, pool, hand, PlannerParams(threads=threads), support)
        t1 = time.perf_counter()
        stamp("call_end")
        on[0] = False
        rec = {"threads": threads, "wall": t1 - t0, "cpu": cpu() - c0}
        if threads == 2:
            ev = [json.loads(x) for x in open(LOG)]
            rec.update(summary(ev))
            if SHOW and k == PLANS - 1:
                rec["events"] = ev
        recs.append(rec)
os.sched_setaffinity(0, set(cpus))
print("RESULT " + json.dumps({"pool": len(pool), "plans": recs}))
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


def run_child(tree: Path, plans: int, show: bool) -> dict:
    env = {**os.environ, "PYTHONPATH": str(tree), "OMP_NUM_THREADS": "1"}
    env["OPENBLAS_NUM_THREADS"] = "1"
    with tempfile.TemporaryDirectory() as tmp:
        log = str(Path(tmp) / "timeline.jsonl")
        cmd = [sys.executable, "-c", CHILD, log, str(plans), "1" if show else "0"]
        p = subprocess.run(cmd, cwd=tree, env=env, capture_output=True, text=True, check=True)
    line = next(x for x in p.stdout.splitlines() if x.startswith("RESULT "))
    return json.loads(line[len("RESULT ") :])


def show_timeline(events: list[dict]) -> None:
    parent, t0 = events[0]["pid"], events[0]["t"]
    print("\ntimeline of the last forked plan (ms from the call; P parent, C copy):")
    for e in events:
        if e["ev"] == "job" and e["dt"] < 0.003:
            continue  # the quality jobs of the settling: only the long ones
        who = "P" if e["pid"] == parent else "C"
        extra = {k: v for k, v in e.items() if k not in ("pid", "t", "cpu", "flt", "ev")}
        if "dt" in extra:
            extra["dt"] = round(extra["dt"] * 1e3, 2)
        print(
            f"{(e['t'] - t0) * 1e3:8.1f} {who} {e['ev']:10s} {json.dumps(extra) if extra else ''}"
        )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--old", default=None, help="a commit to compare with, in alternation")
    ap.add_argument("--rounds", type=int, default=3, help="fresh processes per tree")
    ap.add_argument("--plans", type=int, default=3, help="forked and one-core plans per process")
    ap.add_argument("--show", action="store_true", help="print this tree's last timeline")
    args = ap.parse_args()
    trees = {"now": REPO} if args.old is None else {args.old: old_tree(args.old), "now": REPO}
    out: dict[str, list[dict]] = {k: [] for k in trees}
    load0, t_start = os.getloadavg(), time.gmtime()
    last: dict = {}
    for r in range(args.rounds):  # interleaved rounds
        for name, tree in trees.items():
            show = args.show and name == "now" and r == args.rounds - 1
            rec = run_child(tree, args.plans, show)
            out[name].extend(rec["plans"])
            pool = rec["pool"]
            if show:
                last = rec["plans"][-2]
    load = os.getloadavg()
    print(
        f"# {platform.machine()} {os.cpu_count()} CPUs, Python {platform.python_version()}, "
        f"{time.strftime('%Y-%m-%d %H:%M', t_start)}-{time.strftime('%H:%M UTC', time.gmtime())},"
        f" load average {load0[0]:.1f} at the start, {load[0]:.1f} at the end; "
        f"{args.rounds} processes x {args.plans} plans per tree; {pool} pre-grasps"
    )
    keys = [
        ("wall", "forked plan, wall"),
        ("cpu", "forked plan, CPU of both processes"),
        ("fork", "call to the parent's first chunk (context, fork)"),
        ("chunks", "chunks: first start to last end"),
        ("chunks_P", "parent's chunk loop, wall"),
        ("chunks_cpu_P", "parent's chunk loop, CPU"),
        ("chunks_C", "copy's chunk loop, wall"),
        ("chunks_cpu_C", "copy's chunk loop, CPU"),
        ("pipe_P", "parent: the copy's chunks read and unpickled"),
        ("pipe_C", "copy: its chunks pickled and sent"),
        ("tail", "tail: one process waiting for the other's last chunk"),
        ("settle", "exact settling, wall"),
        ("jobs_P", "settling's quality jobs in the parent"),
        ("jobs_C", "settling's quality jobs in the copy"),
        ("end", "after the settling: ranking, the copy let go"),
    ]
    med = statistics.median
    print("\n| ms (min / median) | " + " | ".join(trees) + " |")
    print("|---|" + "---:|" * len(trees))
    for key, label in keys:
        cells = []
        for name in trees:
            v = [p[key] * 1e3 for p in out[name] if p["threads"] == 2 and key in p]
            cells.append(f"{min(v):.1f} / {med(v):.1f}" if v else "-")
        print(f"| {label} | " + " | ".join(cells) + " |")
    for key, label in (("faults_P", "parent's page faults in its chunks"),
                       ("faults_C", "copy's page faults in its chunks"),
                       ("rounds_C", "settling rounds handed to the copy")):  # fmt: skip
        cells = []
        for name in trees:
            v = [p[key] for p in out[name] if p["threads"] == 2 and key in p]
            cells.append(f"{min(v):.0f} / {med(v):.0f}" if v else "-")
        print(f"| {label} | " + " | ".join(cells) + " |")
    for key, label in (("wall", "one core, wall"), ("cpu", "one core, CPU")):
        cells = []
        for name in trees:
            v = [p[key] * 1e3 for p in out[name] if p["threads"] == 1]
            cells.append(f"{min(v):.1f} / {med(v):.1f}")
        print(f"| {label} | " + " | ".join(cells) + " |")
    for name in trees:
        one = min(p["wall"] for p in out[name] if p["threads"] == 1)
        two = min(p["wall"] for p in out[name] if p["threads"] == 2)
        print(f"\n{name}: two processes {one / two:.2f} x one core (min wall); "
              f"{pool / two:.0f} pre-grasps/s forked, {pool / one:.0f}/s on one core")  # fmt: skip
    if last.get("events"):
        show_timeline(last["events"])


if __name__ == "__main__":
    main()
