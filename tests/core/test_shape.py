"""PCA shape classes and grasp types.

References: the analytic covariance of a regular grid filling a box (per axis, m points evenly
spaced over a side a have variance a^2 (m + 1) / (12 (m - 1))), numpy's own ``np.cov``, and
invariance under seeded random rigid motions.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from pregrasp_core.box import OrientedBox
from pregrasp_core.decomposition import DecompositionParams, decompose
from pregrasp_core.errors import DegenerateGeometryError
from pregrasp_core.shape import (
    GRASP_TYPE_OF_CLASS,
    GraspType,
    NodeShape,
    ShapeClass,
    ShapeParams,
    classify_eigenvalues,
    classify_points,
    classify_tree,
    is_small,
    pca_eigenvalues,
)


def _grid_box(extents, m=(12, 10, 8)) -> np.ndarray:
    """Regular grid of m[0] x m[1] x m[2] points filling a box of the given side lengths."""
    axes = [np.linspace(-e / 2, e / 2, k) for e, k in zip(extents, m, strict=True)]
    g = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    return g


def _grid_variance(extents, m=(12, 10, 8)) -> np.ndarray:
    """Analytic per-axis variances of ``_grid_box``, sorted descending (= the eigenvalues)."""
    e, k = np.asarray(extents, float), np.asarray(m, float)
    return np.sort(e**2 * (k + 1) / (12 * (k - 1)))[::-1]


def _rigid(seed):
    rng = np.random.default_rng(seed)
    R = Rotation.random(random_state=rng).as_matrix()
    return R, rng.uniform(-1, 1, 3)


ROD = (0.20, 0.02, 0.02)
PLATE = (0.10, 0.08, 0.005)
CUBE = (0.10, 0.09, 0.08)
SMALL_CUBE = (0.03, 0.028, 0.025)

CASES = [
    (ROD, ShapeClass.ONE_D, GraspType.CYLINDRICAL),
    (PLATE, ShapeClass.TWO_D, GraspType.THREE_FINGER_TIP),
    (CUBE, ShapeClass.THREE_D_LARGE, GraspType.SPHERICAL),
    (SMALL_CUBE, ShapeClass.THREE_D_SMALL, GraspType.TWO_FINGER_TIP),
]


def test_mapping_and_enum_values():
    assert {c.value for c in ShapeClass} == {"1D", "2D", "3D-large", "3D-small"}
    assert {g.value for g in GraspType} == {
        "cylindrical",
        "spherical",
        "three_finger_tip",
        "two_finger_tip",
    }
    assert GRASP_TYPE_OF_CLASS == {
        ShapeClass.ONE_D: GraspType.CYLINDRICAL,
        ShapeClass.TWO_D: GraspType.THREE_FINGER_TIP,
        ShapeClass.THREE_D_LARGE: GraspType.SPHERICAL,
        ShapeClass.THREE_D_SMALL: GraspType.TWO_FINGER_TIP,
    }
    assert ShapeClass("3D-small") is ShapeClass.THREE_D_SMALL
    assert GraspType.SPHERICAL == "spherical" and str(ShapeClass.ONE_D) == "1D"


@pytest.mark.parametrize(("extents", "cls", "grasp"), CASES, ids=["rod", "plate", "cube", "small"])
def test_known_shapes(extents, cls, grasp):
    pts = _grid_box(extents)
    box = OrientedBox(center=np.zeros(3), rotation=np.eye(3), extents=np.array(extents))
    shape = classify_points(pts, box)
    assert isinstance(shape, NodeShape)
    assert np.allclose(shape.eigenvalues, _grid_variance(extents), rtol=1e-10, atol=1e-15)
    assert shape.shape_class is cls and shape.grasp_type is grasp
    assert shape.to_dict() == {
        "eigenvalues": shape.eigenvalues.tolist(),
        "shape_class": cls.value,
        "grasp_type": grasp.value,
    }


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize(("extents", "cls", "grasp"), CASES, ids=["rod", "plate", "cube", "small"])
def test_rigid_motion_invariance(extents, cls, grasp, seed):
    R, t = _rigid(seed)
    pts = _grid_box(extents) @ R.T + t
    box = OrientedBox.from_points_in_frame(pts, R)
    shape = classify_points(pts, box)
    assert np.allclose(shape.eigenvalues, _grid_variance(extents), rtol=1e-9, atol=1e-15)
    assert shape.shape_class is cls and shape.grasp_type is grasp


def test_eigenvalues_match_numpy_cov():
    rng = np.random.default_rng(4)
    pts = rng.normal(size=(500, 3)) @ rng.normal(size=(3, 3))
    ref = np.sort(np.linalg.eigvalsh(np.cov(pts.T, bias=True)))[::-1]
    assert np.allclose(pca_eigenvalues(pts), ref, rtol=1e-10)


def test_thresholds_move_the_class():
    # a 0.10 x 0.06 x 0.06 block: s2/s1 = 0.6 (grid: slightly different, still ~0.6)
    ext = (0.10, 0.06, 0.06)
    pts = _grid_box(ext, m=(11, 11, 11))
    box = OrientedBox(center=np.zeros(3), rotation=np.eye(3), extents=np.array(ext))
    assert classify_points(pts, box).shape_class is ShapeClass.THREE_D_LARGE
    assert classify_points(pts, box, ShapeParams(max_ratio_1d=0.61)).shape_class is (
        ShapeClass.ONE_D
    )
    assert classify_points(pts, box, ShapeParams(small_size=0.1)).shape_class is (
        ShapeClass.THREE_D_SMALL
    )
    # a 0.10 x 0.10 x 0.03 slab: s3/s2 = 0.3 -> 2D; with max_ratio_2d 0.29 -> 3D
    ext = (0.10, 0.10, 0.03)
    pts = _grid_box(ext, m=(11, 11, 11))
    box = OrientedBox(center=np.zeros(3), rotation=np.eye(3), extents=np.array(ext))
    assert classify_points(pts, box).shape_class is ShapeClass.TWO_D
    assert classify_points(pts, box, ShapeParams(max_ratio_2d=0.29)).shape_class is (
        ShapeClass.THREE_D_LARGE
    )


def test_is_small_boundary():
    p = ShapeParams(small_size=0.05)
    box = OrientedBox(center=np.zeros(3), rotation=np.eye(3), extents=np.array([0.05, 0.01, 0.01]))
    assert is_small(box, p)
    box2 = OrientedBox(center=np.zeros(3), rotation=np.eye(3), extents=np.array([0.0501, 0, 0]))
    assert not is_small(box2, p)
    assert is_small(box)  # default small_size 0.05


def test_params_validation():
    p = ShapeParams()
    assert (p.max_ratio_1d, p.max_ratio_2d, p.small_size) == (0.55, 0.45, 0.05)
    for name in ("max_ratio_1d", "max_ratio_2d"):
        for bad in (0.0, -1.0, 1.01, float("nan"), "x", True):
            with pytest.raises(ValueError, match=name):
                ShapeParams(**{name: bad})
    for bad in (-0.01, float("inf"), None, 10.5, "0.05"):
        with pytest.raises(ValueError, match=r"^small_size must be a length in \[0, 10\] m, got"):
            ShapeParams(small_size=bad)
    with pytest.raises(ValueError, match=r"^max_ratio_1d must be a number in \(0, 1\], got 0.0"):
        ShapeParams(max_ratio_1d=0.0)


def test_bad_input():
    box = OrientedBox(center=np.zeros(3), rotation=np.eye(3), extents=np.ones(3))
    with pytest.raises(DegenerateGeometryError, match="coincide"):
        classify_points(np.zeros((10, 3)), box)
    with pytest.raises(DegenerateGeometryError, match="at least 2"):
        classify_points(np.zeros((1, 3)), box)
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        classify_points(np.zeros((10, 4)), box)
    with pytest.raises(ValueError, match=r"shape \(3,\)"):
        classify_eigenvalues(np.ones(2), box)
    with pytest.raises(ValueError, match="descending"):
        classify_eigenvalues(np.array([1.0, 2.0, 0.5]), box)
    with pytest.raises(ValueError, match=r"shape \(3,\)"):
        NodeShape(np.ones(4), ShapeClass.ONE_D, GraspType.CYLINDRICAL)
    shape = classify_points(np.random.default_rng(0).random((50, 3)), box)
    with pytest.raises(ValueError, match="read-only"):
        shape.eigenvalues[0] = 1.0


def test_classify_tree_hammer_like():
    """A long handle with a cube head at its end: two parts, 1D (handle) and 3D-large (head)."""
    # random points filling the solids (a sparse grid would split between its lattice planes)
    rng = np.random.default_rng(0)
    handle = rng.uniform(-1, 1, (3000, 3)) * [0.125, 0.015, 0.015]
    head = rng.uniform(-1, 1, (2000, 3)) * 0.03 + [0.156, 0.0, 0.0]
    pts = np.vstack([handle, head])
    tree = decompose(pts, DecompositionParams(min_points=200))
    shapes = classify_tree(tree, pts)
    assert len(shapes) == len(tree.nodes)
    assert tree.leaves() == [1, 2]
    assert tree.node(1).n_points == len(handle)
    assert shapes[1].shape_class is ShapeClass.ONE_D
    assert shapes[1].grasp_type is GraspType.CYLINDRICAL
    assert shapes[2].shape_class is ShapeClass.THREE_D_LARGE
    assert shapes[2].grasp_type is GraspType.SPHERICAL
    for nd, sh in zip(tree.nodes, shapes, strict=True):
        assert np.allclose(sh.eigenvalues, pca_eigenvalues(pts[nd.indices]))
    with pytest.raises(ValueError, match=r"like the tree's cloud"):
        classify_tree(tree, pts[:-1])


@settings(max_examples=40, deadline=None)
@given(
    st.tuples(st.floats(0.005, 0.3), st.floats(0.005, 0.3), st.floats(0.005, 0.3)).map(
        lambda e: tuple(sorted(e, reverse=True))
    ),
    st.integers(0, 2**31 - 1),
)
def test_class_follows_aspect_ratios(extents, seed):
    """For a grid-filled box the class is decided by the analytic std ratios."""
    m = (9, 9, 9)
    var = _grid_variance(extents, m)
    s = np.sqrt(var)
    r21, r32 = s[1] / s[0], s[2] / s[1]
    params = ShapeParams()
    margins = (r21 - params.max_ratio_1d, r32 - params.max_ratio_2d, extents[0] - params.small_size)
    if min(abs(m) for m in margins) < 1e-6:
        return  # on a threshold: round-off decides
    R, t = _rigid(seed)
    pts = _grid_box(extents, m) @ R.T + t
    box = OrientedBox.from_points_in_frame(pts, R)
    cls = classify_points(pts, box, params).shape_class
    if r21 < params.max_ratio_1d:
        assert cls is ShapeClass.ONE_D
    elif r32 < params.max_ratio_2d:
        assert cls is ShapeClass.TWO_D
    elif max(extents) <= params.small_size:
        assert cls is ShapeClass.THREE_D_SMALL
    else:
        assert cls is ShapeClass.THREE_D_LARGE
