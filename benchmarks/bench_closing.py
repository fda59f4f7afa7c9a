"""Closing model, batched (``Hand.close_fingers``) against the loop of ``Hand.close_finger`` on
the real slices of a pre-grasp pool.

For each object the pool is built (``run_pipeline(..., until="pool")``); for every pre-grasp
and every finger of its grasp type the slice is built as the planner's ``finger_slices`` does
at the pre-grasp pose (no approach, no table): the cloud in the hand frame, the points within
half a finger width of the flexion plane and within the finger's reach, thinned with the
planner's ``thin_2d`` (0.7 mm), the preshape's flexion as ``q_start``, the planner's defaults
(48 steps, 1 mm margin). One ``close_fingers`` call on all slices is timed against the loop of
``close_finger`` calls (same run, same slices), and every result is compared (q, path, contacts,
flags). Timings are medians of ``--repeats`` runs of the process's CPU time, one BLAS thread.

Usage: .venv/bin/python benchmarks/bench_closing.py [--repeats 5] [--chunk 64] [--truncate 200 5]
``--chunk N`` also times batches of N pre-grasps' slices (the planner's chunks); ``--truncate``
the same slices cut to their first N points (small slices, where ``close_finger`` is mostly
numpy call overhead).
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
from _timing import median_time  # noqa: E402

from pregrasp_core.hand import FingerClosing, load_hand  # noqa: E402
from pregrasp_core.io import load_point_cloud  # noqa: E402
from pregrasp_core.pipeline import run_pipeline  # noqa: E402
from pregrasp_core.planner import PlannerParams  # noqa: E402
from pregrasp_core.planner.slicing import thin_2d  # noqa: E402

OBJECTS = Path(__file__).resolve().parents[1] / "assets" / "objects"


def pool_slices(hand, name: str) -> tuple[list, list[int]]:
    """The slices of every pre-grasp of the object's pool, and the pre-grasp of each slice."""
    prm = PlannerParams()
    cloud = load_point_cloud(OBJECTS / f"{name}.obj", n_points=20000, seed=0)
    pool = run_pipeline(cloud, hand=hand, until="pool").pool
    points = np.asarray(cloud.points, dtype=np.float64)
    slices, owner = [], []
    for i in range(len(pool.spread)):  # loop over pre-grasps (benchmark set-up only)
        T = pool.T_world_hand[i]
        p_h = (points - T[:3, 3]) @ T[:3, :3]  # world -> hand frame
        for f in hand.fingers_for(pool.grasp_type[i]):
            plane = hand.flexion_plane(f, float(pool.spread[i]))
            band = np.flatnonzero(np.abs((p_h - plane.origin) @ plane.normal) <= 0.5 * f.width)
            p2, off = plane.to_plane(p_h[band])
            r_f = f.middle_length + np.hypot(f.distal_length, 0.5 * f.thickness)
            r_f += prm.closing_margin
            keep = (np.abs(off) <= 0.5 * f.width) & (
                p2[:, 0] ** 2 + p2[:, 1] ** 2 <= (r_f + 1e-9) ** 2
            )
            slices.append(
                (f, thin_2d(p2[keep], prm.slice_resolution), pool.q[i][list(f.flex_index)])
            )
            owner.append(i)
    return slices, owner


def same(a: FingerClosing, b: FingerClosing) -> bool:
    """Bit-equal results (q, path, contacts, flags)."""
    flags = ("stopped_middle", "stopped_distal", "palm_stop", "at_limits", "start_in_contact")
    return (
        a.finger == b.finger
        and np.array_equal(a.q, b.q)
        and np.array_equal(a.path, b.path)
        and all(getattr(a, k) == getattr(b, k) for k in flags)
        and len(a.contacts) == len(b.contacts)
        and all(
            c.link == d.link and c.index == d.index and np.array_equal(c.point, d.point)
            for c, d in zip(a.contacts, b.contacts, strict=True)
        )
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--chunk", type=int, default=64, help="pre-grasps per batch (0: skip)")
    ap.add_argument("--objects", nargs="+", default=["mug_handle", "bottle"])
    ap.add_argument(
        "--truncate",
        nargs="*",
        type=int,
        default=[200, 5],
        help="also time the same slices cut to their first N points (small slices)",
    )
    args = ap.parse_args()
    hand = load_hand()
    prm = PlannerParams()
    kw = dict(n_steps=prm.closing_steps, margin=prm.closing_margin)
    print(
        f"machine: {platform.machine()} {platform.processor() or ''}, {os.cpu_count()} cores, "
        f"python {platform.python_version()}, numpy {np.__version__}; one BLAS thread; "
        f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}"
    )
    print()
    print(
        "| object | batch | slices | points (median / max per slice) | loop of close_finger "
        "| close_fingers | per slice (loop / batch) | speed-up | results equal |"
    )
    print("|---|---|---:|---:|---:|---:|---:|---:|---|")
    for name in args.objects:
        slices, owner = pool_slices(hand, name)
        sizes = np.array([len(s[1]) for s in slices])
        ref = [hand.close_finger(*s, **kw) for s in slices]
        got = hand.close_fingers(slices, **kw)
        n_bad = sum(not same(a, b) for a, b in zip(got, ref, strict=True))
        t_loop = median_time(
            lambda sl=slices: [hand.close_finger(*s, **kw) for s in sl], args.repeats
        )
        t_batch = median_time(lambda sl=slices: hand.close_fingers(sl, **kw), args.repeats)
        rows = [("all", slices, t_loop, t_batch, n_bad)]
        if args.chunk > 0:
            owner = np.asarray(owner)
            groups = [
                [s for s, o in zip(slices, owner, strict=True) if lo <= o < lo + args.chunk]
                for lo in range(0, int(owner.max()) + 1, args.chunk)
            ]

            def batched(gs=groups):
                return [hand.close_fingers(g, **kw) for g in gs]

            t_chunks = median_time(batched, args.repeats)
            n_bad_c = sum(
                not same(a, b)
                for a, b in zip([c for cs in batched() for c in cs], ref, strict=True)
            )
            rows.append((f"{args.chunk} pre-grasps", slices, t_loop, t_chunks, n_bad_c))
        for n_keep in args.truncate:
            cut = [(f, P[:n_keep], q) for f, P, q in slices]
            ref_c = [hand.close_finger(*s, **kw) for s in cut]
            bad_c = sum(
                not same(a, b) for a, b in zip(hand.close_fingers(cut, **kw), ref_c, strict=True)
            )
            tl = median_time(lambda sl=cut: [hand.close_finger(*s, **kw) for s in sl], args.repeats)
            tb = median_time(lambda sl=cut: hand.close_fingers(sl, **kw), args.repeats)
            rows.append((f"all, first {n_keep} points", cut, tl, tb, bad_c))
        for label, sl, tl, tb, bad in rows:
            n = len(sl)
            sizes = np.array([len(s[1]) for s in sl])
            print(
                f"| {name} | {label} | {n} | {int(np.median(sizes))} / {int(sizes.max())} "
                f"| {tl * 1e3:.0f} ms | {tb * 1e3:.0f} ms "
                f"| {tl / n * 1e3:.3f} / {tb / n * 1e3:.3f} ms "
                f"| {tl / tb:.1f}x | {'yes' if bad == 0 else f'NO ({bad} differ)'} |"
            )


if __name__ == "__main__":
    main()
