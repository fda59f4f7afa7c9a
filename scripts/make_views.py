"""Generate single-view depth-camera test data from the demo meshes.

For every mesh in ``assets/objects/*.obj`` (or those named by ``--objects``): the object stands on
a square table (``z = 0``, half side 0.3 m + the object's radius), seen by a pinhole camera
(480 x 360 pixels, fx = fy = 420, about a RealSense at 640 x 480 downsampled) from 3 positions
(azimuths 30, 150 and 270 degrees, elevation 35 degrees, looking at the object's centre from
``max(0.45, 3 r / tan(22 deg))`` m, r the half diagonal of its box), each at 0, 1 and 2 mm of
Gaussian range noise along the rays. Rays are cast by ``pregrasp_core.sensor.synthetic`` (exact
float64 ray-triangle intersection, no embree or rtree needed).

Written under ``OUT`` (default ``/tmp/pregrasp_views``):

- ``<object>/view<k>_noise<mm>.pcd``: binary PCD, world frame, fields ``x y z`` (F 4) and
  ``label`` (U 1: 1 table, 2 object), ``VIEWPOINT`` = the camera pose (position, then the
  quaternion w x y z of the OpenCV camera frame);
- ``<object>/view0_noise<mm>.png`` + ``<object>/view0.json``: camera 0 as a 16-bit depth PNG in
  millimetres (0 = no return) and its intrinsics with width, height and ``T_world_camera``;
- ``<object>/<object>.obj``: a copy of the true mesh;
- ``manifest.json``: one entry per view (object, camera, pose, intrinsics, noise, seed, files,
  point counts, the true mesh's path).

``--demo`` also writes the committed demo ``assets/objects/mug_depth.png`` + ``mug_depth.json``
(``mug_handle`` on the table, one view, 1 mm noise).

Run: ``.venv/bin/python scripts/make_views.py [OUT] [--objects mug can_soda] [--demo]``.
Same arguments, same bytes (the noise is seeded per object, camera and level).
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import zlib
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import trimesh
from scipy.spatial.transform import Rotation

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from pregrasp_core.sensor.depth import Intrinsics  # noqa: E402
from pregrasp_core.sensor.synthetic import (  # noqa: E402
    LABEL_OBJECT,
    LABEL_TABLE,
    SyntheticView,
    orbit_camera,
    render_view,
)

WIDTH, HEIGHT = 480, 360
INTRINSICS = Intrinsics(fx=420.0, fy=420.0, cx=239.5, cy=179.5)
AZIMUTHS_DEG = (30.0, 150.0, 270.0)
ELEVATION_DEG = 35.0
NOISES_M = (0.0, 0.001, 0.002)
DEMO = ("mug_handle", 300.0, 0.001)  # object, azimuth (deg), noise (m)


def view_setup(mesh: trimesh.Trimesh) -> tuple[np.ndarray, float, float]:
    """(target, camera distance, table half side) for a mesh standing on z = 0."""
    radius = float(np.linalg.norm(mesh.extents)) / 2.0
    target = np.array([0.0, 0.0, float(mesh.bounds[1, 2]) / 2.0])
    # the vertical half field of view is atan(180 / 420) = 23.2 degrees: at this distance the
    # object's bounding sphere spans at most a third of it
    distance = max(0.45, 3.0 * radius / np.tan(np.radians(22.0)))
    return target, distance, 0.3 + radius


def make_view(mesh: trimesh.Trimesh, azimuth_deg: float, noise: float, seed: int) -> SyntheticView:
    """One simulated depth frame of ``mesh`` on its table."""
    target, distance, table_half = view_setup(mesh)
    T = orbit_camera(target, distance, np.radians(azimuth_deg), np.radians(ELEVATION_DEG))
    return render_view(
        mesh.vertices, mesh.faces, T, INTRINSICS, WIDTH, HEIGHT, table_half=table_half,
        noise=noise, rng=np.random.default_rng(seed),
    )  # fmt: skip


def view_seed(name: str, camera: int, noise: float) -> int:
    """A seed fixed by the object's name, the camera and the noise level."""
    return zlib.crc32(f"{name}/{camera}/{noise:.4f}".encode())


def pcd_bytes(points: np.ndarray, labels: np.ndarray, T_world_camera: np.ndarray) -> bytes:
    """A binary PCD (x y z float32, label uint8) with the camera pose as VIEWPOINT."""
    qx, qy, qz, qw = Rotation.from_matrix(T_world_camera[:3, :3]).as_quat()
    tx, ty, tz = T_world_camera[:3, 3]
    n = len(points)
    header = (
        "# .PCD v0.7 - Point Cloud Data file format\n"
        "# written by pregrasp scripts/make_views.py; label 1 = table, 2 = object\n"
        "VERSION 0.7\nFIELDS x y z label\nSIZE 4 4 4 1\nTYPE F F F U\nCOUNT 1 1 1 1\n"
        f"WIDTH {n}\nHEIGHT 1\n"
        f"VIEWPOINT {tx:.9g} {ty:.9g} {tz:.9g} {qw:.9g} {qx:.9g} {qy:.9g} {qz:.9g}\n"
        f"POINTS {n}\nDATA binary\n"
    )
    rec = np.zeros(n, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("label", "u1")])
    rec["x"], rec["y"], rec["z"] = points.T.astype(np.float32)
    rec["label"] = labels
    return header.encode("ascii") + rec.tobytes()


def depth_png(view: SyntheticView) -> np.ndarray:
    """(H, W) uint16 depth in millimetres, 0 = no return."""
    mm = np.where(np.isfinite(view.depth), np.round(view.depth * 1000.0), 0.0)
    return np.clip(mm, 0, 65535).astype(np.uint16)


def camera_json(view: SyntheticView) -> str:
    """Intrinsics JSON with the image size and the camera pose."""
    doc = {**INTRINSICS.to_dict(), "width": WIDTH, "height": HEIGHT}
    head = json.dumps(doc)[:-1]
    rows = ",\n  ".join(json.dumps(r) for r in np.round(view.T_world_camera, 12).tolist())
    return f'{head},\n "T_world_camera": [\n  {rows}\n ]\n}}\n'


def write_object(mesh_path: Path, out: Path) -> list[dict[str, object]]:
    """All views of one object; returns their manifest entries."""
    name = mesh_path.stem
    mesh = trimesh.load(mesh_path, force="mesh")
    folder = out / name
    folder.mkdir(parents=True, exist_ok=True)
    true_mesh = folder / mesh_path.name
    shutil.copyfile(mesh_path, true_mesh)
    entries: list[dict[str, object]] = []
    for cam, az in enumerate(AZIMUTHS_DEG):
        for noise in NOISES_M:
            seed = view_seed(name, cam, noise)
            view = make_view(mesh, az, noise, seed)
            pts, lab = view.points_world()
            label = np.where(lab == LABEL_OBJECT, 2, 1).astype(np.uint8)
            stem = f"view{cam}_noise{round(noise * 1000)}"
            (folder / f"{stem}.pcd").write_bytes(pcd_bytes(pts, label, view.T_world_camera))
            entry: dict[str, object] = {
                "object": name,
                "camera": cam,
                "azimuth_deg": az,
                "elevation_deg": ELEVATION_DEG,
                "T_world_camera": view.T_world_camera.tolist(),
                "intrinsics": INTRINSICS.to_dict(),
                "width": WIDTH,
                "height": HEIGHT,
                "noise_m": noise,
                "seed": seed,
                "pcd": str((folder / f"{stem}.pcd").relative_to(out)),
                "true_mesh": str(true_mesh.relative_to(out)),
                "n_points": int(len(pts)),
                "n_object": int(np.sum(lab == LABEL_OBJECT)),
                "n_table": int(np.sum(lab == LABEL_TABLE)),
                "table": {"normal": [0.0, 0.0, 1.0], "height": 0.0},
            }
            if cam == 0:
                iio.imwrite(folder / f"{stem}.png", depth_png(view))
                (folder / "view0.json").write_text(camera_json(view))
                entry["depth_png"] = str((folder / f"{stem}.png").relative_to(out))
                entry["intrinsics_json"] = str((folder / "view0.json").relative_to(out))
            entries.append(entry)
    return entries


def write_demo() -> None:
    """The committed depth-camera demo in assets/objects/."""
    name, az, noise = DEMO
    mesh = trimesh.load(REPO / "assets" / "objects" / f"{name}.obj", force="mesh")
    view = make_view(mesh, az, noise, view_seed(name, 0, noise))
    iio.imwrite(REPO / "assets" / "objects" / "mug_depth.png", depth_png(view))
    (REPO / "assets" / "objects" / "mug_depth.json").write_text(camera_json(view))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("out", nargs="?", default="/tmp/pregrasp_views", type=Path,
                        help="output folder (default /tmp/pregrasp_views)")  # fmt: skip
    parser.add_argument("--objects", nargs="*", default=None,
                        help="demo object names (default: every assets/objects/*.obj)")  # fmt: skip
    parser.add_argument(
        "--demo", action="store_true",
        help="also write assets/objects/mug_depth.png and mug_depth.json",
    )  # fmt: skip
    args = parser.parse_args(argv)
    meshes = sorted((REPO / "assets" / "objects").glob("*.obj"))
    if args.objects:
        known = {p.stem: p for p in meshes}
        unknown = [o for o in args.objects if o not in known]
        if unknown:
            parser.error(f"unknown objects {unknown}; choose from {sorted(known)}")
        meshes = [known[o] for o in args.objects]
    args.out.mkdir(parents=True, exist_ok=True)
    manifest = []
    for path in meshes:
        manifest.extend(write_object(path, args.out))
        print(f"{path.stem}: {len(AZIMUTHS_DEG) * len(NOISES_M)} views", flush=True)
    (args.out / "manifest.json").write_text(json.dumps(manifest, indent=1) + "\n")
    print(f"{len(manifest)} views in {args.out}")
    if args.demo:
        write_demo()
        print("wrote assets/objects/mug_depth.png and mug_depth.json")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
