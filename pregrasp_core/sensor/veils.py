"""Flying pixels: points a depth camera strings along its rays between an edge and what lies
behind it.

Time-of-flight and many structured-light cameras give a pixel that straddles a depth jump (the
rim of a mug in front of the table) a range between the two surfaces: the "mixed" or "flying"
pixels. In the cloud they form a sparse curtain, or veil, behind every silhouette, above the
table and touching the object, so they join the object's cluster, widen its boxes and pull
contacts off its surface (``docs/input.md``, "Flying pixels").

The test (:func:`flying_points`), per point ``p`` seen along the unit ray ``r`` from the camera:
among the points within ``VeilParams.window`` pixels of it in the image (the rays' directions,
projected onto a plane in front of the camera, binned by the pixel pitch), is there one
**nearer** and one **farther** along ``r`` by more than ``VeilParams.min_gap``, each within
``VeilParams.angle_deg`` of the ray (the segment from ``p`` to it nearly parallel to ``r``)?
Then ``p`` lies in the middle of a depth jump: a flying pixel. A real surface does not: at a
silhouette the front pixel has only farther neighbours along its ray (the background), the
first background pixel only nearer ones (the object); a surface seen obliquely has its
neighbours off the ray by its own angle to the ray, more than ``angle_deg`` unless the camera
grazes it. What is lost: points of surfaces seen within ``angle_deg`` of grazing (the far
table, the last pixel of a cylinder's outline), measured in ``docs/benchmarks.md``.

The pixel pitch is the median distance between neighbouring rays (a depth image's ``1 / f``),
so the test needs no intrinsics and works on any cloud of one camera (a PCD with
``VIEWPOINT``, a depth image's points). The loop over the window is compiled (numba, on first
use); the grid's cells are sorted once.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from ..geometry import as_points
from ..jit import Lazy, njit

PITCH_SAMPLES: int = 4000
"""Points whose nearest neighbour's distance in the image gives the pixel pitch (evenly spread
over the cloud's order: deterministic, and a camera's pixels are in a fixed order)."""

MAX_CELLS_PER_SIDE: int = 7_000
"""Most cells along each side of the image grid (at most 49 M cells): a cloud spread over a wider
angle than that many pixels, or with nearly coincident rays, uses a coarser pitch."""

MAX_RAY_ANGLE_DEG: float = 80.0
"""Points more than this off the camera's mean viewing direction are not tested (the image
plane's projection stretches them); they are kept."""


@dataclass(frozen=True)
class VeilParams:
    """The flying-pixel test (see the module)."""

    window: int = 2
    """Pixels on each side of a point whose points are its neighbours (2: a 5 x 5 window)."""
    angle_deg: float = 10.0
    """A neighbour counts when the segment to it lies within this angle of the point's ray."""
    min_gap: float = 0.005
    """Metres: ... and it lies at least this much nearer or farther along the ray (above the
    range noise of a depth camera at a metre, 1-2 mm)."""

    def __post_init__(self) -> None:
        if int(self.window) != self.window or not 1 <= self.window <= 5:
            raise ValueError(f"window must be an integer in [1, 5], got {self.window!r}")
        if not (math.isfinite(self.angle_deg) and 0.0 < self.angle_deg < 45.0):
            raise ValueError(f"angle_deg must lie in (0, 45), got {self.angle_deg!r}")
        if not (math.isfinite(self.min_gap) and self.min_gap > 0.0):
            raise ValueError(f"min_gap must be positive, got {self.min_gap!r}")


def _veil_loop(
    p: np.ndarray,
    r: np.ndarray,
    cell: np.ndarray,
    start: np.ndarray,
    members: np.ndarray,
    n_rows: int,
    n_cols: int,
    window: int,
    tan2: float,
    gap: float,
    out: np.ndarray,
) -> None:
    """``out[i]`` = point ``i`` (of ``p`` (N, 3), rays ``r`` (N, 3), grid cell ``cell`` (N, 2),
    -1 = not tested) has a nearer and a farther neighbour in its window (see the module);
    ``members[start[c]:start[c + 1]]`` are the points of cell ``c = row * n_cols + col``."""
    for i in range(p.shape[0]):
        ci = cell[i, 0]
        cj = cell[i, 1]
        if ci < 0:
            continue
        nearer = False
        farther = False
        for a in range(max(ci - window, 0), min(ci + window + 1, n_rows)):
            for b in range(max(cj - window, 0), min(cj + window + 1, n_cols)):
                c = a * n_cols + b
                for m in range(start[c], start[c + 1]):
                    q = members[m]
                    dx = p[q, 0] - p[i, 0]
                    dy = p[q, 1] - p[i, 1]
                    dz = p[q, 2] - p[i, 2]
                    along = dx * r[i, 0] + dy * r[i, 1] + dz * r[i, 2]
                    if abs(along) <= gap:
                        continue
                    lat2 = dx * dx + dy * dy + dz * dz - along * along
                    if lat2 < tan2 * along * along:
                        if along < 0.0:
                            nearer = True
                        else:
                            farther = True
                if nearer and farther:
                    break
            if nearer and farther:
                break
        out[i] = nearer and farther


_KERNEL = Lazy(lambda: njit(_veil_loop))


def _image_frame(rays: np.ndarray) -> np.ndarray:
    """(3, 3) columns: two image axes and the mean viewing direction of unit ``rays`` (N, 3)."""
    f = rays.mean(axis=0)
    norm = float(np.linalg.norm(f))
    f = f / norm if norm > 1e-9 else np.array([0.0, 0.0, 1.0])
    x = np.cross(f, np.eye(3)[int(np.argmin(np.abs(f)))])
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(f, x), f], axis=1)


def flying_points(
    points: np.ndarray,
    viewpoint: np.ndarray | tuple[float, float, float],
    params: VeilParams | None = None,
) -> np.ndarray:
    """(N,) bool: True for the flying pixels of ``points`` (N, 3) seen by one camera at
    ``viewpoint`` (3,) (see the module). Points at the camera or more than
    ``MAX_RAY_ANGLE_DEG`` off its mean direction are never flagged; with fewer than 16 points
    none is."""
    prm = params or VeilParams()
    pts = as_points(points)
    vp = np.asarray(viewpoint, dtype=np.float64)
    if vp.shape != (3,) or not np.all(np.isfinite(vp)):
        raise ValueError(f"viewpoint must be a finite 3-vector, got {viewpoint!r}")
    out = np.zeros(len(pts), dtype=bool)
    v = pts - vp
    rho = np.linalg.norm(v, axis=1)
    ok = rho > 1e-9
    if np.count_nonzero(ok) < 16:
        return out
    rays = np.zeros_like(v)
    rays[ok] = v[ok] / rho[ok, None]
    R = _image_frame(rays[ok])
    loc = rays @ R
    ok &= loc[:, 2] > math.cos(math.radians(MAX_RAY_ANGLE_DEG))
    if np.count_nonzero(ok) < 16:
        return out
    idx = np.flatnonzero(ok)
    uv = loc[idx, :2] / loc[idx, 2:3]
    # the pixel pitch: the median distance from a ray to its nearest other ray (a sample)
    step = max(1, len(idx) // PITCH_SAMPLES)
    d, _ = cKDTree(uv).query(uv[::step], k=2)
    pitch = float(np.median(d[:, 1]))
    lo = uv.min(axis=0)
    span = uv.max(axis=0) - lo
    if not pitch > 0.0:  # duplicated rays: half of the points share one
        pitch = float(np.max(span)) / math.sqrt(len(idx)) if np.max(span) > 0.0 else 1.0
    pitch = max(pitch, float(np.max(span)) / MAX_CELLS_PER_SIDE)
    ij = np.floor((uv - lo) / pitch).astype(np.int64)
    n_rows, n_cols = int(ij[:, 0].max()) + 1, int(ij[:, 1].max()) + 1
    cell = np.full((len(pts), 2), -1, dtype=np.int64)
    cell[idx] = ij
    flat = ij[:, 0] * n_cols + ij[:, 1]
    order = np.argsort(flat, kind="stable")
    members = idx[order]
    start = np.zeros(n_rows * n_cols + 1, dtype=np.int64)
    np.cumsum(np.bincount(flat, minlength=n_rows * n_cols), out=start[1:])
    tan2 = math.tan(math.radians(prm.angle_deg)) ** 2
    _KERNEL.get()(
        np.ascontiguousarray(pts), np.ascontiguousarray(rays), cell, start, members,
        n_rows, n_cols, int(prm.window), tan2, float(prm.min_gap), out,
    )  # fmt: skip
    return out
