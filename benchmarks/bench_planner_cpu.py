"""The planner's CPU time per phase and per pre-grasp on one core, side by side with older code
in the same process (issue 15, session 11).

The default object's pool is built once (this tree's pipeline, 20,000 points, seed 0); then
``plan_grasps`` with ``threads=1`` runs alternately with this tree's planner and with the
planner of ``--old`` (its ``pregrasp_core`` taken out of git with ``git archive`` into a
temporary folder and imported under another name, so that both live in one process and share
the inputs, the pinned CPU and the load, plan by plan), ``--rounds`` rounds of ``--per``
plans each, the order of the two trees swapped every round, after one warm-up plan each.

Each plan's CPU time is the process's (``time.process_time``, one BLAS thread, the process
pinned to one CPU). The phases (``GraspSet.phase_seconds``: approach and slicing, closing,
verification, quality) are read with the planner module's clock replaced by the process's CPU
clock for the run (``planner.plan.time`` swapped for a namespace whose ``perf_counter`` is
``process_time``; nothing else changes), so they are CPU seconds as well. A digest of every
grasp (pose, joints, contacts, scores, exactness, rank) must be the same for the two trees in
every plan: the comparison is only meaningful between trees with equal results.

Usage::

    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/bench_planner_cpu.py \\
        [--old 702618a] [--rounds 6] [--per 3]
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import hashlib  # noqa: E402
import importlib  # noqa: E402
import platform  # noqa: E402
import statistics  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
import types  # noqa: E402
from pathlib import Path  # noqa: E402

from _timing import pin_one_core  # noqa: E402

REPO = Path(__file__).resolve().parents[1]


def old_package(commit: str, tmp: Path) -> types.ModuleType:
    """``pregrasp_core`` of ``commit`` imported as ``pregrasp_old_<commit>`` (every import inside
    the package is relative, so it runs as its own copy)."""
    name = f"pregrasp_old_{commit}"
    dst = tmp / commit
    dst.mkdir(parents=True, exist_ok=True)
    archive = subprocess.run(
        ["git", "-C", str(REPO), "archive", commit, "pregrasp_core"],
        check=True,
        capture_output=True,
    ).stdout
    subprocess.run(["tar", "-x", "-C", str(dst)], input=archive, check=True)
    (dst / "pregrasp_core").rename(dst / name)
    sys.path.insert(0, str(dst))
    return importlib.import_module(name)


def digest(gs: object) -> str:
    rows = [
        (
            g.pregrasp, g.rejection, g.epsilon, g.volume, g.rank, g.q.tobytes(),
            g.T_world_hand.tobytes(), g.epsilon_exact, g.volume_exact, g.quality_bound,
            tuple((c.link, c.point_index, c.point.tobytes(), c.normal.tobytes())
                  for c in g.contacts),
        )
        for g in gs.grasps  # type: ignore[attr-defined]
    ]  # fmt: skip
    return hashlib.sha256(repr(rows).encode()).hexdigest()[:16]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--old", default="702618a", help="the commit to compare with")
    ap.add_argument("--rounds", type=int, default=6)
    ap.add_argument("--per", type=int, default=3, help="plans per tree and round")
    args = ap.parse_args()
    pinned = pin_one_core()

    import pregrasp_core
    from pregrasp_core.hand import load_hand
    from pregrasp_core.io import load_point_cloud
    from pregrasp_core.paths import DEFAULT_OBJECT
    from pregrasp_core.pipeline import run_pipeline

    cloud = load_point_cloud(DEFAULT_OBJECT, n_points=20000, seed=0)
    res = run_pipeline(cloud, hand=load_hand(), until="grasps")  # (the normals and the pool)
    inputs = (cloud.points, res.normals, res.pool)
    support = res.masks.support
    with tempfile.TemporaryDirectory() as tmp:
        trees = {f"before ({args.old})": old_package(args.old, Path(tmp)), "now": pregrasp_core}
        run = {}
        for name, pkg in trees.items():
            planner = importlib.import_module(pkg.__name__ + ".planner")
            plan_mod = importlib.import_module(pkg.__name__ + ".planner.plan")
            hand = importlib.import_module(pkg.__name__ + ".hand").load_hand()
            run[name] = (planner, plan_mod, hand)
        cpu_clock = types.SimpleNamespace(perf_counter=time.process_time)
        recs: dict[str, list[tuple[float, dict[str, float], str]]] = {k: [] for k in trees}

        def plan(name: str) -> tuple[float, dict[str, float], str]:
            planner, plan_mod, hand = run[name]
            saved, plan_mod.time = plan_mod.time, cpu_clock  # phases in CPU seconds
            try:
                c0 = time.process_time()
                gs = planner.plan_grasps(*inputs, hand, planner.PlannerParams(threads=1), support)
                cpu = time.process_time() - c0
            finally:
                plan_mod.time = saved
            return cpu, dict(gs.phase_seconds), digest(gs)

        for name in trees:
            plan(name)  # warm-up (numba's kernels loaded or compiled)
        loads = [os.getloadavg()[0]]
        t_start = time.gmtime()
        for r in range(args.rounds):  # interleaved: the order swapped every round
            for name in list(trees) if r % 2 == 0 else list(trees)[::-1]:
                for _ in range(args.per):
                    recs[name].append(plan(name))
            loads.append(os.getloadavg()[0])
    n = len(inputs[2])
    med = statistics.median
    print(
        f"# {platform.machine()}, Python {platform.python_version()}, "
        f"{time.strftime('%Y-%m-%d %H:%M', t_start)}-{time.strftime('%H:%M', time.gmtime())} "
        f"UTC, load average {min(loads):.1f}-{max(loads):.1f}, {pinned}, {args.rounds} rounds "
        f"x {args.per} plans per tree, interleaved"
    )
    print(f"\ndefault object (mug_handle, 20,000 points, seed 0): {n} pre-grasps, threads=1\n")
    print("| CPU, one core | " + " | ".join(trees) + " |")
    print("|---|" + "---:|" * len(trees))

    def row(label: str, values: list[str]) -> None:
        print(f"| {label} | " + " | ".join(values) + " |")

    for stat, f in (("min", min), ("median", med)):
        row(
            f"plan, {stat} (s; pre-grasps per CPU second; ms per pre-grasp)",
            [
                f"{f(c for c, _, _ in recs[k]):.3f}; {n / f(c for c, _, _ in recs[k]):.0f}; "
                f"{f(c for c, _, _ in recs[k]) * 1e3 / n:.2f}"
                for k in trees
            ],
        )
    for ph in recs["now"][0][1]:
        row(
            f"phase {ph}, min / median (ms per pre-grasp)",
            [
                f"{min(p[ph] for _, p, _ in recs[k]) * 1e3 / n:.3f} / "
                f"{med(p[ph] for _, p, _ in recs[k]) * 1e3 / n:.3f}"
                for k in trees
            ],
        )
    digests = {k: {d for _, _, d in recs[k]} for k in trees}
    same = len(set().union(*digests.values())) == 1
    print(f"\nthe same grasps in every plan of both trees: {same} ({sorted(digests['now'])})")


if __name__ == "__main__":
    main()
