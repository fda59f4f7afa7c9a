"""Timing helpers shared by the benchmark scripts (imported as ``_timing`` when a script runs
as ``python benchmarks/bench_x.py``, whose folder is then first on ``sys.path``)."""

from __future__ import annotations

import json
import os
import time
from collections.abc import Callable
from pathlib import Path

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


def views_manifest(views: Path) -> list[dict] | None:
    """The entries of ``views/manifest.json`` (written by ``scripts/make_views.py``), or None
    after saying how to make them when the file is missing."""
    path = views / "manifest.json"
    if not path.is_file():
        print(f"{path} not found: run .venv/bin/python scripts/make_views.py first")  # noqa: T201
        return None
    return json.loads(path.read_text())
