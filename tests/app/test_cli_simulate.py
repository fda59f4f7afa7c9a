"""`pregrasp plan --simulate K`: the MuJoCo lift test of the best K grasps in the result file,
the re-ranking by it (simulated grasps that lifted first), the summary's lift column, the
batch report's columns, determinism and the flag's error."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest

from app.cli import main
from app.commands.plan import rank_by_lift
from pregrasp_core.paths import OBJECTS_DIR
from pregrasp_core.planner import GraspSet

CAN = OBJECTS_DIR / "can_soda.obj"
FAST = ["--points", "5000"]
K = 8  # on the can at 5000 points, one of the best 8 grasps drops the can (a real re-ranking)

# the fields of SimulationResult.to_dict() that docs/result-schema.md lists, written by hand
FIELDS = {
    "success", "outcome", "rise", "slip", "slip_angle", "push", "approach_push",
    "initial_penetration", "planned_penetration", "contact_links", "object_held", "q_closed",
    "sim_time", "n_steps", "cpu_time", "phase_times",
}  # fmt: skip


@pytest.fixture(scope="module")
def can_docs(tmp_path_factory):
    """The can planned without and with --simulate K (twice: determinism)."""
    d = tmp_path_factory.mktemp("sim")
    docs = {}
    for name, extra in (("plain", []), ("sim", ["--simulate", str(K)]),
                        ("again", ["--simulate", str(K)])):  # fmt: skip
        out = d / f"{name}.json"
        assert main(["plan", str(CAN), *FAST, *extra, "-o", str(out)]) == 0
        docs[name] = json.loads(out.read_text())
    return docs


def test_the_file_holds_k_simulation_objects(can_docs):
    doc, plain = can_docs["sim"], can_docs["plain"]
    items = doc["grasps"]["items"]
    simulated = [g for g in items if g["simulation"] is not None]
    assert len(simulated) == K == doc["grasps"]["n_simulated"]
    # the simulated ones are the planner's best K (the ranking without --simulate)
    assert {g["pregrasp"] for g in simulated} == set(plain["grasps"]["ranking"][:K])
    for g in simulated:
        sim = g["simulation"]
        assert set(sim) == FIELDS
        assert sim["success"] == (sim["outcome"] == "lifted")
        assert sim["outcome"] in ("lifted", "slipped", "dropped", "unstable")
        if sim["success"]:  # the documented rule: rose >= 8 cm, slipped < 2 cm
            assert sim["rise"] >= 0.08 and sim["slip"] < 0.02
        assert sim["cpu_time"] > 0.0 and sim["n_steps"] > 0 and len(sim["q_closed"]) > 0
    assert doc["grasps"]["n_lifted"] == sum(g["simulation"]["success"] for g in simulated)
    assert all(g["simulation"] is None for g in plain["grasps"]["items"])
    assert plain["grasps"]["n_simulated"] == 0 and "simulation" not in plain["parameters"]
    par = doc["parameters"]["simulation"]
    assert par["lift_height"] == 0.1 and par["max_slip"] == 0.02 and par["hold_time"] == 1.0
    assert doc["timings"]["simulate"] > 0.0


def test_simulated_successes_rank_first(can_docs):
    doc, plain = can_docs["sim"], can_docs["plain"]
    items, ranking = doc["grasps"]["items"], doc["grasps"]["ranking"]
    before = plain["grasps"]["ranking"]
    lifted = [i for i in before[:K] if items[i]["simulation"]["success"]]
    failed = [i for i in before[:K] if not items[i]["simulation"]["success"]]
    assert failed, "the can's best 8 grasps should include one that does not lift"
    assert ranking == lifted + failed + before[K:]
    assert [items[i]["rank"] for i in ranking] == list(range(len(ranking)))
    best = doc["best"]
    first_fc = next(i for i in lifted if items[i]["epsilon"] > 0)
    assert best == first_fc and items[best]["simulation"]["success"]
    assert doc["best_reason"].startswith("force closure and lifted in simulation")
    assert f"({K} simulated, {len(lifted)} lifted)" in doc["best_reason"]


def test_the_same_run_twice_gives_the_same_outcomes(can_docs):
    a, b = can_docs["sim"]["grasps"]["items"], can_docs["again"]["grasps"]["items"]

    def outcome(g):
        return None if g["simulation"] is None else {
            k: v for k, v in g["simulation"].items() if k != "cpu_time"
        }  # fmt: skip

    assert [outcome(g) for g in a] == [outcome(g) for g in b]
    assert can_docs["sim"]["grasps"]["ranking"] == can_docs["again"]["grasps"]["ranking"]


def test_summary_has_a_lift_column(capsys):
    assert main(["plan", str(CAN), *FAST, "--simulate", "2", "--top", "4"]) == 0
    out = capsys.readouterr().out
    assert "lift test (MuJoCo): 2 simulated, " in out and " lifted (" in out
    lines = out.splitlines()
    header = next(k for k, line in enumerate(lines) if line.split()[:2] == ["#", "type"])
    assert lines[header].split()[-2:] == ["lift", "links"]
    col = [lines[header + 1 + r].split()[-2] for r in range(4)]
    assert sorted(col[:2]) in (["yes", "yes"], ["no", "yes"], ["no", "no"]) and col[2:] == ["-"] * 2
    assert col[:2] == sorted(col[:2], key=lambda c: c != "yes")  # the ones that lifted first


def test_batch_report_counts_simulated_and_lifted(tmp_path, capsys):
    folder = tmp_path / "objects"
    folder.mkdir()
    (folder / "can.obj").write_bytes(CAN.read_bytes())
    report = tmp_path / "r.csv"
    assert main(["plan", str(folder), *FAST, "--simulate", "2", "--report", str(report),
                 "-o", str(tmp_path / "js")]) == 0  # fmt: skip
    (row,) = list(csv.DictReader(report.open()))
    assert list(row)[-2:] == ["simulated", "lifted"] and row["simulated"] == "2"
    doc = json.loads((tmp_path / "js" / "can.json").read_text())
    assert int(row["lifted"]) == doc["grasps"]["n_lifted"]
    assert sum(g["simulation"] is not None for g in doc["grasps"]["items"]) == 2


def test_negative_simulate_is_an_error_naming_the_flag(capsys):
    assert main(["plan", str(CAN), *FAST, "--simulate", "-1"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("pregrasp plan: error: --simulate: must be a number of grasps >= 0")
    assert "Traceback" not in err and len(err.splitlines()) == 1


def _set(epsilons):
    """A GraspSet of kept grasps with these epsilons, ranked in the given order."""
    from pregrasp_core.planner import Grasp

    grasps = tuple(
        Grasp(i, "spherical", np.eye(4), 0.0, "", np.zeros(3), (), (), e, 1.0, i, None)
        for i, e in enumerate(epsilons)
    )
    return GraspSet(grasps, np.arange(len(grasps)), ("a", "b", "c"), {})


def test_rank_by_lift_rule():
    """Hand-made outcomes: lifted first, then failed, then the rest; best = the first
    force-closure grasp that lifted, else the planner's best."""
    gs = _set([0.3, 0.2, 0.0, 0.1, 0.05])
    ranked, best, reason = rank_by_lift(gs, {0: False, 1: False, 2: True, 3: True})
    assert ranked.ranking.tolist() == [2, 3, 0, 1, 4]
    assert [ranked.grasps[i].rank for i in range(5)] == [2, 3, 0, 1, 4]
    assert best == 3 and "(4 simulated, 2 lifted)" in reason  # 2 lifted but has epsilon 0
    # nothing lifted: the ranking and the best are the planner's
    ranked, best, reason = rank_by_lift(gs, {0: False, 1: False})
    assert ranked.ranking.tolist() == [0, 1, 2, 3, 4] and best == gs.best == 0
    assert reason.startswith(gs.best_reason) and "no simulated grasp lifted" in reason
    # only a grasp with epsilon 0 lifted: ranked first, but best stays the planner's
    ranked, best, reason = rank_by_lift(gs, {0: False, 1: False, 2: True})
    assert ranked.ranking.tolist()[0] == 2 and best == 0
    assert "no force-closure grasp lifted" in reason
    with pytest.raises(ValueError, match=r"simulated grasps \[7\] are not kept"):
        rank_by_lift(gs, {7: True})
    assert gs.ranking.tolist() == [0, 1, 2, 3, 4]  # the input set is not changed
    assert [g.rank for g in gs.grasps] == [0, 1, 2, 3, 4]
