"""`pregrasp decompose` through ``app.cli.main`` on generated files."""

from __future__ import annotations

import argparse
import json

import numpy as np
import pytest
import trimesh

from app.cli import main
from app.commands.common import INPUT_OPTIONS, InputOptions, add_input_args, input_path
from app.commands.decompose import PIPELINE_OPTIONS
from pregrasp_core.decomposition import DecompositionParams
from pregrasp_core.paths import DEFAULT_OBJECT
from pregrasp_core.result import SCHEMA, read_result
from pregrasp_core.shape import ShapeParams


@pytest.fixture(scope="module")
def l_cloud(tmp_path_factory) -> tuple:
    """An L of a bar (2000 points) and a small block (600 points) saved as .npy, in metres."""
    rng = np.random.default_rng(0)
    bar = rng.uniform([0, 0, 0], [0.20, 0.03, 0.03], (2000, 3))
    block = rng.uniform([0, 0.035, 0], [0.04, 0.075, 0.02], (600, 3))
    path = tmp_path_factory.mktemp("cli") / "l_shape.npy"
    np.save(path, np.vstack([bar, block]))
    return path, 2600


def test_writes_valid_json(l_cloud, tmp_path, capsys):
    path, n = l_cloud
    out = tmp_path / "res.json"
    rc = main(["decompose", str(path), "--min-points", "100", "--ratio-1d", "0.6", "-o", str(out)])
    assert rc == 0
    printed = capsys.readouterr().out
    assert f"wrote {out}: 2 parts, 3 nodes" in printed
    doc = json.loads(out.read_text())  # plain json, no extensions (NaN etc.)
    assert doc == read_result(out)
    assert doc["schema"] == SCHEMA
    assert doc["input"]["source"] == str(path) and doc["input"]["n_points"] == n
    assert doc["input"]["format"] == "npy" and doc["input"]["seed"] == 0
    assert doc["parameters"]["decomposition"] == {
        "volume_ratio": 0.9,
        "min_points": 100,
        "max_depth": 8,
    }
    assert doc["parameters"]["shape"]["max_ratio_1d"] == 0.6
    assert set(doc["timings"]) == {"load", "decompose", "classify"}
    assert all(v >= 0 for v in doc["timings"].values())
    tree = doc["tree"]
    assert tree["n_splits"] == 1 and tree["leaves"] == [1, 2]
    assert [nd["n_points"] for nd in tree["nodes"]] == [2600, 2000, 600]
    assert tree["nodes"][1]["shape_class"] == "1D"  # the bar
    assert tree["nodes"][1]["grasp_type"] == "cylindrical"
    assert all("indices" not in nd for nd in tree["nodes"])


def test_include_indices_and_stdout(l_cloud, capsys):
    path, n = l_cloud
    assert (
        main(["decompose", str(path), "--min-points", "100", "--include-indices", "-o", "-"]) == 0
    )
    doc = json.loads(capsys.readouterr().out)
    leaves = [doc["tree"]["nodes"][i]["indices"] for i in doc["tree"]["leaves"]]
    assert sorted(sum(leaves, [])) == list(range(n))


def test_summary_without_output(l_cloud, capsys):
    path, _ = l_cloud
    assert main(["decompose", str(path), "--min-points", "100"]) == 0
    text = capsys.readouterr().out
    assert "l_shape.npy" in text and "2600 points" in text
    assert "parts:   2 (1 split; volume ratio 0.9, min points 100" in text
    lines = text.splitlines()
    # the tree listing: root, then its two leaves indented by depth, extents in mm
    row = [ln for ln in lines if ln.strip().startswith("1 *")]
    assert len(row) == 1 and row[0].startswith("    1 *")
    assert "1D" in row[0] and "cylindrical" in row[0] and "200 x 30 x 30" in row[0]
    assert any(ln.strip().startswith("2 *") for ln in lines)
    assert "times:" in text and "decompose" in text


def test_mesh_input_and_max_depth(tmp_path, capsys):
    path = tmp_path / "box.stl"
    trimesh.creation.box(extents=(0.12, 0.05, 0.03)).export(path)
    out = tmp_path / "r.json"
    assert main(["decompose", str(path), "--points", "3000", "--seed", "4", "-o", str(out)]) == 0
    doc = read_result(out)
    assert doc["input"]["kind"] == "mesh" and doc["input"]["n_points"] == 3000
    assert doc["input"]["seed"] == 4
    root = doc["tree"]["nodes"][0]
    assert np.allclose(root["extents"], [0.12, 0.05, 0.03], atol=2e-3)
    assert doc["tree"]["n_nodes"] == 1


@pytest.mark.parametrize(
    ("content", "name", "match"),
    [
        (None, "missing.ply", "missing.ply: file not found"),
        (b"", "empty.xyz", "empty.xyz: the file is empty"),
        (b"1 2\n3 4\n", "cols.xyz", "cols.xyz"),
        (b"hello", "data.abc", "data.abc: unknown file extension"),
    ],
)
def test_bad_file_exit_code_2(tmp_path, capsys, content, name, match):
    path = tmp_path / name
    if content is not None:
        path.write_bytes(content)
    rc = main(["decompose", str(path), "-o", str(tmp_path / "out.json")])
    assert rc == 2
    err = capsys.readouterr().err
    assert err.startswith("pregrasp decompose: error: ")
    assert match in err and "Traceback" not in err
    assert not (tmp_path / "out.json").exists()


@pytest.mark.parametrize(
    ("option", "value", "match"),
    [
        ("--volume-ratio", "1.5", "--volume-ratio: must be a number in (0, 1]"),
        ("--min-points", "2", "--min-points: must be an integer in [4, 1,000,000,000]"),
        ("--max-depth", "-1", "--max-depth: must be an integer in [0, 64]"),
        ("--ratio-1d", "0", "--ratio-1d: must be a number in (0, 1]"),
        ("--ratio-2d", "3", "--ratio-2d: must be a number in (0, 1]"),
        ("--small-size", "-0.1", "--small-size: must be a length"),
    ],
)
def test_bad_option_exit_code_2(l_cloud, capsys, option, value, match):
    path, _ = l_cloud
    assert main(["decompose", str(path), option, value]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"pregrasp decompose: error: {match}") and "Traceback" not in err


def test_output_folder_missing(l_cloud, tmp_path, capsys):
    path, _ = l_cloud
    out = tmp_path / "no" / "r.json"
    assert main(["decompose", str(path), "--min-points", "100", "-o", str(out)]) == 2
    assert "does not exist" in capsys.readouterr().err


def test_common_options_defaults():
    p = argparse.ArgumentParser()
    add_input_args(p, required=False)
    PIPELINE_OPTIONS.add_to(p)
    args = p.parse_args([])
    assert input_path(args) == str(DEFAULT_OBJECT)
    assert INPUT_OPTIONS.build(args) == InputOptions(points=20000, seed=0, scale=None)
    params = PIPELINE_OPTIONS.build(args)
    assert params.decomposition == DecompositionParams()
    assert params.shape == ShapeParams()
    args = p.parse_args(["x.ply", "--volume-ratio", "0.8", "--small-size", "0.04"])
    assert input_path(args) == "x.ply"
    assert PIPELINE_OPTIONS.build(args).decomposition.volume_ratio == 0.8
    assert PIPELINE_OPTIONS.build(args).shape.small_size == 0.04
