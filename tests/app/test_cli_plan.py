"""`pregrasp plan`: summary, JSON result (file and stdout), batch over a folder with a CSV
report and a progress bar, and user-facing errors."""

from __future__ import annotations

import csv
import io
import json
import shutil

import numpy as np
import pytest
import trimesh

from app.cli import main
from app.commands.plan import REPORT_COLUMNS, ProgressBar
from pregrasp_core.paths import OBJECTS_DIR

LEMON = OBJECTS_DIR / "fruit_lemon.obj"
FAST = ["--points", "2500"]


def test_summary_lists_parts_pool_and_best_grasps(capsys):
    assert main(["plan", str(LEMON), *FAST, "--top", "2"]) == 0
    out = capsys.readouterr().out
    assert "object:" in out and "fruit_lemon.obj (2500 points)" in out
    assert "parts: 1" in out
    assert "pool:" in out and "planned:" in out
    assert "timings:" in out and "grasps" in out.split("timings:")[1]
    assert "best 2 grasps (#1 = best; by epsilon, then volume):" in out
    lines = out.splitlines()
    header = next(k for k, line in enumerate(lines) if "contacts" in line and "epsilon" in line)
    assert lines[header].split()[:3] == ["#", "type", "node"]
    first = lines[header + 1].split()
    by_type = lines.index("by grasp type (why the best has its type):")
    assert lines[by_type + 1].strip().startswith(first[1] + ":")  # the best type comes first
    assert "force closure" in lines[by_type + 1] and "best epsilon" in lines[by_type + 1]
    assert first[0] == "1" and first[1] in ("spherical", "cylindrical", "three_finger_tip",
                                            "two_finger_tip")  # fmt: skip


def test_json_result_has_grasps_best_and_timings(tmp_path, capsys):
    out_file = tmp_path / "lemon.json"
    assert main(["plan", str(LEMON), *FAST, "-o", str(out_file)]) == 0
    assert "wrote" in capsys.readouterr().out
    doc = json.loads(out_file.read_text())
    assert doc["schema"] == "pregrasp/1"
    for stage in ("load", "decompose", "classify", "facemask", "pool", "normals", "grasps"):
        assert doc["timings"][stage] >= 0.0
    n_pool = len(doc["pool"]["pregrasps"]) if "pregrasps" in doc["pool"] else None
    items = doc["grasps"]["items"]
    if n_pool is not None:
        assert len(items) == n_pool
    assert [g["pregrasp"] for g in items] == list(range(len(items)))
    ranking = doc["grasps"]["ranking"]
    if ranking:
        assert doc["best"] == ranking[0]
        best = items[doc["best"]]
        assert best["rank"] == 0 and best["status"] == "kept"
        eps = [items[k]["epsilon"] for k in ranking]
        assert eps == sorted(eps, reverse=True)
    else:
        assert doc["best"] is None
    for g in items:
        assert (g["rejection"] is None) == (g["status"] == "kept")
    assert doc["parameters"]["planner"]["quality"]["mu"] == 0.5


def test_an_empty_pool_says_why_every_sample_was_dropped(tmp_path, capsys):
    """A 2 x 2 x 1 cm brick on the table with the fingertip pinches off: the paper's enclosing
    surfaces put the open hand below the table from every side, so every sample is dropped;
    the line says so with the pool's counts (the result file's ``pool.dropped``)."""
    brick = trimesh.creation.box([0.02, 0.02, 0.01])
    brick.apply_translation([0.0, 0.0, 0.005])
    pts, _ = trimesh.sample.sample_surface(brick, 3000, seed=0)
    src = tmp_path / "brick.xyz"
    np.savetxt(src, np.asarray(pts))
    out_file = tmp_path / "brick.json"
    assert main(["plan", str(src), "--no-pinch", "-o", str(out_file)]) == 0
    line = capsys.readouterr().out
    dropped = json.loads(out_file.read_text())["pool"]["dropped"]
    assert sum(dropped.values()) > 0
    said = ", ".join(f"{k} {v}" for k, v in dropped.items() if v)
    assert f"the pre-grasp pool is empty (every sample dropped: {said})" in line


def test_json_to_stdout_and_planner_options(capsys):
    assert main(["plan", str(LEMON), *FAST, "--mu", "0.8", "--cone-edges", "6", "-o", "-"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["parameters"]["planner"]["quality"] == {
        "mu": 0.8, "n_edges": 6, "torque_scale": None, "torque_origin": "object",
        "exact_top": 20, "exact_all": False,
    }  # fmt: skip
    assert doc["grasps"]["quality"]["n_edges"] == 6
    # the thread count is recorded and changes no grasp
    assert main(["plan", str(LEMON), *FAST, "--mu", "0.8", "--cone-edges", "6", "--threads", "1",
                 "-o", "-"]) == 0  # fmt: skip
    one = json.loads(capsys.readouterr().out)
    assert doc["parameters"]["planner"]["threads"] == 0
    assert one["parameters"]["planner"]["threads"] == 1
    assert one["grasps"]["items"] == doc["grasps"]["items"] and one["best"] == doc["best"]


def _box_obj(path):
    trimesh.creation.box(extents=[0.05, 0.07, 0.02]).export(path)


def test_batch_over_a_folder_writes_a_csv_report(tmp_path, capsys):
    folder = tmp_path / "objects"
    folder.mkdir()
    shutil.copy(LEMON, folder / "a_lemon.obj")
    _box_obj(folder / "b_box.obj")
    (folder / "c_empty.xyz").write_text("")
    (folder / "d_manifest.csv").write_text("name,source\nmug,pybullet\n")
    (folder / "notes.md").write_text("not an object")
    report = tmp_path / "report.csv"
    code = main(["plan", str(folder), *FAST, "--report", str(report), "-o", str(tmp_path / "js")])
    captured = capsys.readouterr()
    assert code == 0  # unreadable files are skipped, every object was planned
    rows = list(csv.DictReader(report.open()))
    assert [r["object"] for r in rows] == ["a_lemon.obj", "b_box.obj", "c_empty.xyz",
                                           "d_manifest.csv"]  # fmt: skip
    assert list(rows[0]) == list(REPORT_COLUMNS) == [
        "object", "points", "parts", "pool", "kept", "force_closure", "best_type",
        "best_contacts", "best_epsilon", "best_volume", "seconds", "error", "simulated", "lifted",
    ]  # fmt: skip
    assert rows[0]["simulated"] == rows[0]["lifted"] == "0"  # no --simulate
    assert rows[2]["simulated"] == ""  # a skipped file
    assert rows[0]["error"] == "" and int(rows[0]["points"]) == 2500
    assert int(rows[1]["parts"]) >= 1 and rows[1]["error"] == ""
    assert rows[2]["error"].startswith("skipped:") and "c_empty.xyz" in rows[2]["error"]
    assert "empty" in rows[2]["error"]
    assert rows[3]["error"].startswith("skipped:") and "d_manifest.csv" in rows[3]["error"]
    for r in rows[:2]:
        if r["best_type"]:
            assert float(r["best_epsilon"]) >= 0.0 and int(r["best_contacts"]) >= 1
    assert sorted(p.name for p in (tmp_path / "js").iterdir()) == ["a_lemon.json", "b_box.json"]
    # the progress bar (stderr is not a terminal under pytest: one line per update)
    assert "[" in captured.err and "4/4 d_manifest.csv" in captured.err
    assert "2 objects planned (2 files skipped), best grasp force closure on" in captured.out


def test_batch_without_report_prints_csv(tmp_path, capsys):
    folder = tmp_path / "one"
    folder.mkdir()
    _box_obj(folder / "box.obj")
    assert main(["plan", str(folder), *FAST]) == 0
    rows = list(csv.DictReader(io.StringIO(capsys.readouterr().out)))
    assert len(rows) == 1 and rows[0]["object"] == "box.obj"


def test_batch_on_worker_processes_gives_the_same_report(tmp_path, capsys):
    """--jobs 2 (two spawned worker processes) against the serial batch on the same folder:
    the same rows in name order (all but the seconds), the same result files, a full bar."""
    folder = tmp_path / "objects"
    folder.mkdir()
    shutil.copy(LEMON, folder / "a_lemon.obj")
    _box_obj(folder / "b_box.obj")
    (folder / "c_manifest.csv").write_text("name,source\nmug,pybullet\n")
    reports = []
    for jobs in ("1", "2"):
        report, js = tmp_path / f"r{jobs}.csv", tmp_path / f"js{jobs}"
        argv = ["plan", str(folder), *FAST, "--report", str(report), "-o", str(js)]
        assert main([*argv, "--jobs", jobs]) == 0
        err = capsys.readouterr().err
        assert "3/3" in err
        rows = list(csv.DictReader(report.open()))
        reports.append([{k: v for k, v in r.items() if k != "seconds"} for r in rows])
        docs = {p.name: json.loads(p.read_text()) for p in sorted(js.iterdir())}
        assert sorted(docs) == ["a_lemon.json", "b_box.json"]
        reports[-1].append({n: d["best"] for n, d in docs.items()})
    assert reports[0] == reports[1]
    assert [r["object"] for r in reports[1][:3]] == ["a_lemon.obj", "b_box.obj", "c_manifest.csv"]
    assert reports[1][2]["error"].startswith("skipped:")


class _Tty(io.StringIO):
    """A text stream that says it is a terminal (the progress bar redraws in place there)."""

    def isatty(self):
        return True


def test_progress_bar_redraws_in_place_on_a_terminal():
    s = _Tty()
    bar = ProgressBar(4, stream=s, width=8)
    bar.update(2, "x")
    bar.update(4, "y")
    text = s.getvalue()
    assert text.startswith("\r[####....] 2/4 x") and "\r[########] 4/4 y" in text
    assert text.endswith("\n")


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--mu", "-1"], "--mu: must be"),
        (["--contact-distance", "0.0001"], "--contact-distance: must be at least --closing-m"),
        (["--threads", "-3"], "--threads: must be"),
        (["--top", "-2"], "--top: must be >= 0"),
        (["--report", "r.csv"], "--report is for a folder INPUT"),
        (["--jobs", "0"], "--jobs: must be >= 1"),
        (["--jobs", "2"], "--jobs is for a folder INPUT"),
    ],
)
def test_bad_options_are_one_line_errors(argv, message, capsys):
    assert main(["plan", str(LEMON), *FAST, *argv]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"pregrasp plan: error: {message}")
    assert "Traceback" not in err and len(err.splitlines()) == 1


def test_a_folder_of_unreadable_files_fails(tmp_path, capsys):
    (tmp_path / "a.xyz").write_text("1 2\n")
    assert main(["plan", str(tmp_path), *FAST]) == 1
    rows = list(csv.DictReader(io.StringIO(capsys.readouterr().out)))
    assert rows[0]["error"].startswith("skipped:")


def test_empty_folder_and_missing_file(tmp_path, capsys):
    assert main(["plan", str(tmp_path)]) == 2
    assert "no point cloud or mesh files" in capsys.readouterr().err
    assert main(["plan", str(tmp_path / "missing.obj")]) == 2
    err = capsys.readouterr().err
    assert "missing.obj" in err and "Traceback" not in err


def test_report_row_numbers_match_the_grasp_set():
    """The CSV row is computed from the result, not re-derived: check it on a real run."""
    from app.commands.plan import report_row
    from pregrasp_core.hand import load_hand
    from pregrasp_core.io import load_point_cloud
    from pregrasp_core.pipeline import run_pipeline

    cloud = load_point_cloud(LEMON, n_points=2500)
    result = run_pipeline(cloud, hand=load_hand(), until="grasps")
    row = report_row("lemon", result, 1.23456)
    gs = result.grasps
    assert row["pool"] == len(result.pool) and row["kept"] == len(gs.ranking)
    assert row["force_closure"] == sum(g.epsilon > 0 for g in gs.grasps)
    if gs.best is not None:
        assert row["best_epsilon"] == pytest.approx(gs.grasps[gs.best].epsilon, abs=1e-6)
        assert row["best_type"] == gs.grasps[gs.best].grasp_type
    assert row["seconds"] == pytest.approx(1.2346)
    assert np.isfinite(row["best_volume"])


def test_batch_goes_on_past_a_malformed_file(tmp_path, capsys):
    """A folder with a good object and a malformed mesh (an OBJ vertex with 2 coordinates,
    which once ended the whole batch in a traceback): the report lists both, the object is
    planned, the bad file's row and a line on stderr name it and say what is wrong."""
    folder = tmp_path / "objects"
    folder.mkdir()
    shutil.copy(LEMON, folder / "a_lemon.obj")
    (folder / "b_bad.obj").write_text("v 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    report = tmp_path / "report.csv"
    code = main(["plan", str(folder), *FAST, "--report", str(report)])
    captured = capsys.readouterr()
    assert "Traceback" not in captured.err
    rows = list(csv.DictReader(report.open()))
    assert [r["object"] for r in rows] == ["a_lemon.obj", "b_bad.obj"]
    assert rows[0]["error"] == "" and int(rows[0]["points"]) == 2500
    assert "b_bad.obj" in rows[1]["error"] and rows[1]["points"] == ""
    bad_lines = [ln for ln in captured.err.splitlines() if "b_bad.obj:" in ln]
    assert len(bad_lines) == 1 and bad_lines[0].startswith("pregrasp plan: ")
    assert rows[1]["error"] in bad_lines[0]
    # a reader's InputError lists the file as skipped (exit 0); anything else is a failure
    assert code == (0 if rows[1]["error"].startswith("skipped:") else 1)


@pytest.mark.parametrize("where", ["load", "plan"])
def test_batch_reports_any_exception_and_goes_on(tmp_path, capsys, monkeypatch, where):
    """An unexpected exception (not a PregraspError) while reading or planning one file: that
    row holds the exception's type and message, the other objects are planned, exit 1."""
    import app.commands.common as common_mod
    import app.commands.plan as plan_mod

    folder = tmp_path / "objects"
    folder.mkdir()
    shutil.copy(LEMON, folder / "a_lemon.obj")
    _box_obj(folder / "b_box.obj")
    shutil.copy(LEMON, folder / "c_lemon.obj")
    if where == "load":
        real_load = common_mod.load_point_cloud

        def load(path, **kw):
            if "b_box" in str(path):
                raise IndexError("index 8 is out of bounds for axis 0 with size 3")
            return real_load(path, **kw)

        monkeypatch.setattr(common_mod, "load_point_cloud", load)
        expected = "IndexError: index 8 is out of bounds for axis 0 with size 3"
    else:
        real_run = plan_mod.run_pipeline

        def run_pipeline(cloud, *a, **kw):
            if "b_box" in cloud.source:
                raise MemoryError("Unable to allocate 21.6 GiB")
            return real_run(cloud, *a, **kw)

        monkeypatch.setattr(plan_mod, "run_pipeline", run_pipeline)
        expected = "MemoryError: Unable to allocate 21.6 GiB"
    report = tmp_path / "report.csv"
    assert main(["plan", str(folder), *FAST, "--report", str(report)]) == 1
    captured = capsys.readouterr()
    rows = list(csv.DictReader(report.open()))
    assert [r["object"] for r in rows] == ["a_lemon.obj", "b_box.obj", "c_lemon.obj"]
    assert rows[0]["error"] == rows[2]["error"] == ""
    assert rows[0]["best_type"] == rows[2]["best_type"] != ""  # the same lemon, planned twice
    assert rows[1]["error"] == f"{folder / 'b_box.obj'}: {expected}"
    assert f"pregrasp plan: error: {rows[1]['error']}" in captured.err.splitlines()
    assert "2 objects planned, 1 failed" in captured.out


def test_progress_bar_note_keeps_the_bar_below_it():
    s = _Tty()
    bar = ProgressBar(2, stream=s, width=4)
    bar.update(1, "a")
    bar.note("pregrasp plan: error: b: broken")
    bar.update(2, "b")
    lines = s.getvalue().split("\n")
    assert lines[0].startswith("\r[##..] 1/2 a") and "\rpregrasp plan: error: b: broken" in lines[0]
    assert lines[1].startswith("\r[####] 2/2 b")


@pytest.mark.parametrize("kind", ["mesh", "xyz-only PLY"])
def test_plan_in_a_fresh_process_where_two_threads_start_numba(kind, tmp_path):
    """``pregrasp plan`` as a user runs it, in a new interpreter (numba not imported yet): the
    pipeline's normals thread and the decomposition on the main thread start their compiled
    kernels together, and both import numba. numba's modules import each other in a circle, so
    two threads importing it at once failed with "cannot import name '_Intrinsic' from
    partially initialized module" (a PLY without normals failed 2 runs of 3, the default
    mesh every run once its normals used the grid search); every numba import now goes
    through ``pregrasp_core.jit.import_numba``. Three fresh processes each."""
    import subprocess
    import sys

    if kind == "mesh":
        path = LEMON
    else:
        mesh = trimesh.load(LEMON, force="mesh")
        pts, _ = trimesh.sample.sample_surface(mesh, 2500, seed=4)
        path = tmp_path / "lemon_xyz.ply"
        trimesh.PointCloud(pts).export(path)
    for k in range(3):  # loop over 3 fresh processes
        out = tmp_path / f"r{k}.json"
        run = subprocess.run(
            [sys.executable, "-m", "app.cli", "plan", str(path), *FAST, "-o", str(out)],
            capture_output=True,
            text=True,
            timeout=300,
        )
        assert run.returncode == 0, run.stderr[-2000:]
        assert json.loads(out.read_text())["pool"], "no result written"
