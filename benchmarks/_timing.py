"""Timing helpers shared by the benchmark scripts (imported as ``_timing`` when a script runs
as ``python benchmarks/bench_x.py``, whose folder is then first on ``sys.path``)."""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import sys
import time
from collections.abc import Callable
from pathlib import Path
from types import ModuleType

import numpy as np


def median_time(fn: Callable[[], object], repeats: int) -> float:
    """Median CPU time of this process over ``repeats`` calls (``time.process_time``): with one
    BLAS thread it is the single-core time, and other jobs on a shared machine do not inflate
    it the way they inflate wall-clock time."""
    times = []
    for _ in range(repeats):
        t0 = time.process_time()
        fn()
        times.append(time.process_time() - t0)
    return float(np.median(times))


def pin_one_core() -> str:
    """Pin this process to the first CPU it may use (Linux); says whether it worked."""
    try:
        os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[0]})
        return "pinned to one CPU"
    except (AttributeError, OSError):
        return "not pinned"


def make_views_module() -> ModuleType:
    """``scripts/make_views.py`` (the generator of the single-view test data: its cameras, its
    PCD, PNG and camera-file writers) as a module, registered as ``make_views``."""
    path = Path(__file__).resolve().parents[1] / "scripts" / "make_views.py"
    spec = importlib.util.spec_from_file_location("make_views", path)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    sys.modules["make_views"] = mod
    spec.loader.exec_module(mod)
    return mod


def views_manifest(views: Path) -> list[dict] | None:
    """The entries of ``views/manifest.json`` (written by ``scripts/make_views.py``), or None
    after saying how to make them when the file is missing."""
    path = views / "manifest.json"
    if not path.is_file():
        print(f"{path} not found: run .venv/bin/python scripts/make_views.py first")  # noqa: T201
        return None
    return json.loads(path.read_text())


def lift_first(result, hand, mesh, k: int, params=None) -> tuple[str, int, int]:
    """Lift the first ``k`` grasps of a pipeline ``result`` in MuJoCo with the true ``mesh`` as
    the object (``pregrasp_core.simulate``, imported here so that a script's ``--tree`` applies):
    ``(best, lifted, simulated)``, ``best`` the best force-closure grasp's type and epsilon and
    whether it lifts when it is among the first ``k``."""
    from pregrasp_core.simulate import simulate_grasps

    gs = result.grasps
    top = [gs.grasps[i] for i in gs.ranking[:k]]
    lifted = simulate_grasps(result, top, hand, params, mesh=mesh) if top else []
    best = "none force closure"
    if gs.best is not None:
        g = gs.grasps[gs.best]
        i = [t.pregrasp for t in top].index(g.pregrasp) if g in top else -1
        held = "" if i < 0 else (", lifts" if lifted[i].success else ", drops")
        best = f"{g.grasp_type}, epsilon {g.epsilon:.3f}{held}"
    return best, sum(r.success for r in lifted), len(lifted)


def shape_parser(description: str) -> argparse.ArgumentParser:
    """The options every generated-shape benchmark has: ``--points`` sampled per shape and
    ``--tree``, the checkout whose ``pregrasp_core`` runs (:func:`use_tree`)."""
    ap = argparse.ArgumentParser(description=description)
    ap.add_argument("--points", type=int, default=20000)
    ap.add_argument("--tree", type=Path, default=Path(__file__).resolve().parents[1])
    return ap


def start_shapes(ap: argparse.ArgumentParser) -> tuple[argparse.Namespace, object]:
    """Parse ``ap`` (a :func:`shape_parser`), import ``pregrasp_core`` from ``--tree``, print the
    table's header line and a blank line; ``(args, hand)``, the hand loaded from that tree."""
    args = ap.parse_args()
    header = use_tree(args.tree)
    from pregrasp_core.hand import load_hand

    hand = load_hand()
    print(header)  # noqa: T201
    print()  # noqa: T201
    return args, hand


def use_tree(tree: Path) -> str:
    """Import ``pregrasp_core`` from the checkout ``tree`` (a script's ``--tree``: e.g. a ``git
    worktree`` of the commit before a change) and return the table's header line: machine,
    Python, UTC time, load average and where ``pregrasp_core`` came from."""
    import platform
    import sys

    sys.path.insert(0, str(Path(tree).resolve()))
    import pregrasp_core

    return (
        f"# {platform.machine()}, Python {platform.python_version()}, "
        f"{time.strftime('%Y-%m-%d %H:%M', time.gmtime())} UTC, load average "
        f"{os.getloadavg()[0]:.1f}, pregrasp_core from {Path(pregrasp_core.__file__).parent}"
    )
