"""Single views of shapes that are not demo objects, planned with each ``--occluded`` setting
and checked against the true mesh (issue 13).

The shapes: a standing torus, an L of two boxes, a cone, a hexagonal prism and a lying capsule
(trimesh primitives, standing on the table). Two views each, with the camera and table of
``scripts/make_views.py``: azimuth 40 degrees without noise and 200 degrees at 2 mm of range
noise, elevation 35. Per setting: the one used, grasps kept, whether the best is force closure,
its epsilon, its penetration of the true mesh (mm; negative = clear of it), its worst
contact's distance to the true surface (mm), and whether it lifts the TRUE mesh in MuJoCo
(``pregrasp_core.simulate``, ``docs/simulation.md``'s protocol on the view's support plane).

    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/bench_odd_shapes.py [--everyday]
        [--settings auto completed occupied]

``--everyday``: the shapes of ``bench_everyday.py`` (balls, a pen, a wrench, a phone, ...).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np
import trimesh

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from _timing import make_views_module  # noqa: E402

from pregrasp_core.io import load_point_cloud  # noqa: E402
from pregrasp_core.pipeline import PipelineParams, run_pipeline  # noqa: E402
from pregrasp_core.sensor.synthetic import LABEL_OBJECT, orbit_camera, render_view  # noqa: E402
from pregrasp_core.sensor.truth import MeshDistance, check_grasp  # noqa: E402
from pregrasp_core.simulate import simulate_grasps  # noqa: E402

mv = make_views_module()

SETTINGS = ("auto", "completed", "occupied")
VIEWS = ((40.0, 0.0), (200.0, 0.002))  # (azimuth degrees, noise metres)


def _standing(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """``mesh`` centred over the origin, its lowest point on the table (z = 0)."""
    mesh.apply_translation([-mesh.centroid[0], -mesh.centroid[1], -mesh.bounds[0, 2]])
    return mesh


def shapes() -> dict[str, trimesh.Trimesh]:
    turn_x = trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0])
    turn_y = trimesh.transformations.rotation_matrix(np.pi / 2, [0, 1, 0])
    upright = trimesh.creation.box([0.04, 0.04, 0.10])
    upright.apply_translation([0.04, 0, 0.07])
    return {
        "torus_up": _standing(trimesh.creation.torus(0.05, 0.015).apply_transform(turn_x)),
        "L_block": _standing(
            trimesh.util.concatenate([trimesh.creation.box([0.12, 0.04, 0.04]), upright])
        ),
        "cone": _standing(trimesh.creation.cone(0.04, 0.12)),
        "tall_prism": _standing(trimesh.creation.cylinder(0.03, 0.16, sections=6)),
        "capsule_lying": _standing(trimesh.creation.capsule(0.10, 0.025).apply_transform(turn_y)),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument(
        "--everyday", action="store_true",
        help="the 27 shapes of bench_everyday.py instead of the five above",
    )  # fmt: skip
    ap.add_argument("--settings", nargs="+", default=list(SETTINGS), choices=SETTINGS)
    args = ap.parse_args()
    if args.everyday:
        sys.path.insert(0, str(Path(__file__).resolve().parent))
        from bench_everyday import shapes as everyday

        chosen = everyday()
    else:
        chosen = shapes()
    out = Path(tempfile.mkdtemp(prefix="pregrasp_odd_"))
    rng = np.random.default_rng(0)
    print("| shape | azimuth | noise mm | setting | used | kept | best FC | epsilon "
          "| penetration mm | worst contact mm | lifts the true mesh |")  # fmt: skip
    print("|---|---:|---:|---|---|---:|---|---:|---:|---:|---|")
    for name, mesh in chosen.items():
        truth = MeshDistance(mesh)
        for az, noise in VIEWS:
            target, dist, half = mv.view_setup(mesh)
            cam = orbit_camera(target, dist, np.radians(az), np.radians(35.0))
            view = render_view(
                mesh.vertices, mesh.faces, cam, mv.INTRINSICS, mv.WIDTH, mv.HEIGHT,
                table_half=half, noise=noise, rng=rng,
            )  # fmt: skip
            pts, lab = view.points_world()
            path = out / f"{name}_{int(az)}.pcd"
            label = np.where(lab == LABEL_OBJECT, 2, 1).astype(np.uint8)
            path.write_bytes(mv.pcd_bytes(pts, label, view.T_world_camera))
            cloud = load_point_cloud(path)
            for setting in args.settings:
                res = run_pipeline(cloud, PipelineParams(occluded=setting), until="grasps")
                gs = res.grasps
                assert gs is not None and res.hand is not None
                row = f"| {name} | {az:.0f} | {1000 * noise:.0f} | {setting} | {res.occluded_used}"
                if len(gs.ranking) == 0:
                    print(row + " | 0 | - | - | - | - | - |")
                    continue
                best = gs.best if gs.best is not None else int(gs.ranking[0])
                g = gs.grasps[best]
                check = check_grasp(g, res.hand, truth)
                sim = simulate_grasps(res, [best], res.hand, mesh=mesh)[0]
                print(
                    f"{row} | {len(gs.ranking)} | {'yes' if gs.best is not None else 'no'} "
                    f"| {g.epsilon:.4f} | {1000 * check.penetration:.1f} "
                    f"| {1000 * check.worst_contact:.1f} "
                    f"| {'yes' if sim.success else sim.outcome} |"
                )


if __name__ == "__main__":
    main()
