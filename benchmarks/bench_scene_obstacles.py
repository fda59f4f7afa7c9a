"""The rest of the scene as obstacles: wall and clutter views planned with and without them.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/bench_scene_obstacles.py [--top 20]

Rendered depth views (``sensor.synthetic``, 1 mm of noise), written as a user's PCD
(``VIEWPOINT`` = the camera) and planned at the default settings as ``pregrasp plan`` plans
them: the mug with a handle 4, 8 and 26 cm in front of a wall (its back at y = 0.04; the wall
at y = 0.08, 0.12, 0.30), and a clutter of a can, a 4 cm ball, a small box and a pen lying
down, 4-5 cm apart, each picked, from three cameras, and a dense clutter (``--dense``: a 4 cm
ball among ten boxes 10-14 cm around it, the ball picked, from three cameras). Each view is
loaded with each ``--scene-obstacles`` setting (``SensorOptions.obstacles``): ``all`` (the
default: the other objects, the wall, the space hidden behind the other objects), ``half``
(``all`` with each neighbour's hidden space half as deep, ``NEIGHBOUR_DEPTH_RATIO`` 0.5),
``seen`` (their seen points only) and ``off`` (nothing: the code before session 25). Per plan:
the pool, the force-closure grasps and how many of their hands enter nothing by more than
4 mm (``of them clear``: the grasps valid in the true scene), how many of the ``--top`` best
grasps' hands (collision meshes: vertices and 3,000 surface samples each) enter the wall's
plane or a neighbour's true mesh by more than 4 mm and the deepest, the best epsilon, the
obstacle points and the plan's wall time (load excluded).
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # one BLAS thread, before numpy loads

import argparse  # noqa: E402
import dataclasses  # noqa: E402
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

from _timing import make_views_module  # noqa: E402

from pregrasp_core.hand import Hand  # noqa: E402
from pregrasp_core.io import SensorOptions, load_point_cloud  # noqa: E402
from pregrasp_core.paths import OBJECTS_DIR  # noqa: E402
from pregrasp_core.pipeline import PipelineParams, run_pipeline, with_cloud  # noqa: E402
from pregrasp_core.sensor import Intrinsics, occluded  # noqa: E402
from pregrasp_core.sensor.synthetic import clutter_meshes, orbit_camera, render_view  # noqa: E402

K = Intrinsics(420.0, 420.0, 239.5, 179.5)
MAKE_VIEWS = make_views_module()
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


SETTINGS = (("all", "all", 1.0), ("half", "all", 0.5), ("seen", "seen", 1.0), ("off", "off", 1.0))
"""(label, ``SensorOptions.obstacles``, ``occluded.NEIGHBOUR_DEPTH_RATIO``) per plan of a view."""


def load(path: Path, sensor: SensorOptions, ratio: float):
    """The scene at ``path`` loaded with ``sensor`` and each neighbour's hidden space ``ratio``
    times its width deep (restored after)."""
    old = occluded.NEIGHBOUR_DEPTH_RATIO
    occluded.NEIGHBOUR_DEPTH_RATIO = ratio
    try:
        return load_point_cloud(path, n_points=None, sensor=sensor)
    finally:
        occluded.NEIGHBOUR_DEPTH_RATIO = old


def measure(
    path: Path, sensor: SensorOptions, hand: Hand, top: int,
    depth: Callable[[np.ndarray], float],
) -> dict[str, dict[str, float]]:  # fmt: skip
    """Per setting of :data:`SETTINGS`: the view at ``path`` loaded and planned, and its
    figures (``depth``: how deep a hand's points enter the true scene's other things)."""
    out = {}
    for setting, which, ratio in SETTINGS:
        c = load(path, dataclasses.replace(sensor, obstacles=which), ratio)
        params = with_cloud(PipelineParams(), c)
        t0 = time.perf_counter()
        res = run_pipeline(c, params, hand, until="grasps")
        dt = time.perf_counter() - t0
        gs = res.grasps
        ranked = list(gs.ranked)
        d = [depth(v) for v in hand_points(hand, ranked[:top])]
        fc = [g for g in ranked if g.epsilon > 0.0]
        fc_depth = [depth(v) for v in hand_points(hand, fc)]
        out[setting] = {
            "pool": len(res.pool),
            "fc": gs.n_force_closure,
            "clear": sum(x <= INTO_MM / 1000.0 for x in fc_depth),
            "best_clear": int(bool(fc_depth) and fc_depth[0] <= INTO_MM / 1000.0),
            "checked": len(d),
            "into": sum(x > INTO_MM / 1000.0 for x in d),
            "worst": max([0.0, *d]) * 1000.0,
            "eps": gs[gs.best].epsilon if gs.best is not None else 0.0,
            "obstacles": 0 if c.obstacles is None else len(c.obstacles),
            "time": dt,
        }
    return out


def row(
    label: str, path: Path, sensor: SensorOptions, hand: Hand, top: int,
    depth: Callable[[np.ndarray], float],
) -> None:  # fmt: skip
    """One table row per setting of the view at ``path``."""
    for setting, m in measure(path, sensor, hand, top, depth).items():
        print(f"| {label} | {setting} | {m['pool']} | {m['fc']} | {m['clear']} | "
              f"{m['checked']} | {m['into']} | {m['worst']:.1f} | {m['eps']:.4f} | "
              f"{m['obstacles']} | {m['time']:.2f} |", flush=True)  # fmt: skip


def random_clutter(rng: np.random.Generator) -> dict[str, trimesh.Trimesh]:
    """3-6 boxes, cylinders and balls of everyday sizes (3-9 cm across, up to 15 cm tall)
    standing on z = 0 at random within 0.3 x 0.3 m, at least 2 cm apart (their footprints'
    enclosing circles)."""
    parts: dict[str, trimesh.Trimesh] = {}
    placed: list[tuple[float, float, float]] = []
    for k in range(int(rng.integers(3, 7))):  # loop over the few objects
        kind = ("box", "cylinder", "ball")[int(rng.integers(3))]
        if kind == "box":
            ext = (rng.uniform(0.03, 0.09), rng.uniform(0.03, 0.09), rng.uniform(0.03, 0.15))
            m = trimesh.creation.box(ext)
            m.apply_transform(
                trimesh.transformations.rotation_matrix(rng.uniform(0, np.pi), [0, 0, 1])
            )
            radius = 0.5 * float(np.hypot(ext[0], ext[1]))
        elif kind == "cylinder":
            radius = rng.uniform(0.02, 0.045)
            m = trimesh.creation.cylinder(radius, rng.uniform(0.05, 0.15), sections=48)
        else:
            radius = rng.uniform(0.02, 0.04)
            m = trimesh.creation.icosphere(3, radius)
        for _ in range(50):  # loop over tries at a free place
            x, y = rng.uniform(-0.15, 0.15, 2)
            if all(np.hypot(x - a, y - b) > radius + r + 0.02 for a, b, r in placed):
                break
        else:
            continue
        placed.append((x, y, radius))
        m.apply_translation((x, y, -m.bounds[0, 2]))
        parts[f"{kind} {k}"] = m
    return parts


def dense_clutter() -> dict[str, trimesh.Trimesh]:
    """A 4 cm ball at the origin among ten boxes (4-8 x 3-5 cm, 8-15 cm tall, turned at
    random) 10-14 cm around it, standing on z = 0 (seeded: the same scene every run)."""
    rng = np.random.default_rng(5)
    ball = trimesh.creation.icosphere(3, 0.02)
    parts = {"ball": ball.apply_translation((0.0, 0.0, 0.02))}
    for k in range(10):  # loop over the ten boxes
        ext = (rng.uniform(0.04, 0.08), rng.uniform(0.03, 0.05), rng.uniform(0.08, 0.15))
        box = trimesh.creation.box(ext)
        box.apply_transform(
            trimesh.transformations.rotation_matrix(rng.uniform(0, np.pi), [0, 0, 1])
        )
        r, a = rng.uniform(0.10, 0.14), 2.0 * np.pi * k / 10.0 + rng.uniform(-0.1, 0.1)
        box.apply_translation((r * np.cos(a), r * np.sin(a), ext[2] / 2.0))
        parts[f"box {k}"] = box
    return parts


def neighbour_depth(others: list[trimesh.Trimesh]) -> Callable[[np.ndarray], float]:
    """The deepest point of a hand's points (M, 3) inside one of ``others`` (m; negative:
    none inside)."""

    def depth(v: np.ndarray) -> float:
        d = -1.0
        for o in others:  # loop over the neighbours
            q = v[np.all((v > o.bounds[0]) & (v < o.bounds[1]), axis=1)]
            if len(q):
                d = max(d, float(trimesh.proximity.signed_distance(o, q).max()))
        return d

    return depth


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--top", type=int, default=20, help="best grasps checked per plan")
    ap.add_argument(
        "--only",
        choices=("wall", "clutter", "dense"),
        nargs="*",
        default=["wall", "clutter", "dense"],
        help="which scenes to plan",
    )
    ap.add_argument(
        "--random",
        type=int,
        default=0,
        metavar="N",
        help="also N random clutter scenes (two cameras, two objects picked "
        "each), summed in a second table",
    )
    ap.add_argument("--rows", action="store_true",
                    help="with --random: a row per plan of the random scenes too")  # fmt: skip
    args = ap.parse_args()
    hand = Hand.load()
    tmp = Path(tempfile.mkdtemp(prefix="pregrasp-obstacles-"))
    print(f"# {platform.machine()}, {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, "
          f"load {os.getloadavg()[0]:.2f}; hands entering by more than {INTO_MM:g} mm")  # fmt: skip
    print(
        "| view | obstacles | pool | force closure | of them clear | checked | entering | "
        "deepest (mm) | "
        "best epsilon | obstacle points | plan (s) |"
    )
    print("|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    if "wall" in args.only:
        mug = trimesh.load(OBJECTS_DIR / "mug_handle.obj", force="mesh")
        for wall_y in (0.08, 0.12, 0.30):
            wall = trimesh.creation.box((3.0, 0.001, 1.7))
            wall.apply_translation((0.0, wall_y + 0.0005, 0.65))
            T = orbit_camera(np.array([0.0, 0.0, 0.05]), 0.6, np.radians(270.0), np.radians(35.0))
            pts = render([mug, wall.subdivide_to_size(0.05)], T, 1.0)
            path = write_pcd(tmp / f"wall{wall_y}.pcd", pts, T)
            row(f"mug, wall at y = {wall_y:.2f}", path, SensorOptions(), hand, args.top,
                lambda v, y=wall_y: float(v[:, 1].max()) - y)  # fmt: skip
    scenes = []
    if "clutter" in args.only:
        scenes.append(("clutter", clutter_meshes(), 0.55, 0.35, None))
    if "dense" in args.only:
        scenes.append(("dense", dense_clutter(), 0.7, 0.45, ("ball",)))
    for label, parts, distance, table_half, picked in scenes:
        for az in (30.0, 150.0, 270.0):
            T = orbit_camera(np.zeros(3), distance, np.radians(az), np.radians(40.0))
            pts = render(list(parts.values()), T, table_half)
            path = write_pcd(tmp / f"{label}{int(az)}.pcd", pts, T)
            for name, m in parts.items():
                if picked is not None and name not in picked:
                    continue
                pick = SensorOptions(pick=tuple(float(x) for x in m.bounds.mean(axis=0)))
                others = [o for k, o in parts.items() if k != name]
                row(f"{label} {az:.0f} deg, {name}", path, pick, hand, args.top,
                    neighbour_depth(others))  # fmt: skip
    if args.random:
        random_table(args.random, hand, args.top, tmp, args.rows)
    return 0


def random_table(n: int, hand: Hand, top: int, tmp: Path, rows: bool = False) -> None:
    """``n`` random clutter scenes, two cameras each (azimuth at random, 30-55 degrees up,
    0.6 m), two objects picked per view; the figures summed per setting (``rows``: and a row
    per plan first)."""
    rng = np.random.default_rng(11)
    sums: dict[str, dict[str, float]] = {}
    plans = 0
    for k in range(n):  # loop over the scenes
        parts = random_clutter(rng)
        for c in range(2):  # loop over the two cameras
            az, el = rng.uniform(0.0, 2.0 * np.pi), np.radians(rng.uniform(30.0, 55.0))
            T = orbit_camera(np.array([0.0, 0.0, 0.04]), 0.6, az, el)
            path = write_pcd(tmp / f"random{k}_{c}.pcd", render(list(parts.values()), T, 0.4), T)
            names = list(parts)
            for i in rng.choice(len(names), size=2, replace=False):  # loop over two picks
                name = names[int(i)]
                pick = SensorOptions(pick=tuple(float(x) for x in parts[name].bounds.mean(axis=0)))
                others = [o for j, o in parts.items() if j != name]
                try:
                    got = measure(path, pick, hand, top, neighbour_depth(others))
                except Exception as exc:  # a view the loader refuses: counted, not summed
                    print(f"# random {k} camera {c} {name}: {exc}", flush=True)
                    continue
                plans += 1
                if rows:
                    for setting, m in got.items():
                        print(f"| random {k} cam {c}, {name} | {setting} | {m['pool']} | "
                              f"{m['fc']} | {m['clear']} | {m['checked']} | {m['into']} | "
                              f"{m['worst']:.1f} | {m['eps']:.4f} | {m['obstacles']} | "
                              f"{m['time']:.2f} |", flush=True)  # fmt: skip
                for setting, m in got.items():
                    acc = sums.setdefault(setting, dict.fromkeys(m, 0.0))
                    for key, v in m.items():
                        acc[key] = max(acc[key], v) if key == "worst" else acc[key] + v
    print(f"\n{plans} plans of {n} random clutter scenes (sums; deepest: the largest)\n")
    print("| obstacles | pool | force closure | of them clear | best clear | checked | entering "
          "| deepest (mm) | obstacle points | plan (s) |")  # fmt: skip
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for setting, m in sums.items():
        print(f"| {setting} | {m['pool']:.0f} | {m['fc']:.0f} | {m['clear']:.0f} | "
              f"{m['best_clear']:.0f} | {m['checked']:.0f} | {m['into']:.0f} | "
              f"{m['worst']:.1f} | {m['obstacles']:.0f} | {m['time']:.1f} |")  # fmt: skip


if __name__ == "__main__":
    raise SystemExit(main())
