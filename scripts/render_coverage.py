"""Render the pictures of ``docs/pregrasps.md`` sections 2b and 6b from the real pipeline.

``docs/coverage_handle.png``: the handle of ``assets/objects/mug_handle.obj`` with the usable
(green) and unusable (red) sub-faces of its grasp type under the paper's whole-face rule and
under the sub-face rule. ``docs/coverage_brick.png``: a 32 x 32 x 23 mm brick on the table with
the pinch pre-grasp from above (open, adapted preshape) and the force-closure grasp the planner
reaches from it (closed hand, contacts in red).

A small numpy renderer (matplotlib is not a dependency): surfaces are drawn as dense splats
with a z-buffer and Lambert shading; labels with Pillow (imageio's dependency).

Usage: ``.venv/bin/python scripts/render_coverage.py [--out-dir docs]``
"""

from __future__ import annotations

import argparse
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import trimesh
from PIL import Image, ImageDraw

from pregrasp_core.facemask import FaceMaskParams, subface_rectangles
from pregrasp_core.hand import load_hand
from pregrasp_core.io import PointCloud, load_point_cloud
from pregrasp_core.paths import OBJECTS_DIR
from pregrasp_core.pipeline import PipelineParams, run_pipeline
from pregrasp_core.pregrasps import SURFACES

W, H = 640, 520
LIGHT = np.array([0.3, -0.6, 0.75]) / np.linalg.norm([0.3, -0.6, 0.75])


class Canvas:
    """An orthographic view along ``view`` (unit, towards the scene) with a z-buffer."""

    def __init__(self, centre: np.ndarray, view: np.ndarray, scale: float) -> None:
        z = -np.asarray(view, float) / np.linalg.norm(view)  # towards the viewer
        x = np.cross([0.0, 0.0, 1.0], z)
        x /= np.linalg.norm(x)
        self.R = np.stack([x, np.cross(z, x), z])  # rows: screen x, y, depth
        self.c, self.s = np.asarray(centre, float), scale
        self.rgb = np.full((H, W, 3), 255.0)
        self.depth = np.full((H, W), -np.inf)

    def splat(self, p: np.ndarray, colour: np.ndarray, radius: int = 1) -> None:
        """Points ``p`` (N, 3) with colours (N, 3) in 0..255 (nearest wins)."""
        q = (p - self.c) @ self.R.T
        u = np.round(W / 2 + q[:, 0] * self.s).astype(int)
        v = np.round(H / 2 - q[:, 1] * self.s).astype(int)
        for du in range(-radius, radius + 1):  # a small square splat
            for dv in range(-radius, radius + 1):
                uu, vv = u + du, v + dv
                ok = (uu >= 0) & (uu < W) & (vv >= 0) & (vv < H)
                uu, vv, d, col = uu[ok], vv[ok], q[ok, 2], colour[ok]
                order = np.argsort(d)  # farthest first, so the nearest is written last
                uu, vv, d, col = uu[order], vv[order], d[order], col[order]
                front = d >= self.depth[vv, uu]
                self.depth[vv[front], uu[front]] = d[front]
                self.rgb[vv[front], uu[front]] = col[front]

    def mesh(self, m: trimesh.Trimesh, colour: np.ndarray, n: int = 200_000) -> None:
        """A mesh as shaded splats of ``n`` surface samples (one colour)."""
        p, f = trimesh.sample.sample_surface(m, n, seed=0)
        shade = 0.35 + 0.65 * np.abs(m.face_normals[f] @ LIGHT)
        self.splat(np.asarray(p), shade[:, None] * np.asarray(colour, float)[None, :])

    def cloud(self, p: np.ndarray, normals: np.ndarray | None, colour=(150, 150, 150)) -> None:
        shade = 0.45 + 0.55 * np.abs(normals @ LIGHT) if normals is not None else np.ones(len(p))
        self.splat(p, shade[:, None] * np.asarray(colour, float)[None, :])

    def image(self, title: str) -> np.ndarray:
        img = Image.fromarray(self.rgb.clip(0, 255).astype(np.uint8))
        ImageDraw.Draw(img).text((10, 8), title, fill=(0, 0, 0))
        return np.asarray(img)


def rect_points(corners: np.ndarray, n: int = 3600) -> np.ndarray:
    """(n, 3) points filling a rectangle given by its 4 corners (bl, br, tr, tl), inset 8 %."""
    s, t = np.meshgrid(np.linspace(0.08, 0.92, 60), np.linspace(0.08, 0.92, n // 60))
    s, t = s.ravel()[:, None], t.ravel()[:, None]
    a, b, d = corners[0], corners[1], corners[3]
    return a + s * (b - a) + t * (d - a)


def handle_panel(res, node: int, title: str) -> np.ndarray:
    cloud, box = res.cloud, res.tree.nodes[node].box
    gt = str(res.shapes[node].grasp_type.value)
    cv = Canvas(box.center + [-0.03, 0.0, 0.0], np.array([-0.75, -0.55, -0.35]), 4200.0)
    cv.cloud(np.asarray(cloud.points), cloud.normals, colour=(185, 185, 185))
    use = res.masks.usable(node, gt)
    for f, rects in enumerate(subface_rectangles(box, gt)):
        for s, corners in enumerate(rects):
            col = (40, 170, 60) if use[f][s] else (210, 50, 40)
            pts = rect_points(corners)
            cv.splat(pts, np.tile(col, (len(pts), 1)).astype(float), radius=1)
    n_pre = int(np.count_nonzero(res.pool.node == node))
    n_use = sum(int(u.sum()) for u in use)
    return cv.image(f"{title}: {gt}, {n_use} usable sub-faces, {n_pre} pre-grasps on the handle")


def brick_panels(hand) -> list[np.ndarray]:
    mesh = trimesh.creation.box([0.032, 0.032, 0.023])
    mesh.apply_translation([0.0, 0.0, 0.0115])
    p, f = trimesh.sample.sample_surface(mesh, 6000, seed=0)
    cloud = PointCloud(points=np.asarray(p), normals=mesh.face_normals[f], source="brick")
    res = run_pipeline(cloud, PipelineParams(), hand, until="grasps")
    gs = res.grasps
    g = gs.grasps[gs.best]
    pre = res.pool[g.pregrasp]
    assert pre.surface == SURFACES[SURFACES.index("pinch")]
    table = trimesh.creation.box([0.16, 0.16, 0.002])
    table.apply_translation([0.0, 0.0, -0.001])
    out = []
    for T, q, title in (
        (pre.T_world_hand, pre.q, f"pinch pre-grasp from above ({pre.grasp_type}, adapted)"),
        (g.T_world_hand, g.q, f"closed: epsilon {g.epsilon:.3f}, {g.n_contacts} contacts"),
    ):
        cv = Canvas(np.array([0.0, 0.0, 0.05]), np.array([-0.55, 0.8, -0.25]), 1900.0)
        cv.mesh(table, (225, 215, 195), n=60_000)
        cv.cloud(cloud.points, cloud.normals, colour=(170, 120, 60))
        m = hand.hand_mesh(q)
        m.apply_transform(T)
        cv.mesh(m, (120, 150, 200), n=250_000)
        if q is g.q:
            for c in g.contacts:
                disc = c.point + 0.002 * np.random.default_rng(0).normal(size=(200, 3))
                cv.splat(disc, np.tile((230, 20, 20), (200, 1)).astype(float), radius=1)
        out.append(cv.image(title))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out-dir", type=Path, default=Path(__file__).resolve().parents[1] / "docs")
    args = ap.parse_args()
    hand = load_hand()
    cloud = load_point_cloud(OBJECTS_DIR / "mug_handle.obj")
    panels = []
    for rule, title in (("face", "paper (whole faces)"), ("subface", "sub-face rule")):
        params = PipelineParams(facemask=FaceMaskParams(rule=rule))
        res = run_pipeline(cloud, params, hand, until="pool")
        node = int(np.argmin([nd.box.volume for nd in res.tree.nodes]))  # the handle
        panels.append(handle_panel(res, node, title))
    iio.imwrite(args.out_dir / "coverage_handle.png", np.concatenate(panels, axis=1))
    iio.imwrite(args.out_dir / "coverage_brick.png", np.concatenate(brick_panels(hand), axis=1))


if __name__ == "__main__":
    main()
