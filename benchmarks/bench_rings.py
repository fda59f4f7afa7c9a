"""Rings, frames and rolls lying on the table: grasps, lifts and the pool's time (issue 11's lift
test on shapes that are not demo objects; the rim pinch of ``docs/pregrasps.md``, 6b).

    .venv/bin/python benchmarks/bench_rings.py [--points 20000] [--simulate 5]
        [--tree /path/to/other/checkout] [--repeats 9]

The shapes are made here with trimesh and stand on the table (z = 0): tori of outer diameter
80 to 144 mm (tube 20-30 mm), a wide tape roll (an annulus 140 mm across, 50 mm high) and a
square frame (150 mm, bars 20 mm). Each is sampled to ``--points`` points with its face normals
(seed 0), planned at default settings, and its best grasp and first ``--simulate`` grasps are
lifted in MuJoCo with the **true mesh** as the object (approach, close, lift 10 cm, hold 1 s,
``docs/simulation.md``). Per shape: the pool, the kept and the force-closure grasps, the best
grasp's type and epsilon, how many of the first ``--simulate`` lift, and whether the best does.

The last table times the pool stage (``PipelineResult.timings["pool"]``, minimum and median of
``--repeats`` runs, each recomputing every stage) on the default object and the shapes above.

``--tree``: import ``pregrasp_core`` from another checkout instead of this one (e.g. a
``git worktree`` of the commit before a change), to print the same tables for it; run both,
one after the other, on a quiet machine.
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import statistics  # noqa: E402

import numpy as np  # noqa: E402
import trimesh  # noqa: E402
from _timing import lift_first, shape_parser, start_shapes  # noqa: E402


def shapes() -> dict[str, trimesh.Trimesh]:
    """The shapes of the module docstring, standing on z = 0."""
    out: dict[str, trimesh.Trimesh] = {}
    for outer, tube in ((80, 20), (104, 24), (110, 30), (116, 30), (122, 30), (130, 30), (144, 24)):
        r = tube / 2000.0
        out[f"torus {outer} mm"] = trimesh.creation.torus(outer / 2000.0 - r, r)
    out["tape roll 140 mm"] = trimesh.creation.annulus(0.055, 0.07, 0.05)
    frame = trimesh.boolean.difference(
        [trimesh.creation.box([0.15, 0.15, 0.02]), trimesh.creation.box([0.11, 0.11, 0.04])]
    )
    out["frame 150 mm"] = frame
    for m in out.values():
        m.apply_translation([0.0, 0.0, -m.bounds[0, 2]])
    return out


def main() -> None:
    ap = shape_parser(__doc__.split("\n")[0])
    ap.add_argument("--simulate", type=int, default=5, help="grasps lifted per shape")
    ap.add_argument("--repeats", type=int, default=9, help="runs of the pool stage")
    args, hand = start_shapes(ap)
    from pregrasp_core.io import PointCloud, load_point_cloud
    from pregrasp_core.paths import DEFAULT_OBJECT
    from pregrasp_core.pipeline import run_pipeline

    print(f"| shape | pool | kept | force closure | best grasp | top {args.simulate} that lift |")
    print("|---|---:|---:|---:|---|---:|")
    clouds = {}
    for name, mesh in shapes().items():  # loop over the few shapes
        pts, face = trimesh.sample.sample_surface(mesh, args.points, seed=0)
        cloud = PointCloud(points=np.asarray(pts), normals=mesh.face_normals[face], source=name)
        clouds[name] = cloud
        res = run_pipeline(cloud, None, hand, until="grasps")
        best, n_up, n_sim = lift_first(res, hand, mesh, args.simulate)
        gs = res.grasps
        print(
            f"| {name} | {len(res.pool)} | {len(gs.ranking)} | {gs.n_force_closure} | {best} | "
            f"{n_up} of {n_sim} |"
        )
    print()
    print("| object | pool stage, min / median (ms) |")
    print("|---|---:|")
    timed = {"default object": load_point_cloud(DEFAULT_OBJECT, n_points=args.points, seed=0)}
    timed.update(clouds)
    for name, cloud in timed.items():  # loop over the objects
        run_pipeline(cloud, None, hand, until="pool")  # warm-up
        t = [
            run_pipeline(cloud, None, hand, until="pool").timings["pool"]
            for _ in range(args.repeats)
        ]
        print(f"| {name} | {1000 * min(t):.1f} / {1000 * statistics.median(t):.1f} |")


if __name__ == "__main__":
    main()
