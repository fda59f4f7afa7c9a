"""Pre-grasp pool per object: pool size, drops and the time of every stage up to the pool.

For every demo object in ``assets/objects/`` (meshes sampled to N points with seed 0) the
pipeline runs at default settings (``PipelineParams()``: volume ratio 0.9, min points 500, the
paper's traversal, support plane under the object, interval 0.02 m); the pool size is also given
at ``--other-interval`` (default 0.03 m), re-running only the pool stage. Stage times are the median
of ``--repeats`` runs (each run recomputes every stage). A second table compares the two
batched collision tests of the pool filter on the same poses and cloud in the same run: the
hand model's ``Hand.hands_hit_points`` (k-d tree ball query around every link box) against
``sampling.hand_hits_points`` (the pool's test: link boxes cut into near-cubic cells; since
session 14 the compiled kernel below); both must give the same answer. A third table compares,
on the same poses, the pool's collision test before and after its compiled kernel (issue 15):
``collision.hand_hits_points_numpy`` (the numpy version, ``_batch_hits``) against
``hand_hits_points`` (``collision_kernels``: a voxel grid of the cloud, the exact test per hand
and cell; the cloud's grid built once, as the pool does), interleaved, ``--repeats`` (at least
5) times each, medians, the link cells built beforehand for both; the answers must be equal.
The time of the kernels' first call in the process (numba imported, the kernels loaded from its
cache or compiled) is printed first. A fourth table (issue 15, the pool's pinches and heights)
times, on every call the default object's pool makes, the functions the pool's caches and the
pinches' sorted projections changed against the versions they replaced (kept as the tests'
references): ``pinch._placed`` against ``_placed_reference``, ``collision.link_cells`` against
``_link_cells_reference``, ``hand_min_height`` against its version with fresh corners, the new
ones both with the preshape caches kept (a re-plan) and emptied before each call (a preshape
seen for the first time); interleaved, medians; the results must be equal to the bit.

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
from pregrasp_core.pregrasps import (  # noqa: E402
    build,
    collision,
    collision_kernels,
    hand_hits_points,
    pinch,
)
from pregrasp_core.pregrasps.collision import cloud_grid, hand_hits_points_numpy  # noqa: E402

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


def _hand_poses(G: int, centre: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """(G, 4, 4) hands around the object, palm 0.05-0.15 m from its centre, facing it."""
    T = np.tile(np.eye(4), (G, 1, 1))
    T[:, :3, :3] = Rotation.random(G, random_state=1).as_matrix()
    d = rng.normal(size=(G, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    T[:, :3, 2] = -d
    x = np.cross(T[:, :3, 2], rng.normal(size=(G, 3)))
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    T[:, :3, 0], T[:, :3, 1] = x, np.cross(T[:, :3, 2], x)
    T[:, :3, 3] = centre + d * rng.uniform(0.05, 0.15, (G, 1))
    return T


def collision_table(points: int, hand: Hand) -> None:
    cloud = load_point_cloud(demo_objects()[0].parent / "mug_handle.obj", n_points=points, seed=0)
    pts = cloud.points
    rng = np.random.default_rng(0)
    print(
        "\n| hands | grasp type | Hand.hands_hit_points ms | sampling.hand_hits_points ms | "
        "hits | same answer |"
    )
    print("|---|---|---|---|---|---|")
    grid = cloud_grid(pts)  # once per cloud, as the pool builds it
    centre = pts.mean(axis=0)
    for G in (1000, 4000):
        T = _hand_poses(G, centre, rng)
        for gt in ("spherical", "cylindrical"):
            q = np.tile(hand.preshape(gt), (G, 1))
            t0 = time.perf_counter()
            ref = hand.hands_hit_points(pts, T, q[0], 0.0)
            t1 = time.perf_counter()
            ours = hand_hits_points(hand, T, np.full(G, gt), q, pts, grid=grid)
            t2 = time.perf_counter()
            print(
                f"| {G} | {gt} | {1000 * (t1 - t0):.0f} | {1000 * (t2 - t1):.0f} | "
                f"{int(ref.sum())} | {bool(np.array_equal(ref, ours))} |"
            )


def kernel_table(points: int, repeats: int, hand: Hand) -> None:
    """The numpy version of the pool's collision test against the kernel, same poses, cloud
    and k-d tree, interleaved; the answers are asserted equal."""
    cloud = load_point_cloud(demo_objects()[0].parent / "mug_handle.obj", n_points=points, seed=0)
    pts = cloud.points
    rng = np.random.default_rng(0)
    kd, grid = cKDTree(pts), cloud_grid(pts)  # each version's index of the cloud, built once
    centre = pts.mean(axis=0)
    print(
        "\n| hands | grasp type | margin | numpy (_batch_hits) ms | kernel ms | speed-up | hits "
        "| same answer |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for G in (1000, 4000):
        T = _hand_poses(G, centre, rng)
        for gt in ("spherical", "cylindrical"):
            q = np.tile(hand.preshape(gt), (G, 1))
            gts = np.full(G, gt)
            for margin in (0.0, 0.005):
                cells: dict = {}  # the link cells, built once for both (as the pool keeps them)
                hand_hits_points(hand, T[:1], gts[:1], q[:1], pts, margin, cells, grid)
                old_s, new_s = [], []
                for _ in range(repeats):  # interleaved
                    t0 = time.perf_counter()
                    old = hand_hits_points_numpy(hand, T, gts, q, pts, margin, cells, kd=kd)
                    t1 = time.perf_counter()
                    new = hand_hits_points(hand, T, gts, q, pts, margin, cells, grid)
                    t2 = time.perf_counter()
                    assert np.array_equal(old, new), (G, gt, margin)
                    old_s.append(t1 - t0)
                    new_s.append(t2 - t1)
                a, b = 1000 * statistics.median(old_s), 1000 * statistics.median(new_s)
                print(
                    f"| {G} | {gt} | {margin} | {a:.1f} | {b:.1f} | {a / b:.0f}x | "
                    f"{int(new.sum())} | True |"
                )


def _bits(x: object) -> object:
    """``x`` (arrays, tuples, lists, floats, strings) as something equal iff equal to the bit."""
    if isinstance(x, np.ndarray):
        return (x.dtype.str, x.shape, x.tobytes())
    if isinstance(x, (list, tuple)):
        return tuple(_bits(v) for v in x)
    if isinstance(x, float):
        return float(x).hex()
    return x


def _forget_preshapes(hand: Hand) -> None:
    """Empty the cache a preshape seen for the first time misses (its box poses and corners;
    the cells' layout in the boxes is the hand's and the margin's, kept from the first call)."""
    collision._HAND_POSES.pop(hand, None)


def pinch_table(points: int, repeats: int, hand: Hand) -> None:
    """Old against new on every call of the changed functions in the default object's pool."""
    cloud = load_point_cloud(demo_objects()[0].parent / "mug_handle.obj", n_points=points, seed=0)
    calls: dict[str, list] = {"placed": [], "height": [], "cells": []}
    placed, height, cells = pinch._placed, collision.hand_min_height, collision.link_cells

    def rec_placed(*a):  # type: ignore[no-untyped-def]
        calls["placed"].append(a)
        return placed(*a)

    def rec_height(*a):  # type: ignore[no-untyped-def]
        calls["height"].append(a)
        return height(*a)

    def rec_cells(*a):  # type: ignore[no-untyped-def]
        calls["cells"].append(a)
        return cells(*a)

    pinch._placed, build.hand_min_height, collision.link_cells = rec_placed, rec_height, rec_cells
    try:
        collision.hand_cell_cache(hand).clear()
        run_pipeline(cloud, PipelineParams(), hand, until="pool")
    finally:
        pinch._placed, build.hand_min_height, collision.link_cells = placed, height, cells

    def run_all(fn, args_list, forget: bool) -> tuple[float, list]:  # type: ignore[no-untyped-def]
        out, total = [], 0.0
        for a in args_list:
            if forget:
                _forget_preshapes(hand)
            t0 = time.perf_counter()
            out.append(fn(*a))
            total += time.perf_counter() - t0
        return total, out

    rows = [
        ("pinch._placed", "placed", pinch._placed_reference, pinch._placed),
        ("collision.link_cells", "cells", collision._link_cells_reference, collision.link_cells),
        (
            "collision.hand_min_height",
            "height",
            lambda h, T, g, q, s: collision._hand_min_height_reference(h, T, q, s),
            collision.hand_min_height,
        ),
    ]
    print(
        "\n| function (every call of the default pool) | calls | old ms | new ms, caches kept "
        "| new ms, caches emptied | speed-up (kept / emptied) | equal |"
    )
    print("|---|---|---|---|---|---|---|")
    for name, key, old_fn, new_fn in rows:
        args = calls[key]
        old_s, kept_s, cold_s = [], [], []
        for _ in range(repeats):  # interleaved
            t_old, ref = run_all(old_fn, args, False)
            t_cold, got_cold = run_all(new_fn, args, True)
            t_kept, got = run_all(new_fn, args, False)
            assert _bits(ref) == _bits(got) == _bits(got_cold), name
            old_s.append(t_old)
            kept_s.append(t_kept)
            cold_s.append(t_cold)
        a, b, c = (1000 * statistics.median(x) for x in (old_s, kept_s, cold_s))
        print(
            f"| {name} | {len(args)} | {a:.2f} | {b:.2f} | {c:.2f} | {a / b:.1f}x / {a / c:.1f}x "
            "| True |"
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
    t0 = time.perf_counter()
    collision_kernels.warm_up()
    print(
        f"collision kernels, first call (numba import + cache load or compile): "
        f"{time.perf_counter() - t0:.2f} s\n"
    )
    pool_table(a.points, a.repeats, hand, a.other_interval)
    collision_table(a.points, hand)
    kernel_table(a.points, max(a.repeats, 5), hand)
    pinch_table(a.points, max(a.repeats, 5), hand)


if __name__ == "__main__":
    main()
