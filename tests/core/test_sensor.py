"""Tests of pregrasp_core.sensor: depth images against analytic planes and spheres rendered here,
the ray caster against the analytic sphere and trimesh's ray casting, the table segmentation on
tilted scenes, the millimetre rule on the demo clouds, and the completion against the true mesh.
"""

from __future__ import annotations

import json
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from pregrasp_core.errors import InputError
from pregrasp_core.facemask import FaceMaskParams, SupportPlane, support_plane
from pregrasp_core.io import load_point_cloud
from pregrasp_core.paths import OBJECTS_DIR, demo_objects
from pregrasp_core.sensor import (
    CompletionParams,
    Intrinsics,
    SegmentParams,
    complete_view,
    depth_to_points,
    detect_units,
    fit_plane_ransac,
    load_camera_pose,
    load_depth_image,
    pcd_viewpoint,
    prepare_view,
    remove_outliers,
    segment_table,
    voxel_clusters,
)
from pregrasp_core.sensor.synthetic import (
    LABEL_OBJECT,
    LABEL_TABLE,
    clutter_meshes,
    orbit_camera,
    render_mesh_depth,
    render_view,
)

ASSETS = Path(__file__).resolve().parents[2] / "assets" / "objects"
"""This checkout's demo folder (the committed depth demo lives beside the meshes)."""

K = Intrinsics(fx=300.0, fy=310.0, cx=79.5, cy=59.5)
W, H = 160, 120


def rays(k: Intrinsics = K, w: int = W, h: int = H) -> np.ndarray:
    """(H, W, 3) z = 1 rays through the pixel centres (independent of the code under test)."""
    j, i = np.meshgrid(np.arange(w), np.arange(h))
    return np.stack([(j - k.cx) / k.fx, (i - k.cy) / k.fy, np.ones((h, w))], axis=-1)


def plane_depth(n: np.ndarray, d: float) -> np.ndarray:
    """Depth z of the plane n . p = d along every pixel's ray."""
    return d / (rays() @ n)


def sphere_depth(c: np.ndarray, r: float) -> np.ndarray:
    """Depth z of the first hit of every pixel's ray on the sphere |p - c| = r, NaN for a miss."""
    v = rays()
    a = np.sum(v * v, axis=-1)
    b = -2.0 * v @ c
    cc = c @ c - r * r
    disc = b * b - 4 * a * cc
    with np.errstate(invalid="ignore"):
        t = (-b - np.sqrt(disc)) / (2 * a)
    return np.where(disc >= 0, t, np.nan)


# ------------------------------------------------------------------------------------------------
# depth images


def test_npy_plane_back_projects_onto_the_plane(tmp_path: Path) -> None:
    n = np.array([0.2, -0.3, 1.0])
    n /= np.linalg.norm(n)
    z = plane_depth(n, 0.8)
    z[10:20, 30:50] = 0.0  # no return
    z[50, 60] = np.nan
    path = tmp_path / "plane.npy"
    np.save(path, z)
    cloud = load_depth_image(path, K)
    assert cloud.n_points == W * H - 200 - 1
    assert np.allclose(cloud.points @ n, 0.8, atol=1e-12)
    assert np.array_equal(cloud.viewpoint, np.zeros(3))
    r, c = cloud.pixels[0]
    assert (r, c) == (0, 0) and np.isclose(cloud.points[0, 2], z[0, 0])
    assert cloud.source == str(path)


def test_png_in_millimetres_matches_the_sphere(tmp_path: Path) -> None:
    c, r = np.array([0.05, -0.02, 0.6]), 0.1
    z = sphere_depth(c, r)
    mm = np.where(np.isfinite(z), np.round(z * 1000.0), 0).astype(np.uint16)
    path = tmp_path / "sphere.png"
    iio.imwrite(path, mm)
    (tmp_path / "k.json").write_text(json.dumps({**K.to_dict(), "width": W, "height": H}))
    cloud = load_depth_image(path, tmp_path / "k.json")
    assert cloud.n_points == int(np.isfinite(z).sum())
    # 0.5 mm quantisation along the ray moves a point at most 0.5 mm * |d| off the sphere
    dist = np.linalg.norm(cloud.points - c, axis=1) - r
    assert np.abs(dist).max() < 0.5e-3 * np.linalg.norm(rays(), axis=-1).max() + 1e-9
    # the same cloud from four numbers
    again = load_depth_image(path, (K.fx, K.fy, K.cx, K.cy))
    assert np.array_equal(again.points, cloud.points)


def test_intrinsics_json_and_pose(tmp_path: Path) -> None:
    T = orbit_camera(np.zeros(3), 0.5, 0.3, 0.6)
    p = tmp_path / "cam.json"
    p.write_text(json.dumps({**K.to_dict(), "T_world_camera": T.tolist()}))
    assert Intrinsics.from_json(p) == K
    assert np.allclose(load_camera_pose(p), T)
    p2 = tmp_path / "nopose.json"
    p2.write_text(json.dumps(K.to_dict()))
    assert load_camera_pose(p2) is None
    assert np.allclose(K.matrix() @ [0.0, 0.0, 1.0], [K.cx, K.cy, 1.0])


@pytest.mark.parametrize(
    ("doc", "match"),
    [
        ({"fx": 1.0, "fy": 1.0, "cx": 0.0}, "lack cy"),
        ({"fx": 1.0, "fy": 1.0, "cx": 0.0, "cy": 0.0, "Fx": 2}, "unknown intrinsics keys"),
        ({"fx": "a", "fy": 1.0, "cx": 0.0, "cy": 0.0}, "fx must be a number"),
        ({"fx": -1.0, "fy": 1.0, "cx": 0.0, "cy": 0.0}, "must be positive focal lengths"),
        ([1, 2, 3, 4], "JSON object"),
    ],
)
def test_bad_intrinsics_json(tmp_path: Path, doc: object, match: str) -> None:
    p = tmp_path / "bad.json"
    p.write_text(json.dumps(doc))
    with pytest.raises(InputError, match=match):
        Intrinsics.from_json(p)


def test_bad_intrinsics_values(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="four numbers fx fy cx cy"):
        Intrinsics.from_values([1.0, 2.0, 3.0])
    with pytest.raises(InputError, match="fy must be finite"):
        Intrinsics(1.0, float("nan"), 0.0, 0.0)
    with pytest.raises(InputError, match="not found"):
        Intrinsics.from_json(tmp_path / "none.json")
    (tmp_path / "x.json").write_text("{fx: 1")
    with pytest.raises(InputError, match=r"x\.json: not a JSON file"):
        Intrinsics.from_json(tmp_path / "x.json")


def test_bad_depth_files(tmp_path: Path) -> None:
    good = plane_depth(np.array([0.0, 0.0, 1.0]), 0.5)
    cases: list[tuple[str, object, str]] = [
        ("d8.png", (good * 100).astype(np.uint8), "must be 16-bit"),
        ("rgb.png", np.zeros((H, W, 3), np.uint8) + 50, "one channel"),
        ("int.npy", (good * 1000).astype(np.int32), "float array in metres"),
        ("cube.npy", np.ones((4, 4, 4)), "must be 2-D"),
        ("neg.npy", -good, "negative depths"),
        ("inf.npy", np.where(good > 0, np.inf, 0.0), "infinite"),
        ("zero.npy", np.zeros((H, W)), "no valid pixel"),
        ("mm.npy", good * 1000.0, "hold metres"),
        ("few.npy", np.pad(np.ones((2, 2)), 5), "only 4 valid pixels"),
    ]
    for name, arr, match in cases:
        path = tmp_path / name
        if name.endswith(".png"):
            iio.imwrite(path, arr)
        else:
            np.save(path, arr)
        with pytest.raises(InputError, match=match) as e:
            load_depth_image(path, K)
        assert name in str(e.value)
    with pytest.raises(InputError, match="unknown depth-image extension"):
        load_depth_image(tmp_path / "d.tiff", K)
    with pytest.raises(InputError, match="file not found"):
        load_depth_image(tmp_path / "nothing.png", K)
    (tmp_path / "empty.npy").write_bytes(b"")
    with pytest.raises(InputError, match="empty"):
        load_depth_image(tmp_path / "empty.npy", K)
    np.save(tmp_path / "ok.npy", good)
    (tmp_path / "k.json").write_text(json.dumps({**K.to_dict(), "width": W + 1, "height": H}))
    with pytest.raises(InputError, match="intrinsics file .* says 161 x 120"):
        load_depth_image(tmp_path / "ok.npy", tmp_path / "k.json")
    with pytest.raises(InputError, match="must be 2-D"):
        depth_to_points(np.ones(5), K)


def test_committed_depth_demo_reads_and_segments() -> None:
    png, cam = ASSETS / "mug_depth.png", ASSETS / "mug_depth.json"
    assert png.stat().st_size < 1_000_000
    cloud = load_depth_image(png, cam)
    T = load_camera_pose(cam)
    assert T is not None and cloud.shape == (360, 480)
    seg = segment_table(cloud.points, viewpoint=cloud.viewpoint)
    # the table is z = 0 of the world the pose gives (the mug stands on it), the normal is up
    up = T[:3, :3] @ seg.plane.normal
    assert up[2] > np.cos(np.radians(1.0))
    origin_height = seg.plane.normal @ T[:3, :3].T @ (-T[:3, 3]) - seg.plane.height
    assert abs(origin_height) < 0.002
    world = seg.object_points @ T[:3, :3].T + T[:3, 3]
    mesh = trimesh.load(OBJECTS_DIR / "mug_handle.obj", force="mesh")
    assert abs(world[:, 2].max() - mesh.bounds[1, 2]) < 0.004  # the rim is seen
    assert np.all(np.abs(world[:, :2]) < mesh.extents[:2] / 2 + 0.006)


# ------------------------------------------------------------------------------------------------
# the ray caster (the test data generator's)


def test_ray_caster_matches_the_analytic_sphere_and_trimesh() -> None:
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=0.1)
    sphere.apply_translation([0.05, -0.02, 0.6])
    z = render_mesh_depth(sphere.vertices, sphere.faces, np.eye(4), K, W, H)
    ref = sphere_depth(np.array([0.05, -0.02, 0.6]), 0.1)
    hit = np.isfinite(z)
    # the hits lie on the icosphere's facets: never outside the sphere, inside it by at most the
    # deepest facet's sagitta (0.1 m - the nearest facet plane's distance from the centre)
    c = np.array([0.05, -0.02, 0.6])
    plane_dist = np.einsum("ij,ij->i", sphere.face_normals, sphere.triangles_center - c)
    sagitta = 0.1 - plane_dist.min()
    assert 0.0 < sagitta < 0.2e-3
    radial = np.linalg.norm(z[hit][:, None] * rays()[hit] - c, axis=1) - 0.1
    assert radial.max() < 1e-9 and radial.min() > -sagitta - 1e-9
    assert np.isfinite(z).sum() == pytest.approx(np.isfinite(ref).sum(), rel=0.02)
    # exactly trimesh's first hits where trimesh's ray casting finds one
    d = rays().reshape(-1, 3)
    loc, idx, _ = sphere.ray.intersects_location(np.zeros_like(d), d, multiple_hits=False)
    assert len(idx) > 1000
    assert np.allclose(z.reshape(-1)[idx], loc[:, 2], atol=1e-6)


# ------------------------------------------------------------------------------------------------
# table segmentation


def scene(noise: float, seed: int = 3):
    """Two objects on a table, seen from above at 40 degrees, moved by a random rigid motion:
    (points, labels per point (0 table, 1 can, 2 box and ball, -1 none), viewpoint, the true
    plane)."""
    can = trimesh.creation.cylinder(radius=0.03, height=0.09, sections=48)
    can.apply_translation([0.0, 0.0, 0.045])
    box = trimesh.creation.box(extents=[0.06, 0.04, 0.12])
    box.apply_translation([0.0, 0.12, 0.06])
    # a part of the box that the view cuts off from it (like a handle behind a body): a ball
    # floating 17 mm beside the box's +y face
    ball = trimesh.creation.icosphere(subdivisions=2, radius=0.01)
    ball.apply_translation([0.0, 0.167, 0.09])
    both = trimesh.util.concatenate([can, box, ball])
    T = orbit_camera(np.array([0.0, 0.05, 0.05]), 0.55, 0.4, np.radians(40))
    Kc = Intrinsics(320.0, 320.0, 159.5, 119.5)
    view = render_view(both.vertices, both.faces, T, Kc, 320, 240, table_half=0.35, noise=noise,
                       rng=np.random.default_rng(seed))  # fmt: skip
    p, lab = view.points_world()
    which = np.where(lab == LABEL_TABLE, 0, -1)
    obj = lab == LABEL_OBJECT
    which[obj] = np.where(p[obj, 1] > 0.09, 2, 1)  # the box and its ball, or the can
    R = Rotation.random(random_state=seed).as_matrix()
    t = np.array([0.3, -1.0, 2.0])
    return p @ R.T + t, which, T[:3, 3] @ R.T + t, SupportPlane(R[:, 2], float(R[:, 2] @ t))


@pytest.mark.parametrize("noise", [0.0, 0.002])
def test_segment_table_on_a_tilted_scene(noise: float) -> None:
    pts, which, vp, truth = scene(noise)
    seg = segment_table(pts, viewpoint=vp)
    angle = np.degrees(np.arccos(np.clip(seg.plane.normal @ truth.normal, -1, 1)))
    assert angle < 1.0
    assert abs(seg.plane.height - truth.height) < 0.002
    # the largest cluster is the box (more points than the can from this side)
    n_box, n_can = int(np.sum(which == 2)), int(np.sum(which == 1))
    assert n_box > n_can
    assert np.sum(seg.object_mask & (which == 2)) >= 0.99 * n_box
    assert np.sum(seg.object_mask & (which == 1)) == 0
    assert np.sum(seg.table_mask & (which == 0)) >= 0.99 * np.sum(which == 0)
    assert np.sum(seg.table_mask & (which == 2)) <= 0.01 * n_box
    if noise == 0.0:  # without the merge the ball is a cluster of its own, lost
        alone = segment_table(pts, viewpoint=vp, params=SegmentParams(merge_gap=0.0))
        assert np.sum(alone.object_mask & (which == 2)) < 0.97 * n_box
    # pick the can instead: the cluster nearest a point by the can
    can_top = pts[which == 1].mean(axis=0)
    picked = segment_table(pts, viewpoint=vp, pick=can_top)
    assert np.sum(picked.object_mask & (which == 1)) >= 0.99 * n_can
    assert np.sum(picked.object_mask & (which == 2)) == 0
    # usable as the pipeline's support plane
    fm = FaceMaskParams(up=tuple(seg.plane.normal), support_height=seg.plane.height)
    sp = support_plane(seg.object_points, fm)
    assert sp is not None and np.allclose(sp.normal, seg.plane.normal)
    assert np.all(sp.signed_distance(seg.object_points) > -3 * seg.band - 1e-3)


def test_segment_table_is_seeded_and_orients_the_normal() -> None:
    pts, _, vp, truth = scene(0.001)
    a = segment_table(pts, viewpoint=vp, params=SegmentParams(seed=5))
    b = segment_table(pts, viewpoint=vp, params=SegmentParams(seed=5))
    assert np.array_equal(a.object_mask, b.object_mask)
    assert np.array_equal(a.plane.normal, b.plane.normal)
    # no viewpoint: the normal points to the side holding the objects (the same one)
    c = segment_table(pts)
    assert c.plane.normal @ truth.normal > 0.999
    assert np.array_equal(c.object_mask, a.object_mask) or (
        np.sum(c.object_mask ^ a.object_mask) < 0.01 * a.object_mask.sum()
    )


def test_segment_table_errors() -> None:
    rng = np.random.default_rng(0)
    flat = np.c_[rng.uniform(-1, 1, (2000, 2)), np.zeros(2000)]
    with pytest.raises(InputError, match="nothing stands above the table"):
        segment_table(flat, viewpoint=(0, 0, 1))
    with pytest.raises(InputError, match="NaN or infinite"):
        segment_table(np.vstack([flat, [np.nan, 0, 0]]))
    with pytest.raises(ValueError, match="shape"):
        segment_table(flat[:, :2])
    with pytest.raises(ValueError, match="cluster_radius"):
        SegmentParams(cluster_radius=0.0)


def test_fit_plane_ransac_finds_the_dominant_plane_among_outliers() -> None:
    rng = np.random.default_rng(1)
    R = Rotation.random(random_state=2).as_matrix()
    plane = np.c_[rng.uniform(-0.5, 0.5, (3000, 2)), rng.normal(0, 0.001, 3000)]
    junk = rng.uniform(-0.5, 0.5, (3000, 3))  # half the points are not on the plane
    pts = np.vstack([plane, junk]) @ R.T
    n, h, inl = fit_plane_ransac(pts, threshold=0.004, rng=np.random.default_rng(0))
    assert abs(n @ R[:, 2]) > np.cos(np.radians(0.5))
    assert abs(h) < 1e-3
    assert inl[:3000].mean() > 0.99 and inl[3000:].mean() < 0.02


def test_voxel_clusters_and_outlier_removal() -> None:
    rng = np.random.default_rng(4)
    a = rng.normal(0, 0.005, (600, 3))
    b = rng.normal(0, 0.005, (300, 3)) + [0.1, 0, 0]
    lab = voxel_clusters(np.vstack([b, a]), 0.01)
    assert set(lab[300:]) == {0} and set(lab[:300]) == {1}
    grid = np.stack(np.meshgrid(np.arange(40), np.arange(40), [0]), -1).reshape(-1, 3) * 0.002
    out = rng.uniform(-0.5, 0.5, (20, 3)) + [0.04, 0.04, 0.3]
    keep = remove_outliers(np.vstack([grid, out]), k=8, std_ratio=2.0)
    assert not keep[len(grid) :].any()
    assert keep[: len(grid)].all()


# ------------------------------------------------------------------------------------------------
# units


def test_millimetre_rule_on_demo_clouds() -> None:
    for path in demo_objects():
        pts = load_point_cloud(path).points
        m = detect_units(pts)
        assert (m.unit, m.scale) == ("m", 1.0), path.name
        mm = detect_units(pts * 1000.0)
        assert (mm.unit, mm.scale) == ("mm", 0.001), (path.name, mm.spacing)
        assert "--scale 1" in mm.notice and "millimetres" in mm.notice


def test_millimetre_rule_no_false_positives_on_metre_scenes() -> None:
    # a 2 m table top at 3 mm spacing with a mug on it
    g = np.arange(0.0, 2.0, 0.003)
    table = np.stack(np.meshgrid(g, g[:300], [0.0]), -1).reshape(-1, 3)
    mug = load_point_cloud(OBJECTS_DIR / "mug.obj").points + [1.0, 0.4, 0.0]
    m = detect_units(np.vstack([table, mug]))
    assert m.unit == "m" and "at most 3 units" in m.notice and "--scale 0.001" in m.notice
    # a 10 m x 6 m room floor sampled every 2 cm
    f = np.stack(np.meshgrid(np.arange(0, 10, 0.02), np.arange(0, 6, 0.02), [0.0]), -1)
    room = detect_units(f.reshape(-1, 3))
    assert room.unit == "m" and room.extent > 9 and "densely sampled" in room.notice


# ------------------------------------------------------------------------------------------------
# completion


def true_view(name: str, azimuth_deg: float):
    """(object points, viewpoint, support plane, true mesh) of a demo object on a table."""
    mesh = trimesh.load(OBJECTS_DIR / f"{name}.obj", force="mesh")
    target = np.array([0.0, 0.0, mesh.bounds[1, 2] / 2])
    T = orbit_camera(target, 0.5, np.radians(azimuth_deg), np.radians(35.0))
    Kc = Intrinsics(420.0, 420.0, 239.5, 179.5)
    view = render_view(mesh.vertices, mesh.faces, T, Kc, 480, 360, table_half=0.3)
    p, lab = view.points_world()
    seg = segment_table(p, viewpoint=T[:3, 3])
    assert np.sum(seg.object_mask & (lab == LABEL_OBJECT)) >= 0.99 * np.sum(lab == LABEL_OBJECT)
    return seg.object_points, T[:3, 3], seg.plane, mesh


@pytest.mark.parametrize(("name", "azimuth"), [("can_soda", 30.0), ("box_cereal", 150.0),
                                               ("mug", 30.0)])  # fmt: skip
def test_completion_recovers_the_true_box(name: str, azimuth: float) -> None:
    pts, vp, plane, mesh = true_view(name, azimuth)
    done = complete_view(pts, vp, plane)
    assert np.array_equal(done.points[~done.assumed], pts)
    assert done.assumed.sum() > 0.3 * len(pts)
    # each copy is its source moved by the symmetry; the points that close holes lie between
    # two others, in a hole (no other point within a spacing)
    M = done.transform
    copy = done.copied
    src = done.source[copy]
    assert np.allclose(done.points[copy], pts[src] @ M[:3, :3].T + M[:3, 3])
    assert np.array_equal(done.moved, copy | (done.filled & done.moved))
    if done.filled.any():
        others = cKDTree(done.points[~done.filled])
        d, _ = others.query(done.points[done.filled])
        spacing = float(np.median(cKDTree(pts).query(pts, k=2)[0][:, 1]))
        assert d.min() > spacing and d.max() <= CompletionParams().gap_max
    assert np.array_equal(done.source[~done.assumed], np.arange(len(pts)))
    assert abs(abs(np.linalg.det(M[:3, :3])) - 1.0) < 1e-12
    lo, hi = done.points.min(axis=0), done.points.max(axis=0)
    err = np.abs(np.concatenate([lo - mesh.bounds[0], hi - mesh.bounds[1]]))
    assert err.max() < 0.004, err
    # more of the true surface (sampled; the underside and the inside of the walls cannot be
    # seen) lies within 3 mm of the completed cloud than of the visible part
    surface, _ = trimesh.sample.sample_surface(mesh, 5000, seed=1)
    cov_vis = np.mean(cKDTree(pts).query(surface)[0] < 0.003)
    cov_done = np.mean(cKDTree(done.points).query(surface)[0] < 0.003)
    assert cov_done > cov_vis + 0.1, (cov_vis, cov_done)
    # assumed points lie near the true surface (the symmetry holds for these objects)
    d = np.abs(trimesh.proximity.signed_distance(mesh, done.points[done.assumed][::10]))
    assert np.median(d) < 0.003


def test_prepare_view_carries_viewpoint_plane_and_normals() -> None:
    mesh = trimesh.load(OBJECTS_DIR / "box_cereal.obj", force="mesh")
    T = orbit_camera(np.array([0.0, 0.0, 0.075]), 0.55, np.radians(150.0), np.radians(35.0))
    view = render_view(mesh.vertices, mesh.faces, T, Intrinsics(420.0, 420.0, 239.5, 179.5),
                       480, 360, table_half=0.3)  # fmt: skip
    pts, lab = view.points_world()
    sv = prepare_view(pts, T[:3, 3], outliers=(16, 3.0))
    assert sv.kept.sum() > 0.97 * len(pts)
    assert np.array_equal(sv.viewpoint, T[:3, 3])
    assert sv.plane.normal[2] > 0.9999 and abs(sv.plane.height) < 1e-6
    assert sv.assumed.any() and sv.n_visible == int(sv.segmentation.object_mask.sum())
    fm = sv.face_mask_params()
    assert fm.support and np.allclose(fm.up, sv.plane.normal) and fm.support_height is not None
    # normals: the visible ones pass through, the assumed ones follow their source's symmetry;
    # the box's true outward face normals, moved by the symmetry, stay the true ones
    visible = sv.points[~sv.assumed]
    _, _, tri = trimesh.proximity.closest_point(mesh, visible)
    nv = mesh.face_normals[tri]
    full = sv.full_normals(nv)
    assert np.array_equal(full[~sv.assumed], nv)
    _, _, tri_a = trimesh.proximity.closest_point(mesh, sv.points[sv.assumed])
    agree = np.einsum("ij,ij->i", full[sv.assumed], mesh.face_normals[tri_a]) > 0.9
    assert agree.mean() > 0.9
    with pytest.raises(ValueError, match="visible_normals must have shape"):
        sv.full_normals(nv[:-1])
    flat = prepare_view(pts, T[:3, 3], complete=False)
    assert flat.completion is None and not flat.assumed.any()


def test_pcd_viewpoint(tmp_path: Path) -> None:
    T = orbit_camera(np.array([0.0, 0.0, 0.05]), 0.6, 1.0, 0.5)
    qx, qy, qz, qw = Rotation.from_matrix(T[:3, :3]).as_quat()
    head = "VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 1\nHEIGHT 1\n"
    p = tmp_path / "v.pcd"
    p.write_text(head + f"VIEWPOINT {T[0, 3]} {T[1, 3]} {T[2, 3]} {qw} {qx} {qy} {qz}\n"
                 "POINTS 1\nDATA ascii\n0 0 0\n")  # fmt: skip
    assert np.allclose(pcd_viewpoint(p), T)
    p.write_text(head + "VIEWPOINT 0 0 0 1 0 0 0\nPOINTS 1\nDATA ascii\n0 0 0\n")
    assert pcd_viewpoint(p) is None
    p.write_text(head + "POINTS 1\nDATA ascii\n0 0 0\n")
    assert pcd_viewpoint(p) is None
    p.write_text(head + "VIEWPOINT 0 0 1\nPOINTS 1\nDATA ascii\n0 0 0\n")
    with pytest.raises(InputError, match=r"v\.pcd: VIEWPOINT must hold 7 numbers"):
        pcd_viewpoint(p)


def test_completion_input_checks() -> None:
    plane = SupportPlane(np.array([0.0, 0.0, 1.0]), 0.0)
    pts = np.random.default_rng(0).uniform(0, 0.05, (100, 3))
    with pytest.raises(ValueError, match="not above the support plane"):
        complete_view(pts, (0, 0, -1), plane)
    with pytest.raises(ValueError, match="viewpoint must be"):
        complete_view(pts, (0, 0), plane)
    with pytest.raises(ValueError, match="tolerance"):
        CompletionParams(tolerance=-1.0)


@pytest.mark.parametrize(("radius", "azimuth"), [(0.01, 200.0), (0.0125, 40.0)])
def test_a_small_part_on_a_noisy_table_is_not_lost_to_the_tables_noise(
    radius: float, azimuth: float
) -> None:
    """A ball 20 or 25 mm across on the table, seen at 2 mm of range noise under a random rigid
    motion: the table's Gaussian tail that clears the noise band chains into a cluster larger
    than the ball (hundreds of points spread over the whole table), which used to be taken as
    the object. Such a cluster holds a few points per hundred table points inside its
    footprint, an object far more than one (it hides the table under it), so the segmentation
    sets it aside: the object is the ball, by the renderer's labels and the true sphere."""
    ball = trimesh.creation.icosphere(subdivisions=3, radius=radius)
    ball.apply_translation([0.0, 0.0, radius])
    T = orbit_camera(np.zeros(3), 0.45, np.radians(azimuth), np.radians(35.0))
    view = render_view(ball.vertices, ball.faces, T, Intrinsics(420.0, 420.0, 239.5, 179.5),
                       480, 360, table_half=0.31, noise=0.002,
                       rng=np.random.default_rng(7))  # fmt: skip
    p, lab = view.points_world()
    R = Rotation.random(random_state=11).as_matrix()
    t = np.array([0.2, 0.4, -1.0])
    pts, vp = p @ R.T + t, T[:3, 3] @ R.T + t
    true_ball = lab == LABEL_OBJECT
    # the noise tail is there: without the footprint test the object is mostly not the ball
    plain = segment_table(pts, viewpoint=vp, params=SegmentParams(noise_cover=0.0))
    assert np.sum(plain.object_mask & ~true_ball) > np.sum(true_ball)
    seg = segment_table(pts, viewpoint=vp)
    got = seg.object_mask
    assert np.sum(got & true_ball) >= 0.6 * np.sum(true_ball)  # its bottom is in the band
    # what else it holds is the ball's foot in the band, not the table's noise far away
    centre = np.array([0.0, 0.0, radius]) @ R.T + t
    off = np.linalg.norm(pts[got & ~true_ball] - centre, axis=1) - radius
    assert np.all(off < 0.02), off.max()  # the noise cluster spans the table (0.2-0.3 m)


def test_a_picked_small_part_in_clutter_does_not_take_in_its_larger_neighbour() -> None:
    """A can, a 4 cm ball, a small box and a pen lying down, 4-5 cm apart, seen from above at
    40 degrees: the pen is partly hidden behind the can. Picking the pen used to give the can
    and the pen as one object (the hidden-gap merge: their images touch with no table seen
    between them); a picked part now takes in only clusters no larger than itself, so the pick
    gives the pen, the box or the ball alone, by the true meshes. Without a pick the object is
    still the largest cluster, the can."""
    parts = clutter_meshes()
    scene_mesh = trimesh.util.concatenate(list(parts.values()))
    T = orbit_camera(np.zeros(3), 0.55, np.radians(30.0), np.radians(40.0))
    view = render_view(scene_mesh.vertices, scene_mesh.faces, T,
                       Intrinsics(420.0, 420.0, 239.5, 179.5), 480, 360, table_half=0.35,
                       noise=0.001, rng=np.random.default_rng(1))  # fmt: skip
    pts, _ = view.points_world()
    vp = T[:3, 3]

    def on(mesh: trimesh.Trimesh, p: np.ndarray) -> float:
        return float(np.mean(np.abs(trimesh.proximity.signed_distance(mesh, p)) < 0.006))

    largest = segment_table(pts, viewpoint=vp).object_points
    assert on(parts["can"], largest) > 0.8
    for name in ("pen", "box", "ball"):
        got = segment_table(pts, viewpoint=vp, pick=parts[name].bounds.mean(axis=0))
        assert on(parts[name], got.object_points) > 0.95, name
        assert on(parts["can"], got.object_points) < 0.02, name


@pytest.mark.parametrize(("azimuth", "moved"), [(250.0, False), (290.0, True)])
def test_two_objects_standing_on_the_table_stay_two_when_one_hides_the_other(
    azimuth: float, moved: bool
) -> None:
    """A can 3 cm in front of a taller box, seen low (25 degrees) so that the can hides the
    box's lower middle: their images touch with no table seen between them, the hidden-gap
    rule's sign of one object cut by its own occlusion. Both stand on the table, so they are
    two objects (``SegmentParams.stand_height``): picking either gives it alone, by the true
    meshes, also under a random rigid motion of the scene; with the rule off the picked box
    takes in the can (40-50 % of its points, measured)."""
    can = trimesh.creation.cylinder(0.033, 0.10, sections=48)
    can.apply_translation((0.0, 0.0, 0.05))
    box = trimesh.creation.box((0.09, 0.07, 0.15))
    box.apply_translation((0.0, 0.095, 0.075))
    scene_mesh = trimesh.util.concatenate([can, box])
    T = orbit_camera(np.array([0.0, 0.05, 0.05]), 0.6, np.radians(azimuth), np.radians(25.0))
    view = render_view(scene_mesh.vertices, scene_mesh.faces, T,
                       Intrinsics(420.0, 420.0, 239.5, 179.5), 480, 360, table_half=0.4,
                       noise=0.001, rng=np.random.default_rng(2))  # fmt: skip
    world, _ = view.points_world()
    R, t = np.eye(3), np.zeros(3)
    if moved:
        R, t = Rotation.random(random_state=5).as_matrix(), np.array([0.2, -0.4, 0.9])
    pts, vp = world @ R.T + t, T[:3, 3] @ R.T + t

    def on(mesh: trimesh.Trimesh, p: np.ndarray) -> float:
        back = (p - t) @ R  # into the meshes' frame
        return float(np.mean(np.abs(trimesh.proximity.signed_distance(mesh, back)) < 0.006))

    for mesh, other in ((box, can), (can, box)):
        pick = mesh.bounds.mean(axis=0) @ R.T + t
        got = segment_table(pts, viewpoint=vp, pick=pick).object_points
        assert on(mesh, got) > 0.99 and on(other, got) < 0.01
    old = SegmentParams(stand_height=0.0)
    merged = segment_table(pts, viewpoint=vp, pick=box.bounds.mean(axis=0) @ R.T + t, params=old)
    assert on(can, merged.object_points) > 0.3


def _wall_scene(objects: dict[str, trimesh.Trimesh], wall_y: float, elevation: float, seed: int):
    """A depth view of ``objects`` on the table z = 0 with a wall y = ``wall_y`` behind them
    (3 m wide, 1.7 m high, from 0.2 m under the table), seen from -y at ``elevation`` degrees
    and 1 mm of noise, under a random rigid motion. Returns (points, viewpoint, rotation,
    translation, world-frame points): the true geometry stays with the caller."""
    wall = trimesh.creation.box((3.0, 0.001, 1.7))
    wall.apply_translation((0.0, wall_y + 0.0005, 0.65))
    scene_mesh = trimesh.util.concatenate([*objects.values(), wall.subdivide_to_size(0.05)])
    T = orbit_camera(np.array([0.0, 0.0, 0.05]), 0.6, np.radians(270.0), np.radians(elevation))
    view = render_view(scene_mesh.vertices, scene_mesh.faces, T,
                       Intrinsics(420.0, 420.0, 239.5, 179.5), 480, 360, table_half=1.0,
                       noise=0.001, rng=np.random.default_rng(seed))  # fmt: skip
    p, _ = view.points_world()
    R = Rotation.random(random_state=seed).as_matrix()
    t = np.array([0.3, -0.2, 0.8])
    return p @ R.T + t, T[:3, 3] @ R.T + t, R, t, p


def _near(mesh: trimesh.Trimesh, p: np.ndarray, tol: float = 0.005) -> np.ndarray:
    """(N,) bool: the points within ``tol`` of the true surface of ``mesh`` (trimesh's
    distance, on the points inside its bounding box grown by ``tol``)."""
    out = np.zeros(len(p), dtype=bool)
    box = np.all((p > mesh.bounds[0] - tol) & (p < mesh.bounds[1] + tol), axis=1)
    out[box] = np.abs(trimesh.proximity.signed_distance(mesh, p[box])) < tol
    return out


@pytest.mark.parametrize(
    ("wall_y", "elevation"),
    [(0.3, 35.0), (0.1, 35.0), (0.1, 20.0)],
    ids=["far wall", "near wall", "low camera, more wall than table"],
)
def test_a_wall_behind_the_table_is_set_aside_and_the_object_kept(wall_y, elevation) -> None:
    """The mug with a handle on a table against a wall, seen by a depth camera: the wall's
    points outnumber the mug's tenfold and, seen from a low camera, the table's too (the plane
    search finds the wall first). The table comes out within 1 degree and 2 mm of z = 0, the
    object holds at least 99 % of the mug's points above the band (by the true mesh) and not
    one point of the wall, which is reported as a background plane about as long as the wall
    is seen (wider than any object)."""
    mug = trimesh.load(OBJECTS_DIR / "mug_handle.obj", force="mesh")
    pts, vp, R, t, world = _wall_scene({"mug": mug}, wall_y, elevation, seed=5)
    on_wall = np.abs(world[:, 1] - wall_y) < 0.005
    on_mug = _near(mug, world) & (world[:, 2] > 0.004)
    assert on_wall.sum() > 10 * on_mug.sum()
    if elevation < 30.0:  # the case: more wall than table
        assert on_wall.sum() > np.sum(np.abs(world[:, 2]) < 0.003)
    seg = segment_table(pts, viewpoint=vp)
    n_true = R @ np.array([0.0, 0.0, 1.0])
    angle = np.degrees(np.arccos(np.clip(seg.plane.normal @ n_true, -1.0, 1.0)))
    assert angle < 1.0 and abs(seg.plane.height - n_true @ t) < 0.002, (angle, seg.plane)
    got = seg.object_mask
    assert np.sum(got & on_mug) >= 0.99 * on_mug.sum()
    assert not np.any(got & on_wall)
    assert len(seg.background) >= 1 and seg.background_mask is not None
    wall = seg.background[0]
    assert abs(abs(np.asarray(wall.normal) @ (R @ np.array([0.0, 1.0, 0.0]))) - 1.0) < 1e-3
    assert wall.span > 0.5 and np.sum(seg.background_mask & on_wall) > 0.9 * on_wall.sum()


def test_an_object_leaning_on_the_wall_is_kept_without_the_wall() -> None:
    """A box (10 x 5 x 15 cm) standing against the wall, touching it: one cluster with the
    wall until the wall's plane is set aside; the object is then the box (at least 97 % of its
    points above the band, by the true mesh), with nothing of the wall farther than its noise
    band from the plane the box touches."""
    box = trimesh.creation.box((0.1, 0.05, 0.15))
    box.apply_translation((0.0, 0.125, 0.075))  # its back face on the wall y = 0.15
    pts, vp, R, t, world = _wall_scene({"box": box}, 0.15, 35.0, seed=8)
    on_box = _near(box, world) & (world[:, 2] > 0.004) & (world[:, 1] < 0.145)
    seg = segment_table(pts, viewpoint=vp)
    got = seg.object_mask
    assert np.sum(got & on_box) >= 0.97 * on_box.sum()
    stray = got & ~_near(box, world)
    assert np.all(world[stray, 1] > 0.145), world[stray].min(axis=0)  # only the wall's band


def test_a_long_narrow_object_on_the_table_is_not_background() -> None:
    """A 60 cm ruler (3 cm wide, 1 cm thick) lying on the table, with no wall: longer than
    ``background_span`` but narrower than ``background_width``, so it stays the object (all of
    its points above the band); a 60 x 40 cm board there is background, and with nothing else
    on the table it is kept as the cluster it is (nothing is thrown away)."""
    ruler = trimesh.creation.box((0.6, 0.03, 0.01))
    ruler.apply_translation((0.0, 0.0, 0.005))
    T = orbit_camera(np.zeros(3), 0.8, np.radians(250.0), np.radians(50.0))
    kw = dict(intrinsics=Intrinsics(420.0, 420.0, 239.5, 179.5), width=480, height=360,
              table_half=0.6, noise=0.001)  # fmt: skip
    view = render_view(ruler.vertices, ruler.faces, T, rng=np.random.default_rng(2), **kw)
    p, lab = view.points_world()
    seg = segment_table(p, viewpoint=T[:3, 3])
    above = (lab == LABEL_OBJECT) & (p[:, 2] > 0.004)
    assert not seg.background and np.all(seg.object_mask[above])
    board = trimesh.creation.box((0.6, 0.4, 0.01))
    board.apply_translation((0.0, 0.0, 0.005))
    view = render_view(board.vertices, board.faces, T, rng=np.random.default_rng(2), **kw)
    p, lab = view.points_world()
    seg = segment_table(p, viewpoint=T[:3, 3])
    above = (lab == LABEL_OBJECT) & (p[:, 2] > 0.004)
    assert not seg.background and np.sum(seg.object_mask[above]) > 0.95 * above.sum()
