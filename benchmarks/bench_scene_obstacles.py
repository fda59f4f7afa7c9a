"""The rest of the scene as obstacles: wall and clutter views planned with and without them.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/bench_scene_obstacles.py [--top 20]

Rendered depth views (``sensor.synthetic``, 1 mm of noise), written as a user's PCD
(``VIEWPOINT`` = the camera) and planned at the default settings as ``pregrasp plan`` plans
them: the mug with a handle 4, 8 and 26 cm in front of a wall (its back at y = 0.04; the wall
at y = 0.08, 0.12, 0.30), and a clutter of a can, a 4 cm ball, a small box and a pen lying
down, 4-5 cm apart, each picked, from three cameras. Each view is planned twice: as loaded
(``PointCloud.obstacles``: the other objects, the wall, the space hidden behind the other
objects) and with ``obstacles=None`` (the code before session 25). Per plan: the pool, the
force-closure grasps, how many of the ``--top`` best grasps' hands (collision meshes: vertices
and 3,000 surface samples each) enter the wall's plane or a neighbour's true mesh by more than
4 mm and the deepest, the best epsilon, the obstacle points and the plan's wall time
(load excluded).
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # one BLAS thread, before numpy loads

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import importlib.util  # noqa: E402
import platform  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from collections.abc import Callable  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import trimesh  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # this checkout's pregrasp_core, not an installed one

from pregrasp_core.hand import Hand  # noqa: E402
from pregrasp_core.io import SensorOptions, load_point_cloud  # noqa: E402
from pregrasp_core.paths import OBJECTS_DIR  # noqa: E402
from pregrasp_core.pipeline import PipelineParams, run_pipeline, with_cloud  # noqa: E402
from pregrasp_core.sensor import Intrinsics  # noqa: E402
from pregrasp_core.sensor.synthetic import clutter_meshes, orbit_camera, render_view  # noqa: E402

K = Intrinsics(420.0, 420.0, 239.5, 179.5)
_spec = importlib.util.spec_from_file_location("make_views", ROOT / "scripts" / "make_views.py")
assert _spec is not None and _spec.loader is not None
MAKE_VIEWS = importlib.util.module_from_spec(_spec)
sys.modules["make_views"] = MAKE_VIEWS
_spec.loader.exec_module(MAKE_VIEWS)
INTO_MM = 4.0


def write_pcd(path: Path, points: np.ndarray, T: np.ndarray) -> Path:
    """``points`` as a user's PCD scene with the camera pose ``T`` as its VIEWPOINT
    (``scripts/make_views.py``'s writer; every point labelled 1)."""
    path.write_bytes(MAKE_VIEWS.pcd_bytes(points, np.ones(len(points), dtype=np.uint8), T))
    return path


def render(meshes: list[trimesh.Trimesh], T: np.ndarray, table_half: float) -> np.ndarray:
    scene = trimesh.util.concatenate(meshes)
    view = render_view(scene.vertices, scene.faces, T, K, 480, 360, table_half=table_half,
                       noise=0.001, rng=np.random.default_rng(1))  # fmt: skip
    return view.points_world()[0]


def hand_points(hand: Hand, grasps: list) -> list[np.ndarray]:
    out = []
    for g in grasps:
        m = hand.collision_mesh(g.q)
        p = np.concatenate([m.vertices, trimesh.sample.sample_surface(m, 3000, seed=0)[0]])
        out.append(p @ g.T_world_hand[:3, :3].T + g.T_world_hand[:3, 3])
    return out


def row(label: str, cloud, hand: Hand, top: int, depth: Callable[[np.ndarray], float]) -> None:
    params = with_cloud(PipelineParams(), cloud)
    for setting, c in (("obstacles", cloud), ("none", dataclasses.replace(cloud, obstacles=None))):
        t0 = time.perf_counter()
        res = run_pipeline(c, params, hand, until="grasps")
        dt = time.perf_counter() - t0
        gs = res.grasps
        d = [depth(v) for v in hand_points(hand, list(gs.ranked)[:top])]
        into = sum(x > INTO_MM / 1000.0 for x in d)
        worst = max([0.0, *d]) * 1000.0
        best = gs.best
        eps = gs[best].epsilon if best is not None else 0.0
        n_obs = 0 if c.obstacles is None else len(c.obstacles)
        print(f"| {label} | {setting} | {len(res.pool)} | {gs.n_force_closure} | {len(d)} | "
              f"{into} | {worst:.1f} | {eps:.4f} | {n_obs} | {dt:.2f} |", flush=True)  # fmt: skip


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--top", type=int, default=20, help="best grasps checked per plan")
    args = ap.parse_args()
    hand = Hand.load()
    tmp = Path(tempfile.mkdtemp(prefix="pregrasp-obstacles-"))
    print(f"# {platform.machine()}, {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, "
          f"load {os.getloadavg()[0]:.2f}; hands entering by more than {INTO_MM:g} mm")  # fmt: skip
    print(
        "| view | obstacles | pool | force closure | checked | entering | deepest (mm) | "
        "best epsilon | obstacle points | plan (s) |"
    )
    print("|---|---|---:|---:|---:|---:|---:|---:|---:|---:|")
    mug = trimesh.load(OBJECTS_DIR / "mug_handle.obj", force="mesh")
    for wall_y in (0.08, 0.12, 0.30):
        wall = trimesh.creation.box((3.0, 0.001, 1.7))
        wall.apply_translation((0.0, wall_y + 0.0005, 0.65))
        T = orbit_camera(np.array([0.0, 0.0, 0.05]), 0.6, np.radians(270.0), np.radians(35.0))
        pts = render([mug, wall.subdivide_to_size(0.05)], T, 1.0)
        cloud = load_point_cloud(write_pcd(tmp / f"wall{wall_y}.pcd", pts, T), n_points=None)
        row(f"mug, wall at y = {wall_y:.2f}", cloud, hand, args.top,
            lambda v, y=wall_y: float(v[:, 1].max()) - y)  # fmt: skip
    parts = clutter_meshes()
    for az in (30.0, 150.0, 270.0):
        T = orbit_camera(np.zeros(3), 0.55, np.radians(az), np.radians(40.0))
        path = write_pcd(tmp / f"clutter{int(az)}.pcd", render(list(parts.values()), T, 0.35), T)
        for name, m in parts.items():
            pick = SensorOptions(pick=tuple(float(x) for x in m.bounds.mean(axis=0)))
            cloud = load_point_cloud(path, n_points=None, sensor=pick)
            others = [o for k, o in parts.items() if k != name]

            def depth(v: np.ndarray, others=others) -> float:
                d = -1.0
                for o in others:  # the deepest point of the hand inside a neighbour
                    q = v[np.all((v > o.bounds[0]) & (v < o.bounds[1]), axis=1)]
                    if len(q):
                        d = max(d, float(trimesh.proximity.signed_distance(o, q).max()))
                return d

            row(f"clutter {az:.0f} deg, {name}", cloud, hand, args.top, depth)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
