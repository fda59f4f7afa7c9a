"""Decomposition speed against the number of points, and parts per demo object.

Prints two tables (Markdown):

Times are CPU seconds of this process (``time.process_time``), which other jobs on a shared
machine disturb much less than wall-clock time (printed beside them); BLAS is single-threaded,
so on an idle machine the two agree.

1. scaling: for each cloud size n, the median time of ``decompose`` and how it splits into
   the MVBB fits (``minimum_volume_box``: the root, two quick fits per tried split whose
   parent-frame ratio is not already below the threshold, two full refits per split that is
   accepted or close to the threshold; "(quick)" counts the quick ones), the exact cut search
   (``best_cut``) and the rest; ``t / (n log2 n)`` should stay roughly flat;
2. objects: for every demo object at ``--points`` points, parts (leaves), splits, depth,
   shape classes of the leaves and the median time, at the default parameters (0.9 / 500).

3. ``--compare [REV]`` (issue 15): this tree against the code of commit REV (default fe74cdf,
   before issue 15's decomposition work) in one run. REV is checked out in a temporary
   ``git worktree``; one worker process runs each tree's code on the same clouds (every demo
   object at ``--points`` points, seed 0), the two are driven alternately (old then new, new then
   old on the next round), and the table gives the median over ``--repeats`` rounds (at least
   7) of each side's CPU and wall time per decomposition, and whether the trees (nodes, point
   indices and the bytes of every box) are identical. A worker warms up on every cloud first;
   the new side's first call in a fresh process (numba import and cache load) is printed apart.

Run on one core:  .venv/bin/python benchmarks/bench_decomposition.py
Options: --object NAME --sizes 1000,10000,... --repeats R --points N --skip-objects
         --compare [REV]
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import hashlib  # noqa: E402
import json  # noqa: E402
import math  # noqa: E402
import statistics  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from collections import Counter  # noqa: E402
from pathlib import Path  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
if "--worker" in sys.argv:  # a worker runs the code of the tree it is given
    sys.path.insert(0, sys.argv[sys.argv.index("--worker") + 1])
else:
    sys.path.insert(0, str(REPO))  # this tree's code, not whatever is installed

from pregrasp_core import decomposition as dec  # noqa: E402
from pregrasp_core.decomposition import DecompositionParams, decompose  # noqa: E402
from pregrasp_core.io import load_point_cloud  # noqa: E402
from pregrasp_core.paths import DEFAULT_OBJECT, OBJECTS_DIR, demo_objects  # noqa: E402
from pregrasp_core.shape import ShapeParams, classify_tree  # noqa: E402


class _Timed:
    """Wraps a module function of ``decomposition`` to count calls and sum their time."""

    def __init__(self, name: str):
        self.name, self.orig = name, getattr(dec, name)
        self.calls, self.seconds, self.quick = 0, 0.0, 0

    def __call__(self, *a, **kw):
        t0 = time.process_time()
        try:
            return self.orig(*a, **kw)
        finally:
            self.seconds += time.process_time() - t0
            self.calls += 1
            if len(a) > 1 and a[1] is getattr(dec, "QUICK_MVBB", None):
                self.quick += 1

    def __enter__(self):
        setattr(dec, self.name, self)
        return self

    def __exit__(self, *exc):
        setattr(dec, self.name, self.orig)


def _median_time(points, params, repeats):
    """Median CPU time (process_time: robust when other jobs share the cores) and wall time."""
    cpu, wall = [], []
    tree = None
    for _ in range(repeats):
        c0, w0 = time.process_time(), time.perf_counter()
        tree = decompose(points, params)
        cpu.append(time.process_time() - c0)
        wall.append(time.perf_counter() - w0)
    return statistics.median(cpu), statistics.median(wall), tree


def scaling(path, sizes, repeats, params):
    print(
        f"### Scaling: {path.name}, volume ratio {params.volume_ratio}, "
        f"min points {params.min_points}\n"
    )
    print(
        "| points | parts | MVBB calls (quick) | MVBB ms | cut search ms | other ms "
        "| total CPU ms (median) | wall ms (median) | ns / (n log2 n) |"
    )
    print("|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for n in sizes:
        pts = load_point_cloud(path, n_points=n, seed=0).points
        r = max(1, repeats if n <= 20_000 else repeats // 4 if n <= 100_000 else 1)
        decompose(pts, params)  # warm-up
        med, wall, tree = _median_time(pts, params, r)
        with _Timed("minimum_volume_box") as mv, _Timed("best_cut") as bc:
            t0 = time.process_time()
            decompose(pts, params)
            tot = time.process_time() - t0
        other = tot - mv.seconds - bc.seconds
        norm = med * 1e9 / (n * math.log2(n))
        print(
            f"| {n:,} | {len(tree.leaves())} | {mv.calls} ({mv.quick}) | {mv.seconds * 1e3:.1f} | "
            f"{bc.seconds * 1e3:.1f} | {other * 1e3:.1f} | {med * 1e3:.1f} | {wall * 1e3:.1f} | "
            f"{norm:.0f} |"
        )
    print()


def objects(n_points, repeats, params):
    sp = ShapeParams()
    print(
        f"### Parts per object: {n_points:,} points (seed 0), volume ratio "
        f"{params.volume_ratio}, min points {params.min_points}, max depth {params.max_depth}\n"
    )
    print("| object | parts | splits | depth | leaf classes | CPU ms (median) | wall ms (median) |")
    print("|---|---:|---:|---:|---|---:|---:|")
    for path in demo_objects():
        pts = load_point_cloud(path, n_points=n_points, seed=0).points
        med, wall, tree = _median_time(pts, params, repeats)
        shapes = classify_tree(tree, pts, sp)
        classes = Counter(shapes[i].shape_class.value for i in tree.leaves())
        cls = ", ".join(f"{v} {k}" for k, v in sorted(classes.items()))
        depth = max(nd.depth for nd in tree.nodes)
        print(
            f"| {path.stem} | {len(tree.leaves())} | {tree.n_splits} | {depth} | {cls} | "
            f"{med * 1e3:.1f} | {wall * 1e3:.1f} |"
        )
    print()


def tree_signature(tree) -> str:
    """Hash of everything a tree holds: structure, point indices and the bytes of every box."""
    h = hashlib.sha256()
    for nd in tree.nodes:
        h.update(repr((nd.parent, nd.children, nd.depth, nd.split_order)).encode())
        for arr in (nd.indices, nd.box.center, nd.box.rotation, nd.box.extents):
            h.update(arr.tobytes())
    return h.hexdigest()[:16]


def worker(n_points: int) -> None:
    """Decompose on request: reads an object name per line, answers one JSON line."""
    t0 = time.perf_counter()
    from pregrasp_core.decomposition import decompose as dec_fn
    from pregrasp_core.io import load_point_cloud as load
    from pregrasp_core.paths import DEFAULT_OBJECT as default
    from pregrasp_core.paths import demo_objects as objs

    clouds = {p.stem: load(p, n_points=n_points, seed=0).points for p in objs()}
    t_import = time.perf_counter() - t0
    t1 = time.perf_counter()
    dec_fn(clouds[default.stem])  # the first call of a fresh process
    first = time.perf_counter() - t1
    for pts in clouds.values():  # warm-up
        dec_fn(pts)
    print(json.dumps({"objects": list(clouds), "first": first, "import": t_import}), flush=True)
    for line in sys.stdin:
        name = line.strip()
        if not name:
            break
        c0, w0 = time.process_time(), time.perf_counter()
        tree = dec_fn(clouds[name])
        cpu, wall = time.process_time() - c0, time.perf_counter() - w0
        out = {"cpu": cpu, "wall": wall, "sig": tree_signature(tree), "parts": len(tree.leaves())}
        print(json.dumps(out), flush=True)


def compare(rev: str, n_points: int, repeats: int) -> None:
    """This tree against commit ``rev``, side by side (see the module docstring)."""
    repeats = max(7, repeats)
    tmp = Path(tempfile.mkdtemp(prefix="bench_dec_"))
    old_tree = tmp / "old"
    git = ["git", "-C", str(REPO)]
    subprocess.run([*git, "worktree", "add", "--detach", str(old_tree), rev], check=True,
                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)  # fmt: skip
    procs = {}
    try:
        for side, tree in (("old", old_tree), ("new", REPO)):
            procs[side] = subprocess.Popen(
                [sys.executable, str(Path(__file__).resolve()), "--worker", str(tree),
                 "--points", str(n_points)],
                stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, cwd=str(tree),
                env={**os.environ, "PYTHONPATH": str(tree)},
            )  # fmt: skip
        hello = {side: json.loads(p.stdout.readline()) for side, p in procs.items()}
        names = hello["new"]["objects"]
        runs: dict[tuple[str, str], list[dict]] = {(s, n): [] for s in procs for n in names}
        for r in range(repeats):
            for i, name in enumerate(names):
                sides = ("old", "new") if (r + i) % 2 == 0 else ("new", "old")
                for side in sides:
                    procs[side].stdin.write(name + "\n")
                    procs[side].stdin.flush()
                    runs[side, name].append(json.loads(procs[side].stdout.readline()))
    finally:
        for p in procs.values():
            if p.stdin:
                p.stdin.close()
            p.wait(timeout=60)
        subprocess.run([*git, "worktree", "remove", "--force", str(old_tree)], check=False,
                       stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)  # fmt: skip
    load = os.getloadavg()
    print(
        f"### Side by side: this tree against {rev}, {n_points:,} points (seed 0), default "
        f"parameters, median of {repeats} interleaved runs; load average "
        f"{load[0]:.1f} / {load[1]:.1f} at the end\n"
    )
    print(
        "| object | parts | old CPU ms | new CPU ms | new / old | old wall ms | new wall ms "
        "| identical trees |"
    )
    print("|---|---:|---:|---:|---:|---:|---:|---|")
    ratios = []
    for name in names:
        o, n = runs["old", name], runs["new", name]
        oc, nc = (statistics.median(x["cpu"] for x in v) * 1e3 for v in (o, n))
        ow, nw = (statistics.median(x["wall"] for x in v) * 1e3 for v in (o, n))
        same = len({x["sig"] for x in o + n}) == 1
        ratios.append(nc / oc)
        print(
            f"| {name} | {n[0]['parts']} | {oc:.1f} | {nc:.1f} | {nc / oc:.2f} | {ow:.1f} | "
            f"{nw:.1f} | {'yes' if same else 'NO'} |"
        )
    print(f"\nmedian new / old CPU: {statistics.median(ratios):.2f}")
    for side in ("old", "new"):
        print(
            f"{side}: first decomposition of the default object in a fresh process "
            f"{hello[side]['first'] * 1e3:.0f} ms (after imports and cloud loading)"
        )
    print()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--object", default=DEFAULT_OBJECT.stem, help="object for the scaling table")
    ap.add_argument("--sizes", default="1000,3000,10000,20000,100000,300000,1000000")
    ap.add_argument("--repeats", type=int, default=9)
    ap.add_argument("--points", type=int, default=20000, help="points per object (table 2)")
    ap.add_argument("--skip-objects", action="store_true")
    ap.add_argument("--skip-scaling", action="store_true")
    ap.add_argument("--compare", nargs="?", const="fe74cdf", metavar="REV",
                    help="side by side with the code of commit REV (default fe74cdf)")  # fmt: skip
    ap.add_argument("--worker", metavar="TREE", help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.worker:
        worker(a.points)
        return
    if a.compare:
        compare(a.compare, a.points, a.repeats)
        return
    params = DecompositionParams()
    path = next((p for p in demo_objects() if p.stem == a.object), OBJECTS_DIR / a.object)
    sizes = [int(s) for s in a.sizes.split(",")]
    print(
        f"machine: {os.cpu_count()} cpus, single-threaded BLAS; date "
        f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}\n"
    )
    if not a.skip_scaling:
        scaling(path, sizes, a.repeats, params)
    if not a.skip_objects:
        objects(a.points, max(1, a.repeats // 3), params)


if __name__ == "__main__":
    main()
