"""How far the smoothing of a noisy view moves its points from the TRUE mesh, near and far.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/bench_smoothing.py [--objects A,B]
        [--noise 0.001,0.002]

Each demo mesh is rendered (``sensor.synthetic``) from 35 degrees of elevation at azimuth 60,
at the generated views' distance (``near``) and at 2.5 times it (``far``: a few hundred
points, ``bench_odd_views.py``'s ``far2.5x``), its object points taken by their labels, and
measured against the mesh they were cast from (``sensor.truth.MeshDistance``) as the camera
gave them (``raw``), after main's projection (``smooth_view``, 24 neighbours: what
``prepare_view`` does to a noisy view) and after the two limits on it tried in session 28
(``docs/limits.md``, "The smoothing of a sparse view"): ``r10``, only the neighbours within
10 mm fitted, a point with fewer than 8 of them left; ``gate2``, a point moved only where its
neighbours lie within twice the table's noise (RMS) of their plane (the table's noise is
``noise * sin(35 degrees)``, what ``segment_table`` measures on these views). Per view: the
24th neighbour's median distance, then for each variant the share of points more than 3 mm
off the true surface and their RMS distance to it.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # one BLAS thread, before numpy loads

import argparse  # noqa: E402
import platform  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
from scipy.spatial import cKDTree  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # this checkout's pregrasp_core, not an installed one
sys.path.insert(0, str(ROOT / "benchmarks"))

import bench_odd_views as odd  # noqa: E402

from pregrasp_core.paths import demo_objects  # noqa: E402
from pregrasp_core.sensor.smooth import smooth_view  # noqa: E402
from pregrasp_core.sensor.synthetic import LABEL_OBJECT, render_view  # noqa: E402
from pregrasp_core.sensor.truth import MeshDistance  # noqa: E402
from pregrasp_core.sensor.view import SMOOTH_K as K  # noqa: E402


def limited(points: np.ndarray, radius: float | None, gate: float | None) -> np.ndarray:
    """The projection of ``smooth_view`` with one of the tried limits: neighbours beyond
    ``radius`` left out (a point with fewer than 8 within it stays), or a point left where its
    neighbours' RMS distance from their plane exceeds ``gate`` (metres)."""
    dist, idx = cKDTree(points).query(points, k=K, distance_upper_bound=np.inf if radius is None
                                      else radius)  # fmt: skip
    use = np.isfinite(dist)
    nbrs = np.where(use[..., None], points[np.minimum(idx, len(points) - 1)], 0.0)
    count = use.sum(axis=1)
    mean = nbrs.sum(axis=1) / count[:, None]
    spread = np.where(use[..., None], nbrs - mean[:, None], 0.0)
    lam, vec = np.linalg.eigh(np.einsum("nki,nkj->nij", spread, spread))
    normal = vec[:, :, 0]
    shift = np.einsum("ni,ni->n", points - mean, normal)
    stay = count < 8
    if gate is not None:
        stay |= np.sqrt(np.maximum(lam[:, 0], 0.0) / count) > gate
    return points - np.where(stay, 0.0, shift)[:, None] * normal


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--objects", default="", help="comma-separated demo objects (default all)")
    ap.add_argument("--noise", default="0.001,0.002", help="comma-separated noise levels (m)")
    args = ap.parse_args()
    names = args.objects.split(",") if args.objects else [p.stem for p in demo_objects()]
    noises = [float(x) for x in args.noise.split(",")]
    print(f"# {platform.machine()}, {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}")
    print("| object | distance | noise (mm) | points | 24th neighbour (mm) | raw: > 3 mm / RMS "
          "| main | r10 | gate2 |")  # fmt: skip
    print("|---|---|---:|---:|---:|---|---|---|---|")
    for name in names:
        mesh = odd.load_mesh(name)
        truth = MeshDistance(mesh)
        _, _, table_half = odd.MAKE_VIEWS.view_setup(mesh)
        for noise in noises:
            for label, factor in (("near", 1.0), ("far", 2.5)):
                T = odd.camera(mesh, 35.0, factor, False)
                view = render_view(
                    mesh.vertices, mesh.faces, T, odd.MAKE_VIEWS.INTRINSICS,
                    odd.MAKE_VIEWS.WIDTH, odd.MAKE_VIEWS.HEIGHT, table_half=table_half,
                    noise=noise, rng=np.random.default_rng(3),
                )  # fmt: skip
                pts, lab = view.points_world()
                obj = pts[lab == LABEL_OBJECT]
                if len(obj) <= K:
                    print(
                        f"| {name} | {label} | {noise * 1e3:.0f} | {len(obj)} | - | - | - | - | - |"
                    )
                    continue
                main_view = smooth_view(obj, K)
                # without a limit the variants' projection is main's (only the limit differs)
                assert np.allclose(limited(obj, None, None), main_view, rtol=0.0, atol=1e-12)
                reach = float(np.median(cKDTree(obj).query(obj, k=K)[0][:, -1]))
                sigma = noise * np.sin(np.radians(35.0))
                cells = []
                for p in (obj, main_view, limited(obj, 0.010, None),
                          limited(obj, None, 2.0 * sigma)):  # fmt: skip
                    d = np.abs(truth.signed(p))
                    cells.append(
                        f"{100.0 * np.mean(d > 0.003):.1f} % / {np.sqrt(np.mean(d**2)) * 1e3:.2f}"
                    )
                print(f"| {name} | {label} | {noise * 1e3:.0f} | {len(obj)} | {reach * 1e3:.1f} | "
                      + " | ".join(cells) + " |", flush=True)  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
