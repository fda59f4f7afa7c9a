"""The skirt of a view from above: the walls an overhead camera cannot see (``add_skirt``).

References from outside the code under test: the true mesh the view was ray cast from
(trimesh's closest points and face normals), rigid motions of the whole scene, and the lift of
the grasp simulated in MuJoCo with the true mesh.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from pregrasp_core.hand import Hand
from pregrasp_core.io import SensorOptions, load_point_cloud
from pregrasp_core.paths import OBJECTS_DIR
from pregrasp_core.pipeline import PipelineParams, run_pipeline, with_cloud
from pregrasp_core.sensor import CompletionParams, Intrinsics, complete_view, segment_table
from pregrasp_core.sensor import completion as completion_module
from pregrasp_core.sensor.synthetic import LABEL_OBJECT, orbit_camera, render_view
from pregrasp_core.sensor.truth import MeshDistance, check_grasp

KC = Intrinsics(420.0, 420.0, 239.5, 179.5)
W, H = 480, 360


def _view(mesh: trimesh.Trimesh, elevation: float, motion: np.ndarray | None = None):
    """(object points, viewpoint, support plane, mesh) of ``mesh`` standing on a table, seen
    from ``elevation`` degrees at 0.5 m; ``motion`` (4, 4) moves the whole scene."""
    target = np.array([0.0, 0.0, mesh.bounds[1, 2] / 2])
    T = orbit_camera(target, 0.5, np.radians(40.0), np.radians(elevation))
    view = render_view(mesh.vertices, mesh.faces, T, KC, W, H, table_half=0.3,
                       noise=0.0005, rng=np.random.default_rng(2))  # fmt: skip
    p, lab = view.points_world()
    if motion is not None:
        p = p @ motion[:3, :3].T + motion[:3, 3]
        T = motion @ T
        mesh = mesh.copy()
        mesh.apply_transform(motion)
    seg = segment_table(p, viewpoint=T[:3, 3])
    assert np.sum(seg.object_mask & (lab == LABEL_OBJECT)) >= 0.99 * np.sum(lab == LABEL_OBJECT)
    return seg.object_points, T[:3, 3], seg.plane, mesh


def _motion(seed: int) -> np.ndarray:
    M = np.eye(4)
    M[:3, :3] = Rotation.random(random_state=seed).as_matrix()
    M[:3, 3] = np.random.default_rng(seed).uniform(-1.0, 1.0, 3)
    return M


BOX = trimesh.creation.box((0.06, 0.09, 0.11))
BOX.apply_translation((0.0, 0.0, 0.055))
CAN = trimesh.creation.cylinder(radius=0.04, height=0.07, sections=96)
CAN.apply_translation((0.0, 0.0, 0.035))


@pytest.mark.parametrize("mesh", [BOX, CAN], ids=["box", "cylinder"])
@pytest.mark.parametrize("seed", [None, 5])
def test_the_skirt_lies_on_the_walls_an_overhead_camera_cannot_see(mesh, seed) -> None:
    motion = None if seed is None else _motion(seed)
    pts, vp, plane, true = _view(mesh, 85.0, motion)
    params = CompletionParams()
    done = complete_view(pts, vp, plane, params)
    sk = done.points[done.skirt]
    assert len(sk) > 100
    # the skirt comes last and takes nothing from the copy: each copied point is still its
    # source moved by the symmetry
    assert done.assumed[done.skirt].all() and not (done.skirt & done.filled).any()
    assert np.flatnonzero(done.skirt).min() == len(done.points) - len(sk)
    M = done.transform
    src = done.source[done.copied]
    assert np.allclose(done.points[done.copied], pts[src] @ M[:3, :3].T + M[:3, 3])
    # on the true walls or just inside them: below the outermost seen point, which lies within
    # a spacing of the edge (plus the view's noise, 0.5 mm, and the pixel's slant), never
    # outside the object by more than the noise
    spacing = float(np.median(cKDTree(pts).query(pts, k=2)[0][:, 1]))
    _, dist, face = trimesh.proximity.closest_point(true, sk)
    assert dist.max() < 2.0 * spacing
    assert trimesh.proximity.signed_distance(true, sk).min() > -0.0005  # trimesh: + inside
    # normals the walls' outward ones, but within 5 mm of a box's vertical edge (no single
    # normal there: the outline's direction turns through 90 degrees over a few cells)
    agree = np.einsum("ij,ij->i", done.skirt_normals, true.face_normals[face])
    corners = true.vertices if mesh is BOX else np.zeros((0, 3))
    rel = sk[:, None, :] - corners[None]
    horiz = np.linalg.norm(rel - (rel @ plane.normal)[..., None] * plane.normal, axis=2)
    flat = np.all(horiz > 0.005, axis=1)
    assert flat.mean() > 0.8
    assert np.mean(agree[flat] > 0.95) > 0.97 and agree[flat].min() > 0.8
    assert np.allclose(done.skirt_normals @ plane.normal, 0.0, atol=1e-9)
    # straight below a visible point of the outline, at most `skirt` down, above the table
    src = done.points[done.source[done.skirt]]
    drop = plane.signed_distance(src) - plane.signed_distance(sk)
    lateral = np.linalg.norm((src - sk) - np.outer(drop, plane.normal), axis=1)
    assert lateral.max() < 1e-9
    assert drop.min() > 0.0 and drop.max() <= params.skirt + 1e-9
    assert plane.signed_distance(sk).min() > 0.0
    # more of the true side walls lies within 3 mm of the completed cloud than without it
    walls, _ = trimesh.sample.sample_surface(true, 4000, seed=1)
    height = plane.signed_distance(walls)
    top = height.max()
    band = (height > top - params.skirt) & (height < top - 0.003)
    cov_with = np.mean(cKDTree(done.points).query(walls[band])[0] < 0.003)
    cov_without = np.mean(cKDTree(done.points[~done.skirt]).query(walls[band])[0] < 0.003)
    assert cov_with > cov_without + 0.3, (cov_with, cov_without)


def test_no_skirt_from_a_side_camera_or_when_switched_off() -> None:
    pts, vp, plane, _ = _view(BOX, 35.0)
    assert not complete_view(pts, vp, plane).skirt.any()
    pts, vp, plane, _ = _view(BOX, 85.0)
    done = complete_view(pts, vp, plane, CompletionParams(skirt=0.0))
    assert not done.skirt.any() and done.skirt_normals.shape == (0, 3)
    # a shallower skirt is a subset of the deeper one's depths
    shallow = complete_view(pts, vp, plane, CompletionParams(skirt=0.005))
    deep = complete_view(pts, vp, plane)
    assert 0 < shallow.skirt.sum() < deep.skirt.sum()


@pytest.mark.parametrize(
    ("field", "value"), [("skirt", -0.01), ("skirt", np.nan), ("skirt_angle", 91.0)]
)
def test_skirt_parameters_are_bounded(field: str, value: float) -> None:
    with pytest.raises(ValueError, match=field):
        CompletionParams(**{field: value})


def test_a_ramekin_seen_from_above_gets_a_grasp_that_holds(tmp_path, monkeypatch) -> None:
    """From 85 degrees the ramekin's outer wall is out of sight: without the skirt no kept grasp
    is force closure (its contacts all on the rim's top); with it the best grasp is, its hand
    clear of the true mesh, its contacts on it, and it lifts the true mesh in MuJoCo."""
    from pregrasp_core.simulate import SimulationParams, simulate_grasps

    mesh = trimesh.load(OBJECTS_DIR / "ramekin.obj", force="mesh")
    target = np.array([0.0, 0.0, mesh.bounds[1, 2] / 2])
    T = orbit_camera(target, 0.45, np.radians(60.0), np.radians(85.0))
    view = render_view(mesh.vertices, mesh.faces, T, KC, W, H, table_half=0.3,
                       noise=0.001, rng=np.random.default_rng(3))  # fmt: skip
    p, lab = view.points_world()
    path = tmp_path / "ramekin_above.ply"
    trimesh.PointCloud(p).export(path)
    hand = Hand.load()
    truth = MeshDistance(mesh)

    def plan():
        opts = SensorOptions(viewpoint=tuple(T[:3, 3]), scene=True)
        cloud = load_point_cloud(path, n_points=None, sensor=opts)
        return cloud, run_pipeline(cloud, with_cloud(PipelineParams(), cloud), hand,
                                   until="grasps")  # fmt: skip

    cloud, res = plan()
    done = cloud.sensor.completion
    assert cloud.info["scene"]["n_skirt"] == int(done.skirt.sum()) > 0
    gs = res.grasps
    assert gs is not None and gs.best is not None
    g = gs.grasps[gs.best]
    check = check_grasp(g, res.hand, truth)
    assert g.epsilon > 0.0
    assert check.penetration <= 0.002 and check.worst_contact <= 0.003
    sim = simulate_grasps(res, [gs.best], hand, SimulationParams(), mesh=mesh)[0]
    assert sim.success, sim

    orig = completion_module.add_skirt
    monkeypatch.setattr(
        completion_module, "add_skirt",
        lambda v, c, vis, prm: orig(v, c, vis, dataclasses.replace(prm, skirt=0.0)),
    )  # fmt: skip
    cloud, res = plan()
    assert "n_skirt" not in cloud.info["scene"]
    assert res.grasps is not None and res.grasps.n_force_closure == 0
