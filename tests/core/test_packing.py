"""Grasps packed for the planner's pipes (``planner/packing.py``): what comes out equals what
went in, field by field, with every value's type and every float's bits, through pickle; the
planner's own grasps, odd values (NumPy scalars, NaN, None, assumed contacts, rejections) and
layouts the packing does not stack (other shapes, dtypes, array subclasses)."""

from __future__ import annotations

import dataclasses
import math
import pickle

import numpy as np
import pytest

from pregrasp_core.planner.packing import (
    pack_grasp_set,
    pack_grasps,
    unpack_grasp_set,
    unpack_grasps,
)
from pregrasp_core.planner.types import Contact, FingerTrace, Grasp, GraspSet


def _same(a, b, where="") -> None:
    """``a`` and ``b`` equal with the same types, arrays by dtype, shape and bytes, floats by
    their bits (NaN included), dataclasses field by field."""
    assert type(a) is type(b), f"{where}: {type(a).__name__} != {type(b).__name__}"
    if dataclasses.is_dataclass(a):
        for f in dataclasses.fields(a):
            _same(getattr(a, f.name), getattr(b, f.name), f"{where}.{f.name}")
    elif isinstance(a, np.ndarray):
        assert a.dtype == b.dtype and a.shape == b.shape, where
        assert a.tobytes() == b.tobytes(), where
    elif isinstance(a, (tuple, list)):
        assert len(a) == len(b), where
        for k, (x, y) in enumerate(zip(a, b, strict=True)):
            _same(x, y, f"{where}[{k}]")
    elif isinstance(a, dict):
        assert list(a) == list(b), where
        for k in a:
            _same(a[k], b[k], f"{where}[{k!r}]")
    elif isinstance(a, float):  # np.float64 too (a float subclass)
        assert np.float64(a).tobytes() == np.float64(b).tobytes(), f"{where}: {a!r} != {b!r}"
    else:
        assert a == b, f"{where}: {a!r} != {b!r}"


def _through_pipe(gs):
    return unpack_grasps(pickle.loads(pickle.dumps(pack_grasps(gs), pickle.HIGHEST_PROTOCOL)))


def test_the_packing_knows_every_field_of_the_grasp_types():
    """A field added to ``Grasp``, ``FingerTrace`` or ``Contact`` must be added to the packing
    (it would come back as its default otherwise): the fields it packs are these, in order."""
    names = {t: tuple(f.name for f in dataclasses.fields(t)) for t in (Grasp, FingerTrace, Contact)}
    assert names[Grasp] == (
        "pregrasp", "grasp_type", "T_world_hand", "approach_distance", "approach_stop", "q",
        "fingers", "contacts", "epsilon", "volume", "rank", "rejection", "detail",
        "epsilon_exact", "volume_exact", "quality_bound",
    )  # fmt: skip
    assert names[FingerTrace] == (
        "finger", "n_slice", "q", "links_touched", "palm_stop", "support_stop", "at_limits",
        "corrected",
    )  # fmt: skip
    assert names[Contact] == (
        "point", "normal", "link", "point_index", "distance", "tangent", "assumed", "crest",
    )  # fmt: skip


@pytest.fixture(scope="module")
def planned():
    """The planner's grasps of the default object at 5,000 points (kept, bounded, exact and
    rejected ones)."""
    from pregrasp_core.hand import load_hand
    from pregrasp_core.io import load_point_cloud
    from pregrasp_core.paths import DEFAULT_OBJECT
    from pregrasp_core.pipeline import run_pipeline

    cloud = load_point_cloud(DEFAULT_OBJECT, n_points=5000, seed=0)
    res = run_pipeline(cloud, hand=load_hand(), until="grasps")
    assert res.grasps is not None
    return res.grasps


def test_crest_contacts_come_back_flagged():
    """A cloud without normals has contacts on crest points (their normal the mean of the
    cloud's and the link's, flagged ``Contact.crest``): they come back bit for bit and still
    flagged."""
    import dataclasses as dc

    from pregrasp_core.hand import load_hand
    from pregrasp_core.io import load_point_cloud
    from pregrasp_core.paths import DEFAULT_OBJECT
    from pregrasp_core.pipeline import run_pipeline

    cloud = dc.replace(load_point_cloud(DEFAULT_OBJECT, n_points=5000, seed=0), normals=None)
    res = run_pipeline(cloud, hand=load_hand(), until="grasps")
    assert res.grasps is not None and res.crest is not None
    gs = list(res.grasps.grasps)
    flags = [c.crest for g in gs for c in g.contacts]
    assert any(flags) and not all(flags)
    assert flags == [bool(res.crest[c.point_index]) for g in gs for c in g.contacts]
    back = _through_pipe(gs)
    _same(gs, back, "grasps")
    assert [c.crest for g in back for c in g.contacts] == flags
    # the result file keeps them (``crest`` only where true) and the viewer reads them back
    import json

    from app.result_file import read_result_file
    from pregrasp_core.pipeline import result_document
    from pregrasp_core.result import to_jsonable

    doc = to_jsonable(result_document(res))
    written = [c for g in doc["grasps"]["items"] for c in g.get("contacts", [])]
    assert any("crest" in c for c in written) and not all("crest" in c for c in written)
    assert all(c["crest"] is True for c in written if "crest" in c)
    read = read_result_file(json.dumps(doc).encode(), "bare.json", res.hand).result
    assert read.grasps is not None
    assert [c.crest for g in read.grasps.grasps for c in g.contacts] == [
        c.crest for g in res.grasps.grasps for c in g.contacts
    ]


def test_the_planners_grasps_come_back_bit_for_bit(planned):
    gs = list(planned.grasps)
    assert any(g.kept for g in gs) and any(not g.kept for g in gs)
    assert sum(len(g.contacts) for g in gs) > 50
    back = _through_pipe(gs)
    _same(gs, back, "grasps")
    # and a whole GraspSet (the viewer's planner process sends one)
    same_set = unpack_grasp_set(pickle.loads(pickle.dumps(pack_grasp_set(planned))))
    _same(planned, same_set, "set")
    # the arrays are C-ordered and writeable, as pickle's copies are, and not shared
    g = back[0]
    assert g.T_world_hand.flags.c_contiguous and g.q.flags.writeable
    g.q[0] += 1.0
    assert back[1].q[0] == gs[1].q[0]


def test_odd_values_keep_their_types_and_bits(planned):
    """NumPy scalars where floats are expected, NaN, negative zero, None, assumed contacts, a
    grasp with no finger or contact, an empty list."""
    kept = next(g for g in planned.grasps if g.kept and g.contacts)
    c0 = kept.contacts[0]
    odd_contacts = (
        dataclasses.replace(c0, distance=np.float64(-0.0), assumed=True),
        dataclasses.replace(c0, point_index=np.int64(7), distance=float("nan")),
    )
    gs = [
        dataclasses.replace(kept, contacts=odd_contacts, epsilon=np.float64(0.25), rank=None),
        dataclasses.replace(kept, fingers=(), contacts=(), rejection="approach", detail="x"),
        kept,
    ]
    back = _through_pipe(gs)
    _same(gs, back, "odd")
    assert type(back[0].contacts[0].distance) is np.float64
    assert math.copysign(1.0, back[0].contacts[0].distance) == -1.0
    assert math.isnan(back[0].contacts[1].distance)
    assert _through_pipe([]) == []


def test_rows_that_cannot_be_stacked_are_passed_on_as_they_are(planned):
    """Other shapes, dtypes or an ndarray subclass in any array field: the grasps go through
    unpacked (plain pickle) and still come back equal."""
    kept = [g for g in planned.grasps if g.kept and g.contacts][:3]
    c = kept[0].contacts[0]
    f = kept[0].fingers[0]
    variants = [
        dataclasses.replace(kept[0], q=kept[0].q[:-1]),  # a shorter joint vector
        dataclasses.replace(kept[0], T_world_hand=kept[0].T_world_hand.astype(np.float32)),
        dataclasses.replace(
            kept[0], contacts=(dataclasses.replace(c, normal=c.normal.view(np.matrix)),)
        ),
        dataclasses.replace(kept[0], fingers=(dataclasses.replace(f, q=f.q.tolist()),)),
    ]
    for v in variants:  # loop over the 4 layouts
        gs = [kept[1], v, kept[2]]
        packed = pack_grasps(gs)
        assert packed[0] == "pregrasp-grasps-plain"
        _same(gs, _through_pipe(gs), "variant")
    with pytest.raises(ValueError, match="not a packed list"):
        unpack_grasps(("something else",))


def test_a_grasp_set_without_grasps():
    empty = GraspSet((), np.zeros(0, dtype=np.int64), ("j",), {"approach": 0}, {})
    _same(empty, unpack_grasp_set(pickle.loads(pickle.dumps(pack_grasp_set(empty)))), "empty")
