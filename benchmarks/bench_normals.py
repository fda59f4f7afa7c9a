"""Normals with orientation of a cloud without normals: this code against the code before
issue 15 (commit fe74cdf, loaded from git into the same process), side by side.

    .venv/bin/python benchmarks/bench_normals.py [--repeats 7]

The default object (the mug with a handle) sampled to 5,000 / 10,000 / 20,000 points and its
normals dropped (what a PLY with xyz only gives). Rows: the old default (visibility with 64
views), the old Hoppe propagation (issue 15's "about 1 s"), and the new default; each timed
interleaved (old, propagation, new, old, ...), median of ``--repeats`` calls, CPU time of this
process (``time.process_time``, not inflated by other jobs) and wall time. Then the new code's
stages at 20,000 points, the share of normals that agree with the mesh's, and the kernels' first
call (compilation, in a fresh process with an empty numba cache, and loading from the cache).
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # one BLAS thread, before numpy loads
os.environ.setdefault("OMP_NUM_THREADS", "1")

import argparse  # noqa: E402
import importlib.util  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
import types  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))  # this checkout's pregrasp_core, not an installed one
OLD_COMMIT = "fe74cdf"


def old_normals_module() -> types.ModuleType:
    """pregrasp_core/normals.py as of ``OLD_COMMIT``, as a module of the current package (its
    relative imports of errors, geometry and tolerances resolve to today's, unchanged since)."""
    src = subprocess.run(
        ["git", "-C", str(ROOT), "show", f"{OLD_COMMIT}:pregrasp_core/normals.py"],
        check=True,
        capture_output=True,
        text=True,
    ).stdout
    name = "pregrasp_core.normals_" + OLD_COMMIT
    spec = importlib.util.spec_from_loader(name, loader=None)
    assert spec is not None
    mod = importlib.util.module_from_spec(spec)
    mod.__package__ = "pregrasp_core"
    sys.modules[name] = mod
    exec(compile(src, f"{OLD_COMMIT}:pregrasp_core/normals.py", "exec"), mod.__dict__)
    return mod


def timed(fn, repeats: int) -> tuple[float, float]:
    """Median CPU and wall seconds of ``repeats`` calls."""
    cpu, wall = [], []
    for _ in range(repeats):
        c0, w0 = time.process_time(), time.perf_counter()
        fn()
        cpu.append(time.process_time() - c0)
        wall.append(time.perf_counter() - w0)
    return float(np.median(cpu)), float(np.median(wall))


def first_call_seconds() -> tuple[float, float]:
    """Seconds of the kernels' first call in a fresh process: with an empty numba cache
    (compilation) and then with the cache that run wrote (loading)."""
    code = (
        "import time; t = time.perf_counter();"
        "from pregrasp_core import normal_kernels; normal_kernels.warm_up();"
        "print(time.perf_counter() - t)"
    )
    out = []
    with tempfile.TemporaryDirectory() as cache:
        env = dict(os.environ, NUMBA_CACHE_DIR=cache, PYTHONPATH=str(ROOT))
        for _ in range(2):
            r = subprocess.run(
                [sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True
            )
            out.append(float(r.stdout.strip().splitlines()[-1]))
    return out[0], out[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=7)
    args = ap.parse_args()

    from pregrasp_core import normal_kernels
    from pregrasp_core import normals as new
    from pregrasp_core.io import load_point_cloud
    from pregrasp_core.paths import DEFAULT_OBJECT

    old = old_normals_module()
    normal_kernels.warm_up()
    print(f"# {DEFAULT_OBJECT.name}, medians of {args.repeats}, CPU ms / wall ms")
    print("| points | before: visibility (fe74cdf) | before: propagation | now | speed-up (CPU) |")
    print("|---:|---:|---:|---:|---:|")
    clouds = {}
    for n in (5000, 10000, 20000):
        cloud = load_point_cloud(DEFAULT_OBJECT, n_points=n, seed=0)
        pts = np.asarray(cloud.points)
        clouds[n] = cloud
        runs = {
            "old": lambda pts=pts: old.estimate_normals(pts, old.NormalParams()),
            "prop": lambda pts=pts: old.estimate_normals(pts, old.NormalParams(orient="propagate")),
            "new": lambda pts=pts: new.estimate_normals(pts, new.NormalParams()),
        }
        res: dict[str, list[tuple[float, float]]] = {k: [] for k in runs}
        for _ in range(args.repeats):  # interleaved: the same load on every variant
            for k, fn in runs.items():
                res[k].append(timed(fn, 1))
        med = {k: np.median(np.array(v), axis=0) * 1e3 for k, v in res.items()}
        cells = [f"{med[k][0]:.0f} / {med[k][1]:.0f}" for k in ("old", "prop", "new")]
        print(f"| {n:,} | " + " | ".join(cells) + f" | {med['old'][0] / med['new'][0]:.1f}x |")

    cloud = clouds[20000]
    pts = np.asarray(cloud.points)
    prm = new.NormalParams()
    nrm, var, d16, n16 = new.scale_selected_normals(pts, prm.k)
    rough = var >= new.SCALE_FLAT
    spacing = float(np.median(d16[:, 4]))
    stages = {
        "neighbours (grid, k = 16)": lambda: new.nearest_neighbours(pts, prm.k),
        "neighbours and scale-selected PCA": lambda: new.scale_selected_normals(pts, prm.k),
        "visibility votes (64 views)": lambda: new._visibility_votes(pts, nrm, spacing, 64),
        "orientation (votes, crests, fill, propagation)": lambda: new._orient_visibility(
            pts, nrm, n16, d16, 64, rough
        ),
    }
    print("\n| stage at 20,000 points | CPU ms | wall ms |\n|---|---:|---:|")
    for name, fn in stages.items():
        c, w = timed(fn, args.repeats)
        print(f"| {name} | {c * 1e3:.1f} | {w * 1e3:.1f} |")

    ref = np.asarray(cloud.normals)
    for label, cn in (
        ("before", old.estimate_normals(pts, old.NormalParams())),
        ("now", new.estimate_normals(pts, new.NormalParams())),
    ):
        agree = float(np.mean(np.einsum("ij,ij->i", cn.normals, ref) > 0))
        print(f"agreement with the mesh normals, {label}: {100 * agree:.2f} %")
    compile_s, load_s = first_call_seconds()
    print(
        f"first call of the kernels: {compile_s:.1f} s compiling (empty cache), "
        f"{load_s:.2f} s loading the cache (fresh process, numba import included)"
    )


if __name__ == "__main__":
    main()
