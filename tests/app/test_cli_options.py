"""The options of every command, generated from the parameter dataclasses: each flag is accepted
and reaches its dataclass field (in the built parameters and in the result file), a bad value is
reported with the flag's name, ``view`` takes every pipeline flag of ``plan``, and the generator
reads field docstrings and types."""

from __future__ import annotations

import argparse
import dataclasses
import enum
import json
from typing import Any, Literal

import pytest

from app.cli import build_parser, main
from app.commands import common, decompose, plan, pregrasps, view
from app.commands.options import Flag, OptionError, Options, field_docs
from pregrasp_core.io import MIN_POINTS
from pregrasp_core.paths import OBJECTS_DIR
from pregrasp_core.pregrasps import TraversalPolicy

LEMON = OBJECTS_DIR / "fruit_lemon.obj"

# flag -> (arguments after the flag, where the value lands, the value expected there). The
# places are written by hand from the dataclasses' field names (not read from the generator),
# and every value differs from the field's default.
FLAGS: dict[str, tuple[list[str], str, object]] = {
    "--points": (["2500"], "input.points", 2500),
    "--seed": (["3"], "input.seed", 3),
    "--scale": (["0.5"], "input.scale", 0.5),
    "--pick": (["0.1", "0", "0.2"], "input.pick", (0.1, 0.0, 0.2)),
    "--intrinsics": (["cam.json"], "input.intrinsics", ("cam.json",)),
    "--scene": ([], "input.scene", True),
    "--flying-pixels": ([], "input.flying_pixels", True),
    "--scene-obstacles": (["seen"], "input.scene_obstacles", "seen"),
    "--no-scene": ([], "input.scene", False),
    "--volume-ratio": (["0.8"], "params.decomposition.volume_ratio", 0.8),
    "--min-points": (["300"], "params.decomposition.min_points", 300),
    "--max-depth": (["4"], "params.decomposition.max_depth", 4),
    "--ratio-1d": (["0.5"], "params.shape.max_ratio_1d", 0.5),
    "--ratio-2d": (["0.4"], "params.shape.max_ratio_2d", 0.4),
    "--small-size": (["0.04"], "params.shape.small_size", 0.04),
    "--face-clearance": (["0.03"], "params.facemask.clearance", 0.03),
    "--overlap-tolerance": (["0.001"], "params.facemask.overlap_tolerance", 0.001),
    "--min-coverage": (["0.1"], "params.facemask.min_coverage", 0.1),
    "--no-support": ([], "params.facemask.support", False),
    "--up": (["0", "1", "0"], "params.facemask.up", (0.0, 1.0, 0.0)),
    "--support-height": (["-0.01"], "params.facemask.support_height", -0.01),
    "--support-tolerance": (["0.003"], "params.facemask.support_tolerance", 0.003),
    "--interval": (["0.025"], "params.sampling.interval", 0.025),
    "--policy": (["leaves"], "params.sampling.policy", TraversalPolicy.LEAVES),
    "--aperture-scale": (["1.1"], "params.sampling.aperture_scale", 1.1),
    "--standoff": (["0.012"], "params.sampling.standoff", 0.012),
    "--collision-margin": (["0.001"], "params.sampling.collision_margin", 0.001),
    "--support-margin": (["-0.001"], "params.sampling.support_margin", -0.001),
    "--max-backoff": (["0.05"], "params.sampling.max_backoff", 0.05),
    "--backoff-step": (["0.025"], "params.sampling.backoff_step", 0.025),
    "--no-fallback": ([], "params.sampling.fallback", False),
    "--no-pinch": ([], "params.sampling.pinch", False),
    "--rule": (["face"], "params.facemask.rule", "face"),
    "--clearance": (["0.003"], "params.planner.approach_clearance", 0.003),
    "--max-approach": (["0.12"], "params.planner.max_approach", 0.12),
    "--max-lift": (["0.02"], "params.planner.max_lift", 0.02),
    "--closing-margin": (["0.0015"], "params.planner.closing_margin", 0.0015),
    "--closing-steps": (["24"], "params.planner.closing_steps", 24),
    "--slice-resolution": (["0.0005"], "params.planner.slice_resolution", 0.0005),
    "--contact-distance": (["0.004"], "params.planner.contact_distance", 0.004),
    "--penetration-tol": (["0.003"], "params.planner.penetration_tol", 0.003),
    "--assumed-clearance": (["0.003"], "params.planner.assumed_clearance", 0.003),
    "--occluded": (["occupied"], "params.occluded", "occupied"),
    "--threads": (["1"], "params.planner.threads", 1),
    "--mu": (["0.8"], "params.planner.quality.mu", 0.8),
    "--cone-edges": (["6"], "params.planner.quality.n_edges", 6),
    "--torque-scale": (["0.05"], "params.planner.quality.torque_scale", 0.05),
    "--normals-k": (["12"], "params.planner.normals.k", 12),
    "--normals-orient": (["centroid"], "params.planner.normals.orient", "centroid"),
    "--viewpoint": (["0.5", "0", "1"], "params.planner.normals.viewpoint", (0.5, 0.0, 1.0)),
    "--normals-views": (["32"], "params.planner.normals.n_views", 32),
    "--torque-origin": (["contacts"], "params.planner.quality.torque_origin", "contacts"),
    "--exact-top": (["30"], "params.planner.quality.exact_top", 30),
    "--exact-all": ([], "params.planner.quality.exact_all", True),
    "--top": (["3"], "output.top", 3),
    "--output": (["out.json"], "output.output", "out.json"),
    "--report": (["r.csv"], "output.report", "r.csv"),
    "--include-indices": ([], "output.include_indices", True),
    "--jobs": (["2"], "output.jobs", 2),
    "--scheduler": (["tcp://10.0.0.5:8786"], "output.scheduler", "tcp://10.0.0.5:8786"),
    "--simulate": (["2"], "output.simulate", 2),
    "--host": (["0.0.0.0"], "serve.host", "0.0.0.0"),
    "--port": (["9000"], "serve.port", 9000),
}
# the other spelling of a bool flag: its own value
FLAGS["--support"] = ([], "params.facemask.support", True)
FLAGS["--fallback"] = ([], "params.sampling.fallback", True)
FLAGS["--pinch"] = ([], "params.sampling.pinch", True)
FLAGS["--no-exact-all"] = ([], "params.planner.quality.exact_all", False)
# view's second result file is read by the command itself (no options dataclass)
FLAGS["--compare"] = (["b.json"], "args.compare", "b.json")

COMMANDS = {"decompose": decompose, "pregrasps": pregrasps, "plan": plan, "view": view}

PIPELINE_FLAGS = [f for f, (_, place, _) in FLAGS.items() if place.startswith("params.")]


def _subparser(name: str) -> argparse.ArgumentParser:
    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    return sub.choices[name]


def _flags_of(name: str) -> set[str]:
    """Every long option string of command ``name`` (``-h`` and ``-o`` left out)."""
    return {
        s for a in _subparser(name)._actions for s in a.option_strings if s.startswith("--")
    } - {"--help"}


def _built(name: str, ns: argparse.Namespace) -> dict[str, Any]:
    """What the command builds from its parsed options, by the names used in :data:`FLAGS`."""
    mod = COMMANDS[name]
    out: dict[str, Any] = {
        "input": common.INPUT_OPTIONS.build(ns),
        "params": mod.PIPELINE_OPTIONS.build(ns),
    }
    out["args"] = ns
    if name == "view":
        out["serve"] = view.SERVE_OPTIONS.build(ns)
    else:
        out["output"] = mod.OUTPUT_OPTIONS.build(ns)
    return out


def _at(obj: Any, place: str) -> Any:
    head, *rest = place.split(".")
    value = obj[head]
    for name in rest:
        value = getattr(value, name)
    return value


def _as_json(value: object) -> object:
    if isinstance(value, enum.Enum):
        return value.value
    if isinstance(value, tuple):
        return list(value)
    return value


@pytest.mark.parametrize("name", list(COMMANDS))
def test_every_flag_reaches_its_field(name):
    """Each flag of the command, alone with a non-default value, lands in its field; the other
    fields keep their defaults."""
    flags = _flags_of(name)
    assert flags - set(FLAGS) == set(), "a flag without a test value"
    defaults = _built(name, _subparser(name).parse_args(["in.ply"]))
    for flag in sorted(flags):
        args, place, expected = FLAGS[flag]
        built = _built(name, _subparser(name).parse_args(["in.ply", flag, *args]))
        got = _at(built, place)
        assert got == expected and type(got) is type(expected), (flag, got)
        for section, obj in built.items():  # nothing else moved
            if flag == "--viewpoint" and section == "input":  # the loader's camera as well
                assert obj.viewpoint == expected
                obj = dataclasses.replace(obj, viewpoint=None)
            if dataclasses.is_dataclass(obj) and section != place.split(".")[0]:
                assert obj == defaults[section], flag


def test_commands_take_the_flags_of_their_stages():
    """decompose: decomposition and shapes; pregrasps: + face masks, sampling; plan: + planner
    and ``--occluded`` (PipelineParams.occluded); view: every pipeline flag of plan, plus
    --host and --port (not the output options)."""
    stage = {f: place.split(".")[1] for f, (_, place, _) in FLAGS.items() if "params." in place}
    by_cmd = {n: {stage[f] for f in _flags_of(n) if f in stage} for n in COMMANDS}
    assert by_cmd["decompose"] == {"decomposition", "shape"}
    assert by_cmd["pregrasps"] == {"decomposition", "shape", "facemask", "sampling"}
    assert by_cmd["plan"] == by_cmd["view"] == {*by_cmd["pregrasps"], "planner", "occluded"}
    plan_pipeline = {f for f in _flags_of("plan") if f in stage}
    assert plan_pipeline == set(PIPELINE_FLAGS)
    assert _flags_of("view") == plan_pipeline | {"--points", "--seed", "--scale", "--pick",
                                                 "--intrinsics", "--scene", "--no-scene",
                                                 "--flying-pixels", "--scene-obstacles",
                                                 "--host", "--port",
                                                 "--compare"}  # fmt: skip


def test_help_lists_every_flag_grouped_by_stage(capsys):
    """--help of plan and view: every flag of today's options, in a group per stage, with the
    field docstring as help; the flags spelled as before this change (scripts keep working)."""
    before = {  # the flags of `pregrasp plan` written by hand before the generator
        "--points", "--seed", "--scale", "--volume-ratio", "--min-points", "--max-depth",
        "--ratio-1d", "--ratio-2d", "--small-size", "--face-clearance", "--no-support",
        "--support-height", "--up", "--interval", "--policy", "--aperture-scale",
        "--max-backoff", "--no-fallback", "--mu", "--cone-edges", "--clearance",
        "--contact-distance", "--penetration-tol", "--threads", "--jobs", "--top", "--output",
        "--report", "--include-indices",
    }  # fmt: skip
    for name in ("plan", "view"):
        with pytest.raises(SystemExit) as exit_info:
            main([name, "--help"])
        assert exit_info.value.code == 0
        text = capsys.readouterr().out
        output = {"--jobs", "--top", "--output", "--report", "--include-indices"}
        wanted = before if name == "plan" else before - output
        for flag in wanted:
            assert f"{flag} " in text or f"{flag}," in text or f"{flag}\n" in text, (name, flag)
        for group in ("decomposition:", "shape classes (PCA):", "face masks and support plane:",
                      "traversal and sampling:", "planner:", "cloud normals:"):  # fmt: skip
            assert f"\n{group}\n" in text, (name, group)
        # help from the field docstring (QualityParams.mu), with the default
        flat = " ".join(text.split())
        assert "--mu MU Coulomb friction coefficient (dimensionless, >= 0). (default: 0.5)" in flat
        assert "below --closing-margin no link" in flat  # a field's literal -> its flag
        assert "SSH" in text if name == "view" else "-o OUT, --output OUT" in text


def test_every_pipeline_flag_reaches_the_result_file(tmp_path, capsys):
    """All pipeline flags of plan at once, non-default, on the lemon: each value is in the result
    file's ``parameters`` section (the file the planner's run wrote)."""
    argv = ["plan", str(LEMON), "--points", "2500", "-o", str(tmp_path / "r.json")]
    for flag in PIPELINE_FLAGS:
        if flag not in ("--support", "--fallback", "--pinch", "--no-exact-all"):  # the other
            # spelling of each is set here
            argv += [flag, *FLAGS[flag][0]]
    assert main(argv) == 0, capsys.readouterr().err
    doc = json.loads((tmp_path / "r.json").read_text())
    for flag in PIPELINE_FLAGS:
        if flag in ("--support", "--fallback", "--pinch", "--no-exact-all"):
            continue
        _, place, expected = FLAGS[flag]
        got: Any = doc["parameters"]
        for key in place.split(".")[1:]:
            got = got[key]
        assert got == _as_json(expected), (flag, got)
    # decompose writes its two sections the same way
    out = tmp_path / "d.json"
    assert main(["decompose", str(LEMON), "--points", "2500", "--max-depth", "3", "--ratio-1d",
                 "0.5", "-o", str(out)]) == 0  # fmt: skip
    par = json.loads(out.read_text())["parameters"]
    assert par["decomposition"]["max_depth"] == 3 and par["shape"]["max_ratio_1d"] == 0.5


def test_view_passes_the_flags_to_the_viewer(monkeypatch):
    """`pregrasp view` builds the same PipelineParams as `pregrasp plan` from the same flags and
    hands them, with the input options, to ``ViewerConfig`` (the server is not started)."""
    import app.server

    seen: list[app.server.ViewerConfig] = []
    monkeypatch.setattr(app.server, "serve", seen.append)
    flags = ["--mu", "0.7", "--cone-edges", "5", "--interval", "0.03", "--no-support",
             "--min-points", "300", "--threads", "1"]  # fmt: skip
    assert main(["view", str(LEMON), "--scale", "0.5", "--points", "3000", "--seed", "2",
                 "--port", "0", "--host", "localhost", *flags]) == 0  # fmt: skip
    (config,) = seen
    ns = _subparser("plan").parse_args([str(LEMON), *flags])
    assert config.params == plan.PIPELINE_OPTIONS.build(ns)
    assert config.params.planner.quality.n_edges == 5 and config.params.facemask.support is False
    assert (config.scale, config.n_points, config.seed) == (0.5, 3000, 2)
    assert (config.host, config.port) == ("localhost", 0) and config.input == LEMON


def test_the_app_starts_with_the_scale_and_parameters_of_the_command_line(make_app):
    """``ViewerConfig.scale`` multiplies the coordinates of the object the app opens, and the
    first run of the app uses ``ViewerConfig.params`` (what `pregrasp view` passes on)."""
    import numpy as np

    from pregrasp_core.io import load_point_cloud

    ns = _subparser("view").parse_args(["--interval", "0.03", "--max-depth", "0", "--mu", "0.7"])
    params = view.PIPELINE_OPTIONS.build(ns)
    app = make_app(input=LEMON, scale=0.5, n_points=500, params=params)
    state = app.controller.state
    ref = load_point_cloud(LEMON, n_points=500, seed=0)
    assert state.cloud is not None
    assert np.allclose(np.asarray(state.cloud.points), 0.5 * np.asarray(ref.points))
    assert state.params == params and state.result.params == params
    assert len(state.tree.nodes) == 1  # --max-depth 0: no split


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["plan", "--mu", "-1"], "pregrasp plan: error: --mu: must be a friction coefficient in"),
        (["plan", "--cone-edges", "2"], "pregrasp plan: error: --cone-edges: must be an integer"),
        (["plan", "--normals-k", "2"], "pregrasp plan: error: --normals-k: must be an integer"),
        (["plan", "--points", "5"], f"pregrasp plan: error: --points: must be in [{MIN_POINTS}, "),
        (["plan", "--seed", "-1"], "pregrasp plan: error: --seed: must be >= 0"),
        (["plan", "--scale", "0"], "pregrasp plan: error: --scale: must be a positive"),
        (["plan", "--closing-margin", "0.0002"], "pregrasp plan: error: --closing-margin: must "
         "be at least --slice-resolution x sqrt(2) (0.00099 m)"),
        (["pregrasps", "--interval", "0"], "pregrasp pregrasps: error: --interval: must be > 0"),
        (["pregrasps", "--up", "0", "0", "0"], "pregrasp pregrasps: error: --up: must be a non"),
        (["decompose", "--min-points", "3"], "pregrasp decompose: error: --min-points: must be"),
        (["view", "--mu", "-1"], "pregrasp view: error: --mu: must be a friction"),
        (["view", "--port", "70000"], "pregrasp view: error: --port: must be in [0, 65535]"),
    ],
)  # fmt: skip
def test_a_bad_value_names_its_flag(argv, message, capsys):
    """A value the dataclass rejects: one line naming the flag, exit 2, before any slow work."""
    assert main([argv[0], str(LEMON), *argv[1:]]) == 2
    err = capsys.readouterr().err
    assert err.startswith(message), err
    assert len(err.splitlines()) == 1 and "Traceback" not in err


def test_a_value_of_the_wrong_type_names_its_flag(capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["plan", str(LEMON), "--cone-edges", "six"])
    assert exit_info.value.code == 2
    assert "argument --cone-edges: invalid int value: 'six'" in capsys.readouterr().err


# ---------------------------------------------------------------------- the generator itself


class _Mode(str, enum.Enum):
    """A test enum."""

    SLOW = "slow"
    """Careful."""
    FAST = "fast"
    """Hasty."""


@dataclasses.dataclass(frozen=True)
class _Params:
    """Parameters of a made-up stage."""

    step_size: float = 0.5
    """Metres: the step, at most ``limit_value``."""
    limit_value: float = 2.0
    """Largest step (> 0)."""
    count: int = 3
    """How many."""
    mode: _Mode = _Mode.SLOW
    """How (:class:`_Mode` or its value)."""
    on: bool = True
    """Whether it runs; ``False`` = never."""
    where: tuple[float, float] = (0.0, 1.0)
    """A point."""
    cap: float | None = None
    """A cap; ``None`` = none."""
    shape: Literal["round", "square"] = "round"
    """Its shape."""

    def __post_init__(self) -> None:
        if not self.step_size <= self.limit_value:
            raise ValueError(f"step_size ({self.step_size}) must be <= limit_value")
        if self.count < 1:
            raise ValueError("count must be >= 1")
        if self.cap is not None and self.cap < 0:
            raise ValueError("the cap is negative")


def test_field_docs_reads_the_docstring_below_each_field():
    docs = field_docs(_Params)
    assert docs["step_size"] == "Metres: the step, at most ``limit_value``."
    assert docs["cap"] == "A cap; ``None`` = none."
    assert field_docs(_Mode) == {"SLOW": "Careful.", "FAST": "Hasty."}


def test_generated_options_of_a_dataclass(capsys):
    opts: Options[_Params] = Options(_Params, "made up", "made", flags={"count": Flag("--n")})
    p = argparse.ArgumentParser(prog="x")
    opts.add_to(p)
    assert opts.build(p.parse_args([])) == _Params()
    argv = "--step-size 1 --n 5 --mode fast --no-on --where 2 3 --cap 4 --shape square".split()
    built = opts.build(p.parse_args(argv))
    assert built == _Params(1.0, 2.0, 5, _Mode.FAST, False, (2.0, 3.0), 4.0, "square")
    assert opts.help_text("step_size") == "Metres: the step, at most --limit-value."
    assert opts.help_text("on") == "Whether it runs; --no-on = never."
    assert opts.help_text("cap") == "A cap; not given = none."
    assert opts.help_text("mode") == "How. slow: Careful. fast: Hasty."
    with pytest.raises(SystemExit):
        p.parse_args(["--help"])
    text = capsys.readouterr().out
    assert "--step-size M" in text and "--n N" in text and "--where X Y" in text
    assert "--on, --no-on" in text and "(default: --on)" in text and "(default: 0.0 1.0)" in text
    assert "--shape {round,square}" in text
    with pytest.raises(SystemExit):
        p.parse_args(["--shape", "oval"])
    assert "argument --shape: invalid choice: 'oval'" in capsys.readouterr().err
    with pytest.raises(OptionError, match=r"^--step-size: \(3.0\) must be <= --limit-value$"):
        opts.build(p.parse_args(["--step-size", "3"]))
    with pytest.raises(OptionError, match="^--n: must be >= 1$"):
        opts.build(p.parse_args(["--n", "0"]))
    # a message that names no field: the group is named instead
    with pytest.raises(OptionError, match="^invalid made up option: the cap is negative$"):
        opts.build(p.parse_args(["--cap", "-1"]))


@pytest.mark.parametrize(
    ("name", "before"),
    [
        ("decompose", "--points --seed --scale --volume-ratio --min-points --max-depth --ratio-1d "
         "--ratio-2d --small-size --include-indices --output"),
        ("pregrasps", "--points --seed --scale --volume-ratio --min-points --max-depth --ratio-1d "
         "--ratio-2d --small-size --face-clearance --no-support --support-height --up --interval "
         "--policy --aperture-scale --max-backoff --no-fallback --output"),
    ],
)  # fmt: skip
def test_decompose_and_pregrasps_keep_their_flags(name, before, capsys):
    """The flags these commands had before the generator are all still listed in --help."""
    with pytest.raises(SystemExit):
        main([name, "--help"])
    listed = set(capsys.readouterr().out.replace(",", " ").replace("[", " ").split())
    assert set(before.split()) <= listed
    assert "-o" in listed


def test_the_chosen_command_alone_is_imported_and_parsed():
    """``pregrasp plan ...`` builds the parser of ``plan`` only and does not import the other
    commands' modules (the viewer's, the decomposition's); a line without a known command gets
    every command's parser (for the help and the error)."""
    import subprocess
    import sys

    from app.cli import chosen_command

    assert chosen_command(["-v", "plan", "x.ply"]) == "plan"
    assert chosen_command(["view"]) == "view"
    assert chosen_command(["--help"]) is None and chosen_command(["nope", "plan"]) is None
    actions = build_parser("plan")._actions
    sub = next(a for a in actions if isinstance(a, argparse._SubParsersAction))
    assert list(sub.choices) == ["plan"]
    code = (
        "import sys; from app.cli import main\n"
        "try:\n    main(['plan', '--help'])\nexcept SystemExit:\n    pass\n"
        "print(sorted(m for m in sys.modules if m.startswith('app.')))"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True
    ).stdout
    loaded = out.strip().splitlines()[-1]
    assert "'app.commands.plan'" in loaded
    assert "'app.commands.view'" not in loaded and "'app.commands.decompose'" not in loaded
