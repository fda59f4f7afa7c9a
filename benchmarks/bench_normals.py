"""Normals with orientation of a cloud without normals: this code against the code before
issue 15 (commit fe74cdf) and before its threaded kernels (commit 55c2563), loaded from git into
the same process, side by side; then the clouds with normals (mesh samples) against ce739ef,
before their neighbours came from the grid search.

    .venv/bin/python benchmarks/bench_normals.py [--repeats 7]

The default object (the mug with a handle) sampled to 5,000 / 10,000 / 20,000 points and its
normals dropped (what a PLY with xyz only gives). Columns: the default before issue 15
(visibility with 64 views), the Hoppe propagation of then (issue 15's "about 1 s"), the default
of 55c2563 (compiled kernels, one thread), and this code on 1 thread and on the usable CPUs;
each timed interleaved (one call of each in turn), median of ``--repeats`` calls, CPU time of
this process (``time.process_time``: all its threads, not inflated by waiting for other jobs)
and wall time. Then this code's stages at 20,000 points (1 thread and the usable CPUs), the
share of normals that agree with the mesh's, whether this code's normals equal 55c2563's to the
bit, and the kernels' first call (compilation, in a fresh process with an empty numba cache,
and loading from the cache). The load average is printed before and after.
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
OLD_COMMIT = "fe74cdf"  # before issue 15
PREV_COMMIT = "55c2563"  # before the threaded kernels (issue 15, session 6)
REF_COMMIT = "ce739ef"  # the reference rule's k-d tree, before its grid search (session 18)


def _git_show(commit: str, path: str) -> str:
    return subprocess.run(
        ["git", "-C", str(ROOT), "show", f"{commit}:{path}"],
        check=True,
        capture_output=True,
        text=True,
    ).stdout


def _module_from_source(name: str, src: str) -> types.ModuleType:
    """``src`` as the module ``pregrasp_core.<name>`` (its relative imports of errors, geometry
    and tolerances resolve to today's, unchanged since), from a file in a folder of this
    benchmark's (numba caches compiled kernels beside their file)."""
    folder = Path(tempfile.gettempdir()) / "pregrasp_bench_normals"
    folder.mkdir(exist_ok=True)
    path = folder / f"{name}.py"
    if not path.exists() or path.read_text() != src:
        path.write_text(src)
    full = "pregrasp_core." + name
    spec = importlib.util.spec_from_file_location(full, path)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    mod.__package__ = "pregrasp_core"
    sys.modules[full] = mod
    spec.loader.exec_module(mod)
    return mod


def old_normals_module(commit: str = OLD_COMMIT) -> types.ModuleType:
    """pregrasp_core/normals.py as of ``commit``, with its compiled kernels of then if it had
    any (pregrasp_core/normal_kernels.py of that commit)."""
    src = _git_show(commit, "pregrasp_core/normals.py")
    if "from . import normal_kernels" in src:
        kernels = f"normal_kernels_{commit}"
        _module_from_source(kernels, _git_show(commit, "pregrasp_core/normal_kernels.py"))
        src = src.replace("from . import normal_kernels as nk", f"from . import {kernels} as nk")
        src = src.replace(
            "from . import normal_kernels\n", f"from . import {kernels} as normal_kernels\n"
        )
    return _module_from_source(f"normals_{commit}", src)


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


def _with_reference(mod: types.ModuleType, pts: np.ndarray, nrm: np.ndarray, threads: int):
    """The call of ``mod``'s ``estimate_normals`` on ``pts`` signed by ``nrm``."""
    return lambda: mod.estimate_normals(pts, mod.NormalParams(), reference=nrm, threads=threads)


def reference_rule(clouds: dict, repeats: int, cpus: int) -> None:
    """The clouds WITH normals (mesh samples: the sign from the mesh's normals, what every mesh
    input and the default object take): :data:`REF_COMMIT`'s k-d tree against this code's grid
    search and numpy's ``eigh`` against this code's grid search and closed-form PCA (session 23),
    interleaved; and the largest angle between the two codes' normals."""
    from pregrasp_core import normals as new

    ref_old = old_normals_module(REF_COMMIT)
    print(
        f"\n# clouds with normals (the reference rule), CPU ms / wall ms\n"
        f"| points | {REF_COMMIT}, 1 thread | now, 1 thread | {REF_COMMIT}, {cpus} threads "
        f"| now, {cpus} threads | largest angle between the two |\n|---:|---:|---:|---:|---:|---|"
    )
    for n, cloud in clouds.items():  # loop over the 3 sizes
        pts, nrm = np.asarray(cloud.points), np.asarray(cloud.normals)
        runs = {
            "old1": _with_reference(ref_old, pts, nrm, 1),
            "new1": _with_reference(new, pts, nrm, 1),
            "old": _with_reference(ref_old, pts, nrm, 0),
            "new": _with_reference(new, pts, nrm, 0),
        }
        res: dict[str, list[tuple[float, float]]] = {k: [] for k in runs}
        for _ in range(repeats):  # interleaved
            for k, fn in runs.items():
                res[k].append(timed(fn, 1))
        med = {k: np.median(np.array(v), axis=0) * 1e3 for k, v in res.items()}
        a, b = runs["old"](), runs["new"]()
        cos = np.clip(np.abs(np.einsum("ij,ij->i", a.normals, b.normals)), 0.0, 1.0)
        signs = bool(np.all(np.einsum("ij,ij->i", a.normals, b.normals) > 0.0))
        same = f"{np.degrees(np.arccos(cos.min())):.1e} deg, signs equal: {signs}"
        cells = [f"{med[k][0]:.0f} / {med[k][1]:.0f}" for k in runs]
        print(f"| {n:,} | " + " | ".join(cells) + f" | {same} |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=7)
    args = ap.parse_args()

    from pregrasp_core import normal_kernels
    from pregrasp_core import normals as new
    from pregrasp_core.io import load_point_cloud
    from pregrasp_core.paths import DEFAULT_OBJECT

    cpus = new.usable_cpus()
    print(f"# load average before: {os.getloadavg()}, usable CPUs: {cpus}")
    old = old_normals_module(OLD_COMMIT)
    prev = old_normals_module(PREV_COMMIT)
    sys.modules[f"pregrasp_core.normal_kernels_{PREV_COMMIT}"].warm_up()
    normal_kernels.warm_up()
    print(f"# {DEFAULT_OBJECT.name}, medians of {args.repeats}, CPU ms / wall ms")
    print(
        f"| points | before issue 15 ({OLD_COMMIT}) | propagation ({OLD_COMMIT}) "
        f"| before threads ({PREV_COMMIT}) | now, 1 thread | now, {cpus} threads "
        f"| CPU {PREV_COMMIT} / now | wall {PREV_COMMIT} / now ({cpus} threads) |"
    )
    print("|---:|---:|---:|---:|---:|---:|---:|---:|")
    clouds = {}
    for n in (5000, 10000, 20000):
        cloud = load_point_cloud(DEFAULT_OBJECT, n_points=n, seed=0)
        pts = np.asarray(cloud.points)
        clouds[n] = cloud
        runs = {
            "old": lambda pts=pts: old.estimate_normals(pts, old.NormalParams()),
            "prop": lambda pts=pts: old.estimate_normals(pts, old.NormalParams(orient="propagate")),
            "prev": lambda pts=pts: prev.estimate_normals(pts, prev.NormalParams()),
            "new1": lambda pts=pts: new.estimate_normals(pts, new.NormalParams(), threads=1),
            "new": lambda pts=pts: new.estimate_normals(pts, new.NormalParams()),
        }
        res: dict[str, list[tuple[float, float]]] = {k: [] for k in runs}
        for _ in range(args.repeats):  # interleaved: the same load on every variant
            for k, fn in runs.items():
                res[k].append(timed(fn, 1))
        med = {k: np.median(np.array(v), axis=0) * 1e3 for k, v in res.items()}
        cells = [f"{med[k][0]:.0f} / {med[k][1]:.0f}" for k in runs]
        print(
            f"| {n:,} | " + " | ".join(cells) + f" | {med['prev'][0] / med['new'][0]:.2f}x "
            f"| {med['prev'][1] / med['new'][1]:.2f}x |"
        )

    cloud = clouds[20000]
    pts = np.asarray(cloud.points)
    prm = new.NormalParams()
    nrm, var, d16, n16, order = new._scale_selected(pts, prm.k)
    rough = var >= new.SCALE_FLAT
    spacing = float(np.median(d16[:, 4]))
    stages = {
        "neighbours (grid, k = 16)": lambda t: new.nearest_neighbours(pts, prm.k, threads=t),
        "neighbours and scale-selected PCA": lambda t: new.scale_selected_normals(pts, prm.k, t),
        "visibility votes (64 views)": lambda t: new._visibility_votes(
            pts, nrm, spacing, 64, threads=t, order=order
        ),
        "orientation (votes, crests, fill, propagation)": lambda t: new._orient_visibility(
            pts, nrm, n16, d16, 64, rough, t, order
        ),
    }
    print(
        f"\n| stage at 20,000 points | 1 thread: CPU / wall ms | {cpus} threads: CPU / wall ms |"
        "\n|---|---:|---:|"
    )
    for name, fn in stages.items():
        one = timed(lambda fn=fn: fn(1), args.repeats)
        many = timed(lambda fn=fn: fn(cpus), args.repeats)
        print(
            f"| {name} | {one[0] * 1e3:.1f} / {one[1] * 1e3:.1f} "
            f"| {many[0] * 1e3:.1f} / {many[1] * 1e3:.1f} |"
        )

    ref = np.asarray(cloud.normals)
    got = {
        "before issue 15": old.estimate_normals(pts, old.NormalParams()),
        f"before threads ({PREV_COMMIT})": prev.estimate_normals(pts, prev.NormalParams()),
        "now": new.estimate_normals(pts, new.NormalParams()),
    }
    for label, cn in got.items():
        agree = float(np.mean(np.einsum("ij,ij->i", cn.normals, ref) > 0))
        print(f"agreement with the mesh normals, {label}: {100 * agree:.2f} %")
    same = np.array_equal(got["now"].normals, got[f"before threads ({PREV_COMMIT})"].normals)
    print(f"normals now equal to {PREV_COMMIT}'s to the bit: {same}")
    reference_rule(clouds, args.repeats, cpus)
    compile_s, load_s = first_call_seconds()
    print(
        f"first call of the kernels: {compile_s:.1f} s compiling (empty cache), "
        f"{load_s:.2f} s loading the cache (fresh process, numba import included)"
    )
    print(f"# load average after: {os.getloadavg()}")


if __name__ == "__main__":
    main()
