"""The staged pipeline up to the pool: stages, reuse of unchanged stages, the result document."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from pregrasp_core.decomposition import DecompositionParams
from pregrasp_core.errors import WorkLimitError
from pregrasp_core.facemask import FaceMaskParams
from pregrasp_core.hand import load_hand
from pregrasp_core.io import PointCloud, load_point_cloud
from pregrasp_core.limits import WorkLimits
from pregrasp_core.paths import DEFAULT_OBJECT
from pregrasp_core.pipeline import (
    STAGES,
    PipelineParams,
    pool_section,
    result_document,
    run_pipeline,
)
from pregrasp_core.pregrasps import SamplingParams
from pregrasp_core.result import read_result, write_result
from pregrasp_core.shape import ShapeParams

POOL_STAGES = STAGES[: STAGES.index("pool") + 1]
"""The stages up to the pool (later stages, e.g. planning, are not run here)."""


def l_shape_cloud(seed: int = 0) -> PointCloud:
    """Points on the surface of an L: a bar on the table and a post on its end (metres)."""
    rng = np.random.default_rng(seed)
    out = []
    for lo, hi, n in (
        ([0.0, -0.03, 0.0], [0.16, 0.03, 0.04], 3000),
        ([0.12, -0.02, 0.04], [0.16, 0.02, 0.15], 2000),
    ):
        lo, hi = np.array(lo), np.array(hi)
        p = lo + rng.uniform(size=(n, 3)) * (hi - lo)
        axis = rng.integers(0, 3, n)
        p[np.arange(n), axis] = np.where(rng.uniform(size=n) < 0.5, lo[axis], hi[axis])
        out.append(p)
    return PointCloud.from_array(np.concatenate(out), source="l_shape")


def _box_surface(extents, n: int, seed: int = 0) -> np.ndarray:
    """``n`` points on the surface of a box of ``extents`` (metres) centred at the origin."""
    rng = np.random.default_rng(seed)
    hi = 0.5 * np.asarray(extents, dtype=float)
    p = (rng.uniform(size=(n, 3)) * 2.0 - 1.0) * hi
    axis = rng.integers(0, 3, n)
    p[np.arange(n), axis] = np.where(rng.uniform(size=n) < 0.5, -hi[axis], hi[axis])
    return p


@pytest.fixture(scope="module")
def hand():
    return load_hand()


@pytest.fixture(scope="module")
def params():
    return PipelineParams(decomposition=DecompositionParams(min_points=300))


@pytest.fixture(scope="module")
def first(hand, params):
    return run_pipeline(l_shape_cloud(), params, hand, until="pool")


def test_all_stages_run_and_are_timed(first):
    assert first.tree is not None and len(first.tree.leaves()) >= 2
    assert len(first.shapes) == len(first.tree.nodes)
    assert first.masks.blocked.shape == (len(first.tree.nodes), 6)
    assert first.masks.support is not None and first.masks.support.height == pytest.approx(0.0)
    assert first.traversal is not None and len(first.pool) > 0
    assert set(first.timings) == set(POOL_STAGES) and all(v >= 0 for v in first.timings.values())
    assert first.reused == ()


def test_unchanged_stages_are_reused(first, hand, params):
    again = run_pipeline(first.cloud, params, hand, previous=first, until="pool")
    assert again.reused == POOL_STAGES
    assert again.tree is first.tree and again.pool is first.pool
    # a new sampling interval re-runs only the pool
    p2 = dataclasses.replace(params, sampling=SamplingParams(interval=0.05))
    r2 = run_pipeline(first.cloud, p2, hand, previous=first, until="pool")
    assert r2.reused == ("decompose", "classify", "facemask")
    assert r2.masks is first.masks and r2.pool is not first.pool
    # a new clearance re-runs the masks and the pool, not the tree or the shapes
    p3 = dataclasses.replace(params, facemask=FaceMaskParams(clearance=0.01))
    r3 = run_pipeline(first.cloud, p3, hand, previous=first, until="pool")
    assert r3.reused == ("decompose", "classify")
    # a new shape threshold: everything from classify on
    p4 = dataclasses.replace(params, shape=ShapeParams(small_size=0.1))
    assert run_pipeline(first.cloud, p4, hand, previous=first, until="pool").reused == (
        "decompose",
        "facemask",
    )
    # another cloud: nothing is reused
    other = l_shape_cloud(seed=1)
    assert run_pipeline(other, params, hand, previous=first, until="pool").reused == ()


def test_until_stops_early_and_rejects_unknown_stages(first, params):
    r = run_pipeline(first.cloud, params, until="decompose")
    assert r.tree is not None and r.shapes is None and r.masks is None and r.pool is None
    assert set(r.timings) == {"decompose"}
    with pytest.raises(ValueError, match="until must be one of"):
        run_pipeline(first.cloud, params, until="everything")


def test_progress_reaches_one(first, hand, params):
    seen: list[float] = []
    run_pipeline(first.cloud, params, hand, previous=first, progress=seen.append, until="pool")
    assert seen == sorted(seen) and seen[-1] == 1.0 and len(seen) == len(POOL_STAGES)


def test_support_off_frees_the_bottom(first, hand, params):
    p = dataclasses.replace(params, facemask=FaceMaskParams(support=False))
    r = run_pipeline(first.cloud, p, hand, previous=first, until="pool")
    assert r.masks.support is None and not r.masks.by_support.any()
    assert first.masks.by_support[0].sum() == 1  # the root's bottom face, with the table


def test_result_document_has_masks_and_pool(first, params, tmp_path):
    doc = result_document(first, params, extra_timings={"load": 0.01})
    assert list(doc["timings"])[0] == "load" and set(POOL_STAGES) <= set(doc["timings"])
    nodes = doc["tree"]["nodes"] if isinstance(doc["tree"], dict) else doc["tree"]
    assert all(np.shape(n["face_mask"]) == (6, 5) for n in nodes)
    assert np.array_equal([n["face_mask"] for n in nodes], first.masks.masks)
    pool = doc["pool"]
    assert pool["count"] == len(first.pool) == len(pool["pregrasps"])
    assert pool["support_plane"]["normal"] == [0.0, 0.0, 1.0]
    assert pool["traversal"]["candidates"] == list(first.traversal.candidates)
    assert {"decomposition", "shape", "facemask", "sampling"} <= set(doc["parameters"])
    assert doc["parameters"]["sampling"]["policy"] == "paper"
    out = write_result(doc, tmp_path / "r.json")
    back = read_result(out)
    assert back["pool"]["pregrasps"][0]["T_world_hand"] == first.pool.T_world_hand[0].tolist()
    assert json.loads(json.dumps(pool_section(first)))["count"] == len(first.pool)


def test_the_default_object_gets_a_pool_identical_for_the_same_seed(hand):
    cloud = load_point_cloud(DEFAULT_OBJECT, n_points=6000, seed=0)
    r = run_pipeline(
        cloud, PipelineParams(decomposition=DecompositionParams(min_points=150)), hand, until="pool"
    )
    assert len(r.pool) > 0
    assert set(np.unique(r.pool.node)) <= set(r.traversal.candidates)
    # every pre-grasp of a real object is collision-free for the hand model's own query (per
    # preshape: the enclosing-surface samples of a type share one, a pinch has its own)
    qs, which = np.unique(r.pool.q, axis=0, return_inverse=True)
    for k, q in enumerate(qs):
        sel = which.ravel() == k
        hits = hand.hands_hit_points(cloud.points, r.pool.T_world_hand[sel], q)
        assert not hits.any()
    # the same file and seed give the same pool, bit for bit
    cloud2 = load_point_cloud(DEFAULT_OBJECT, n_points=6000, seed=0)
    r2 = run_pipeline(
        cloud2,
        PipelineParams(decomposition=DecompositionParams(min_points=150)),
        hand,
        until="pool",
    )
    for name in ("T_world_hand", "q", "node", "face", "subface", "backoff", "grasp_type"):
        assert np.array_equal(getattr(r.pool, name), getattr(r2.pool, name))
    assert r.pool.dropped == r2.pool.dropped


ISSUE_16_RUN = """
import json, sys, time
from pregrasp_core.decomposition import DecompositionParams
from pregrasp_core.errors import PregraspError
from pregrasp_core.io import load_point_cloud
from pregrasp_core.paths import DEFAULT_OBJECT
from pregrasp_core.pipeline import PipelineParams, run_pipeline

cloud = load_point_cloud(DEFAULT_OBJECT)
params = PipelineParams(decomposition=DecompositionParams(1.0, 4, 20))
t0, c0 = time.perf_counter(), time.process_time()
try:
    result = run_pipeline(cloud, params, until="facemask")
    outcome = {"parts": len(result.tree.leaves())}
except PregraspError as exc:
    outcome = {"error": type(exc).__name__, "message": str(exc)}
outcome["seconds"] = time.perf_counter() - t0
outcome["cpu_seconds"] = time.process_time() - c0
# this process's own peak (VmHWM, KiB; ru_maxrss would report the parent's size at fork, which a
# long pytest run makes large: Linux keeps it across exec)
hwm = [ln for ln in open("/proc/self/status") if ln.startswith("VmHWM:")][0]
outcome["max_rss"] = int(hwm.split()[1]) * 1024
print(json.dumps(outcome))
"""


def test_issue_16_settings_end_in_a_clear_error_quickly_and_small():
    """Volume ratio 1.0, min points 4, max depth 20 on the default mug: 2,135 parts, which made
    the face masks ask for 21.6 GB. Now the decomposition stops at WorkLimits.max_parts with a
    message naming the parameters, within 10 s of CPU (about 2.2 s; the wall clock of a shared
    test machine only bounds hangs); the whole process (interpreter, numpy, cloud) peaks far
    below 2 GiB (its resident size bounds what tracemalloc would count: about 140 MiB)."""
    proc = subprocess.run(
        [sys.executable, "-c", ISSUE_16_RUN],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=Path(__file__).resolve().parents[2],
    )
    assert proc.returncode == 0, proc.stderr
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    assert out["error"] == "WorkLimitError"
    assert out["message"].startswith("the decomposition needs more than 256 parts (max_parts)")
    for name in ("volume_ratio 1", "min_points 4", "max_depth 20", "raise max_parts"):
        assert name in out["message"]
    assert out["cpu_seconds"] < 10.0 and out["seconds"] < 60.0
    assert out["max_rss"] < 2**30, f"{out['max_rss'] / 2**20:.0f} MiB"


def test_limits_reach_the_stages(first, hand, params):
    """run_pipeline passes its WorkLimits to the decomposition and the face masks."""
    with pytest.raises(WorkLimitError, match="max_parts"):
        run_pipeline(l_shape_cloud(), params, hand, until="decompose", limits=WorkLimits(1))
    n_nodes = len(first.tree.nodes)
    n_cut = len(first.tree.leaves())
    with pytest.raises(WorkLimitError, match=f"{n_nodes * n_cut:,} pairs"):
        run_pipeline(
            l_shape_cloud(),
            dataclasses.replace(params, facemask=FaceMaskParams(clearance=0.03)),
            hand,
            until="facemask",
            previous=first,
            limits=WorkLimits(max_face_mask_pairs=n_nodes * n_cut - 1),
        )


def test_normals_are_carried_through_a_run_that_stops_at_the_pool(first, hand, params):
    """The viewer's threshold change runs to the pool (new scene), then plans from that result:
    the cloud's normals (a function of the cloud and the normal parameters only) are computed
    once, not again for every re-plan."""
    from pregrasp_core.normals import NormalParams
    from pregrasp_core.pipeline import view_normals

    nrm = view_normals(first.cloud, params.planner.normals)
    planned = dataclasses.replace(first, normals=nrm, timings={**first.timings, "normals": 1.5})
    p2 = dataclasses.replace(params, sampling=SamplingParams(interval=0.05))
    shown = run_pipeline(first.cloud, p2, hand, previous=planned, until="pool")
    assert shown.normals is nrm and shown.timings["normals"] == 1.5
    replanned = run_pipeline(first.cloud, p2, hand, previous=shown, until="grasps")
    assert replanned.normals is nrm and replanned.grasps is not None
    # other normal parameters or another cloud: not carried
    p3 = dataclasses.replace(
        p2, planner=dataclasses.replace(p2.planner, normals=NormalParams(k=12))
    )
    assert run_pipeline(first.cloud, p3, hand, previous=planned, until="pool").normals is None
    other = l_shape_cloud(seed=1)
    assert run_pipeline(other, p2, hand, previous=planned, until="pool").normals is None


def test_normals_beside_the_stages_equal_a_serial_run_and_leave_no_thread(
    hand, params, monkeypatch
):
    """A run up to the planner computes the normals on a thread of their own beside the stages
    up to the pool: the planner gets the bits ``view_normals`` gives alone, and no thread
    outlives the run (the planner forks only from a process running one thread), also when a
    stage or the normals fail."""
    import threading

    from pregrasp_core import pipeline
    from pregrasp_core.pipeline import view_cloud_normals

    cloud = l_shape_cloud()
    before = threading.active_count()
    res = run_pipeline(cloud, params, hand, until="grasps")
    assert threading.active_count() == before
    ref = view_cloud_normals(res.cloud, res.params.planner.normals)
    assert res.normals is not None and res.normals.tobytes() == ref.normals.tobytes()
    # a cloud without normals: the crest-rule points the planner took (docs/design.md)
    assert ref.crest is not None and res.crest is not None
    assert res.crest.tobytes() == ref.crest.tobytes()
    assert res.grasps is not None and len(res.grasps.grasps) == len(res.pool)
    assert list(res.timings) == [*STAGES, "normals", "grasps"] and res.timings["normals"] > 0
    with pytest.raises(WorkLimitError, match="max_parts"):
        run_pipeline(cloud, params, hand, until="grasps", limits=WorkLimits(1))
    assert threading.active_count() == before

    def fails(*args):
        raise RuntimeError("normals failed")

    monkeypatch.setattr(pipeline, "view_cloud_normals", fails)
    with pytest.raises(RuntimeError, match="normals failed"):
        run_pipeline(cloud, params, hand, until="grasps")
    assert threading.active_count() == before


def test_a_document_left_as_built_writes_the_plain_documents_file(hand, params, tmp_path):
    """``pregrasp plan`` writes its document without making the pool and grasps plain first
    (``plain=False``): the same file, byte for byte, and the JSON module reads it back as the
    plain document."""
    from pregrasp_core.result import to_jsonable

    res = run_pipeline(l_shape_cloud(), params, hand, until="grasps")
    plain = result_document(res)
    raw = result_document(res, plain=False)
    assert to_jsonable(raw) == plain
    a = write_result(plain, tmp_path / "plain.json").read_bytes()
    b = write_result(raw, tmp_path / "raw.json").read_bytes()
    assert a == b and json.loads(b) == plain


@pytest.mark.parametrize(("scale", "hinted"), [(1.0 / 0.0254, True), (1.0, False)])
def test_an_object_no_part_of_which_fits_the_hand_says_why(hand, scale, hinted, caplog):
    """The L shape in inches (4 to 6 units a side, which the millimetre rule leaves as metres):
    no candidate, and a warning naming the part whose grip of the grasp type its shape gives it
    is the narrowest (the widths the hand must span, by the box sides of docs/pregrasps.md)
    against what the hand opens for it, with the hint that the file may not be in metres; the L
    in metres gets pre-grasps and no such warning."""
    import logging

    cloud = l_shape_cloud()
    cloud = PointCloud.from_array(cloud.points * scale, source="l_inches.ply")
    with caplog.at_level(logging.WARNING, logger="pregrasp_core.pipeline"):
        res = run_pipeline(cloud, None, hand, until="pool")
    said = [r.getMessage() for r in caplog.records if "fits the hand" in r.getMessage()]
    if not hinted:
        assert said == [] and len(res.pool) > 0
        return
    assert len(res.pool) == 0 and res.traversal.candidates == ()
    side = {"cylindrical": 1, "spherical": 0, "three_finger_tip": 2, "two_finger_tip": 0}

    def grip(n, t):
        k = side[t]
        return float(n.box.extents[k]) / float(hand.aperture(t)), float(n.box.extents[k]), t, n.id

    own = min(grip(n, res.shapes[n.id].grasp_type) for n in res.tree.nodes)
    assert min(grip(n, t) for n in res.tree.nodes for t in side)[0] > 3.0  # (1.57 m sides)
    _, width, gt, i = own
    assert len(said) == 1 and said[0].startswith("l_inches.ply: no part of the object fits")
    assert f"the narrowest is part {i}, {gt} across {width:.3g} m" in said[0]
    assert f"the hand opens {float(hand.aperture(gt)):.3g} m for it" in said[0]
    assert "0.0254 for inches" in said[0]


def test_the_no_fit_sentence_names_a_grasp_type_that_would_fit(hand):
    """A 20 x 15 x 2 cm slab whose parts are all given the spherical type (its longest side,
    20 cm, is more than the hand opens): the sentence names the spherical grip that does not
    fit, and that a three-finger tip grip across the 2 cm thickness would; no hint at units."""
    import dataclasses

    from pregrasp_core.pregrasps.traversal import no_fit_hint

    cloud = PointCloud.from_array(_box_surface((0.20, 0.15, 0.02), 4000), source="slab.ply")
    res = run_pipeline(cloud, None, hand, until="facemask")
    shapes = [dataclasses.replace(s, grasp_type="spherical") for s in res.shapes]
    text = no_fit_hint(res.tree, shapes, hand)
    assert "spherical across 0.2 m" in text
    assert "a three_finger_tip grip of part" in text and "would fit" in text
    assert "--scale" not in text


@pytest.mark.parametrize("name", ["mug_handle", "bottle"])
def test_a_y_up_copy_planned_with_up_y_is_the_z_up_plan_turned(hand, tmp_path, name):
    """A rigid motion of the input: the demo mesh turned so that it stands along +y (as glTF
    files and Blender's or ShapeNet's OBJ files do) and planned with ``up`` = +y gives the
    z-up plan turned by the same motion: the same parts, pool, kept grasps and best epsilon,
    the best hand pose turned. Planned as z-up (lying on its side) it is another object."""
    import trimesh

    from pregrasp_core.paths import OBJECTS_DIR

    turn = trimesh.transformations.rotation_matrix(-np.pi / 2, [1.0, 0.0, 0.0])  # +z -> +y
    mesh = trimesh.load(OBJECTS_DIR / f"{name}.obj", force="mesh")
    mesh.apply_transform(turn)
    mesh.export(tmp_path / f"{name}_y.obj")
    z_up = load_point_cloud(OBJECTS_DIR / f"{name}.obj", n_points=8000)
    y_up = load_point_cloud(tmp_path / f"{name}_y.obj", n_points=8000)
    np.testing.assert_allclose(y_up.points, z_up.points @ turn[:3, :3].T, atol=1e-15)
    p = PipelineParams()
    py = dataclasses.replace(p, facemask=FaceMaskParams(up=(0.0, 1.0, 0.0)))
    a = run_pipeline(z_up, p, hand, until="grasps")
    b = run_pipeline(y_up, py, hand, until="grasps")
    assert b.masks is not None and np.allclose(b.masks.support.normal, [0.0, 1.0, 0.0])
    assert len(b.tree.leaves()) == len(a.tree.leaves()) and len(b.pool) == len(a.pool)
    assert a.grasps is not None and b.grasps is not None
    assert len(b.grasps.ranking) == len(a.grasps.ranking) > 0
    ga, gb = a.grasps.grasps[a.grasps.best], b.grasps.grasps[b.grasps.best]
    assert gb.epsilon == pytest.approx(ga.epsilon, rel=1e-6)
    np.testing.assert_allclose(gb.T_world_hand, turn @ ga.T_world_hand, atol=1e-9)
    side = run_pipeline(y_up, p, hand, until="pool")  # the same file with the default +z
    assert len(side.pool) != len(a.pool)
