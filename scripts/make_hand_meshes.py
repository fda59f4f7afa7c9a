"""Generate the hand's visual meshes (``assets/meshes/*.stl``) from its URDF collision boxes.

The URDF is the single source of the hand's dimensions: every link has one collision ``<box>``
and one visual ``<mesh>``. For each mesh file this script builds a rounded version of the box of
the links that use it: the convex hull of small spheres placed in the box's corners, so the
visual mesh always lies inside the collision box (collision checks stay conservative). The
distal phalanx gets a larger rounding at its tip end. Links sharing a mesh file must have the
same box size and the same box offset from their visual origin (checked).

Usage: ``.venv/bin/python scripts/make_hand_meshes.py [--urdf assets/hand.urdf]``
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import trimesh
import yourdfpy

REPO = Path(__file__).resolve().parents[1]

#: Corner rounding radius (metres) per mesh file: (radius at the low-z end, radius at the high-z
#: end) in the link frame. The distal link's tip end is rounder.
ROUNDING: dict[str, tuple[float, float]] = {
    "palm.stl": (0.006, 0.006),
    "knuckle.stl": (0.004, 0.004),
    "middle.stl": (0.004, 0.004),
    "distal.stl": (0.004, 0.0095),
}


def rounded_box(
    size: np.ndarray, center: np.ndarray, r_low: float, r_high: float
) -> trimesh.Trimesh:
    """Convex hull of 8 corner spheres inside the box ``size`` (3,) centred at ``center`` (3,)."""
    half = np.asarray(size, dtype=np.float64) / 2.0
    sphere = trimesh.creation.icosphere(subdivisions=2, radius=1.0).vertices  # (162, 3)
    clouds = []
    for sx in (-1.0, 1.0):
        for sy in (-1.0, 1.0):
            for sz in (-1.0, 1.0):
                r = r_low if sz < 0 else r_high
                r = min(r, half[0], half[1])
                c = np.array([sx * (half[0] - r), sy * (half[1] - r), sz * (half[2] - r)])
                clouds.append(c + r * sphere)
    pts = np.concatenate(clouds) + np.asarray(center, dtype=np.float64)
    hull = trimesh.convex.convex_hull(pts)
    hull.fix_normals()
    return hull


def box_specs(urdf: yourdfpy.URDF) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Mesh file name -> (box size (3,), box centre in the visual frame (3,)), checked."""
    specs: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    for link in urdf.robot.links:
        if len(link.visuals) != 1 or len(link.collisions) != 1:
            raise SystemExit(f"link {link.name}: expected one visual and one collision element")
        vis, col = link.visuals[0], link.collisions[0]
        if vis.geometry.mesh is None or col.geometry.box is None:
            raise SystemExit(f"link {link.name}: expected a visual <mesh> and a collision <box>")
        name = Path(vis.geometry.mesh.filename).name
        T_vis = np.eye(4) if vis.origin is None else vis.origin
        T_col = np.eye(4) if col.origin is None else col.origin
        T_vis_col = np.linalg.inv(T_vis) @ T_col
        if not np.allclose(T_vis_col[:3, :3], np.eye(3)):
            raise SystemExit(f"link {link.name}: visual and collision frames must be parallel")
        spec = (np.asarray(col.geometry.box.size, dtype=np.float64), T_vis_col[:3, 3].copy())
        if name in specs:
            old = specs[name]
            if not (np.allclose(old[0], spec[0]) and np.allclose(old[1], spec[1])):
                raise SystemExit(f"mesh {name} is shared by links with different boxes")
        specs[name] = spec
    return specs


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--urdf", type=Path, default=REPO / "assets" / "hand.urdf")
    args = parser.parse_args(argv)
    urdf = yourdfpy.URDF.load(str(args.urdf), build_scene_graph=False, load_meshes=False)
    out_dir = args.urdf.parent / "meshes"
    out_dir.mkdir(exist_ok=True)
    for name, (size, center) in sorted(box_specs(urdf).items()):
        r_low, r_high = ROUNDING[name]
        mesh = rounded_box(size, center, r_low, r_high)
        mesh.export(out_dir / name)
        print(f"{out_dir / name}: {len(mesh.faces)} faces, bounds {mesh.bounds.tolist()}")


if __name__ == "__main__":
    main()
