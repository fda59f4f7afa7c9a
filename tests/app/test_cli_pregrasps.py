"""`pregrasp pregrasps` through ``app.cli.main`` on generated files."""

from __future__ import annotations

import argparse

import numpy as np
import pytest

from app.cli import main
from app.commands.options import OptionError
from app.commands.pregrasps import PIPELINE_OPTIONS
from pregrasp_core.facemask import FaceMaskParams
from pregrasp_core.pregrasps import SamplingParams, TraversalPolicy
from pregrasp_core.result import SCHEMA, read_result


@pytest.fixture(scope="module")
def box_cloud(tmp_path_factory):
    """Points on the surface of a 0.08 x 0.06 x 0.05 m box standing on z = 0, as .npy."""
    rng = np.random.default_rng(0)
    lo, hi = np.array([0.0, 0.0, 0.0]), np.array([0.08, 0.06, 0.05])
    n = 3000
    p = lo + rng.uniform(size=(n, 3)) * (hi - lo)
    axis = rng.integers(0, 3, n)
    p[np.arange(n), axis] = np.where(rng.uniform(size=n) < 0.5, lo[axis], hi[axis])
    path = tmp_path_factory.mktemp("cli") / "box.npy"
    np.save(path, p)
    return path


def test_writes_the_pool_into_the_result(box_cloud, tmp_path, capsys):
    out = tmp_path / "pool.json"
    assert main(["pregrasps", str(box_cloud), "--min-points", "200", "-o", str(out)]) == 0
    assert "pre-grasps" in capsys.readouterr().out
    doc = read_result(out)
    assert doc["schema"] == SCHEMA
    pool = doc["pool"]
    assert pool["count"] == len(pool["pregrasps"]) > 0
    assert pool["support_plane"]["height"] == pytest.approx(0.0)
    g = pool["pregrasps"][0]
    assert np.shape(g["T_world_hand"]) == (4, 4) and len(g["preshape"]) == 7
    assert {"load", "decompose", "classify", "facemask", "pool"} <= set(doc["timings"])
    nodes = doc["tree"]["nodes"] if isinstance(doc["tree"], dict) else doc["tree"]
    assert all(np.shape(n["face_mask"]) == (6, 5) for n in nodes)
    # the box stands on the table: its bottom face is blocked in the root's mask
    assert sum(row[0] for row in nodes[0]["face_mask"]) >= 1
    assert doc["parameters"]["facemask"]["support"] is True


def test_options_reach_the_pipeline(box_cloud, tmp_path, capsys):
    out = tmp_path / "pool.json"
    args = [
        "pregrasps", str(box_cloud), "--min-points", "200", "--no-support", "--interval", "0.025",
        "--policy", "all", "--no-fallback", "-o", str(out),
    ]  # fmt: skip
    assert main(args) == 0
    doc = read_result(out)
    assert doc["pool"]["support_plane"] is None
    assert doc["parameters"]["sampling"]["interval"] == 0.025
    assert doc["parameters"]["sampling"]["policy"] == "all"
    assert doc["pool"]["traversal"]["candidates"] == [n["id"] for n in doc["tree"]["nodes"]]
    # without a table the bottom face is free: no face of the root is blocked
    assert not any(row[0] for row in doc["tree"]["nodes"][0]["face_mask"])


def test_summary_without_output(box_cloud, capsys):
    assert main(["pregrasps", str(box_cloud), "--min-points", "200"]) == 0
    text = capsys.readouterr().out
    assert "pool:" in text and "dropped:" in text and "support:  normal" in text
    assert "candidate" in text


def test_bad_input_and_options_exit_2(box_cloud, tmp_path, capsys):
    missing = tmp_path / "nope.ply"
    assert main(["pregrasps", str(missing)]) == 2
    err = capsys.readouterr().err
    assert "pregrasp pregrasps: error:" in err and "nope.ply" in err
    assert main(["pregrasps", str(box_cloud), "--interval", "-1"]) == 2
    assert "pregrasp pregrasps: error: --interval: must be > 0" in capsys.readouterr().err
    assert main(["pregrasps", str(box_cloud), "--face-clearance", "-0.1"]) == 2
    assert "error: --face-clearance: must be a length in [0, 10] m" in capsys.readouterr().err


def test_options_build_the_dataclasses():
    p = argparse.ArgumentParser()
    PIPELINE_OPTIONS.add_to(p)
    params = PIPELINE_OPTIONS.build(p.parse_args([]))
    assert params.facemask == FaceMaskParams()
    assert params.sampling == SamplingParams()
    a = p.parse_args(["--support-height", "0.1", "--up", "0", "1", "0", "--policy", "leaves"])
    params = PIPELINE_OPTIONS.build(a)
    assert params.facemask.support_height == 0.1 and params.facemask.up == (0.0, 1.0, 0.0)
    assert params.sampling.policy is TraversalPolicy.LEAVES
    a = p.parse_args(["--up", "0", "0", "0"])
    with pytest.raises(OptionError, match="^--up: must be a non-zero"):
        PIPELINE_OPTIONS.build(a)
