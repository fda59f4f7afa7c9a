"""The viewer's hidden-space layer (issue 13): the space behind a single depth view that
``--occluded occupied`` keeps the hand out of, drawn in its own colour.

References outside the app: the true mesh of the view's object (``scripts/make_views.py``'s
ray-cast view of the soda can from camera 0, no noise): a ray from the camera to a drawn point
meets the can's surface before the point, give or take one voxel; the analytic boundary of a
voxel block. Inside the app: the layer draws the ``OccupiedSpace`` the pipeline built for the
pool (one call of ``occupied_space`` for the load and the plan together), and its checkbox
shows and hides it without running the pipeline.
"""

from __future__ import annotations

import itertools
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from app.gui import LEGEND
from app.scene import NAMES
from app.scene_data import HIDDEN_POINTS, HIDDEN_RGB, TABLE_RGB, hidden_space_points, node_colors
from pregrasp_core import pipeline
from pregrasp_core.paths import OBJECTS_DIR
from pregrasp_core.pipeline import PipelineParams
from pregrasp_core.sensor.synthetic import LABEL_OBJECT

OCCUPIED = PipelineParams(occluded="occupied")


@dataclass(frozen=True)
class CanView:
    path: Path
    """The view as a PCD (label 2 = the can, VIEWPOINT = the camera)."""
    mesh: trimesh.Trimesh
    """The true mesh."""
    camera: np.ndarray
    """(3,) the camera's position."""
    seen: np.ndarray
    """(M, 3) the points the camera saw on the can (ray-cast)."""


@pytest.fixture(scope="module")
def can_view(make_views: ModuleType, tmp_path_factory) -> CanView:
    mv = make_views
    mesh = trimesh.load(OBJECTS_DIR / "can_soda.obj", force="mesh")
    view = mv.make_view(mesh, mv.AZIMUTHS_DEG[0], 0.0, mv.view_seed("can_soda", 0, 0.0))
    pts, lab = view.points_world()
    label = np.where(lab == LABEL_OBJECT, 2, 1).astype(np.uint8)
    path = tmp_path_factory.mktemp("hidden") / "can_soda.pcd"
    path.write_bytes(mv.pcd_bytes(pts, label, view.T_world_camera))
    return CanView(path, mesh, view.T_world_camera[:3, 3].copy(), pts[lab == LABEL_OBJECT])


@pytest.fixture(scope="module")
def hidden_app(can_view) -> Iterator[tuple]:
    """The app on the can's view planned with ``--occluded occupied``, and every
    ``OccupiedSpace`` that ``occupied_space`` returned while it loaded and planned."""
    import viser

    from app.server import ViewerConfig, run

    built: list = []
    real = pipeline.occupied_space
    mp = pytest.MonkeyPatch()
    mp.setattr(pipeline, "occupied_space", lambda *a, **k: built.append(real(*a, **k)) or built[-1])
    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    app = run(ViewerConfig(input=can_view.path, params=OCCUPIED, plan_on_start=True), server)
    try:
        _wait_idle(app.controller)
        yield app, built
    finally:
        app.close()
        server.stop()
        mp.undo()


def _wait_idle(controller, timeout: float = 60.0) -> None:
    import time

    deadline = time.monotonic() + timeout
    while not controller.idle():
        assert time.monotonic() < deadline, "the app did not finish its work"
        time.sleep(0.02)


def first_hit(mesh: trimesh.Trimesh, origin: np.ndarray, q: np.ndarray) -> np.ndarray:
    """(K,) distance from ``origin`` to the nearest triangle of ``mesh`` along the ray toward
    each of ``q`` (K, 3); inf where the ray misses (Moller-Trumbore, float64)."""
    v0 = mesh.triangles[:, 0]
    e1, e2 = mesh.triangles[:, 1] - v0, mesh.triangles[:, 2] - v0
    d = q - origin
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    s = origin - v0  # (T, 3)
    sxe1 = np.cross(s, e1)
    t_num = np.einsum("ti,ti->t", e2, sxe1)
    out = np.full(len(q), np.inf)
    for k0 in range(0, len(q), 256):  # chunks of rays
        D = d[k0 : k0 + 256, None, :]
        p = np.cross(D, e2[None])  # (k, T, 3)
        det = np.einsum("kti,ti->kt", p, e1)
        ok = np.abs(det) > 1e-15
        inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
        a = np.einsum("ti,kti->kt", s, p) * inv
        b = (d[k0 : k0 + 256] @ sxe1.T) * inv
        t = t_num[None] * inv
        hit = ok & (a >= 0.0) & (b >= 0.0) & (a + b <= 1.0) & (t > 0.0)
        out[k0 : k0 + 256] = np.where(hit, t, np.inf).min(axis=1)
    return out


def behind_surface(mesh: trimesh.Trimesh, camera: np.ndarray, q: np.ndarray, tol: float):
    """(K,) bool: the ray from ``camera`` toward each of ``q`` meets ``mesh`` no farther than
    ``tol`` beyond the point (the point lies behind the surface the camera sees, or within
    ``tol`` in front of it)."""
    return first_hit(mesh, camera, q) <= np.linalg.norm(q - camera, axis=1) + tol


def test_the_layer_draws_the_hidden_space_behind_the_seen_can(hidden_app, can_view) -> None:
    app, built = hidden_app
    s = app.controller.state
    assert s.error == "" and s.planned and s.params.occluded == "occupied"
    occ = s.result.occupied
    # the very space the pool and the planner used: built once for the load and the plan
    assert len(built) == 1 and occ is built[0]
    h = app.server.scene.get_handle_by_name(NAMES["hidden"])
    assert h is not None
    pts = np.asarray(h.points, dtype=np.float64)
    assert len(pts) == app.scene.n_hidden_points_shown
    assert 1000 < len(pts) <= HIDDEN_POINTS  # the can's 2,700 boundary voxels, all of them
    assert len(pts) == len(hidden_space_points(occ, max_points=10**9))
    np.testing.assert_array_equal(np.asarray(h.colors).reshape(-1, 3)[0], HIDDEN_RGB)
    # in hidden voxels, and every drawn point is an obstacle point of the pool and the planner
    # (the boundary voxels are all obstacles)
    assert np.all(occ.contains(pts))
    d, _ = cKDTree(occ.points).query(pts)
    assert d.max() < 1e-6
    # against the true can: the camera's ray to a drawn point meets the can before it (within
    # a voxel); the few that miss lie at the silhouette, each within a voxel (one grid step in
    # any direction) of a point that does
    v = occ.voxel
    seen = can_view.seen[:: max(len(can_view.seen) // 300, 1)]  # the ray test meets the seen
    hit = first_hit(can_view.mesh, can_view.camera, seen)  # points where the camera saw them
    np.testing.assert_allclose(hit, np.linalg.norm(seen - can_view.camera, axis=1), atol=1e-6)
    ok = behind_surface(can_view.mesh, can_view.camera, pts, v)
    assert ok.mean() > 0.98, ok.mean()
    rescued = np.zeros(int((~ok).sum()), dtype=bool)
    for o in itertools.product((-1.0, 0.0, 1.0), repeat=3):
        moved = pts[~ok] + v * (occ.frame @ np.array(o))
        rescued |= behind_surface(can_view.mesh, can_view.camera, moved, v)
    assert rescued.all()
    # the layer is the hidden space, not all of the view: points in front of the can's seen
    # surface by more than a voxel (toward the camera) would fail above; and it covers the
    # back, the part of the can the camera does not see (the far half of its axis box)
    centre = can_view.mesh.bounds.mean(axis=0)
    away = (pts - centre)[:, :2] @ (centre - can_view.camera)[:2]
    assert np.mean(away > 0.0) > 0.4


def test_the_checkbox_hides_and_shows_it_without_running_the_pipeline(
    hidden_app, monkeypatch
) -> None:
    app, built = hidden_app
    calls: list[str] = []
    real = pipeline.run_pipeline
    monkeypatch.setattr(
        pipeline, "run_pipeline", lambda *a, **k: calls.append(k.get("until", "")) or real(*a, **k)
    )
    s0 = app.controller.state
    before = np.asarray(app.server.scene.get_handle_by_name(NAMES["hidden"]).points).copy()
    assert not app.gui.show_hidden.disabled and app.gui.show_hidden.value
    app.gui.show_hidden.value = False
    s1 = app.controller.state
    assert not s1.view.show_hidden_space and s1.result is s0.result
    assert app.server.scene.get_handle_by_name(NAMES["hidden"]) is None
    assert app.scene.n_hidden_points_shown == 0
    app.gui.show_hidden.value = True
    h = app.server.scene.get_handle_by_name(NAMES["hidden"])
    np.testing.assert_array_equal(np.asarray(h.points), before)
    assert app.controller.state.result is s0.result
    assert calls == [] and len(built) == 1  # no pipeline run, no hidden space built again
    assert "hidden space (occupied)" in app.gui.pool_info.content


def test_no_layer_for_a_complete_cloud_even_with_occupied(make_app) -> None:
    app = make_app(params=OCCUPIED)  # the default mug, sampled on its mesh: no view
    s = app.controller.state
    assert s.error == "" and s.cloud.sensor is None and s.params.occluded == "occupied"
    assert s.result.pool is not None and s.result.occupied is None
    assert app.server.scene.get_handle_by_name(NAMES["hidden"]) is None
    assert app.scene.n_hidden_points_shown == 0 and app.gui.show_hidden.disabled
    assert "hidden space" not in app.gui.pool_info.content


def test_boundary_of_a_voxel_block_and_the_cap() -> None:
    """A solid 5 x 6 x 7 block of hidden voxels: 210 voxels, 3 x 4 x 5 inside, so 150 on its
    boundary, at their centres; past the cap an even subsample of them."""

    @dataclass
    class Block:
        grid: np.ndarray
        origin: np.ndarray
        frame: np.ndarray
        voxel: float

    grid = np.zeros((9, 9, 9), dtype=bool)
    grid[2:7, 1:7, 1:8] = True
    c, s = np.cos(0.3), np.sin(0.3)
    frame = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    occ = Block(grid, np.array([0.1, -0.2, 0.05]), frame, 0.003)
    pts = hidden_space_points(occ, max_points=10_000)
    assert len(pts) == 150
    g = np.rint((pts - occ.origin) @ frame / occ.voxel).astype(int)
    assert np.all(grid[g[:, 0], g[:, 1], g[:, 2]])
    on_face = (g[:, 0] == 2) | (g[:, 0] == 6) | (g[:, 1] == 1) | (g[:, 1] == 6)
    on_face |= (g[:, 2] == 1) | (g[:, 2] == 7)
    assert on_face.all()
    capped = hidden_space_points(occ, max_points=40)
    assert len(capped) == 40
    idx = cKDTree(pts).query(capped)[1]
    assert len(set(idx.tolist())) == 40 and np.all(np.diff(idx) >= 3)  # every 3rd or 4th
    assert hidden_space_points(None).shape == (0, 3)


def test_its_colour_and_legend_line() -> None:
    parts = node_colors(np.arange(500)).astype(int)
    sat = lambda rgb: 1.0 - np.min(rgb, axis=-1) / np.max(rgb, axis=-1)  # noqa: E731
    assert sat(np.array(HIDDEN_RGB)) < 0.5 * sat(parts).min()  # paler than every part
    assert HIDDEN_RGB[2] - HIDDEN_RGB[0] >= 50 and HIDDEN_RGB != TABLE_RGB  # bluer than the table
    (row,) = [m for c, m in LEGEND if c == "pale blue points"]
    assert "--occluded occupied" in row and "hidden space" in row


def test_the_layer_draws_the_space_hidden_behind_the_other_objects(
    make_app, make_views: ModuleType, tmp_path
) -> None:
    """A soda can 3 cm beside a 7 cm ball, seen by a depth camera, the ball picked: the ball's
    plan keeps the hand out of the can and out of the space hidden behind it, and the layer
    draws that space (planned with ``completed``: no hidden space of the object's own): 95 %
    of the drawn points lie behind the can's true surface seen from the camera (a ray to it
    meets the can first, within a 4 mm voxel; the rest at its silhouette), none at the ball;
    the pool panel counts the scene's obstacles."""
    from pregrasp_core.io import SensorOptions
    from pregrasp_core.sensor import Intrinsics
    from pregrasp_core.sensor.synthetic import orbit_camera, render_view

    ball = trimesh.creation.icosphere(subdivisions=3, radius=0.035)
    ball.apply_translation((0.0, 0.0, 0.035))
    can = trimesh.creation.cylinder(radius=0.033, height=0.12, sections=48)
    can.apply_translation((0.098, 0.0, 0.06))
    scene = trimesh.util.concatenate([ball, can])
    T = orbit_camera(np.array([0.0, 0.0, 0.05]), 0.6, np.radians(250.0), np.radians(35.0))
    view = render_view(scene.vertices, scene.faces, T, Intrinsics(420.0, 420.0, 239.5, 179.5),
                       480, 360, table_half=0.5)  # fmt: skip
    pts, lab = view.points_world()
    path = tmp_path / "clutter.pcd"
    path.write_bytes(make_views.pcd_bytes(pts, np.where(lab == LABEL_OBJECT, 2, 1), T))
    app = make_app(input=path, sensor=SensorOptions(pick=(0.0, 0.0, 0.035)), plan_on_start=True,
                   params=PipelineParams(occluded="completed"))  # fmt: skip
    _wait_idle(app.controller)
    s = app.controller.state
    assert s.error == "" and s.planned and s.result.occupied is None
    assert s.cloud.obstacles is not None and not app.gui.show_hidden.disabled
    h = app.server.scene.get_handle_by_name(NAMES["hidden"])
    drawn = np.asarray(h.points, dtype=np.float64)
    assert len(drawn) == app.scene.n_hidden_points_shown > 100
    ok = behind_surface(can, T[:3, 3], drawn, 0.004)  # within a 4 mm voxel
    assert ok.mean() > 0.95, ok.mean()  # the rest at the can's silhouette
    assert np.all(np.linalg.norm(drawn - [0.0, 0.0, 0.035], axis=1) > 0.035 + 0.004)
    assert "scene obstacles:" in app.gui.pool_info.content
    app.gui.show_hidden.value = False
    assert app.server.scene.get_handle_by_name(NAMES["hidden"]) is None
