"""Grasps planned on single views, checked against the TRUE mesh (issue 13).

For every view of ``scripts/make_views.py``'s manifest (by default the 45 views of mug,
can_soda, box_cereal, bottle and ramekin; ``--all`` for every object): the PCD is loaded as a
user's scene is (``load_point_cloud``: table by RANSAC, the object, smoothing of a noisy view,
completion), planned with default parameters (``run_pipeline(..., until="grasps")``), and the
best grasp (the best force-closure grasp; the top-ranked one where none is force closure) is
measured against the mesh the view was cast from (``pregrasp_core.sensor.truth``):

- penetration: the deepest of 7 x 7 x 7 grid points in every link box inside the mesh;
- contacts: the largest distance of the grasp's contact points to the mesh surface;
- the number of its contacts on assumed (completed) points;
- the completion's copies against the mesh: the median signed distance of the copied points
  (positive inside; not the midpoints that close holes), whether the copy leans in or out;
- parts: leaves of the decomposition against the complete cloud's (the mesh sampled to 20,000
  points), the issue's "within 1".

Targets (issue 13): force closure on >= 80 % of the views, penetration <= 2 mm, contacts within
3 mm, parts within 1 on >= 80 %.

With ``--simulate K`` the best grasp and the first K of the ranking are also lifted in MuJoCo
(``pregrasp_core.simulate``, the protocol of ``docs/simulation.md``) with the TRUE mesh as the
object on the view's support plane: columns ``lift`` (the best grasp lifted it) and ``top``
(how many of the K did); ``--json FILE`` writes every row.

Usage: .venv/bin/python scripts/make_views.py /tmp/pregrasp_views   (once)
       PYTHONPATH=. .venv/bin/python benchmarks/bench_partial_grasps.py [VIEWS] [--all]
                                               [--clearance D] [--no-smooth]
                                               [--occluded auto completed occupied]
                                               [--simulate K] [--json FILE]

``--occluded`` with several settings plans each view with each of them in turn (interleaved, one
run) and prints one table per setting; ``kept`` is the number of kept grasps (the tables add
the pre-grasps left in the pool by its collision filter), ``cpu s`` the CPU seconds of the
view (this process and the planner's forked copies: ``os.times``).
"""

from __future__ import annotations

import os
import sys

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import trimesh  # noqa: E402
from _timing import views_manifest  # noqa: E402

from pregrasp_core import pipeline  # noqa: E402
from pregrasp_core.decomposition import decompose  # noqa: E402
from pregrasp_core.hand import Hand  # noqa: E402
from pregrasp_core.io import load_point_cloud  # noqa: E402
from pregrasp_core.pipeline import PipelineParams, run_pipeline  # noqa: E402
from pregrasp_core.sensor import occluded  # noqa: E402
from pregrasp_core.sensor import view as sensor_view  # noqa: E402
from pregrasp_core.sensor.occluded import OCCLUDED_MODES  # noqa: E402
from pregrasp_core.sensor.truth import MeshDistance, check_grasp  # noqa: E402

DEFAULT_OBJECTS = ("mug", "can_soda", "box_cereal", "bottle", "ramekin")
PEN_MAX, CONTACT_MAX = 0.002, 0.003


@dataclasses.dataclass
class Row:
    """One view's figures."""

    object: str
    noise: float
    parts: int
    full: int
    found: bool = False
    fc: bool = False
    pen: float = np.inf
    cont: float = np.inf
    copy: float = np.nan
    kept: int = 0
    pool: int = 0
    cpu: float = 0.0
    mode: str = "completed"
    used: str = "completed"
    fallback: str | None = None
    eps: float = 0.0
    camera: int = 0
    lift: bool | None = None
    top_lifts: int = 0
    top_n: int = 0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("views", nargs="?", default="/tmp/pregrasp_views", type=Path)
    parser.add_argument("--all", action="store_true", help="every object of the manifest")
    parser.add_argument("--objects", nargs="*", default=None)
    parser.add_argument("--clearance", type=float, default=None,
                        help="PlannerParams.assumed_clearance (default: its default)")  # fmt: skip
    parser.add_argument("--no-smooth", action="store_true", help="no smoothing of noisy views")
    parser.add_argument("--no-parts", action="store_true", help="skip the parts count")
    parser.add_argument(
        "--occluded", nargs="+", default=["auto"], choices=OCCLUDED_MODES,
        help="PipelineParams.occluded settings, each view planned with each (default: auto, "
        "the default; its rows say auto:occ or auto:com, the setting it used)",
    )  # fmt: skip
    parser.add_argument(
        "--occluded-margin", type=float, default=None, metavar="M",
        help="OccludedParams.margin of the occupied setting (default: its default)",
    )  # fmt: skip
    parser.add_argument(
        "--occluded-carve", type=float, default=None, metavar="D",
        help="OccludedParams.carve of the occupied setting (default: its default)",
    )  # fmt: skip
    parser.add_argument(
        "--simulate", type=int, default=0, metavar="K",
        help="also lift the best grasp and the first K of the ranking in MuJoCo with the TRUE "
        "mesh as the object (pregrasp_core.simulate; columns lift and top-K)",
    )  # fmt: skip
    parser.add_argument(
        "--auto-min-epsilon", type=float, default=None, metavar="F",
        help="pipeline.AUTO_MIN_EPSILON, the weak-force-closure floor of auto (default: its "
        "default, 0 = off)",
    )  # fmt: skip
    parser.add_argument(
        "--synchronous", action="store_true", help="SimulationParams.synchronous for the lifts: "
        "the fingers reach their planned contacts at the same moment",
    )  # fmt: skip
    parser.add_argument("--json", type=Path, default=None, help="write every row to this file")
    args = parser.parse_args()
    if args.auto_min_epsilon is not None:
        pipeline.AUTO_MIN_EPSILON = args.auto_min_epsilon
    for name in ("margin", "carve"):
        value = getattr(args, f"occluded_{name}")
        if value is not None:
            occluded.DEFAULT_OCCLUDED = dataclasses.replace(
                occluded.DEFAULT_OCCLUDED, **{name: value}
            )
    manifest = views_manifest(args.views)
    if manifest is None:
        return 1
    objects = None if args.all else set(args.objects or DEFAULT_OBJECTS)
    manifest = [e for e in manifest if objects is None or e["object"] in objects]
    if args.no_smooth:
        sensor_view.SMOOTH_K = 0
    params = PipelineParams()
    if args.clearance is not None:
        params = dataclasses.replace(
            params, planner=dataclasses.replace(params.planner, assumed_clearance=args.clearance)
        )
    hand = Hand.load()
    print(f"# {platform.node()} {platform.processor() or platform.machine()}, "
          f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, {len(manifest)} views, "
          f"one BLAS thread, assumed_clearance {params.planner.assumed_clearance * 1e3:.1f} mm, "
          f"smoothing {'off' if args.no_smooth else 'on'}, "
          f"occluded {' / '.join(args.occluded)} (auto's epsilon floor "
          f"{pipeline.AUTO_MIN_EPSILON:g}, margin "
          f"{occluded.DEFAULT_OCCLUDED.margin * 1e3:.0f} mm, carve "
          f"{occluded.DEFAULT_OCCLUDED.carve * 1e3:.0f} mm), load "
          f"{' '.join(f'{x:.2f}' for x in os.getloadavg())}; {' '.join(sys.argv[1:])}")  # fmt: skip
    print(
        f"{'object':<12} {'cam':>3} {'noise':>5} {'occluded':<9} {'kept':>4} {'fc':>4} {'eps':>6} "
        f"{'pen mm':>6} {'link':<13} {'cont mm':>7} {'assumed':>7} {'parts':>7} {'copy mm':>7} "
        f"{'s':>5} {'cpu s':>5}" + (f" {'lift':>4} {'top':>5}" if args.simulate else "")
    )
    truths: dict[str, MeshDistance] = {}
    full_parts: dict[str, int] = {}
    rows: list[Row] = []
    runs = [(e, mode) for e in manifest for mode in args.occluded]
    for e, mode in runs:
        t0, c0 = time.perf_counter(), os.times()
        cloud = load_point_cloud(args.views / e["pcd"])
        res = run_pipeline(cloud, dataclasses.replace(params, occluded=mode), hand, until="grasps")
        dt, c1 = time.perf_counter() - t0, os.times()
        cpu = sum(c1[:4]) - sum(c0[:4])
        gs = res.grasps
        assert gs is not None and res.tree is not None
        name = e["object"]
        if name not in truths:
            mesh = trimesh.load(args.views / e["true_mesh"], force="mesh")
            truths[name] = MeshDistance(mesh)
            if not args.no_parts:
                full = load_point_cloud(args.views / e["true_mesh"]).points
                full_parts[name] = len(decompose(full).leaves())
        parts = len(res.tree.leaves())
        row = Row(name, float(e["noise_m"]), parts, full_parts.get(name, -1))
        row.kept, row.cpu, row.mode, row.used = len(gs.ranking), cpu, mode, res.occluded_used
        row.fallback = res.fallback
        row.pool = len(res.pool) if res.pool is not None else 0
        row.camera = int(e["camera"])
        best = gs.best
        if best is None and len(gs.ranking):
            best = int(gs.ranking[0])
        shown = f"auto:{res.occluded_used[:3]}" if mode == "auto" else mode
        line = f"{name:<12} {e['camera']:>3} {e['noise_m'] * 1000:>4.0f}m {shown:<9} "
        line += f"{len(gs.ranking):>4} "
        line += f"{gs.n_force_closure:>4} "
        if best is None:
            line += f"{'-':>6} {'-':>6} {'-':<13} {'-':>7} {'-':>7}"
        else:
            g = gs.grasps[best]
            ch = check_grasp(g, hand, truths[name])
            n_ass = sum(c.assumed for c in g.contacts)
            row.found, row.fc = True, g.epsilon > 0.0
            row.pen, row.cont, row.eps = ch.penetration, ch.worst_contact, float(g.epsilon)
            line += (f"{g.epsilon:>6.3f} {ch.penetration * 1e3:>6.1f} {ch.link:<13} "
                     f"{ch.worst_contact * 1e3:>7.1f} {n_ass:>3}/{g.n_contacts:<3}")  # fmt: skip
        done = cloud.sensor.completion if cloud.sensor is not None else None
        if done is not None and np.any(done.copied):
            row.copy = float(np.median(truths[name].signed(cloud.points[done.copied])))
        line += f" {parts:>3}/{full_parts.get(name, -1):<3} {row.copy * 1e3:>+7.1f} {dt:>5.1f}"
        line += f" {cpu:>5.1f}"
        if args.simulate and best is not None:  # one MuJoCo scene (the true mesh) for them all
            from pregrasp_core.simulate import SimulationParams, simulate_grasps

            sims = simulate_grasps(
                res, [best, *gs.ranking[: args.simulate]], hand,
                SimulationParams(synchronous=args.synchronous), mesh=truths[name].mesh,
            )  # fmt: skip
            lifted = [s.success for s in sims]
            row.lift = lifted[0]
            row.top_lifts, row.top_n = sum(lifted[1:]), len(lifted) - 1
            line += f" {'yes' if row.lift else 'no':>4} {row.top_lifts:>2}/{row.top_n:<2}"
        rows.append(row)
        print(line, flush=True)

    def summary(label: str, rs: list[Row]) -> str:
        n = len(rs)
        ok = [r for r in rs if r.found]
        fc = sum(r.fc for r in ok)
        pen = sum(r.pen <= PEN_MAX for r in ok)
        cont = sum(r.cont <= CONTACT_MAX for r in ok)
        both = sum(r.fc and r.pen <= PEN_MAX and r.cont <= CONTACT_MAX for r in ok)
        parts = sum(abs(r.parts - r.full) <= 1 for r in rs)
        pm = np.array([r.pen for r in ok]) * 1e3
        cm = np.array([r.cont for r in ok]) * 1e3

        def med(a: np.ndarray) -> str:
            return f"{np.median(a):.1f} / {a.max():.1f}" if len(a) else "-"

        cp = np.array([r.copy for r in rs if np.isfinite(r.copy)]) * 1e3
        lean = (f"{np.median(cp):+.1f} / {np.median(np.abs(cp)):.1f} / {np.abs(cp).max():.1f}"
                if len(cp) else "-")  # fmt: skip
        kept = np.array([r.kept for r in rs])
        pool = np.array([r.pool for r in rs])
        cpu = np.array([r.cpu for r in rs])
        sim = [r for r in ok if r.lift is not None]
        lifted = (f" {sum(r.lift for r in sim)}/{n} | "
                  f"{sum(r.top_lifts for r in sim)}/{sum(r.top_n for r in sim)} |"
                  if args.simulate else "")  # fmt: skip
        return (f"| {label} | {fc}/{n} | {med(pm)} | {pen}/{n} | {med(cm)} | {cont}/{n} | "
                f"{both}/{n} | {parts}/{n} | {lean} | {pool.sum()} | "
                f"{int(np.median(kept))} / {kept.sum()} | "
                f"{np.median(cpu):.2f} / {cpu.max():.2f} |{lifted}")  # fmt: skip

    for mode in args.occluded:
        mine = [r for r in rows if r.mode == mode]
        print()
        why = {f: sum(r.fallback == f for r in mine) for f in {r.fallback for r in mine} if f}
        fell = sum(r.used == "completed" for r in mine)
        print(
            f"occluded = {mode}:"
            + (
                f" {fell} of {len(mine)} views planned with the back completed ("
                + ", ".join(f"{k} {v}" for k, v in sorted(why.items()))
                + ")"
                if mode == "auto"
                else ""
            )
        )
        print(
            "| views | best grasp force closure | penetration median / worst (mm) | "
            "penetration <= 2 mm | contact median / worst (mm) | contacts within 3 mm | "
            "all three | parts within 1 | copies' median signed distance: median / median abs "
            "/ worst abs (mm) | pre-grasps in the pool (sum) | grasps kept median / sum | "
            "CPU s per view median / worst |"
            + (" best grasp lifts the true mesh | top grasps that lift |" if args.simulate else "")
        )
        print("| --- " * (14 if args.simulate else 12) + "|")
        for name in sorted({r.object for r in mine}):
            print(summary(name, [r for r in mine if r.object == name]))
        for noise in sorted({r.noise for r in mine}):
            print(summary(f"noise {noise * 1000:.0f} mm", [r for r in mine if r.noise == noise]))
        print(summary("all", mine))
    if args.json is not None:
        args.json.write_text(json.dumps([dataclasses.asdict(r) for r in rows], default=float))
    print(f"# load at the end {' '.join(f'{x:.2f}' for x in os.getloadavg())}, "
          f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}")  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
