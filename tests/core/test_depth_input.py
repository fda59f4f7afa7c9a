"""Depth-camera input through ``load_point_cloud``: depth images with intrinsics, PCD scenes with
a ``VIEWPOINT``, ``pick``, millimetre clouds, and the pipeline's use of the viewpoint.

References: the scenes are rendered by ray casting (``pregrasp_core.sensor.synthetic``) from
trimesh boxes on the table z = 0, so the true table, the true objects and the camera are known
outside the loader; the committed demo ``assets/objects/mug_depth.png`` was rendered the same way
(``scripts/make_views.py --demo``) with the camera pose in ``mug_depth.json``.
"""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from pregrasp_core.errors import InputError
from pregrasp_core.io import SensorOptions, load_point_cloud
from pregrasp_core.paths import OBJECTS_DIR
from pregrasp_core.pipeline import PipelineParams, view_normals, with_cloud
from pregrasp_core.sensor import Intrinsics
from pregrasp_core.sensor.synthetic import orbit_camera, render_view

K = Intrinsics(300.0, 300.0, 159.5, 119.5)
DEMO = OBJECTS_DIR / "mug_depth.png"


def write_scene_pcd(path: Path, points: np.ndarray, T: np.ndarray) -> None:
    """An ascii PCD of ``points`` with the camera pose ``T`` as VIEWPOINT."""
    qx, qy, qz, qw = Rotation.from_matrix(T[:3, :3]).as_quat()
    tx, ty, tz = T[:3, 3]
    head = (
        "VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\n"
        f"WIDTH {len(points)}\nHEIGHT 1\n"
        f"VIEWPOINT {tx:.9g} {ty:.9g} {tz:.9g} {qw:.9g} {qx:.9g} {qy:.9g} {qz:.9g}\n"
        f"POINTS {len(points)}\nDATA ascii\n"
    )
    body = "\n".join(" ".join(f"{v:.6f}" for v in p) for p in points)
    path.write_text(head + body + "\n")


def two_boxes() -> tuple[trimesh.Trimesh, np.ndarray, np.ndarray]:
    """A large and a small box on z = 0, 15 cm apart; their centres."""
    big = trimesh.creation.box((0.08, 0.06, 0.12))
    big.apply_translation((0.0, 0.0, 0.06))
    small = trimesh.creation.box((0.04, 0.04, 0.05))
    small.apply_translation((0.0, 0.15, 0.025))
    return (
        trimesh.util.concatenate([big, small]),
        np.array([0, 0, 0.06]),
        np.array([0, 0.15, 0.025]),
    )


def render(mesh: trimesh.Trimesh) -> tuple[np.ndarray, np.ndarray]:
    T = orbit_camera(np.array([0.0, 0.07, 0.05]), 0.7, np.radians(20.0), np.radians(40.0))
    view = render_view(mesh.vertices, mesh.faces, T, K, 320, 240, table_half=0.4)
    pts, _ = view.points_world()
    return pts, T


@pytest.fixture(scope="module")
def scene_pcd(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, np.ndarray]:
    mesh, _, _ = two_boxes()
    pts, T = render(mesh)
    path = tmp_path_factory.mktemp("scene") / "boxes.pcd"
    write_scene_pcd(path, pts, T)
    return path, T


def test_demo_depth_png_reads_its_sidecar_and_pose() -> None:
    cloud = load_point_cloud(DEMO)
    doc = json.loads(DEMO.with_suffix(".json").read_text())
    T = np.asarray(doc["T_world_camera"])
    np.testing.assert_allclose(cloud.viewpoint, T[:3, 3])
    sc = cloud.info["scene"]
    assert cloud.info["kind"] == "depth" and sc["n_table"] > 50_000
    # the demo's table is z = 0 of the JSON's world frame
    assert abs(sc["plane"]["height"]) < 1e-3 and sc["plane"]["normal"][2] > 0.9998
    assert cloud.assumed is not None and sc["n_assumed"] == int(cloud.assumed.sum()) > 0
    assert sc["n_visible"] + sc["n_assumed"] == cloud.n_points
    # table removed: the object stands on it, nothing lies below it
    assert cloud.points[:, 2].min() > -0.003
    assert np.count_nonzero(cloud.points[:, 2] < 0.002) < 0.05 * cloud.n_points


def test_pcd_viewpoint_scene_removes_table_and_gives_support_plane(scene_pcd) -> None:
    path, T = scene_pcd
    cloud = load_point_cloud(path)
    np.testing.assert_allclose(cloud.viewpoint, T[:3, 3], atol=1e-6)
    assert cloud.info["scene"]["n_table"] > 10_000
    _, big, _ = two_boxes()
    visible = cloud.points[~cloud.assumed]
    # the largest object is kept: the big box's visible points, none of the small one
    assert np.all(np.abs(visible[:, 1] - big[1]) < 0.035)
    params = with_cloud(PipelineParams(), cloud)
    assert params.facemask.support
    assert np.degrees(np.arccos(min(1.0, params.facemask.up[2]))) < 0.5
    assert abs(params.facemask.support_height) < 1e-3
    assert params.planner.normals.viewpoint == pytest.approx(tuple(T[:3, 3]))
    # the normals of what the camera saw face it
    n = view_normals(cloud, params.planner.normals)
    seen = ~cloud.assumed
    to_cam = cloud.viewpoint - cloud.points[seen]
    assert np.all(np.einsum("ij,ij->i", n[seen], to_cam) >= 0.0)
    # an explicit support height is kept
    fixed = with_cloud(
        PipelineParams(facemask=params.facemask.__class__(support_height=0.01)), cloud
    )
    assert fixed.facemask.support_height == 0.01


def test_an_uploaded_pcd_scene_is_read_as_its_file(scene_pcd) -> None:
    """The viewer's upload (the bytes and the file's name) reads the VIEWPOINT as the path
    does: the same scene, table removed, the same camera (before, an upload's VIEWPOINT was
    ignored: the table and both boxes became one object with normals by visibility)."""
    from pregrasp_core.io import load_point_cloud_bytes

    path, T = scene_pcd
    by_path = load_point_cloud(path)
    up = load_point_cloud_bytes(path.read_bytes(), "boxes.pcd")
    np.testing.assert_allclose(up.viewpoint, T[:3, 3], atol=1e-6)
    assert up.info["scene"] == by_path.info["scene"]
    assert np.array_equal(up.points, by_path.points)


def test_pick_selects_the_other_object(scene_pcd) -> None:
    path, _ = scene_pcd
    _, _, small = two_boxes()
    cloud = load_point_cloud(path, sensor=SensorOptions(pick=tuple(small)))
    visible = cloud.points[~cloud.assumed]
    assert np.all(np.linalg.norm(visible[:, :2] - small[:2], axis=1) < 0.035)
    assert visible[:, 2].max() < 0.052


def test_no_scene_keeps_every_point_and_the_viewpoint(scene_pcd) -> None:
    path, T = scene_pcd
    cloud = load_point_cloud(path, n_points=None, sensor=SensorOptions(scene=False))
    assert "scene" not in cloud.info and cloud.sensor is None
    assert cloud.n_points == cloud.info["n_read"]
    np.testing.assert_allclose(cloud.viewpoint, T[:3, 3], atol=1e-6)


def test_a_view_of_an_object_cut_out_of_its_scene_is_read_as_one_object(tmp_path) -> None:
    """A PCD view (with its VIEWPOINT) of the large box with the table's points cut away, as a
    user crops a depth camera's cloud: the table search finds a plane through the box, with
    points behind it, which no table has; the scene was only inferred from the VIEWPOINT, so
    the points are read as one object seen from the camera (the same cloud as ``scene=False``)
    with a warning, and its normals face the camera. Asked for as a scene, it is an error that
    says there is no table (before: "nothing stands above the table", with no way out in the
    viewer, which reads every PCD with a VIEWPOINT as a scene)."""
    from pregrasp_core.sensor import NoTableError
    from pregrasp_core.sensor.synthetic import LABEL_OBJECT

    big = trimesh.creation.box((0.08, 0.06, 0.12))
    big.apply_translation((0.0, 0.0, 0.06))
    T = orbit_camera(np.array([0.0, 0.0, 0.06]), 0.6, np.radians(30.0), np.radians(35.0))
    view = render_view(big.vertices, big.faces, T, K, 320, 240, table_half=0.4)
    pts, lab = view.points_world()
    obj = pts[lab == LABEL_OBJECT]
    path = tmp_path / "box_alone.pcd"
    write_scene_pcd(path, obj, T)
    cloud = load_point_cloud(path, n_points=2000)
    assert "scene" not in cloud.info and cloud.sensor is None
    np.testing.assert_allclose(cloud.viewpoint, T[:3, 3], atol=1e-6)
    said = [w for w in cloud.info["warnings"] if "no table in the view" in w]
    assert len(said) == 1 and "read as one object seen from the camera" in said[0]
    plain = load_point_cloud(path, n_points=2000, sensor=SensorOptions(scene=False))
    assert np.array_equal(cloud.points, plain.points)
    params = with_cloud(PipelineParams(), cloud)
    n = view_normals(cloud, params.planner.normals)
    assert np.all(np.einsum("ij,ij->i", n, cloud.viewpoint - cloud.points) >= 0.0)
    with pytest.raises(NoTableError, match=r"box_alone\.pcd: .*no table in the view"):
        load_point_cloud(path, sensor=SensorOptions(scene=True))
    # the whole view, table included, is still a scene
    whole = tmp_path / "box_scene.pcd"
    write_scene_pcd(whole, pts, T)
    assert load_point_cloud(whole).info["scene"]["n_table"] > 10_000


def test_millimetre_cloud_is_scaled_with_a_notice(tmp_path: Path) -> None:
    metres = load_point_cloud(OBJECTS_DIR / "mug_handle.obj", n_points=5000)
    assert metres.info["warnings"] == []
    path = tmp_path / "mug_mm.xyz"
    np.savetxt(path, np.asarray(metres.points) * 1000.0)
    cloud = load_point_cloud(path)
    assert cloud.info["scale"] == 0.001
    assert any("millimetres" in w and "--scale" in w for w in cloud.info["warnings"])
    np.testing.assert_allclose(cloud.points, metres.points, atol=1e-6)
    kept = load_point_cloud(path, scale=1.0)  # an explicit scale wins
    assert kept.info["scale"] == 1.0 and kept.extents.max() > 50.0


def test_npy_depth_map_with_intrinsics_and_npy_cloud_without(tmp_path: Path) -> None:
    mesh, _, _ = two_boxes()
    T = orbit_camera(np.array([0.0, 0.07, 0.05]), 0.7, np.radians(20.0), np.radians(40.0))
    depth = render_view(mesh.vertices, mesh.faces, T, K, 320, 240, table_half=0.4).depth
    path = tmp_path / "frame.npy"
    np.save(path, depth)
    with pytest.raises(InputError, match="column count"):  # no intrinsics: a point cloud
        load_point_cloud(path)
    intr = (K.fx, K.fy, K.cx, K.cy)
    cloud = load_point_cloud(path, sensor=SensorOptions(intrinsics=intr))
    assert cloud.info["format"] == "npy" and cloud.info["kind"] == "depth"
    np.testing.assert_allclose(cloud.viewpoint, 0.0)  # camera frame without a pose
    # in the camera frame the table's normal points back toward the camera (up in the world)
    n_cam = np.asarray(cloud.info["scene"]["plane"]["normal"])
    np.testing.assert_allclose(T[:3, :3] @ n_cam, [0, 0, 1], atol=1e-3)


def test_bad_intrinsics_name_the_flag_or_file(tmp_path: Path) -> None:
    png = tmp_path / "alone.png"
    shutil.copy(DEMO, png)
    with pytest.raises(InputError, match=r"alone\.png: .*--intrinsics FX FY CX CY.*alone\.json"):
        load_point_cloud(png)
    with pytest.raises(InputError, match=r"alone\.png: --intrinsics: .*four numbers"):
        load_point_cloud(png, sensor=SensorOptions(intrinsics=(420.0, 420.0, 239.5)))
    bad = tmp_path / "bad.json"
    bad.write_text('{"fx": 420, "fy": 420, "cx": 239.5}')
    with pytest.raises(InputError, match=r"bad\.json: the intrinsics lack cy"):
        load_point_cloud(png, sensor=SensorOptions(intrinsics=bad))
    wrong = tmp_path / "wrong.json"
    wrong.write_text('{"fx": 420, "fy": 420, "cx": 239.5, "cy": 179.5, "width": 64, "height": 48}')
    with pytest.raises(InputError, match=r"wrong\.json says 64 x 48"):
        load_point_cloud(png, sensor=SensorOptions(intrinsics=wrong))


# ---------------------------------------------------------------------- the camera file (sidecar)
def _demo_copy(tmp_path: Path, name: str, doc: object | None = None, text: str | None = None):
    """The demo PNG copied as ``name``.png with a sidecar ``name``.json: the demo's own (``doc``
    None), the JSON of ``doc``, or the raw ``text``."""
    png = tmp_path / f"{name}.png"
    shutil.copy(DEMO, png)
    side = png.with_suffix(".json")
    if text is not None:
        side.write_text(text)
    elif doc is not None:
        side.write_text(json.dumps(doc))
    else:
        shutil.copy(DEMO.with_suffix(".json"), side)
    return png, side


def _raw(path: Path, **kw) -> np.ndarray:
    """Every point of the depth image (no table removal, no subsampling)."""
    return np.asarray(
        load_point_cloud(path, n_points=None, sensor=SensorOptions(scene=False, **kw)).points
    )


DEMO_DOC = json.loads(DEMO.with_suffix(".json").read_text())


def test_sidecar_is_read_beside_the_image_and_recorded(tmp_path: Path) -> None:
    png, side = _demo_copy(tmp_path, "frame")
    cloud = load_point_cloud(png, n_points=None, sensor=SensorOptions(scene=False))
    dep = cloud.info["depth"]
    assert dep["camera_file"] == str(side) and dep["intrinsics_from"] == str(side)
    assert dep["pose"] and dep["depth_scale"] == 0.001
    assert dep["intrinsics"] == {k: DEMO_DOC[k] for k in ("fx", "fy", "cx", "cy")}
    # the pixels back-projected by hand with the sidecar's numbers and pose (the reference)
    import imageio.v3 as iio

    img = iio.imread(DEMO)
    rows, cols = np.nonzero(img)
    z = img[rows, cols] / 1000.0
    cam = np.stack([(cols - DEMO_DOC["cx"]) * z / DEMO_DOC["fx"],
                    (rows - DEMO_DOC["cy"]) * z / DEMO_DOC["fy"], z], axis=1)  # fmt: skip
    T = np.asarray(DEMO_DOC["T_world_camera"])
    np.testing.assert_allclose(cloud.points, cam @ T[:3, :3].T + T[:3, 3], atol=1e-12)
    np.testing.assert_allclose(cloud.viewpoint, T[:3, 3])


def test_intrinsics_numbers_override_the_sidecar_and_keep_its_pose(tmp_path: Path) -> None:
    png, _ = _demo_copy(tmp_path, "frame")
    base = _raw(png)
    same = (DEMO_DOC["fx"], DEMO_DOC["fy"], DEMO_DOC["cx"], DEMO_DOC["cy"])
    np.testing.assert_array_equal(_raw(png, intrinsics=same), base)
    # twice the focal lengths: in the camera frame x and y halve, z stays (the pose kept)
    double = (2 * same[0], 2 * same[1], same[2], same[3])
    cloud = load_point_cloud(
        png, n_points=None, sensor=SensorOptions(scene=False, intrinsics=double)
    )
    assert cloud.info["depth"]["intrinsics_from"] == "--intrinsics (with the rest of frame.json)"
    T = np.asarray(DEMO_DOC["T_world_camera"])
    to_cam = lambda p: (p - T[:3, 3]) @ T[:3, :3]  # noqa: E731
    np.testing.assert_allclose(
        to_cam(np.asarray(cloud.points)), to_cam(base) * [0.5, 0.5, 1], atol=1e-12
    )
    # a JSON file given replaces the sidecar: here one without a pose (camera frame)
    other = tmp_path / "other.json"
    other.write_text(json.dumps({k: DEMO_DOC[k] for k in ("fx", "fy", "cx", "cy")}))
    np.testing.assert_allclose(_raw(png, intrinsics=other), to_cam(base), atol=1e-12)


def test_depth_scale_of_the_sidecar(tmp_path: Path) -> None:
    """A PNG in 0.1 mm units with ``depth_scale`` 0.0001 gives the demo's cloud."""
    import imageio.v3 as iio

    img = iio.imread(DEMO)
    assert img.max() < 6553  # fits in 16 bits at 0.1 mm
    png = tmp_path / "fine.png"
    iio.imwrite(png, (img * 10).astype(np.uint16))
    png.with_suffix(".json").write_text(json.dumps({**DEMO_DOC, "depth_scale": 0.0001}))
    np.testing.assert_allclose(_raw(png), _raw(DEMO), atol=1e-12)
    cloud = load_point_cloud(png, n_points=None, sensor=SensorOptions(scene=False))
    assert cloud.info["depth"]["depth_scale"] == 0.0001


def test_an_uploaded_camera_file_gives_the_cloud_of_the_file_on_disk() -> None:
    from pregrasp_core.io import load_point_cloud_bytes
    from pregrasp_core.sensor import CameraFile

    side = DEMO.with_suffix(".json")
    cam = CameraFile.parse(side.read_bytes(), "mug_depth.json")
    up = load_point_cloud_bytes(DEMO.read_bytes(), "mug_depth.png", n_points=4000,
                                sensor=SensorOptions(intrinsics=cam))  # fmt: skip
    disk = load_point_cloud(DEMO, n_points=4000)
    np.testing.assert_array_equal(up.points, disk.points)
    np.testing.assert_array_equal(up.assumed, disk.assumed)
    assert up.info["scene"] == disk.info["scene"]
    with pytest.raises(InputError, match=r"mug_depth\.png: a depth image needs .*intrinsics"):
        load_point_cloud_bytes(DEMO.read_bytes(), "mug_depth.png")  # nothing beside an upload


K_KEYS = ("fx", "fy", "cx", "cy")
GOOD = {k: DEMO_DOC[k] for k in (*K_KEYS, "width", "height")}


@pytest.mark.parametrize(
    ("doc", "text", "match"),
    [
        ({**GOOD, "fx": "420"}, None, "fx must be a number, got '420'"),
        ({**GOOD, "fy": 0}, None, "fx and fy must be positive focal lengths in pixels, got fy=0"),
        (None, '{"fx": 420, "fy": 420, "cx": 239.5, "cy": NaN}', "cy must be finite"),
        ({k: GOOD[k] for k in K_KEYS[:3]}, None, "the intrinsics lack cy"),
        ({**GOOD, "fz": 1}, None, r"unknown intrinsics keys \['fz'\]"),
        ({**GOOD, "viewpoint": [0, 0, 1]}, None, "viewpoint: .*pose as T_world_camera"),
        ({**GOOD, "width": 480.5}, None, "width and height must be positive integers"),
        ({**{k: GOOD[k] for k in K_KEYS}, "width": 480}, None, "give both width and height"),
        ({**GOOD, "width": 640, "height": 480}, None, "frame.json says 640 x 480"),
        ({**GOOD, "T_world_camera": np.eye(3).tolist()}, None, "T_world_camera must be a finite 4"),
        ({**GOOD, "T_world_camera": (2 * np.eye(4)).tolist()}, None, "not a proper rotation"),
        ({**GOOD, "T_world_camera": "up"}, None, "T_world_camera must be a 4 x 4 array of numbers"),
        ({**GOOD, "depth_scale": 1000}, None, "depth_scale is metres per .*write 0.001"),
        ({**GOOD, "depth_scale": -0.001}, None, "depth_scale must be positive"),
        ({**GOOD, "depth_scale": True}, None, "depth_scale must be a number"),
        (None, '{"fx": 420, "fx": 421, "fy": 1, "cx": 2, "cy": 3}', "key 'fx' given twice"),
        (None, "[" * 100_000, "not a JSON file"),
        (None, '{"fx": 420,', "not a JSON file"),
        ([420, 420, 239.5, 179.5], None, "must be a JSON object with keys fx, fy, cx, cy"),
    ],
)  # fmt: skip
def test_a_bad_sidecar_is_one_error_naming_the_file_and_the_field(
    tmp_path: Path, doc: object, text: str | None, match: str
) -> None:
    png, side = _demo_copy(tmp_path, "frame", doc, text)
    with pytest.raises(InputError) as err:
        load_point_cloud(png)
    msg = str(err.value)
    assert "\n" not in msg and re.search(match, msg), msg
    assert str(side) in msg  # the sidecar named (the size mismatch names the image too)


def test_a_sidecar_that_is_not_utf8_or_too_large(tmp_path: Path) -> None:
    png, side = _demo_copy(tmp_path, "frame")
    side.write_bytes(b'{"fx": 420\xff}')
    with pytest.raises(InputError, match=r"frame\.json: not a JSON file"):
        load_point_cloud(png)
    side.write_bytes(b" " * (2 << 20))
    with pytest.raises(InputError, match=r"frame\.json: .* bytes, more than"):
        load_point_cloud(png)


# ------------------------------------------------------------------------------------------------
# Camera files as other tools write them (sensor/camera_layouts.py)


def _layouts(doc: dict) -> dict[str, dict]:
    """The demo's camera in the layouts of other tools, each written as that tool's
    documentation gives it (RealSense's rs2_intrinsics fields, ROS 1 and ROS 2
    sensor_msgs/CameraInfo, camera_calibration's file, Open3D's PinholeCameraIntrinsic and
    PinholeCameraParameters with their column-major matrices and world-to-camera extrinsic)."""
    fx, fy, cx, cy = (doc[k] for k in K_KEYS)
    w, h = doc["width"], doc["height"]
    T = doc["T_world_camera"]
    K = [fx, 0.0, cx, 0.0, fy, cy, 0.0, 0.0, 1.0]
    P = [fx, 0.0, cx, 0.0, 0.0, fy, cy, 0.0, 0.0, 0.0, 1.0, 0.0]
    eye = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
    o3d_K = np.asarray(K).reshape(3, 3).T.ravel().tolist()  # column-major
    extrinsic = np.linalg.inv(np.asarray(T)).T.ravel().tolist()  # world -> camera, column-major
    ros1 = {"header": {"seq": 0, "stamp": {"secs": 0, "nsecs": 0}, "frame_id": "depth_optical"},
            "height": h, "width": w, "distortion_model": "plumb_bob", "D": [0.0] * 5, "K": K,
            "R": eye, "P": P, "binning_x": 0, "binning_y": 0,
            "roi": {"x_offset": 0, "y_offset": 0, "height": 0, "width": 0, "do_rectify": False},
            "T_world_camera": T}  # fmt: skip
    return {
        "RealSense": {"width": w, "height": h, "ppx": cx, "ppy": cy, "fx": fx, "fy": fy,
                      "model": "distortion.brown_conrady", "coeffs": [0.0] * 5,
                      "depth_scale": 0.001, "T_world_camera": T},
        "ROS CameraInfo": ros1,
        "ROS 2 CameraInfo": {(k.lower() if len(k) == 1 else k): v for k, v in ros1.items()},
        "ROS calibration": {"image_width": w, "image_height": h, "camera_name": "depth",
                            "camera_matrix": {"rows": 3, "cols": 3, "data": K},
                            "distortion_model": "plumb_bob",
                            "distortion_coefficients": {"rows": 1, "cols": 5, "data": [0.0] * 5},
                            "rectification_matrix": {"rows": 3, "cols": 3, "data": eye},
                            "projection_matrix": {"rows": 3, "cols": 4, "data": P},
                            "T_world_camera": T},
        "Open3D": {"class_name": "PinholeCameraParameters", "extrinsic": extrinsic,
                   "intrinsic": {"width": w, "height": h, "intrinsic_matrix": o3d_K},
                   "version_major": 1, "version_minor": 0},
        "Open3D intrinsic": {"width": w, "height": h, "intrinsic_matrix": o3d_K,
                             "T_world_camera": T},
    }  # fmt: skip


@pytest.mark.parametrize("layout", list(_layouts(DEMO_DOC)))
def test_camera_files_of_other_tools_give_the_cloud_of_pregrasps_own(
    tmp_path: Path, layout: str
) -> None:
    """Each layout beside the demo image gives the points of pregrasp's own camera file (the
    same floats; Open3D's pose through the inverse of its extrinsic, to rounding), records
    its layout and has no note (its distortion is zero)."""
    png, _ = _demo_copy(tmp_path, "frame", _layouts(DEMO_DOC)[layout])
    cloud = load_point_cloud(png, n_points=None, sensor=SensorOptions(scene=False))
    (tmp_path / "own").mkdir()
    ref = _raw(_demo_copy(tmp_path / "own", "frame")[0])
    if layout == "Open3D":
        np.testing.assert_allclose(cloud.points, ref, rtol=0, atol=1e-12)
    else:
        np.testing.assert_array_equal(cloud.points, ref)
    name = layout.replace("ROS 2", "ROS").replace(" intrinsic", "")
    assert cloud.info["depth"]["camera_layout"] == name
    assert cloud.info["depth"]["intrinsics"] == {k: DEMO_DOC[k] for k in K_KEYS}
    assert not cloud.info["warnings"]


def test_distortion_of_another_tool_is_not_applied_and_says_so(tmp_path: Path) -> None:
    """Coefficients that are not zero: the same points as without them, and a warning naming
    the file and the coefficients."""
    docs = _layouts(DEMO_DOC)
    rs = {**docs["RealSense"], "coeffs": [0.12, -0.3, 0.0, 0.001, 0.0]}
    ros = {**docs["ROS CameraInfo"], "D": [0.1, -0.2, 0.0, 0.0, 0.05, 0.0, 0.0, 0.0]}
    base = _raw(_demo_copy(tmp_path, "frame")[0])
    for i, doc in enumerate((rs, ros)):
        png, side = _demo_copy(tmp_path, f"d{i}", doc)
        cloud = load_point_cloud(png, n_points=None, sensor=SensorOptions(scene=False))
        np.testing.assert_array_equal(cloud.points, base)
        (note,) = cloud.info["warnings"]
        assert note.startswith(f"{side}: the distortion ") and "is not applied" in note
        assert ("0.12" if i == 0 else "0.05") in note


def test_a_principal_point_pixel_of_a_ros_camera_lies_on_its_axis() -> None:
    """Analytic: K of a ROS CameraInfo, a depth of 0.8 m at the pixel (row cy, column cx) is the
    point (0, 0, 0.8) of the camera frame; one column on, x = 0.8 / fx; one row on, y = 0.8 / fy."""
    from pregrasp_core.sensor import CameraFile, depth_to_points

    doc = {"K": [500.0, 0.0, 3.0, 0.0, 400.0, 2.0, 0.0, 0.0, 1.0], "D": [], "width": 8,
           "height": 5}  # fmt: skip
    cam = CameraFile.parse(json.dumps(doc).encode(), "info.json")
    assert cam.size == (5, 8) and cam.layout == "ROS CameraInfo"
    dc = depth_to_points(np.full((5, 8), 0.8), cam.intrinsics)
    at = {(int(r), int(c)): p for (r, c), p in zip(dc.pixels, dc.points, strict=True)}
    np.testing.assert_allclose(at[2, 3], [0.0, 0.0, 0.8], atol=1e-15)
    np.testing.assert_allclose(at[2, 4], [0.8 / 500.0, 0.0, 0.8], atol=1e-15)
    np.testing.assert_allclose(at[3, 3], [0.0, 0.8 / 400.0, 0.8], atol=1e-15)


@pytest.mark.parametrize(
    ("change", "match"),
    [(("ROS CameraInfo", "K", [420.0, 1.5, 239.5, 0, 420.0, 179.5, 0, 0, 1]), "K has skew 1.5"),
     (("ROS CameraInfo", "K", [420.0, 0, 239.5]), "K must be a list of 9 finite numbers"),
     (("ROS CameraInfo", "K", [420.0, 0, 239.5, 0, 420.0, 179.5, 0, 0, 2]),
      "K is not a pinhole camera matrix"),
     (("ROS CameraInfo", "binning_x", 2), "binning_x 2: a binned image is not supported"),
     (("ROS CameraInfo", "roi", {"x_offset": 8, "y_offset": 0, "height": 100, "width": 100}),
      "a region of interest is not supported"),
     (("ROS CameraInfo", "D", "plumb_bob"), "D must be a list of finite numbers"),
     (("ROS CameraInfo", "fx", 420.0), r"unknown keys \['fx'\] for a ROS CameraInfo camera file"),
     (("RealSense", "ppy", None), "the RealSense intrinsics lack ppy"),
     (("RealSense", "coeffs", [0, 0]), "coeffs must be a list of 5 finite numbers"),
     (("RealSense", "fy", 0), "fx and fy must be positive focal lengths"),
     (("Open3D", "extrinsic", [2.0] + [0.0] * 15), "extrinsic's rotation is not a proper rotation"),
     (("Open3D", "intrinsic", None), "the Open3D camera parameters lack an intrinsic object"),
     (("Open3D", "T_world_camera", np.eye(4).tolist()), "give the camera pose once"),
     (("ROS calibration", "camera_matrix", [1, 2]), "camera_matrix must be an object with rows"),
     (("Open3D intrinsic", "intrinsic_matrix", [1.0] * 9),
      r"intrinsic_matrix \(column-major\) has skew 1")],
)  # fmt: skip
def test_a_bad_camera_file_of_another_tool_names_the_file_and_the_field(
    tmp_path: Path, change: tuple[str, str, object], match: str
) -> None:
    layout, key, value = change
    doc = dict(_layouts(DEMO_DOC)[layout])
    if value is None:
        del doc[key]
    else:
        doc[key] = value
    png, side = _demo_copy(tmp_path, "frame", doc)
    with pytest.raises(InputError) as err:
        load_point_cloud(png)
    msg = str(err.value)
    assert "\n" not in msg and re.search(match, msg) and msg.startswith(str(side)), msg


# ------------------------------------------------------------------------------------------------
# Complete scenes: a mesh or a fused scan with its table, read with --scene and no viewpoint


def _scan_scene(tmp_path: Path, table: str) -> tuple[Path, np.ndarray, int, int]:
    """A scan of the mug with a handle and the soda can on a table, as an XYZ file of points
    sampled on each surface (labels known outside the loader): ``table`` ``"patch"`` (a
    one-sided patch, as a phone scan keeps) or ``"box"`` (a 2 cm slab with its bottom, as a
    scene mesh has). Returns (path, labels 0 table / 1 mug / 2 can, index of the can's first
    point, points)."""
    mug = trimesh.load(OBJECTS_DIR / "mug_handle.obj", force="mesh")
    can = trimesh.load(OBJECTS_DIR / "can_soda.obj", force="mesh")
    can.apply_translation((0.2, 0.12, 0.0))
    if table == "patch":
        slab = trimesh.Trimesh([[-0.25, -0.2, 0], [0.35, -0.2, 0], [0.35, 0.3, 0], [-0.25, 0.3, 0]],
                               [[0, 1, 2], [0, 2, 3]])  # fmt: skip
    else:
        slab = trimesh.creation.box((0.6, 0.5, 0.02))
        slab.apply_translation((0.05, 0.05, -0.01))
    parts = []
    for k, (m, n) in enumerate(((slab, 40000), (mug, 12000), (can, 6000))):
        pts, _ = trimesh.sample.sample_surface(m, n, seed=k)
        parts.append((np.asarray(pts), np.full(n, k)))
    pts = np.concatenate([p for p, _ in parts])
    labels = np.concatenate([lab for _, lab in parts])
    path = tmp_path / f"scan_{table}.xyz"
    np.savetxt(path, pts, fmt="%.9f")
    return path, labels, 52000, len(pts)


@pytest.mark.parametrize("table", ["patch", "box"])
def test_a_complete_scene_keeps_its_object_whole_on_the_table_found(tmp_path, table) -> None:
    """``--scene`` without a viewpoint on a scan: the table found within 1 degree and 2 mm of
    the true top z = 0 (a slab's top, not its bottom 2 cm below), the object kept is the mug,
    at least 99 % of its points above the table's plane (its bottom face lies in that plane)
    and nothing of the can nor of the table beyond the mug's foot; ``pick`` near the can keeps
    the can; nothing is completed and the table becomes the support plane of the pipeline."""
    from pregrasp_core.pipeline import with_cloud

    path, labels, _, n = _scan_scene(tmp_path, table)
    truth = np.loadtxt(path)
    cloud = load_point_cloud(path, n_points=None, sensor=SensorOptions(scene=True))
    sc = cloud.info["scene"]
    assert sc["complete"] and cloud.viewpoint is None and cloud.sensor is None
    normal, height = np.asarray(sc["plane"]["normal"]), sc["plane"]["height"]
    assert np.degrees(np.arccos(min(1.0, normal @ [0, 0, 1]))) < 1.0 and abs(height) < 0.002
    kept = {tuple(p) for p in np.round(cloud.points, 9)}
    got = np.array([tuple(p) in kept for p in np.round(truth, 9)])
    up = truth[:, 2] > 0.003  # the mug's bottom face lies in the table's plane: the table's
    assert got[(labels == 1) & up].mean() >= 0.99 and not got[labels == 2].any()
    foot = truth[got & (labels == 0)]  # the table under the mug's rim (its foot) at most
    gap, _ = cKDTree(truth[labels == 1, :2]).query(foot[:, :2])
    assert len(foot) < 100 and gap.max(initial=0.0) < 0.005
    assert cloud.support is not None and cloud.assumed is None
    fm = with_cloud(PipelineParams(), cloud).facemask
    assert fm.support_height == pytest.approx(height) and np.allclose(fm.up, normal)
    can = load_point_cloud(path, n_points=None,
                           sensor=SensorOptions(scene=True, pick=(0.2, 0.12, 0.06)))  # fmt: skip
    kept = {tuple(p) for p in np.round(can.points, 9)}
    got = np.array([tuple(p) in kept for p in np.round(truth, 9)])
    assert got[(labels == 2) & up].mean() >= 0.99 and not got[labels == 1].any()
    assert any("read as a complete scene" in w for w in cloud.info["warnings"])
    assert n == len(truth)
    # the can is the mug's obstacle (every point of it near the can's true points); a
    # complete scan hides nothing, so "seen" is the same; "off" keeps the same object alone
    assert cloud.obstacles is not None and "n_obstacles_hidden" not in sc
    d, _ = cKDTree(truth[labels == 2]).query(cloud.obstacles)
    assert d.max() < 0.004 and sc["obstacles"] == "all"
    for which in ("seen", "off"):
        other = load_point_cloud(path, n_points=None,
                                 sensor=SensorOptions(scene=True, obstacles=which))  # fmt: skip
        np.testing.assert_array_equal(other.points, cloud.points)
        assert other.info["scene"]["obstacles"] == which
        if which == "seen":
            np.testing.assert_array_equal(other.obstacles, cloud.obstacles)
        else:
            assert other.obstacles is None and "n_obstacles" not in other.info["scene"]


def test_a_complete_scene_upside_down_or_against_a_wall_keeps_its_object(tmp_path) -> None:
    """The same scan turned upside down (180 degrees about x: the objects under the table along
    +z, as a z-down export has them) is read with up -z, with a warning, and keeps the mug; with
    a 60 x 50 cm wall standing at the table's back edge the wall is set aside as background (the
    largest cluster above the table before) and the mug is kept, its points as before."""
    path, labels, _, _ = _scan_scene(tmp_path, "patch")
    truth = np.loadtxt(path)
    up = truth[:, 2] > 0.003

    def kept_of(cloud) -> np.ndarray:
        kept = {tuple(p) for p in np.round(cloud.points, 9)}
        return np.array([tuple(p) in kept for p in np.round(truth, 9)])

    turned = truth * [1.0, -1.0, -1.0]
    np.savetxt(tmp_path / "turned.xyz", turned, fmt="%.9f")
    cloud = load_point_cloud(tmp_path / "turned.xyz", n_points=None,
                             sensor=SensorOptions(scene=True))  # fmt: skip
    assert any("read upside down (up -z)" in w for w in cloud.info["warnings"])
    assert np.allclose(cloud.info["scene"]["plane"]["normal"], [0, 0, -1], atol=0.02)
    kept = {tuple(p) for p in np.round(cloud.points * [1.0, -1.0, -1.0], 9)}
    got = np.array([tuple(p) in kept for p in np.round(truth, 9)])
    assert got[(labels == 1) & up].mean() >= 0.99 and not got[labels == 2].any()
    wall = trimesh.Trimesh([[-0.25, 0.3, 0], [0.35, 0.3, 0], [0.35, 0.3, 0.5], [-0.25, 0.3, 0.5]],
                           [[0, 1, 2], [0, 2, 3]])  # fmt: skip
    wall_pts, _ = trimesh.sample.sample_surface(wall, 40000, seed=9)
    np.savetxt(tmp_path / "wall.xyz", np.vstack([truth, wall_pts]), fmt="%.9f")
    cloud = load_point_cloud(tmp_path / "wall.xyz", n_points=None,
                             sensor=SensorOptions(scene=True))  # fmt: skip
    assert cloud.info["scene"]["n_background"] > 0.9 * len(wall_pts)
    assert any("set aside as background" in w for w in cloud.info["warnings"])
    got = kept_of(cloud)
    assert got[(labels == 1) & up].mean() >= 0.99 and not got[labels == 2].any()
    far, _ = cKDTree(truth).query(cloud.points)
    assert far.max() < 1e-6  # nothing of the wall


def test_a_scan_with_its_table_read_as_one_object_says_so(tmp_path) -> None:
    """Without ``--scene`` a scan keeps its table patch, with a warning that names the plane
    and the flag; a box lying on its side (its bottom face as wide as itself) and the demo
    objects get none."""
    path, _, _, _ = _scan_scene(tmp_path, "patch")
    cloud = load_point_cloud(path, n_points=None)
    (hint,) = [w for w in cloud.info["warnings"] if "read the file with --scene" in w]
    assert hint.startswith(f"{path}: ") and "0.60 x 0.50 m" in hint
    lying = trimesh.creation.box((0.3, 0.2, 0.06))
    lying.apply_translation((0, 0, 0.03))
    lying.export(tmp_path / "lying.stl")
    for p in [tmp_path / "lying.stl", *sorted(OBJECTS_DIR.glob("*.obj"))]:
        c = load_point_cloud(p, n_points=4000)
        assert not any("--scene" in w for w in c.info["warnings"]), p.name


@pytest.mark.parametrize("shift", [0.0, 0.95])
def test_an_object_running_off_the_depth_image_is_said(make_views, tmp_path, shift) -> None:
    """The mug with a handle rendered as a depth image (``make_views``' PNG and camera file,
    1 mm of noise) with the camera aimed beside it, the mug at the image's right edge
    (``shift`` 0.95 of the half field of view: part of it out of the frame) or in the middle
    (0): the first says that the object runs off the image's right edge and counts its points
    there, by the pinhole projection (``DepthScene.pixels``, checked against the pixels the
    points were back-projected from); the centred view and the committed demo say nothing."""
    import imageio.v3 as iio

    from pregrasp_core.io.cloud import FileData
    from pregrasp_core.io.depth_image import read_depth_image

    mesh = trimesh.load(OBJECTS_DIR / "mug_handle.obj", force="mesh")
    target, dist, table_half = make_views.view_setup(mesh)
    az = np.radians(60.0)
    right = np.array([-np.sin(az), np.cos(az), 0.0])
    half = dist * (make_views.WIDTH / 2.0) / make_views.INTRINSICS.fx
    T = orbit_camera(target - right * half * shift, dist, az, np.radians(35.0))
    view = render_view(mesh.vertices, mesh.faces, T, make_views.INTRINSICS, make_views.WIDTH,
                       make_views.HEIGHT, table_half=table_half + 1.0, noise=0.001,
                       rng=np.random.default_rng(3))  # fmt: skip
    png = tmp_path / "edge.png"
    iio.imwrite(png, make_views.depth_png(view))
    png.with_suffix(".json").write_text(make_views.camera_json(view))
    depth = read_depth_image(FileData(png.read_bytes(), str(png), png), ".png", None)
    assert depth.shape == (make_views.HEIGHT, make_views.WIDTH)
    rows, cols = np.nonzero(make_views.depth_png(view) > 0)  # row-major, as back-projected
    np.testing.assert_allclose(depth.pixels(depth.points), np.column_stack([cols, rows]),
                               atol=1e-6)  # fmt: skip
    cloud = load_point_cloud(png, n_points=None)
    said = [w for w in cloud.info["warnings"] if "runs off the image" in w]
    if shift == 0.0:
        assert said == [] and "n_image_edge" not in cloud.info["scene"]
        demo = load_point_cloud(DEMO, n_points=None)
        assert not any("runs off" in w for w in demo.info["warnings"])
        return
    n = cloud.info["scene"]["n_image_edge"]
    assert n >= 10 and len(said) == 1 and "(right edge:" in said[0]
    assert said[0].startswith(f"{png}: the object runs off the image")
    seen = cloud.points[~cloud.assumed]
    # the points on the edge are the mug's: within 3 mm of the true mesh
    edge = depth.pixels(seen)[:, 0] >= make_views.WIDTH - 2.5
    assert np.count_nonzero(edge) == n
    assert np.all(np.abs(trimesh.proximity.signed_distance(mesh, seen[edge])) < 0.003)
