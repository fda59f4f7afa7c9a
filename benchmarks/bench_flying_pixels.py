"""Flying pixels: demo views with mixed edge pixels, planned with and without ``--flying-pixels``.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/bench_flying_pixels.py \\
        [--objects mug,can_soda] [--fractions 0.3 1.0] [--noise 0.001]

Each demo mesh is ray cast as ``scripts/make_views.py`` casts it (its cameras, intrinsics and
seeds), then ``sensor.synthetic.add_mixed_pixels`` gives ``--fractions`` of the pixels at a
depth jump of more than 2 cm a depth between the jump's two sides (the time-of-flight model); the
scene is written as a user's PCD (``VIEWPOINT`` = the camera) and planned at the default
settings as ``pregrasp plan`` plans it, once as it is and once with the flying-pixel test
(``SensorOptions(flying_pixels=True)``). Per view and setting: the scene points dropped, the
object's seen points more than 3 mm from the true mesh, the parts, and the best grasp's epsilon,
deepest penetration of the true mesh and worst contact distance to it (``sensor.truth``), and
whether it passes all three checks of ``docs/partial-views.md`` (force closure, penetration at
most 2 mm, contacts within 3 mm). Fraction 0 gives the clean views.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # one BLAS thread, before numpy loads

import argparse  # noqa: E402
import platform  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # this checkout's pregrasp_core, not an installed one

from _timing import make_views_module  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--objects", default="mug,can_soda,box_cereal,fruit_lemon,tool_hammer")
    ap.add_argument("--fractions", type=float, nargs="+", default=[0.3, 1.0])
    ap.add_argument("--noise", type=float, default=0.001, help="range noise, metres")
    args = ap.parse_args()

    import trimesh

    from pregrasp_core.io import SensorOptions, load_point_cloud
    from pregrasp_core.paths import OBJECTS_DIR
    from pregrasp_core.pipeline import PipelineParams, run_pipeline
    from pregrasp_core.sensor.synthetic import add_mixed_pixels
    from pregrasp_core.sensor.truth import MeshDistance, check_grasp

    mv = make_views_module()
    tmp = Path(tempfile.mkdtemp(prefix="bench_flying_"))
    print(
        f"# {platform.machine()}, Python {platform.python_version()}, "
        f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, load {os.getloadavg()[0]:.1f}"
    )
    print("| object | camera | mixed | --flying-pixels | dropped | seen off > 3 mm | parts | "
          "best epsilon | penetration mm | worst contact mm | all three |")  # fmt: skip
    print("|---|---:|---:|---|---:|---:|---:|---:|---:|---:|---|")
    passed = {False: 0, True: 0}
    n_views = 0
    for name in args.objects.split(","):
        mesh = trimesh.load(OBJECTS_DIR / f"{name}.obj", force="mesh")
        truth = MeshDistance(mesh)
        for cam in range(len(mv.AZIMUTHS_DEG)):
            for frac in args.fractions:
                seed = mv.view_seed(name, cam, args.noise)
                view = mv.make_view(mesh, mv.AZIMUTHS_DEG[cam], args.noise, seed)
                if frac > 0.0:
                    view = add_mixed_pixels(view, frac, 0.02, np.random.default_rng(seed + 1))
                pts, lab = view.points_world()
                path = tmp / f"{name}_{cam}_{frac:g}.pcd"
                path.write_bytes(mv.pcd_bytes(pts, lab, view.T_world_camera))
                n_views += 1
                for on in (False, True):
                    cloud = load_point_cloud(path, sensor=SensorOptions(flying_pixels=on))
                    seen = cloud.points if cloud.assumed is None else cloud.points[~cloud.assumed]
                    off = int(np.count_nonzero(np.abs(truth.signed(seen)) > 0.003))
                    res = run_pipeline(cloud, PipelineParams(), until="grasps")
                    gs = res.grasps
                    parts = len(res.tree.leaves()) if res.tree is not None else 0
                    row = (f"| {name} | {cam} | {frac:g} | {'on' if on else 'off'} | "
                           f"{cloud.info['scene'].get('n_flying', 0)} | {off} of {len(seen)} | "
                           f"{parts} | ")  # fmt: skip
                    if gs is None or gs.best is None or res.hand is None:
                        print(row + "- | - | - | no |")
                        continue
                    g = gs.grasps[gs.best]
                    ch = check_grasp(g, res.hand, truth)
                    ok = ch.penetration <= 0.002 and ch.worst_contact <= 0.003
                    passed[on] += ok
                    print(row + f"{g.epsilon:.4f} | {1000 * ch.penetration:.1f} | "
                          f"{1000 * ch.worst_contact:.1f} | {'yes' if ok else 'no'} |")  # fmt: skip
    print(f"\nall three checks: off {passed[False]}/{n_views}, on {passed[True]}/{n_views}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
