"""`pregrasp plan DIR --scheduler ADDRESS`: the batch on a Dask distributed cluster (a local one
of 2 worker processes started here) gives the same report and result files as the serial batch;
a scheduler that cannot be reached, or that has no worker, is a one-line error."""

from __future__ import annotations

import csv
import importlib
import io
import re
import shutil
import socket
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from distributed import Client, LocalCluster

import app.commands.plan as plan_mod
from app.cli import main
from pregrasp_core.paths import OBJECTS_DIR

DEMO = ("can_soda.obj", "fruit_lemon.obj", "ramekin.obj")
"""Three small demo objects (one part each, quick to plan)."""
FAST = ["--points", "3000"]
RUN_LIMIT_S = 300.0
"""A batch run in these tests must end within this: a hang guard, not a speed check (a run takes
~10-20 s on the 2-core VM; the first one of a fresh clone also compiles the numba loops into
their cache, which took 50-90 s on that VM under load)."""


def _run(argv: list[str], limit: float = RUN_LIMIT_S) -> int:
    """``main(argv)`` in a thread that must end within ``limit`` seconds (a hung cluster fails
    the test instead of hanging the suite)."""
    code: list[int] = []
    t = threading.Thread(target=lambda: code.append(main(argv)), daemon=True)
    t.start()
    t.join(limit)
    assert not t.is_alive(), f"pregrasp {' '.join(argv[:2])} ... still running after {limit} s"
    assert code, "main raised (see the thread's traceback above)"
    return code[0]


@pytest.fixture(scope="module")
def cluster() -> Iterator[LocalCluster]:
    """2 worker processes, one thread each (spawned: they import the code under test from the
    parent's sys.path and load the hand themselves); the scheduler's HTTP server on a free port
    (8787 may be taken)."""
    with LocalCluster(
        n_workers=2, threads_per_worker=1, processes=True, dashboard_address="127.0.0.1:0"
    ) as c:
        yield c


@pytest.fixture
def folder(tmp_path: Path) -> Path:
    """3 demo objects, a manifest (not an object: skipped) and a cloud of collinear points
    (read, but planning it fails: its error stays in its row, the batch goes on)."""
    d = tmp_path / "objects"
    d.mkdir()
    for name in DEMO:
        shutil.copy(OBJECTS_DIR / name, d / name)
    shutil.copy(OBJECTS_DIR / "manifest.csv", d / "manifest.csv")
    t = np.linspace(0.0, 0.1, 200)
    np.savetxt(d / "line.xyz", np.c_[t, t, t])
    return d


def _without_timings(text: str) -> str:
    """The result file's text without its ``timings`` object (seconds per stage)."""
    out, n = re.subn(r'\n "timings": \{[^{}]*\},', "", text)
    assert n == 1, "the result file has one timings object"
    return out


def test_distributed_batch_gives_the_serial_report_and_files(cluster, folder, tmp_path, capsys):
    """The same report (all but the seconds) and the same result files byte for byte (all but
    the timings) on 2 Dask workers as with --jobs 1; the one other line that differs is the
    recorded planner thread count: workers, local (--jobs 2) or a cluster's, plan with one."""
    with Client(cluster, set_as_default=False) as client:  # the workers run this code
        files_of_workers = client.run(lambda: importlib.import_module("app.commands.plan").__file__)
    assert set(files_of_workers.values()) == {plan_mod.__file__}
    runs = {
        "serial": ["--jobs", "1"],
        "dask": ["--scheduler", cluster.scheduler_address],
    }
    reports, files, stderr = {}, {}, {}
    for name, flags in runs.items():
        report, js = tmp_path / f"{name}.csv", tmp_path / name
        argv = ["plan", str(folder), *FAST, "--report", str(report), "-o", str(js), *flags]
        assert _run(argv) == 1  # line.xyz failed; the others were planned
        out, stderr[name] = capsys.readouterr()
        assert "3 objects planned (1 file skipped), 1 failed" in out
        rows = list(csv.DictReader(report.open()))
        for r in rows:
            assert float(r.pop("seconds")) >= 0.0
        reports[name] = rows
        files[name] = {p.name: p.read_text() for p in sorted(js.iterdir())}
    serial, dask = reports["serial"], reports["dask"]
    assert [r["object"] for r in serial] == [*sorted([*DEMO, "line.xyz", "manifest.csv"])]
    assert dask == serial
    by_name = {r["object"]: r for r in serial}
    assert all(by_name[n]["error"] == "" and by_name[n]["points"] == "3000" for n in DEMO)
    assert by_name["manifest.csv"]["error"].startswith("skipped: ")
    assert by_name["line.xyz"]["error"].startswith(f"{folder / 'line.xyz'}: all points lie on ")
    for name in ("serial", "dask"):
        err = stderr[name]
        assert "Traceback" not in err and "5/5" in err
        assert f"pregrasp plan: error: {by_name['line.xyz']['error']}" in err.splitlines()

    assert (
        sorted(files["dask"])
        == sorted(files["serial"])
        == [n.replace(".obj", ".json") for n in DEMO]
    )
    for fname, text in files["serial"].items():
        a = _without_timings(text).splitlines()
        b = _without_timings(files["dask"][fname]).splitlines()
        assert len(a) == len(b)
        differ = [(x, y) for x, y in zip(a, b, strict=True) if x != y]
        assert differ == [('   "threads": 0', '   "threads": 1')], fname


def test_distributed_batch_equals_the_local_pool_byte_for_byte(cluster, tmp_path, capsys):
    """Against the local process pool (--jobs 2, which plans with the same one-thread planners)
    the result files are equal to the byte once the timings are taken out."""
    d = tmp_path / "objects"
    d.mkdir()
    for name in ("a_lemon.obj", "b_lemon.obj"):  # the smallest demo object, twice
        shutil.copy(OBJECTS_DIR / "fruit_lemon.obj", d / name)
    texts = []
    for flags in (["--jobs", "2"], ["--scheduler", cluster.scheduler_address]):
        js = tmp_path / flags[0].strip("-")
        assert _run(["plan", str(d), *FAST, "-o", str(js), *flags]) == 0
        csv_text = capsys.readouterr().out
        texts.append(
            (
                [
                    {k: v for k, v in r.items() if k != "seconds"}
                    for r in csv.DictReader(io.StringIO(csv_text))
                ],
                {p.name: _without_timings(p.read_text()) for p in sorted(js.iterdir())},
            )
        )
    assert texts[0] == texts[1]
    assert len(texts[0][1]) == 2


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def test_unreachable_scheduler_is_a_one_line_error_within_seconds(folder, capsys):
    address = f"tcp://127.0.0.1:{_free_port()}"  # nothing listens there
    t0 = time.perf_counter()
    assert _run(["plan", str(folder), *FAST, "--scheduler", address], limit=20.0) == 2
    elapsed = time.perf_counter() - t0
    captured = capsys.readouterr()
    err = captured.err
    assert err.startswith(f"pregrasp plan: error: --scheduler {address}: cannot reach the Dask ")
    assert len(err.splitlines()) == 1 and "Traceback" not in err
    assert captured.out == ""  # no report, no progress: nothing was planned
    assert elapsed < 10.0


@pytest.mark.parametrize(
    ("address", "message"),
    [
        ("http://127.0.0.1:8786", "--scheduler http://127.0.0.1:8786: cannot reach the Dask"),
        ("", "--scheduler: must be an address such as tcp://HOST:8786"),
    ],
)
def test_bad_scheduler_address(folder, capsys, address, message):
    assert _run(["plan", str(folder), *FAST, "--scheduler", address], limit=20.0) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"pregrasp plan: error: {message}")
    assert len(err.splitlines()) == 1 and "Traceback" not in err


def test_scheduler_without_workers_is_a_one_line_error(folder, capsys):
    with LocalCluster(n_workers=0, processes=False, dashboard_address="127.0.0.1:0") as empty:
        address = empty.scheduler_address
        assert _run(["plan", str(folder), *FAST, "--scheduler", address], limit=30.0) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"pregrasp plan: error: --scheduler {address}: the scheduler has no ")
    assert len(err.splitlines()) == 1 and "Traceback" not in err


@pytest.mark.parametrize(
    ("where", "flags", "message"),
    [
        ("file", ["--scheduler", "tcp://127.0.0.1:8786"], "--scheduler is for a folder INPUT"),
        (
            "folder",
            ["--scheduler", "tcp://127.0.0.1:8786", "--jobs", "2"],
            "--scheduler: cannot be combined with --jobs",
        ),
    ],
)
def test_scheduler_option_errors(folder, capsys, where, flags, message):
    target = folder / DEMO[0] if where == "file" else folder
    assert main(["plan", str(target), *FAST, *flags]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"pregrasp plan: error: {message}")
    assert len(err.splitlines()) == 1


def test_scheduler_without_dask_installed_says_what_to_install(folder, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "distributed", None)  # `import distributed` fails
    assert main(["plan", str(folder), *FAST, "--scheduler", "tcp://127.0.0.1:8786"]) == 2
    err = capsys.readouterr().err
    assert err == (
        "pregrasp plan: error: --scheduler needs Dask distributed: pip install 'pregrasp[batch]'\n"
    )
