"""The MuJoCo lift test on the demo objects (issue 11; figures in ``docs/simulation.md``).

For every demo object (``assets/objects``): plan with the default pipeline, build the lift
simulator (collision model from the mesh), simulate the best ``--top`` grasps and print per
object the best grasp's type and epsilon, its outcome, the successes among the top grasps, the
CPU time per simulated grasp and the model build time; then the totals. With ``--model-error``
also the collision model's error against the true mesh (``simulate.model_error``). One core:
BLAS on one thread, the process pinned to one CPU; times are CPU seconds (``process_time``).

Usage::

    .venv/bin/python benchmarks/bench_simulate.py [--top 5] [--objects mug can_soda]
        [--model-error] [--bare [--noise 0.002]]
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import datetime  # noqa: E402
import platform  # noqa: E402
import time  # noqa: E402

import mujoco  # noqa: E402
import numpy as np  # noqa: E402
from _timing import pin_one_core  # noqa: E402

from pregrasp_core.hand import load_hand  # noqa: E402
from pregrasp_core.io import load_point_cloud  # noqa: E402
from pregrasp_core.paths import demo_objects  # noqa: E402
from pregrasp_core.pipeline import PipelineParams, run_pipeline  # noqa: E402
from pregrasp_core.planner import PlannerParams  # noqa: E402
from pregrasp_core.simulate import (  # noqa: E402
    LiftSimulator,
    SimulationParams,
    load_object_mesh,
    model_error,
    object_from_cloud,
    object_from_mesh,
)
from pregrasp_core.simulate.run import grasp_specs  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--top", type=int, default=5, help="grasps simulated per object")
    ap.add_argument("--objects", nargs="*", default=None, help="object names (default: all)")
    ap.add_argument("--model-error", action="store_true", help="also the collision model error")
    ap.add_argument(
        "--bare", action="store_true", help="plan on each cloud without its normals (a PLY "
        "with xyz only: the orientation by visibility and the crest rule, docs/design.md)",
    )  # fmt: skip
    ap.add_argument(
        "--noise", type=float, default=0.0, help="metres: Gaussian noise added to every "
        "coordinate of the cloud (seed 1; a fused scan's), with --bare",
    )  # fmt: skip
    ap.add_argument(
        "--synchronous", action="store_true", help="SimulationParams.synchronous: fingers "
        "reach their planned contacts at the same moment",
    )  # fmt: skip
    args = ap.parse_args()
    pinned = pin_one_core()
    now = datetime.datetime.now(datetime.UTC)
    cpu_name = platform.processor() or platform.machine()
    print(
        f"# {now:%Y-%m-%d %H:%M} UTC, {cpu_name}, python {platform.python_version()}, "
        f"mujoco {mujoco.__version__}, {pinned}"
    )
    hand = load_hand()
    sp = SimulationParams(synchronous=args.synchronous)
    pp = PipelineParams(planner=PlannerParams(threads=1))
    paths = [p for p in demo_objects() if args.objects is None or p.stem in args.objects]
    print(
        "| object | best type | epsilon | best outcome | top-5 lifted | pieces | mass (kg) "
        "| model build (s) | CPU per grasp (s) | notes |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    n_best = n_ok = n_all = 0
    cpu: list[float] = []
    errors = []
    for path in paths:
        cloud = source = load_point_cloud(path)
        if args.bare:  # the same points, normals dropped; the mesh is found by its source
            pts = np.asarray(cloud.points)
            if args.noise > 0.0:
                rng = np.random.default_rng(1)
                pts = pts + rng.normal(scale=args.noise, size=pts.shape)
            cloud = dataclasses.replace(cloud, points=pts, normals=None)
        result = run_pipeline(cloud, pp, hand, until="grasps")
        gs = result.grasps
        top = [int(i) for i in gs.ranking[: args.top]]
        mesh = load_object_mesh(source)  # the true mesh, also for a noisy cloud
        t0 = time.process_time()
        obj = object_from_mesh(mesh, sp.object)
        sim = LiftSimulator(hand, obj, result.masks.support, sp, pp.planner.quality.mu)
        build = time.process_time() - t0
        res = [sim.run(s)[0] for s in grasp_specs(hand, top, gs, result.pool)]
        cpu += [r.cpu_time for r in res]
        ok = sum(r.success for r in res)
        n_ok += ok
        n_all += len(res)
        best = gs.grasps[top[0]] if top else None
        n_best += bool(res and res[0].success)
        notes = "held (not at rest)" if sim.held else ""
        print(
            f"| {path.stem} | {best.grasp_type if best else '-'} | "
            f"{best.epsilon:.3f} | {res[0].outcome if res else '-'} | {ok}/{len(res)} | "
            f"{obj.n_pieces} | {obj.mass:.3f} | {build:.2f} | "
            f"{np.median([r.cpu_time for r in res]):.3f} | {notes} |",
            flush=True,
        )
        if args.model_error:
            cobj = object_from_cloud(cloud.points, result.normals, sp.object)
            errors.append(
                (
                    path.stem,
                    obj,
                    model_error(obj, mesh, 20000, 20000),
                    cobj,
                    model_error(cobj, mesh, 20000, 20000),
                )
            )
    print(
        f"\nbest grasp lifted on {n_best}/{len(paths)} objects; top-{args.top}: {n_ok}/{n_all} "
        f"= {n_ok / max(n_all, 1):.0%}; CPU per grasp median {np.median(cpu):.3f} s, "
        f"90th percentile {np.percentile(cpu, 90):.3f} s, max {np.max(cpu):.3f} s"
    )
    if errors:
        print(
            "\n| object | source | pieces | concavity (mm) | mean dist (mm) | p95 (mm) "
            "| Hausdorff (mm) | volume ratio | IoU |"
        )
        print("|---|---|---|---|---|---|---|---|---|")
        for name, obj, e, cobj, ce in errors:
            for src, o, err in (("mesh", obj, e), ("cloud", cobj, ce)):
                print(
                    f"| {name} | {src} | {o.n_pieces} | {1e3 * o.concavity:.1f} | "
                    f"{1e3 * err.mean_distance:.2f} | {1e3 * err.p95_distance:.2f} | "
                    f"{1e3 * err.hausdorff:.1f} | {err.volume_ratio:.3f} | {err.iou:.3f} |"
                )


if __name__ == "__main__":
    main()
