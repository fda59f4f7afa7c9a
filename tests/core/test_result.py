"""The pregrasp/1 result document: fields, JSON round trip, options, atomic writing."""

from __future__ import annotations

import dataclasses
import enum
import json
import math
from pathlib import Path

import numpy as np
import pytest

from pregrasp_core.decomposition import DecompositionParams, decompose
from pregrasp_core.errors import InputError
from pregrasp_core.io import PointCloud
from pregrasp_core.result import (
    CORE_SECTIONS,
    SCHEMA,
    dumps_result,
    read_result,
    result_document,
    to_jsonable,
    write_result,
)
from pregrasp_core.shape import GraspType, ShapeClass, ShapeParams, classify_tree

NODE_KEYS = {
    "id",
    "parent",
    "children",
    "depth",
    "split_order",
    "n_points",
    "center",
    "rotation",
    "extents",
    "volume",
    "eigenvalues",
    "shape_class",
    "grasp_type",
    "face_mask",
}


@pytest.fixture(scope="module")
def parts():
    rng = np.random.default_rng(0)
    bar = rng.uniform([0, 0, 0], [0.2, 0.03, 0.03], (1500, 3))
    block = rng.uniform([0, 0.04, 0], [0.05, 0.09, 0.05], (800, 3))
    cloud = PointCloud.from_array(np.vstack([bar, block]), source="two_parts")
    dp, sp = DecompositionParams(min_points=200), ShapeParams()
    tree = decompose(cloud.points, dp)
    shapes = classify_tree(tree, cloud.points, sp)
    return cloud, dp, sp, tree, shapes


def _doc(parts, **kw):
    cloud, dp, sp, tree, shapes = parts
    timings = {"load": 0.01, "decompose": 0.02, "classify": 0.001}
    return result_document(cloud, {"decomposition": dp, "shape": sp}, timings, tree, shapes, **kw)


def test_fields_and_values(parts):
    cloud, dp, sp, tree, shapes = parts
    assert tree.n_splits == 1  # the fixture really has two parts
    doc = _doc(parts, seed=3)
    assert doc["schema"] == SCHEMA == "pregrasp/1"
    assert set(CORE_SECTIONS) <= set(doc)
    assert doc["input"]["source"] == "two_parts"
    assert doc["input"]["n_points"] == cloud.n_points == 2300
    assert doc["input"]["seed"] == 3 and doc["input"]["format"] == "array"
    assert doc["parameters"] == {
        "decomposition": {"volume_ratio": 0.9, "min_points": 200, "max_depth": 8},
        "shape": {"max_ratio_1d": 0.55, "max_ratio_2d": 0.45, "small_size": 0.05},
    }
    assert doc["timings"] == {"load": 0.01, "decompose": 0.02, "classify": 0.001}
    t = doc["tree"]
    assert (t["n_points"], t["n_nodes"], t["n_splits"]) == (2300, 3, 1)
    assert t["leaves"] == [1, 2] and t["includes_indices"] is False
    for nd, entry, sh in zip(tree.nodes, t["nodes"], shapes, strict=True):
        assert set(entry) == NODE_KEYS
        assert entry["id"] == nd.id and entry["parent"] == nd.parent
        assert entry["children"] == list(nd.children)
        assert entry["n_points"] == nd.n_points and entry["face_mask"] is None
        assert ShapeClass(entry["shape_class"]) is sh.shape_class
        assert GraspType(entry["grasp_type"]) is sh.grasp_type
        # a consumer rebuilding the box from the JSON finds the node's points inside it
        R, c, e = (np.array(entry[k]) for k in ("rotation", "center", "extents"))
        assert np.allclose(R.T @ R, np.eye(3)) and np.linalg.det(R) == pytest.approx(1.0)
        p_box = (cloud.points[nd.indices] - c) @ R
        assert np.all(np.abs(p_box) <= e / 2 + 1e-9)
        assert entry["volume"] == pytest.approx(float(np.prod(e)))
        assert np.allclose(entry["eigenvalues"], sh.eigenvalues)
    assert t["nodes"][1]["shape_class"] == "1D"  # the bar


def test_json_round_trip(parts, tmp_path):
    doc = _doc(parts, include_indices=True)
    out = write_result(doc, tmp_path / "r.json")
    assert out == tmp_path / "r.json"
    assert [p.name for p in tmp_path.iterdir()] == ["r.json"]  # no temporary file left
    back = read_result(out)
    assert back == json.loads(json.dumps(doc))
    assert back == doc  # the document was JSON-ready already


def test_indices_only_on_request(parts):
    _, _, _, tree, _ = parts
    doc = _doc(parts)
    assert all("indices" not in n for n in doc["tree"]["nodes"])
    doc = _doc(parts, include_indices=True)
    assert doc["tree"]["includes_indices"] is True
    leaves = [doc["tree"]["nodes"][i]["indices"] for i in doc["tree"]["leaves"]]
    assert sorted(np.concatenate(leaves).tolist()) == list(range(tree.n_points))


def test_face_masks(parts):
    _, _, _, tree, _ = parts
    masks = np.zeros((3, 6, 5), dtype=int)
    masks[1, 2, :] = 1
    doc = _doc(parts, face_masks=masks)
    assert doc["tree"]["nodes"][1]["face_mask"][2] == [1, 1, 1, 1, 1]
    assert doc["tree"]["nodes"][0]["face_mask"] == [[0] * 5] * 6
    doc = _doc(parts, face_masks=[None, masks[1], None])
    assert doc["tree"]["nodes"][0]["face_mask"] is None
    assert doc["tree"]["nodes"][1]["face_mask"] == masks[1].tolist()
    with pytest.raises(ValueError, match=r"\(3, 6, 5\)"):
        _doc(parts, face_masks=np.zeros((3, 5, 6)))
    with pytest.raises(ValueError, match="3 entries"):
        _doc(parts, face_masks=[None, None])
    with pytest.raises(ValueError, match="only 0 .free. and 1"):
        _doc(parts, face_masks=masks * 2)


def test_extra_sections(parts):
    pool = {"n": 2, "poses": np.eye(4)[None].repeat(2, 0), "type": GraspType.SPHERICAL}
    doc = _doc(parts, extra_sections={"pool": pool, "best": None})
    assert doc["pool"] == {"n": 2, "poses": [np.eye(4).tolist()] * 2, "type": "spherical"}
    assert doc["best"] is None
    assert list(doc)[-2:] == ["pool", "best"]
    with pytest.raises(ValueError, match="core section"):
        _doc(parts, extra_sections={"tree": {}})


def test_bad_arguments(parts):
    cloud, dp, sp, tree, shapes = parts
    with pytest.raises(ValueError, match="timing 'load'"):
        result_document(cloud, {}, {"load": -1.0}, tree, shapes)
    with pytest.raises(ValueError, match="timing 'load'"):
        result_document(cloud, {}, {"load": "fast"}, tree, shapes)
    with pytest.raises(ValueError, match="3 entries"):
        result_document(cloud, {}, {}, tree, shapes[:2])
    small = PointCloud.from_array(cloud.points[:100])
    with pytest.raises(ValueError, match="2300 points"):
        result_document(small, {}, {}, tree, shapes)
    doc = result_document(cloud, {}, {}, tree, None)
    assert doc["tree"]["nodes"][0]["shape_class"] is None


def test_to_jsonable():
    assert to_jsonable(np.float32(1.5)) == 1.5 and to_jsonable(np.int64(3)) == 3
    assert to_jsonable(np.array([1.0, np.nan, np.inf])) == [1.0, None, None]
    assert to_jsonable(math.nan) is None and to_jsonable(np.bool_(True)) is True
    assert to_jsonable(Path("a/b.json")) == "a/b.json"
    assert to_jsonable((ShapeClass.TWO_D, {"k": (1, 2)})) == ["2D", {"k": [1, 2]}]
    assert to_jsonable(np.arange(6).reshape(2, 3)) == [[0, 1, 2], [3, 4, 5]]
    with pytest.raises(TypeError, match="cannot write a object"):
        to_jsonable(object())


def _random_plain(rng: np.random.Generator, depth: int = 0) -> object:
    """A random nested value of plain JSON types with floats of every kind (inf, nan, -0.0,
    subnormal, huge), as the result sections hold them."""
    special = [math.inf, -math.inf, math.nan, -0.0, 5e-324, 1e308, 0.1]
    kind = rng.integers(0, 7 if depth < 4 else 4)
    if kind == 0:
        return float(special[rng.integers(len(special))]) if rng.random() < 0.3 else rng.normal()
    if kind == 1:
        return int(rng.integers(-5, 5))
    if kind == 2:
        return [None, True, False, "t\u00e9xt"][rng.integers(4)]
    if kind == 3:
        return [rng.normal() if rng.random() < 0.8 else math.inf for _ in range(rng.integers(5))]
    if kind == 4:
        return [_random_plain(rng, depth + 1) for _ in range(rng.integers(4))]
    if kind == 5:
        return tuple(_random_plain(rng, depth + 1) for _ in range(rng.integers(3)))
    return {f"k{i}": _random_plain(rng, depth + 1) for i in range(rng.integers(4))}


def test_to_jsonable_of_plain_values_is_the_json_modules_reading():
    """Plain values (the fast paths by exact type): the same as what the json module reads
    back from its own text with every NaN and infinity as null, to the float's sign and bits;
    tuples become lists, and str subclasses, numpy floats and non-str keys take the general
    path."""
    rng = np.random.default_rng(7)
    for _ in range(300):
        value = _random_plain(rng)
        text = json.dumps(value, allow_nan=True)
        for token in ("-Infinity", "Infinity", "NaN"):
            text = text.replace(token, "null")
        expected = json.loads(text)
        got = to_jsonable(value)
        assert json.dumps(got, allow_nan=False) == json.dumps(expected, allow_nan=False)
        assert dumps_result(value) == json.dumps(expected, indent=1, allow_nan=False)
    got = to_jsonable({1: (np.float64(np.inf), np.float32(0.5), -0.0, _Word.A), "x": [_Count.B]})
    assert got == {"1": [None, 0.5, -0.0, "a"], "x": [3]}
    assert math.copysign(1.0, got["1"][2]) == -1.0  # type: ignore[index]
    assert type(got["x"][0]) is int  # type: ignore[index]


class _Word(str, enum.Enum):
    A = "a"


class _Count(enum.IntEnum):
    B = 3


@dataclasses.dataclass
class _Pair:
    x: float
    y: np.ndarray


def test_dumps_result_is_the_standard_encoders_text(parts):
    """The one-pass writer gives the text of ``json.dumps(to_jsonable(...), indent=1)`` (the
    standard library's encoder is the reference), for a real document and every value kind."""
    mixed = {
        "floats": [1.0, math.nan, 2.5e-17, -0.0, 1e300],
        "empty": np.zeros((2, 0)),
        "ints": np.array([[1, 2], [3, 4]], dtype=np.int32),
        "bools": np.array([True, False]),
        "str_enum": _Word.A,
        "int_enum": _Count.B,
        7: [(), {}, [], None, True, np.float32(0.1), np.int64(4), np.bool_(False)],
        "dataclass": _Pair(math.inf, np.arange(3.0)),
        "path": Path("a/b.json"),
        "nan_matrix": np.array([[np.nan, 1.0], [2.0, -np.inf]]),
        "list": [1, 2.0, "x", [1.5, [2.5]], ShapeClass.TWO_D],
        "tuple": (1.5, 2.5),
        "text": 'caf\u00e9 \u2028 "q" \\ \n',
        "nested": {"a": {"b": {}}, "c": [[[]]]},
    }
    for doc in (_doc(parts, include_indices=True), mixed, [], {}, 1.0, "x", None):
        assert dumps_result(doc) == json.dumps(to_jsonable(doc), indent=1, allow_nan=False)
    with pytest.raises(TypeError, match="cannot write a object"):
        dumps_result({"k": [object()]})


def test_write_and_read_errors(tmp_path):
    with pytest.raises(InputError, match="does not exist"):
        write_result({"schema": SCHEMA}, tmp_path / "missing" / "r.json")
    with pytest.raises(InputError, match="file not found"):
        read_result(tmp_path / "nope.json")
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    with pytest.raises(InputError, match="bad.json: not a readable JSON"):
        read_result(bad)
    other = tmp_path / "other.json"
    other.write_text('{"schema": "something/2"}')
    with pytest.raises(InputError, match="not a pregrasp/1 result"):
        read_result(other)
    # overwrite is atomic: the old content is replaced entirely
    p = write_result({"schema": SCHEMA, "x": list(range(100))}, tmp_path / "r.json")
    write_result({"schema": SCHEMA, "x": 1}, p)
    assert read_result(p) == {"schema": SCHEMA, "x": 1}
