"""Parameter bounds: whatever value a field gets (from a file, a flag, a widget or the viewer's
protocol), the parameter dataclass either accepts it or raises a ValueError that starts with
the field's name; never another exception, never a value outside the documented bounds."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pregrasp_core.decomposition import DecompositionParams
from pregrasp_core.facemask import FaceMaskParams
from pregrasp_core.limits import WorkLimits, check_int, check_real
from pregrasp_core.mvbb import MvbbParams
from pregrasp_core.normals import NormalParams
from pregrasp_core.planner import PlannerParams
from pregrasp_core.pregrasps import SamplingParams
from pregrasp_core.quality import QualityParams
from pregrasp_core.sensor.completion import CompletionParams
from pregrasp_core.sensor.occluded import OccludedParams
from pregrasp_core.sensor.table import SegmentParams
from pregrasp_core.shape import ShapeParams
from pregrasp_core.simulate.object_model import ObjectModelParams
from pregrasp_core.simulate.params import SimulationParams

ANY_VALUE = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(min_value=-(10**400), max_value=10**400),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=5),
    st.lists(st.floats(allow_nan=True), max_size=4),
    st.tuples(st.integers(-(10**30), 10**30), st.integers(-3, 3), st.integers(-3, 3)),
    st.integers(-100, 100).map(np.int64),
    st.floats(-1e3, 1e3).map(np.float32),
    st.just(np.bool_(True)),
    st.just(1 + 2j),
)

CLASSES = (
    DecompositionParams,
    ShapeParams,
    FaceMaskParams,
    MvbbParams,
    WorkLimits,
    SamplingParams,
    PlannerParams,
    QualityParams,
    NormalParams,
    OccludedParams,
    SegmentParams,
    CompletionParams,
    SimulationParams,
    ObjectModelParams,
)
PREFIXED = (SimulationParams, ObjectModelParams)
"""The simulator's parameters name the field with its class: ``SimulationParams.timestep``."""


@pytest.mark.parametrize("cls", CLASSES, ids=lambda c: c.__name__)
@settings(max_examples=300, deadline=None)
@given(data=st.data())
def test_any_value_is_accepted_or_names_the_field(cls, data):
    field = data.draw(st.sampled_from([f.name for f in dataclasses.fields(cls)]))
    value = data.draw(ANY_VALUE)
    try:
        made = cls(**{field: value})
    except ValueError as exc:
        prefix = f"{cls.__name__}.{field}" if cls in PREFIXED else field
        assert str(exc).startswith((f"{prefix} must be ", f"{prefix} (")), str(exc)
        return
    got = getattr(made, field)
    # what was accepted is plain, finite and unchanged in value
    if isinstance(got, float):
        assert math.isfinite(got) and got == float(value)
    elif isinstance(got, bool):
        assert got == bool(value)
    elif isinstance(got, int):
        assert got == value
    elif isinstance(got, tuple):
        assert all(isinstance(x, float) and math.isfinite(x) for x in got)
    elif isinstance(got, str):  # a mode, a rule or a policy named by its value
        assert got == value
    else:
        assert got is None and value is None


@pytest.mark.parametrize("cls", CLASSES, ids=lambda c: c.__name__)
def test_defaults_are_inside_the_bounds_and_unchanged(cls):
    default = cls()
    again = cls(**{f.name: getattr(default, f.name) for f in dataclasses.fields(cls)})
    assert again == default


def test_checks_name_the_bounds():
    assert check_int("n", np.int32(5), 1, 10) == 5
    with pytest.raises(ValueError, match=r"^n must be an integer in \[1, 10\], got 11$"):
        check_int("n", 11, 1, 10)
    with pytest.raises(ValueError, match=r"^n must be an integer in \[1, 10\], got 2.0$"):
        check_int("n", 2.0, 1, 10)
    assert check_real("x", 1, 0.0, 1.0, lo_open=True) == 1.0
    with pytest.raises(ValueError, match=r"^x must be a length in \(0, 1\] m, got 0$"):
        check_real("x", 0, 0.0, 1.0, lo_open=True, what="a length", unit=" m")
    with pytest.raises(ValueError, match=r"^x must be a number in \[0, 1\], got 10{400}$"):
        check_real("x", 10**400, 0.0, 1.0)
