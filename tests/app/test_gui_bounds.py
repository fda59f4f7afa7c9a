"""The viewer never shows a bounded score (issue 15, docs/quality.md) as if it were exact: the
grasp chooser's label prints ``eps <= x`` for an upper bound, the exact value otherwise."""

from __future__ import annotations

import dataclasses

import numpy as np

from app.gui import grasp_label
from pregrasp_core.planner import Grasp


def _grasp(eps: float, exact: bool) -> Grasp:
    g = Grasp(0, "spherical", np.eye(4), 0.0, "object", np.zeros(7), (), (), eps, 1e-3, 0, None)
    return dataclasses.replace(
        g, epsilon_exact=exact, volume_exact=exact, quality_bound="" if exact else "half cones"
    )


def test_grasp_label_marks_an_upper_bound():
    assert grasp_label(0, _grasp(0.1234, True)) == "#1 spherical eps 0.123"
    assert grasp_label(24, _grasp(0.1234, False)) == "#25 spherical eps <= 0.123"
    assert grasp_label(3, _grasp(0.0, True)).endswith("eps 0.000 NOT force closure")
