"""Pre-grasp pool per object: pool size, drops and the time of every stage up to the pool.

For every demo object in ``assets/objects/`` (meshes sampled to N points with seed 0) the
pipeline runs at default settings (``PipelineParams()``: volume ratio 0.9, min points 500, the
paper's traversal, support plane under the object, interval 0.02 m); the pool size is also given
at ``--other-interval`` (default 0.03 m), re-running only the pool stage. Stage times are the median
of ``--repeats`` runs (each run recomputes every stage). A second table compares the two
batched collision tests of the pool filter on the same poses and cloud in the same run: the
hand model's ``Hand.hands_hit_points`` (k-d tree ball query around every link box) against
``sampling.hand_hits_points`` (near-cubic cells decided by one nearest-point query each, exact
test only for the undecided cells); both must give the same answer.

    .venv/bin/python benchmarks/bench_pool.py [--points 20000] [--repeats 3]

Timings are wall-clock on one core (``OMP_NUM_THREADS=1`` etc. are set here); under load they
are noisy, so compare rows of one run.
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import platform  # noqa: E402
import statistics  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
from scipy.spatial import cKDTree  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pregrasp_core.hand import Hand  # noqa: E402
from pregrasp_core.io import load_point_cloud  # noqa: E402
from pregrasp_core.paths import demo_objects  # noqa: E402
from pregrasp_core.pipeline import STAGES, PipelineParams, run_pipeline  # noqa: E402
from pregrasp_core.pregrasps import hand_hits_points  # noqa: E402

POOL_STAGES = STAGES[: STAGES.index("pool") + 1]

SHORT = {
    "cylindrical": "cyl",
    "spherical": "sph",
    "three_finger_tip": "3tip",
    "two_finger_tip": "2tip",
}


def pool_table(points: int, repeats: int, hand: Hand, other_interval: float) -> None:
    params = PipelineParams()
    other = dataclasses.replace(
        params, sampling=dataclasses.replace(params.sampling, interval=other_interval)
    )
    head = (
        f"| object | parts | candidates | pool | pool at {other_interval} m | per type | fallback "
        "| dropped (subface / support / collision) | "
        + " | ".join(f"{s} ms" for s in POOL_STAGES)
        + " |"
    )
    print(head)
    print("|" + "---|" * (head.count("|") - 1))
    totals = []
    for path in demo_objects():
        cloud = load_point_cloud(path, n_points=points, seed=0)
        runs = [run_pipeline(cloud, params, hand, until="pool") for _ in range(repeats)]
        r = runs[0]
        n_other = len(run_pipeline(cloud, other, hand, until="pool", previous=r).pool)
        ms = {s: 1000 * statistics.median(x.timings[s] for x in runs) for s in POOL_STAGES}
        totals.append(sum(ms.values()))
        per_type = ", ".join(f"{SHORT[k]} {v}" for k, v in r.pool.counts()["per_type"].items())
        fb = ", ".join(f"{k}: {SHORT[v]}" for k, v in r.pool.fallback.items()) or "-"
        d = r.pool.dropped
        print(
            f"| {path.stem} | {len(r.tree.leaves())} | {len(r.traversal.candidates)} | "
            f"{len(r.pool)} | {n_other} | {per_type or '-'} | {fb} | {d['blocked_subface']} / "
            f"{d['support']} / {d['object_collision']} | "
            + " | ".join(f"{ms[s]:.1f}" for s in POOL_STAGES)
            + " |"
        )
    print(f"\nmedian total over objects: {statistics.median(totals):.0f} ms")


def collision_table(points: int, hand: Hand) -> None:
    cloud = load_point_cloud(demo_objects()[0].parent / "mug_handle.obj", n_points=points, seed=0)
    pts = cloud.points
    rng = np.random.default_rng(0)
    print(
        "\n| hands | grasp type | Hand.hands_hit_points ms | sampling.hand_hits_points ms | "
        "hits | same answer |"
    )
    print("|---|---|---|---|---|---|")
    kd = cKDTree(pts)
    centre = pts.mean(axis=0)
    for G in (1000, 4000):
        T = np.tile(np.eye(4), (G, 1, 1))
        T[:, :3, :3] = Rotation.random(G, random_state=1).as_matrix()
        # hands around the object, palm 0.05-0.15 m from its centre, facing it
        d = rng.normal(size=(G, 3))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        T[:, :3, 2] = -d
        x = np.cross(T[:, :3, 2], rng.normal(size=(G, 3)))
        x /= np.linalg.norm(x, axis=1, keepdims=True)
        T[:, :3, 0], T[:, :3, 1] = x, np.cross(T[:, :3, 2], x)
        T[:, :3, 3] = centre + d * rng.uniform(0.05, 0.15, (G, 1))
        for gt in ("spherical", "cylindrical"):
            q = np.tile(hand.preshape(gt), (G, 1))
            t0 = time.perf_counter()
            ref = hand.hands_hit_points(pts, T, q[0], 0.0)
            t1 = time.perf_counter()
            ours = hand_hits_points(hand, T, np.full(G, gt), q, pts, kd)
            t2 = time.perf_counter()
            print(
                f"| {G} | {gt} | {1000 * (t1 - t0):.0f} | {1000 * (t2 - t1):.0f} | "
                f"{int(ref.sum())} | {bool(np.array_equal(ref, ours))} |"
            )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=int, default=20000)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument(
        "--other-interval", type=float, default=0.03, help="pool size also at this interval"
    )
    a = ap.parse_args()
    print(
        f"# bench_pool: {a.points} points, {a.repeats} repeats, {platform.platform()}, "
        f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}\n"
    )
    hand = Hand.load()
    pool_table(a.points, a.repeats, hand, a.other_interval)
    collision_table(a.points, hand)


if __name__ == "__main__":
    main()
