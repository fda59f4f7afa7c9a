"""Generate ``assets/objects/mug_handle.obj``: a mug with a C-shaped handle (the default object).

Geometry (metres, upright +z, centred in x/y on the body's axis, resting on z = 0):

- Body: a solid of revolution (``trimesh.creation.revolve``) of a closed profile: outer radius
  ``OUTER_RADIUS``, height ``HEIGHT``, wall ``WALL``, a closed bottom ``BOTTOM`` thick, a rounded
  rim (a half circle joining the outer and the inner wall) and a small chamfer on the outer
  bottom edge. The profile starts and ends on the axis, so the revolved body is watertight.
- Handle: a circular tube of radius ``TUBE_RADIUS`` swept along an arc of a circle in the x-z
  plane on +x, centred ``HANDLE_CENTER_X`` from the axis at height ``HANDLE_CENTER_Z``, with
  centre-line radius ``HANDLE_ARC_RADIUS``. The arc is chosen so that the outermost point of the
  tube is ``HANDLE_REACH`` beyond the outer wall, and it ends where its centre line is
  ``END_DEPTH`` inside the wall (so both ends are buried in the wall, never reaching the inside).
  The tube is built here (rings of vertices along the arc, capped with fans).
- The whole mesh is then translated in x/y so that its bounding box is centred on the origin,
  like every other demo object (the body's axis ends up at x = -(HANDLE_REACH / 2)).
- The two watertight parts are merged by a boolean union (manifold3d, through
  ``trimesh.boolean.union``), so the result is ONE watertight mesh with no surface hidden inside
  the wall: points sampled on it are all on the visible surface. manifold3d is needed only to run
  this script, not to use pregrasp (the generated file is committed).

Deterministic: no randomness; the same trimesh/manifold3d give the same file.
Run: ``.venv/bin/python scripts/make_mug_handle.py [--out PATH]``.
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

import numpy as np
import trimesh

logger = logging.getLogger("make_mug_handle")

OUTER_RADIUS = 0.040
"""Outer radius of the body (m): 0.08 m outer diameter."""
HEIGHT = 0.100
"""Height of the body (m)."""
WALL = 0.005
"""Wall thickness (m)."""
BOTTOM = 0.006
"""Thickness of the closed bottom (m)."""
CHAMFER = 0.002
"""Chamfer on the outer bottom edge (m)."""
BODY_SECTIONS = 96
"""Angular sections of the revolved body."""
RIM_SEGMENTS = 8
"""Segments of the half-circle rounding the rim."""

TUBE_RADIUS = 0.005
"""Radius of the handle tube (m): ~0.01 m thick."""
HANDLE_ARC_RADIUS = 0.0195
"""Radius of the handle's centre line (m): the handle is 2 * (0.0195 + 0.005) = 0.049 m tall."""
HANDLE_REACH = 0.031
"""How far the handle sticks out beyond the outer wall (m), outer tube surface."""
HANDLE_CENTER_Z = 0.055
"""Height of the centre of the handle's arc (m)."""
HANDLE_CENTER_X = OUTER_RADIUS + HANDLE_REACH - HANDLE_ARC_RADIUS - TUBE_RADIUS
"""Distance of the arc's centre from the body axis along +x (m)."""
END_DEPTH = 0.002
"""The tube's centre line ends this far inside the outer wall (m), less than WALL - its spread."""
TUBE_SEGMENTS = 24
"""Vertices around the tube's circular cross-section."""
ARC_SEGMENTS = 64
"""Segments along the handle's arc."""


def body_profile() -> np.ndarray:
    """(M, 2) closed profile (r, z) of the body, from the axis at the bottom to the axis inside."""
    R, H, t, b, c = OUTER_RADIUS, HEIGHT, WALL, BOTTOM, CHAMFER
    rim_c = np.array([R - t / 2.0, H - t / 2.0])  # centre of the rim's half circle
    ang = np.linspace(0.0, np.pi, RIM_SEGMENTS + 1)  # outer wall to inner wall, over the top
    rim = rim_c + (t / 2.0) * np.column_stack([np.cos(ang), np.sin(ang)])  # (RIM_SEGMENTS+1, 2)
    return np.vstack(
        [
            [[0.0, 0.0], [R - c, 0.0], [R, c]],
            rim,
            [[R - t, b], [0.0, b]],
        ]
    )


def make_body() -> trimesh.Trimesh:
    """The revolved body: watertight, bottom on z = 0."""
    body = trimesh.creation.revolve(body_profile(), sections=BODY_SECTIONS)
    if not body.is_watertight:
        raise RuntimeError("the revolved body is not watertight")
    return body


def handle_end_angle() -> float:
    """Angle phi (rad, from +x in the x-z plane) where the arc's centre line meets
    x = OUTER_RADIUS - END_DEPTH; the arc runs over [-phi, phi] through +x."""
    cos_phi = (OUTER_RADIUS - END_DEPTH - HANDLE_CENTER_X) / HANDLE_ARC_RADIUS
    return float(np.arccos(cos_phi))


def make_handle() -> trimesh.Trimesh:
    """The swept tube, capped at both ends: watertight."""
    phi = handle_end_angle()
    s = np.linspace(-phi, phi, ARC_SEGMENTS + 1)  # (A,) arc parameter
    a = HANDLE_ARC_RADIUS
    center = np.array([HANDLE_CENTER_X, 0.0, HANDLE_CENTER_Z])
    radial = np.column_stack([np.cos(s), np.zeros_like(s), np.sin(s)])  # (A, 3) in x-z plane
    spine = center + a * radial  # (A, 3) centre line
    y = np.array([0.0, 1.0, 0.0])  # normal of the arc's plane: the second cross-section axis
    u = np.linspace(0.0, 2.0 * np.pi, TUBE_SEGMENTS, endpoint=False)  # (K,)
    # rings: (A, K, 3) = spine + r (cos u * radial + sin u * y)
    rings = (
        spine[:, None, :]
        + TUBE_RADIUS * np.cos(u)[None, :, None] * radial[:, None, :]
        + TUBE_RADIUS * np.sin(u)[None, :, None] * y[None, None, :]
    )
    A, K = rings.shape[:2]
    verts = np.vstack([rings.reshape(-1, 3), spine[0], spine[-1]])
    i = np.arange(A - 1)[:, None]
    k = np.arange(K)[None, :]
    v00 = i * K + k
    v01 = i * K + (k + 1) % K
    v10 = (i + 1) * K + k
    v11 = (i + 1) * K + (k + 1) % K
    side = np.concatenate(
        [np.stack([v00, v10, v11], -1).reshape(-1, 3), np.stack([v00, v11, v01], -1).reshape(-1, 3)]
    )
    c0, c1 = A * K, A * K + 1
    kk = np.arange(K)
    cap0 = np.column_stack([np.full(K, c0), (kk + 1) % K, kk])
    cap1 = np.column_stack([np.full(K, c1), (A - 1) * K + kk, (A - 1) * K + (kk + 1) % K])
    tube = trimesh.Trimesh(verts, np.vstack([side, cap0, cap1]), process=True)
    tube.fix_normals()
    if not tube.is_watertight:
        raise RuntimeError("the handle tube is not watertight")
    return tube


def make_mug_handle() -> trimesh.Trimesh:
    """Body and handle merged into one watertight mesh."""
    body, handle = make_body(), make_handle()
    try:
        import manifold3d  # noqa: F401
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise SystemExit(
            "make_mug_handle.py needs manifold3d for the boolean union: pip install manifold3d"
        ) from exc
    mug = trimesh.boolean.union([body, handle], engine="manifold")
    if not mug.is_watertight or mug.body_count != 1:
        raise RuntimeError(
            f"union is not one watertight body (watertight={mug.is_watertight}, "
            f"bodies={mug.body_count})"
        )
    lo, hi = mug.bounds
    mug.apply_translation([-(lo[0] + hi[0]) / 2.0, -(lo[1] + hi[1]) / 2.0, -lo[2]])
    return mug


def main(argv: list[str] | None = None) -> int:
    from pregrasp_core.paths import DEFAULT_OBJECT

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=DEFAULT_OBJECT, help="output OBJ path")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    mug = make_mug_handle()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(
        trimesh.exchange.obj.export_obj(mug, include_normals=False, include_texture=False, digits=6)
    )
    lo, hi = mug.bounds
    logger.info(
        "wrote %s: %d vertices, %d triangles, watertight=%s, extents %s m, volume %.3e m^3, "
        "area %.4f m^2, handle arc %.1f deg",
        args.out,
        len(mug.vertices),
        len(mug.faces),
        mug.is_watertight,
        np.round(hi - lo, 4).tolist(),
        mug.volume,
        mug.area,
        np.degrees(2.0 * handle_end_angle()),
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
