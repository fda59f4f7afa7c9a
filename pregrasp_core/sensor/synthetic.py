"""Synthetic depth views: a pinhole camera casting one ray per pixel at a mesh on a table.

Used by ``scripts/make_views.py`` (the test data of the depth-sensor input), by
``benchmarks/bench_sensor.py`` and by the tests. Pure numpy, exact in float64 and deterministic.

Ray casting: every pixel (row ``i``, column ``j``) casts the camera-frame ray
``d = ((j - cx) / fx, (i - cy) / fy, 1)`` (see :mod:`.depth`). The broad phase projects each
triangle into the image and keeps the pixels inside its bounding rectangle; each such
(triangle, pixel) pair is intersected exactly (Moller-Trumbore, both sides, float64) and the
nearest hit per pixel wins (a z-buffer). Because ``d`` has z = 1 the ray parameter is the depth
``z`` itself. Triangles with a vertex closer than ``NEAR`` to the camera plane are skipped (the
scenes keep the camera far from the object). The table is the plane ``z_world = 0`` cut to a
square of half side ``table_half``, intersected analytically.

Noise: Gaussian along the ray, on the range (the distance from the camera), of standard deviation
``noise`` metres, as time-of-flight and stereo sensors err mostly along the ray.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from .depth import Intrinsics

if TYPE_CHECKING:
    import trimesh

NEAR: float = 0.01
"""Metres: triangles with a vertex nearer than this to the camera plane are not drawn."""

PAIRS_PER_CHUNK: int = 2_000_000
"""(triangle, pixel) pairs tested at a time (memory bound of the ray caster)."""

LABEL_NONE, LABEL_TABLE, LABEL_OBJECT = 0, 1, 2
"""Per-pixel labels of :class:`SyntheticView`: no return, table, object."""


def look_at(
    eye: np.ndarray, target: np.ndarray, up: tuple[float, float, float] = (0.0, 0.0, 1.0)
) -> np.ndarray:
    """``T_world_camera`` (4, 4) of an OpenCV camera at ``eye`` looking at ``target``.

    Camera +z = forward, +x = right (forward x up), +y = down; ``up`` must not be parallel to
    the viewing direction.
    """
    eye = np.asarray(eye, dtype=np.float64)
    f = np.asarray(target, dtype=np.float64) - eye
    f /= np.linalg.norm(f)
    r = np.cross(f, np.asarray(up, dtype=np.float64))
    nr = np.linalg.norm(r)
    if nr < 1e-9:
        raise ValueError("look_at: up is parallel to the viewing direction")
    r /= nr
    down = np.cross(f, r)
    T = np.eye(4)
    T[:3, :3] = np.stack([r, down, f], axis=1)
    T[:3, 3] = eye
    return T


def orbit_camera(
    target: np.ndarray, distance: float, azimuth: float, elevation: float
) -> np.ndarray:
    """``T_world_camera`` of a camera ``distance`` from ``target``, at ``azimuth`` (radians, from
    +x toward +y) and ``elevation`` (radians above the plane z = const), looking at it."""
    t = np.asarray(target, dtype=np.float64)
    d = np.array(
        [np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth),
         np.sin(elevation)]
    )  # fmt: skip
    return look_at(t + distance * d, t)


def pixel_rays(intrinsics: Intrinsics, width: int, height: int) -> np.ndarray:
    """(H, W, 3) camera-frame rays with z = 1 of every pixel."""
    j, i = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    return np.stack(
        [(j - intrinsics.cx) / intrinsics.fx, (i - intrinsics.cy) / intrinsics.fy,
         np.ones_like(j)], axis=-1,
    )  # fmt: skip


def render_mesh_depth(
    vertices: np.ndarray,
    faces: np.ndarray,
    T_world_camera: np.ndarray,
    intrinsics: Intrinsics,
    width: int,
    height: int,
) -> np.ndarray:
    """(H, W) float64 depth (camera z, metres) of the nearest triangle per pixel, inf for none."""
    V = np.asarray(vertices, dtype=np.float64)
    F = np.asarray(faces, dtype=np.int64)
    R, t = T_world_camera[:3, :3], T_world_camera[:3, 3]
    Vc = (V - t) @ R  # (V, 3) camera frame
    tri = Vc[F]  # (T, 3 vertices, 3)
    front = np.all(tri[:, :, 2] > NEAR, axis=1)
    tri = tri[front]
    uv = np.stack(
        [
            intrinsics.fx * tri[..., 0] / tri[..., 2] + intrinsics.cx,
            intrinsics.fy * tri[..., 1] / tri[..., 2] + intrinsics.cy,
        ],
        axis=-1,
    )  # (T, 3, 2) fmt: skip
    j0 = np.clip(np.ceil(uv[..., 0].min(axis=1)), 0, width).astype(np.int64)
    j1 = np.clip(np.floor(uv[..., 0].max(axis=1)), -1, width - 1).astype(np.int64)
    i0 = np.clip(np.ceil(uv[..., 1].min(axis=1)), 0, height).astype(np.int64)
    i1 = np.clip(np.floor(uv[..., 1].max(axis=1)), -1, height - 1).astype(np.int64)
    nw = np.maximum(j1 - j0 + 1, 0)
    nh = np.maximum(i1 - i0 + 1, 0)
    count = nw * nh  # (T,) candidate pixels per triangle
    keep = count > 0
    tri, j0, i0, nw, count = tri[keep], j0[keep], i0[keep], nw[keep], count[keep]
    depth = np.full(height * width, np.inf)
    ends = np.cumsum(count)
    start = 0
    while start < len(count):
        base = ends[start - 1] if start else 0
        stop = int(np.searchsorted(ends, base + PAIRS_PER_CHUNK, side="right"))
        stop = max(stop, start + 1)
        c = count[start:stop]
        tid = np.repeat(np.arange(start, stop), c)  # (P,) triangle of each pair
        k = np.arange(int(c.sum())) - np.repeat(np.cumsum(c) - c, c)  # index inside its rectangle
        jj = j0[tid] + k % nw[tid]
        ii = i0[tid] + k // nw[tid]
        d = np.stack(
            [
                (jj - intrinsics.cx) / intrinsics.fx,
                (ii - intrinsics.cy) / intrinsics.fy,
                np.ones(len(jj)),
            ],
            axis=1,
        )  # (P, 3) rays, fmt: skip
        v0, v1, v2 = tri[tid, 0], tri[tid, 1], tri[tid, 2]
        e1, e2 = v1 - v0, v2 - v0
        p = np.cross(d, e2)
        det = np.einsum("ij,ij->i", e1, p)
        ok = np.abs(det) > 1e-18
        inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
        s = -v0  # ray origin (0) minus v0
        a = np.einsum("ij,ij->i", s, p) * inv
        q = np.cross(s, e1)
        b = np.einsum("ij,ij->i", d, q) * inv
        z = np.einsum("ij,ij->i", e2, q) * inv
        hit = ok & (a >= 0.0) & (b >= 0.0) & (a + b <= 1.0) & (z > NEAR)
        np.minimum.at(depth, ii[hit] * width + jj[hit], z[hit])
        start = stop
    return depth.reshape(height, width)


def render_table_depth(
    T_world_camera: np.ndarray, intrinsics: Intrinsics, width: int, height: int, table_half: float
) -> np.ndarray:
    """(H, W) depth of the square table ``|x|, |y| <= table_half`` on ``z_world = 0`` (inf off
    it)."""
    rays = pixel_rays(intrinsics, width, height) @ T_world_camera[:3, :3].T  # (H, W, 3) world
    o = T_world_camera[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        z = -o[2] / rays[..., 2]
    hit = np.isfinite(z) & (z > NEAR)
    x = o[0] + z * rays[..., 0]
    y = o[1] + z * rays[..., 1]
    hit &= (np.abs(x) <= table_half) & (np.abs(y) <= table_half)
    return np.where(hit, z, np.inf)


@dataclass(frozen=True, eq=False)
class SyntheticView:
    """One simulated depth frame of an object standing on a table (``z_world = 0``)."""

    depth: np.ndarray
    """(H, W) float64 depth (camera z) in metres after noise, NaN where there is no return."""
    labels: np.ndarray
    """(H, W) uint8: ``LABEL_NONE``, ``LABEL_TABLE`` or ``LABEL_OBJECT`` (the truth per pixel)."""
    T_world_camera: np.ndarray
    """(4, 4) camera pose (OpenCV camera frame)."""
    intrinsics: Intrinsics
    """The camera's intrinsics."""
    noise: float
    """Standard deviation of the range noise, metres."""

    @property
    def viewpoint(self) -> np.ndarray:
        """(3,) camera position, world frame."""
        return self.T_world_camera[:3, 3].copy()

    def points_camera(self) -> tuple[np.ndarray, np.ndarray]:
        """((N, 3) camera-frame points of the valid pixels in row-major order, (N,) labels)."""
        valid = np.isfinite(self.depth)
        rows, cols = np.nonzero(valid)
        z = self.depth[rows, cols]
        K = self.intrinsics
        pts = np.stack([(cols - K.cx) * z / K.fx, (rows - K.cy) * z / K.fy, z], axis=1)
        return pts, self.labels[rows, cols]

    def points_world(self) -> tuple[np.ndarray, np.ndarray]:
        """((N, 3) world-frame points, (N,) labels)."""
        pts, lab = self.points_camera()
        R, t = self.T_world_camera[:3, :3], self.T_world_camera[:3, 3]
        return pts @ R.T + t, lab


def render_view(
    vertices: np.ndarray,
    faces: np.ndarray,
    T_world_camera: np.ndarray,
    intrinsics: Intrinsics,
    width: int,
    height: int,
    table_half: float = 0.5,
    noise: float = 0.0,
    rng: np.random.Generator | None = None,
) -> SyntheticView:
    """A depth frame of the mesh on the square table, with range noise ``noise`` (metres)."""
    obj = render_mesh_depth(vertices, faces, T_world_camera, intrinsics, width, height)
    table = render_table_depth(T_world_camera, intrinsics, width, height, table_half)
    depth = np.minimum(obj, table)
    labels = np.full(depth.shape, LABEL_NONE, dtype=np.uint8)
    labels[np.isfinite(table)] = LABEL_TABLE
    labels[np.isfinite(obj) & (obj <= table)] = LABEL_OBJECT
    if noise > 0.0:
        if rng is None:
            raise ValueError("render_view: noise > 0 needs an rng (np.random.Generator)")
        ray_len = np.linalg.norm(pixel_rays(intrinsics, width, height), axis=-1)  # range per z
        # range r = z |d|; r + N(0, noise) -> z + N(0, noise) / |d|
        depth = depth + rng.normal(0.0, noise, size=depth.shape) / ray_len
    depth = np.where(np.isfinite(depth) & (depth > NEAR), depth, np.nan)
    labels[~np.isfinite(depth)] = LABEL_NONE
    return SyntheticView(depth, labels, np.asarray(T_world_camera, dtype=np.float64),
                         intrinsics, float(noise))  # fmt: skip


LABEL_MIXED: int = 3
"""Label of a flying pixel made by :func:`add_mixed_pixels` (neither table nor object)."""


def add_mixed_pixels(
    view: SyntheticView, fraction: float, jump: float, rng: np.random.Generator
) -> SyntheticView:
    """``view`` with flying pixels, as time-of-flight cameras make them: a pixel whose 3 x 3
    neighbourhood spans a depth jump of more than ``jump`` metres (an edge in front of what lies
    behind it) returns, with probability ``fraction``, a depth drawn uniformly between the
    nearest and the farthest depth of that neighbourhood (its footprint mixes both surfaces).
    Those pixels are labelled ``LABEL_MIXED``."""
    if not 0.0 <= fraction <= 1.0:
        raise ValueError(f"fraction must lie in [0, 1], got {fraction!r}")
    d = view.depth
    H, W = d.shape
    z = np.where(np.isfinite(d), d, np.inf)
    pad = np.pad(z, 1, constant_values=np.inf)
    win = np.stack([pad[1 + a : 1 + a + H, 1 + b : 1 + b + W] for a in (-1, 0, 1)
                    for b in (-1, 0, 1)])  # fmt: skip
    near = win.min(axis=0)
    far = np.where(np.isfinite(win), win, -np.inf).max(axis=0)
    edge = np.isfinite(z) & np.isfinite(far) & (far - near > jump)
    pick = edge & (rng.random(d.shape) < fraction)
    u = rng.random(d.shape)
    mixed = d.copy()
    mixed[pick] = near[pick] + u[pick] * (far[pick] - near[pick])
    labels = view.labels.copy()
    labels[pick] = LABEL_MIXED
    return SyntheticView(mixed, labels, view.T_world_camera, view.intrinsics, view.noise)


def clutter_meshes() -> dict[str, trimesh.Trimesh]:
    """The clutter scene of the tests, the benchmarks and the documentation (trimesh meshes
    standing on z = 0, 4-5 cm apart): ``can`` (a 66 mm cylinder, 12 cm tall) at the origin,
    ``ball`` (4 cm) at (0.09, 0.02), ``box`` (5 x 3 x 2 cm) at (-0.05, 0.09) and ``pen`` (1 cm
    thick, 14 cm long, lying along x) at (0, -0.09)."""
    import trimesh

    rot = trimesh.transformations.rotation_matrix
    parts = {
        "can": trimesh.creation.cylinder(0.033, 0.12, sections=48),
        "ball": trimesh.creation.icosphere(3, 0.02),
        "box": trimesh.creation.box([0.05, 0.03, 0.02]),
        "pen": trimesh.creation.cylinder(0.005, 0.14).apply_transform(rot(np.pi / 2, [0, 1, 0])),
    }
    places = {"can": (0.0, 0.0), "ball": (0.09, 0.02), "box": (-0.05, 0.09), "pen": (0.0, -0.09)}
    for name, m in parts.items():
        m.apply_translation([*places[name], -m.bounds[0, 2]])
    return parts
