"""Render the hand in its four preshapes to ``docs/hand_preshapes.png``.

The meshes and their poses come from the URDF through yourdfpy (its own forward kinematics and
the visual meshes in ``assets/meshes``); only the preshape joint values come from
``pregrasp_core.hand``. Top row: oblique views; bottom row: looking down the approach axis
(-z) onto the palm, with each used finger's closing direction drawn as an arrow from its first
flexion joint and the aperture circle / gap.

Usage: ``.venv/bin/python scripts/render_hand.py [--out docs/hand_preshapes.png]``
"""

from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import trimesh  # noqa: E402
import yourdfpy  # noqa: E402
from mpl_toolkits.mplot3d.art3d import Poly3DCollection  # noqa: E402

from pregrasp_core.hand import GRASP_TYPES, Hand  # noqa: E402
from pregrasp_core.paths import HAND_URDF  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
LIGHT = np.array([0.4, -0.5, 0.8]) / np.linalg.norm([0.4, -0.5, 0.8])


def urdf_mesh(urdf: yourdfpy.URDF, cfg: dict[str, float]) -> trimesh.Trimesh:
    """The visual scene of the URDF at ``cfg`` as one mesh (hand frame), with face colours."""
    urdf.update_cfg(cfg)
    parts = []
    for node in urdf.scene.graph.nodes_geometry:
        T, geom_name = urdf.scene.graph[node]
        m = urdf.scene.geometry[geom_name].copy()
        m.apply_transform(T)
        if not isinstance(m.visual, trimesh.visual.ColorVisuals):
            m.visual = m.visual.to_color()
        parts.append(m)
    return trimesh.util.concatenate(parts)


def draw_mesh(ax, mesh: trimesh.Trimesh) -> None:
    base = np.asarray(mesh.visual.face_colors, dtype=np.float64)[:, :3] / 255.0
    shade = 0.45 + 0.55 * np.clip(mesh.face_normals @ LIGHT, 0.0, 1.0)
    poly = Poly3DCollection(mesh.triangles, facecolors=base * shade[:, None], linewidths=0)
    ax.add_collection3d(poly)


def setup(ax, elev: float, azim: float) -> None:
    ax.set_xlim(-0.11, 0.11)
    ax.set_ylim(-0.11, 0.11)
    ax.set_zlim(-0.05, 0.17)
    ax.set_box_aspect((1, 1, 1))
    ax.view_init(elev=elev, azim=azim)
    ax.set_xlabel("x (m)", fontsize=7)
    ax.set_ylabel("y (m)", fontsize=7)
    ax.set_zlabel("z (m)", fontsize=7)
    ax.tick_params(labelsize=6)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=REPO / "docs" / "hand_preshapes.png")
    args = parser.parse_args(argv)
    hand = Hand.load()
    urdf = yourdfpy.URDF.load(str(HAND_URDF), build_scene_graph=True, load_meshes=True)
    fig = plt.figure(figsize=(16, 8.4))
    for k, gt in enumerate(GRASP_TYPES):
        q = hand.preshape(gt)
        cfg = {n: float(v) for n, v in zip(hand.joint_names, q, strict=True)}
        mesh = urdf_mesh(urdf, cfg)
        spread = np.degrees(hand.spread_for(gt))
        title = f"{gt}\nspread {spread:.0f} deg, aperture {hand.aperture(gt) * 100:.1f} cm"
        ax = fig.add_subplot(2, 4, k + 1, projection="3d")
        draw_mesh(ax, mesh)
        setup(ax, elev=22, azim=-58)
        ax.set_title(title, fontsize=10)
        ax2 = fig.add_subplot(2, 4, k + 5, projection="3d")
        draw_mesh(ax2, mesh)
        setup(ax2, elev=90, azim=-90)
        ax2.set_zticks([])
        for f in hand.fingers_for(gt):
            plane = hand.flexion_plane(f, hand.spread_for(gt))
            o = plane.origin + np.array([0, 0, 0.15])
            ax2.quiver(*o, *(0.04 * plane.v), color="crimson", linewidth=2, arrow_length_ratio=0.3)
            ax2.text(*(o - 0.018 * plane.v), f.name, fontsize=8, color="crimson")
        c = hand.grasp_center(gt)
        ax2.scatter([c[0]], [c[1]], [0.16], color="black", s=12)
        if gt == "spherical":
            t = np.linspace(0, 2 * np.pi, 100)
            r = hand.aperture(gt) / 2
            ax2.plot(c[0] + r * np.cos(t), c[1] + r * np.sin(t), 0.16, color="black", lw=0.8)
        ax2.set_title("top view (closing directions, grasp centre)", fontsize=8)
    fig.suptitle(
        "pregrasp hand (assets/hand.urdf via yourdfpy): preshapes of the four grasp types",
        fontsize=12,
    )
    fig.tight_layout()
    fig.savefig(args.out, dpi=110)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
