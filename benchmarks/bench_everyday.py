"""Everyday shapes on a table, as a user would bring them: the pool, the force-closure grasps,
the best grasp and how many of the first 5 lift the TRUE mesh in MuJoCo (``docs/simulation.md``).

    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/bench_everyday.py [--tree CHECKOUT]
        [--points 20000] [--only NAME] [--estimated] [--synchronous]

The shapes are made here with trimesh and stand on the table (z = 0): a phone, a book, a pen,
balls of 20 to 120 mm, cubes resting on an edge, tilted pebbles, a wine glass, a hammer, a
wrench, a cereal box, a large box, a flat L bracket, a bottle lying down, cones point up and
down, a plate, a tilted box, a dumbbell, and four objects with a handle (a bucket and a basket
with an arched handle, a kettlebell, a toolbox with a bar on top). Each is sampled to
``--points`` points with its face normals (seed 0; ``--estimated``: also without normals,
estimated by the pipeline) and planned at default settings. ``--tree``: import ``pregrasp_core``
from another checkout (e.g. a ``git worktree`` of the commit before a change) to print the same
table for it.
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")


import numpy as np  # noqa: E402
import trimesh  # noqa: E402
from _timing import lift_first, shape_parser, start_shapes  # noqa: E402

R = trimesh.transformations.rotation_matrix


def revolve(profile: list[list[float]], sections: int = 48) -> trimesh.Trimesh:
    """A solid of revolution about z from its (radius, height) profile."""
    return trimesh.creation.revolve(np.asarray(profile), sections=sections)


def arch(span: float, bar: float, height_above: float) -> trimesh.Trimesh:
    """The upper half of a ring of ``span`` across and ``bar`` thick in the xz plane, its
    centre ``height_above`` the origin (a bucket's or a basket's handle)."""
    t = trimesh.creation.torus(span / 2, bar / 2, major_sections=64, minor_sections=16)
    t.apply_transform(R(np.pi / 2, [1, 0, 0]))  # ring in the xz plane
    upper = trimesh.creation.box([span + 2 * bar, 2 * bar, span / 2 + bar])
    upper.apply_translation([0, 0, (span / 2 + bar) / 2])
    a = trimesh.boolean.intersection([t, upper])
    a.apply_translation([0, 0, height_above])
    return a


def shapes() -> dict[str, trimesh.Trimesh]:
    """The shapes of the module docstring, standing on z = 0."""
    out: dict[str, trimesh.Trimesh] = {}
    for d in (20, 30, 40, 45, 50, 60):
        out[f"ball {d}"] = trimesh.creation.icosphere(4, d / 2000)
    for d in (30, 40):
        cube = trimesh.creation.box([d / 1000] * 3)
        out[f"cube {d} on an edge"] = cube.apply_transform(R(np.pi / 4, [1, 0, 0]))
        pebble = trimesh.creation.icosphere(4, 1.0)
        pebble.apply_scale([d / 2000, d / 2600, d / 3000])
        out[f"pebble {d} tilted"] = pebble.apply_transform(R(0.6, [1, 1, 0]))
    out["phone 150x75x8"] = trimesh.creation.box([0.15, 0.075, 0.008])
    out["book 230x160x30"] = trimesh.creation.box([0.23, 0.16, 0.03])
    out["pen 10x140 lying"] = trimesh.creation.cylinder(0.005, 0.14).apply_transform(
        R(np.pi / 2, [0, 1, 0])
    )
    out["ball 120"] = trimesh.creation.icosphere(4, 0.06)
    out["marble 25"] = trimesh.creation.icosphere(3, 0.0125)
    out["wine glass"] = revolve(
        [
            [0, 0],
            [0.035, 0],
            [0.035, 0.004],
            [0.004, 0.01],
            [0.004, 0.09],
            [0.03, 0.11],
            [0.04, 0.15],
            [0.038, 0.15],
            [0.028, 0.112],
            [0, 0.1],
        ]
    )
    h = trimesh.creation.cylinder(0.014, 0.25).apply_transform(R(np.pi / 2, [0, 1, 0]))
    head = trimesh.creation.box([0.025, 0.10, 0.025])
    head.apply_translation([0.125, 0, 0])
    out["hammer lying"] = trimesh.util.concatenate([h, head])
    out["wrench 180x20x6"] = trimesh.creation.box([0.18, 0.02, 0.006])
    out["cereal 60x60x200"] = trimesh.creation.box([0.06, 0.06, 0.20])
    out["big box 200x200x100"] = trimesh.creation.box([0.2, 0.2, 0.1])
    a = trimesh.creation.box([0.10, 0.02, 0.005])
    b = trimesh.creation.box([0.02, 0.10, 0.005])
    b.apply_translation([0.04, 0.04, 0])
    out["L bracket flat"] = trimesh.util.concatenate([a, b])
    out["bottle lying 70x220"] = trimesh.creation.cylinder(0.035, 0.22).apply_transform(
        R(np.pi / 2, [0, 1, 0])
    )
    out["cone point up 80x120"] = trimesh.creation.cone(0.04, 0.12)
    out["cone point down"] = trimesh.creation.cone(0.04, 0.12).apply_transform(R(np.pi, [1, 0, 0]))
    out["plate 220x15"] = revolve(
        [[0, 0], [0.08, 0], [0.11, 0.015], [0.105, 0.015], [0.078, 0.004], [0, 0.004]]
    )
    out["tilted box 50x80x120"] = trimesh.creation.box([0.05, 0.08, 0.12]).apply_transform(
        R(0.5, [1, 1, 0])
    )
    out["dumbbell"] = trimesh.util.concatenate(
        [
            trimesh.creation.cylinder(0.012, 0.12).apply_transform(R(np.pi / 2, [0, 1, 0])),
            trimesh.creation.cylinder(0.035, 0.03)
            .apply_transform(R(np.pi / 2, [0, 1, 0]))
            .apply_translation([0.075, 0, 0]),
            trimesh.creation.cylinder(0.035, 0.03)
            .apply_transform(R(np.pi / 2, [0, 1, 0]))
            .apply_translation([-0.075, 0, 0]),
        ]
    )
    # objects with a handle (session 20: measured, not yet handled, docs/limits.md)
    bucket = trimesh.boolean.difference(
        [
            trimesh.creation.cylinder(0.075, 0.14, sections=64),
            trimesh.creation.cylinder(0.072, 0.14, sections=64).apply_translation([0, 0, 0.004]),
        ]
    )
    bucket.apply_translation([0, 0, 0.07])
    out["bucket 150 with arch"] = trimesh.util.concatenate([bucket, arch(0.15, 0.008, 0.14)])
    basket = trimesh.boolean.difference(
        [
            trimesh.creation.box([0.16, 0.11, 0.07]),
            trimesh.creation.box([0.154, 0.104, 0.07]).apply_translation([0, 0, 0.004]),
        ]
    )
    basket.apply_translation([0, 0, 0.035])
    out["basket 160x110 with arch"] = trimesh.util.concatenate([basket, arch(0.10, 0.012, 0.07)])
    kb = trimesh.creation.icosphere(4, 0.06)
    kb.apply_translation([0, 0, 0.06])
    out["kettlebell"] = trimesh.util.concatenate([kb, arch(0.09, 0.02, 0.1)])
    box = trimesh.creation.box([0.25, 0.18, 0.12])
    box.apply_translation([0, 0, 0.06])
    bar = trimesh.creation.cylinder(0.006, 0.10).apply_transform(R(np.pi / 2, [0, 1, 0]))
    bar.apply_translation([0, 0, 0.155])
    posts = [
        trimesh.creation.cylinder(0.005, 0.035).apply_translation([x, 0, 0.1375])
        for x in (-0.045, 0.045)
    ]
    out["toolbox 250 with top bar"] = trimesh.util.concatenate([box, bar, *posts])
    for m in out.values():
        m.apply_translation([-m.centroid[0], -m.centroid[1], -m.bounds[0, 2]])
    return out


def main() -> None:
    ap = shape_parser(__doc__.split("\n")[0])
    ap.add_argument("--only", default="", help="only the shapes whose name contains this")
    ap.add_argument("--estimated", action="store_true", help="also plan without normals")
    ap.add_argument("--synchronous", action="store_true", help="SimulationParams.synchronous")
    args, hand = start_shapes(ap)
    from pregrasp_core.io import PointCloud
    from pregrasp_core.pipeline import run_pipeline
    from pregrasp_core.simulate import SimulationParams

    print("| shape | normals | pool | kept | force closure | best grasp | first 5 that lift |")
    print("|---|---|---:|---:|---:|---|---:|")
    for name, mesh in shapes().items():  # loop over the few shapes
        if args.only not in name:
            continue
        pts, face = trimesh.sample.sample_surface(mesh, args.points, seed=0)
        for given in (True, False) if args.estimated else (True,):
            normals = mesh.face_normals[face] if given else None
            cloud = PointCloud(points=np.asarray(pts), normals=normals, source=name)
            res = run_pipeline(cloud, None, hand, until="grasps")
            sp = SimulationParams(synchronous=True) if args.synchronous else None
            best, n_up, n_sim = lift_first(res, hand, mesh, 5, sp)
            gs = res.grasps
            print(
                f"| {name} | {'mesh' if given else 'estimated'} | {len(res.pool)} | "
                f"{len(gs.ranking)} | {gs.n_force_closure} | {best} | {n_up} of {n_sim} |",
                flush=True,
            )


if __name__ == "__main__":
    main()
