"""The MVBB's speed devices change no result: per-axis active sets are exact, the quick settings
of the decomposition still give valid tight boxes.

References: the same pattern search with every point active (no active sets), the default
settings, and the boxes' own containment and tightness.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pregrasp_core import mvbb
from pregrasp_core.decomposition import QUICK_MVBB
from pregrasp_core.io import load_point_cloud
from pregrasp_core.mvbb import MvbbParams, minimum_volume_box
from pregrasp_core.paths import OBJECTS_DIR
from pregrasp_core.tolerances import BOX_CONTAINS_TOL

OBJECTS = ["mug", "box_cereal", "toy_teddy", "tool_frypan"]


@pytest.fixture(scope="module")
def clouds() -> dict[str, np.ndarray]:
    return {
        name: load_point_cloud(OBJECTS_DIR / f"{name}.obj", n_points=3000, seed=0).points
        for name in OBJECTS
    }


def _starts(n: int, seed: int) -> np.ndarray:
    """n rotations (n, 3, 3) from seeded random unit quaternions."""
    q = np.random.default_rng(seed).normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = q.T
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        axis=1,
    )


@pytest.mark.parametrize("name", OBJECTS)
def test_active_sets_are_exact(clouds, name):
    """The pattern search on per-axis active sets takes the same path as on all points."""
    pts = clouds[name]
    Q = np.ascontiguousarray((pts - pts.mean(axis=0)).T)
    starts = _starts(4, seed=len(name))
    p = MvbbParams()
    everything = MvbbParams(active_reach=1e9)  # the active sets are the whole cloud
    levels = mvbb._n_levels(p)
    fast = mvbb._pattern_search(starts, Q, p, 0, levels)
    slow = mvbb._pattern_search(starts, Q, everything, 0, levels)
    np.testing.assert_allclose(fast, slow, atol=1e-9)
    np.testing.assert_allclose(mvbb._volumes(fast, Q), mvbb._volumes(slow, Q), rtol=1e-12)
    # and the search did move: every start ends at least as small, most strictly smaller
    v0, v1 = mvbb._volumes(starts, Q), mvbb._volumes(fast, Q)
    assert np.all(v1 <= v0) and np.sum(v1 < 0.99 * v0) >= 3


@pytest.mark.parametrize("name", OBJECTS)
def test_quick_and_snapless_settings_give_valid_tight_boxes(clouds, name):
    pts = clouds[name]
    full = minimum_volume_box(pts).volume
    for params in (QUICK_MVBB, MvbbParams(snap_max=0), MvbbParams(max_rounds=0)):
        box = minimum_volume_box(pts, params)
        assert np.all(box.contains(pts, BOX_CONTAINS_TOL))
        p_box = box.to_box(pts)
        np.testing.assert_allclose(p_box.max(axis=0), box.half_extents, atol=1e-9)
        np.testing.assert_allclose(p_box.min(axis=0), -box.half_extents, atol=1e-9)
        assert box.volume <= full * 1.02


def test_snap_makes_a_face_flush_optimum_exact():
    """A tilted cuboid's optimum is face flush: with the snap the extents are exact to round-off;
    without it the box is never smaller."""
    rng = np.random.default_rng(4)
    ext = np.array([0.3, 0.2, 0.1])
    corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])
    local = np.vstack([corners * ext / 2, rng.uniform(-ext / 2, ext / 2, size=(1500, 3))])
    R = Rotation.from_euler("zx", [math.radians(23.0), 0.4]).as_matrix()
    pts = local @ R.T
    snapped = minimum_volume_box(pts)
    np.testing.assert_allclose(snapped.extents, ext, rtol=1e-9)
    plain = minimum_volume_box(pts, MvbbParams(snap_max=0))
    assert plain.volume >= snapped.volume * (1.0 - 1e-12)


def test_input_is_never_modified():
    """A column-major (N, 3) array (the transpose of a (3, N) array) is not shifted in place."""
    rng = np.random.default_rng(6)
    cols = np.ascontiguousarray(rng.normal(size=(3, 500)) * [[0.3], [0.2], [0.1]] + 1.0)
    pts = cols.T  # (500, 3), Fortran order: pts.T is contiguous
    before = pts.copy()
    first = minimum_volume_box(pts)
    np.testing.assert_array_equal(pts, before)
    second = minimum_volume_box(pts)
    np.testing.assert_array_equal(second.extents, first.extents)
