"""Tests of pregrasp_core.io: every format round-trips a known cloud, meshes are sampled on their
surface (analytic cube oracle), bad input gives InputError with a readable message, and random
bytes never escape as anything but a PregraspError."""

from __future__ import annotations

import csv
import importlib.util
import io
import json
import logging
from pathlib import Path

import numpy as np
import pytest
import trimesh
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from pregrasp_core.errors import DegenerateGeometryError, InputError, PregraspError
from pregrasp_core.io import (
    DEFAULT_N_POINTS,
    MIN_POINTS,
    SUPPORTED_EXTENSIONS,
    PointCloud,
    load_point_cloud,
    load_point_cloud_bytes,
)
from pregrasp_core.paths import DEFAULT_OBJECT, OBJECTS_DIR, demo_objects

REPO = Path(__file__).resolve().parents[2]


# ------------------------------------------------------------------------------------------------
# Known clouds and small writers (independent of the code under test)


def known_cloud(n: int = 200, seed: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """(n, 3) points in a 0.1 m box and (n, 3) unit normals."""
    rng = np.random.default_rng(seed)
    pts = rng.uniform(-0.05, 0.05, size=(n, 3))
    nrm = rng.normal(size=(n, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    return pts, nrm


def write_ply(path: Path, pts, nrm=None, fmt="ascii", dtype="f4", faces=None) -> None:
    names = ["x", "y", "z"] + (["nx", "ny", "nz"] if nrm is not None else [])
    typename = {"f4": "float", "f8": "double"}[dtype]
    head = ["ply", f"format {fmt} 1.0", "comment written by test_io", f"element vertex {len(pts)}"]
    head += [f"property {typename} {n}" for n in names]
    if faces is not None:
        head += [f"element face {len(faces)}", "property list uchar int vertex_indices"]
    head.append("end_header")
    cols = np.hstack([pts, nrm]) if nrm is not None else np.asarray(pts)
    with open(path, "wb") as f:
        f.write(("\n".join(head) + "\n").encode())
        if fmt == "ascii":
            np.savetxt(f, cols, fmt="%.9g")
            if faces is not None:
                np.savetxt(f, np.hstack([np.full((len(faces), 1), 3), faces]), fmt="%d")
        else:
            order = "<" if fmt == "binary_little_endian" else ">"
            rec = np.zeros(len(cols), dtype=[(n, order + dtype) for n in names])
            for i, n in enumerate(names):
                rec[n] = cols[:, i]
            f.write(rec.tobytes())
            if faces is not None:
                frec = np.zeros(len(faces), dtype=[("n", "u1"), ("v", order + "i4", (3,))])
                frec["n"] = 3
                frec["v"] = faces
                f.write(frec.tobytes())


def write_pcd(path: Path, pts, nrm=None, mode="ascii") -> None:
    fields = ["x", "y", "z"] + (["normal_x", "normal_y", "normal_z"] if nrm is not None else [])
    k = len(fields)
    head = [
        "# .PCD v0.7 - Point Cloud Data file format",
        "VERSION 0.7",
        "FIELDS " + " ".join(fields),
        "SIZE " + " ".join(["4"] * k),
        "TYPE " + " ".join(["F"] * k),
        "COUNT " + " ".join(["1"] * k),
        f"WIDTH {len(pts)}",
        "HEIGHT 1",
        "VIEWPOINT 0 0 0 1 0 0 0",
        f"POINTS {len(pts)}",
        f"DATA {mode}",
    ]
    cols = np.hstack([pts, nrm]) if nrm is not None else np.asarray(pts)
    with open(path, "wb") as f:
        f.write(("\n".join(head) + "\n").encode())
        if mode == "ascii":
            np.savetxt(f, cols, fmt="%.9g")
        else:
            f.write(cols.astype("<f4").tobytes())


def f32(a: np.ndarray) -> np.ndarray:
    return np.asarray(a, dtype=np.float32).astype(np.float64)


# ------------------------------------------------------------------------------------------------
# Point-cloud formats round-trip


@pytest.mark.parametrize("fmt", ["ascii", "binary_little_endian", "binary_big_endian"])
@pytest.mark.parametrize("dtype", ["f4", "f8"])
def test_ply_cloud_roundtrip(tmp_path, fmt, dtype):
    pts, nrm = known_cloud()
    p = tmp_path / "c.ply"
    write_ply(p, pts, nrm, fmt=fmt, dtype=dtype)
    cloud = load_point_cloud(p)
    if fmt == "ascii":  # written with 9 significant digits
        ref, atol = pts, 1e-10
    else:  # binary: exactly the stored float32 / float64
        ref, atol = (f32(pts) if dtype == "f4" else pts), 0.0
    np.testing.assert_allclose(cloud.points, ref, rtol=0, atol=atol)
    np.testing.assert_allclose(cloud.normals, nrm, atol=1e-6)
    assert cloud.info["format"] == "ply" and cloud.info["kind"] == "cloud"
    assert cloud.info["n_read"] == len(pts) and cloud.info["n_dropped_nonfinite"] == 0


def test_ply_without_normals(tmp_path):
    pts, _ = known_cloud()
    p = tmp_path / "c.PLY"  # extension is case-insensitive
    write_ply(p, pts, None, fmt="binary_little_endian")
    cloud = load_point_cloud(p)
    np.testing.assert_array_equal(cloud.points, f32(pts))
    assert cloud.normals is None


@pytest.mark.parametrize("mode", ["ascii", "binary"])
def test_pcd_roundtrip(tmp_path, mode):
    pts, nrm = known_cloud()
    p = tmp_path / "c.pcd"
    write_pcd(p, pts, nrm, mode=mode)
    cloud = load_point_cloud(p)
    ref = pts if mode == "ascii" else f32(pts)  # ascii: 9 significant digits; binary: float32
    np.testing.assert_allclose(cloud.points, ref, rtol=0, atol=1e-10)
    np.testing.assert_allclose(cloud.normals, nrm, atol=1e-6)
    assert cloud.info["format"] == "pcd"


def test_pcd_with_extra_fields_and_counts(tmp_path):
    """rgb and a COUNT 2 field between x y z, as PCL writes for other point types."""
    pts, _ = known_cloud(50)
    rec = np.zeros(50, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("rgb", "<u4"),
                              ("h", "<i2", (2,))])  # fmt: skip
    rec["x"], rec["y"], rec["z"] = pts.T
    rec["rgb"] = 0xFF00FF
    head = ("VERSION 0.7\nFIELDS x y z rgb h\nSIZE 4 4 4 4 2\nTYPE F F F U I\nCOUNT 1 1 1 1 2\n"
            "WIDTH 50\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS 50\nDATA binary\n")  # fmt: skip
    p = tmp_path / "rgb.pcd"
    p.write_bytes(head.encode() + rec.tobytes())
    cloud = load_point_cloud(p)
    np.testing.assert_array_equal(cloud.points, f32(pts))
    assert cloud.normals is None


def test_pcd_nan_points_dropped(tmp_path, caplog):
    """Organised PCL clouds mark missing points with NaN: those rows are dropped with a warning."""
    pts, _ = known_cloud(40)
    pts[[3, 7, 11]] = np.nan
    p = tmp_path / "nan.pcd"
    write_pcd(p, pts, mode="binary")
    with caplog.at_level(logging.WARNING, logger="pregrasp_core.io"):
        cloud = load_point_cloud(p)
    assert cloud.n_points == 37
    assert cloud.info["n_dropped_nonfinite"] == 3
    assert any("dropped 3 of 40 rows" in w for w in cloud.info["warnings"])
    assert "dropped 3 of 40 rows" in caplog.text
    np.testing.assert_array_equal(cloud.points, f32(np.delete(pts, [3, 7, 11], axis=0)))


@pytest.mark.parametrize(
    "ext,delim", [(".xyz", " "), (".txt", ","), (".csv", ", "), (".txt", "\t")]
)
def test_text_roundtrip(tmp_path, ext, delim):
    pts, _ = known_cloud()
    p = tmp_path / f"c{ext}"
    np.savetxt(p, pts, delimiter=delim, fmt="%.17g", header="x y z (a comment)")
    cloud = load_point_cloud(p)
    np.testing.assert_array_equal(cloud.points, pts)
    assert cloud.normals is None
    assert cloud.info["format"] == ext[1:]


def test_csv_header_line_skipped(tmp_path):
    pts, _ = known_cloud()
    p = tmp_path / "h.csv"
    np.savetxt(p, pts, delimiter=",", fmt="%.17g", header="x,y,z", comments="")
    assert p.read_text().startswith("x,y,z\n")
    cloud = load_point_cloud(p)
    np.testing.assert_array_equal(cloud.points, pts)
    assert any("read the header line 'x,y,z' as column names" in w for w in cloud.warnings)
    np.savetxt(p, pts, delimiter=",", fmt="%.17g", header="east,north,height", comments="")
    cloud = load_point_cloud(p)  # names without x y z: skipped, the columns in order
    np.testing.assert_array_equal(cloud.points, pts)
    assert any("skipped the header line 'east,north,height'" in w for w in cloud.warnings)


def _columns_file(path: Path, cols: list[np.ndarray], header: str | None = None, sep=" "):
    rows = np.column_stack(cols)
    np.savetxt(path, rows, delimiter=sep, fmt="%.17g", header=header or "", comments="")
    if header is None:
        path.write_text(path.read_text().lstrip("\n"))


@pytest.mark.parametrize(
    ("layout", "header", "normals_at", "ignored"),
    [("x y z r g b nx ny nz", "//X,Y,Z,R,G,B,Nx,Ny,Nz", "7-9", "4-6"),  # CloudCompare, CSV
     ("x y z r g b nx ny nz", None, "7-9", "4-6"),  # the same without its header
     ("x y z nx ny nz r g b", None, "4-6", "7-9"),
     ("i x y z nx ny nz", "intensity x y z nx ny nz", "5-7", "1"),  # names in any order
     ("x y z i", None, None, "4"),  # a scanner's x y z intensity
     ("x y z r g b a", None, None, "4-7"),
     ("x y z r g b nx ny nz", "x y z r g b normal_x normal_y normal_z", "7-9", "4-6")],
)  # fmt: skip
def test_text_clouds_with_colours_intensities_and_normals(tmp_path, layout, header, normals_at,
                                                          ignored):  # fmt: skip
    """Rows as CloudCompare, MeshLab and scanners export them: x y z and the normals found by
    their header names or, without names, as the first unit-vector columns after x y z; every
    other column ignored with a warning naming it; the values read exactly."""
    pts, nrm = known_cloud(300)
    rng = np.random.default_rng(5)
    cols = {"x": pts[:, 0], "y": pts[:, 1], "z": pts[:, 2], "nx": nrm[:, 0], "ny": nrm[:, 1],
            "nz": nrm[:, 2], "i": rng.uniform(0, 1, 300), "a": np.full(300, 255.0)}  # fmt: skip
    cols.update({c: rng.integers(0, 256, 300).astype(float) for c in "rgb"})
    path = tmp_path / ("c.csv" if header and "," in header else "c.xyz")
    sep = "," if path.suffix == ".csv" else " "
    _columns_file(path, [cols[c] for c in layout.split()], header, sep)
    cloud = load_point_cloud(path, n_points=None)
    np.testing.assert_array_equal(cloud.points, pts)
    if normals_at is None:
        assert cloud.normals is None
    else:  # (the loader makes them unit to the last bit)
        np.testing.assert_allclose(cloud.normals, nrm, rtol=0, atol=1e-15)
    (note,) = [w for w in cloud.warnings if "as x y z" in w]
    if normals_at is not None:
        assert f"and {normals_at} as normals" in note
    assert f"ignored column(s) {ignored} " in note


def test_text_normals_named_but_not_unit_are_not_read(tmp_path):
    pts, nrm = known_cloud(300)
    path = tmp_path / "c.xyz"
    _columns_file(path, [pts, 2.0 * nrm], "x y z nx ny nz")
    cloud = load_point_cloud(path, n_points=None)
    np.testing.assert_array_equal(cloud.points, pts)
    assert cloud.normals is None
    assert any("the columns named nx ny nz are not unit vectors" in w for w in cloud.warnings)


def test_text_with_normals_and_with_colours(tmp_path):
    pts, nrm = known_cloud()
    p = tmp_path / "n.xyz"
    np.savetxt(p, np.hstack([pts, nrm]), fmt="%.17g")
    cloud = load_point_cloud(p)
    np.testing.assert_array_equal(cloud.points, pts)
    np.testing.assert_allclose(cloud.normals, nrm, atol=1e-12)
    # x y z r g b: the last columns are not unit vectors -> ignored with a warning
    q = tmp_path / "rgb.xyz"
    rgb = np.random.default_rng(0).integers(0, 256, size=(len(pts), 3))
    np.savetxt(q, np.hstack([pts, rgb]), fmt="%.17g")
    cloud = load_point_cloud(q)
    np.testing.assert_array_equal(cloud.points, pts)
    assert cloud.normals is None
    assert any("not unit vectors" in w for w in cloud.warnings)


def test_npy_and_npz_roundtrip(tmp_path):
    pts, nrm = known_cloud()
    np.save(tmp_path / "a.npy", pts)
    np.testing.assert_array_equal(load_point_cloud(tmp_path / "a.npy").points, pts)
    np.save(tmp_path / "b.npy", np.hstack([pts, nrm]).astype(np.float32))
    c = load_point_cloud(tmp_path / "b.npy")
    np.testing.assert_array_equal(c.points, f32(pts))
    np.testing.assert_allclose(c.normals, nrm, atol=1e-6)
    np.savez(tmp_path / "c.npz", points=pts, normals=nrm, labels=np.arange(len(pts)))
    c = load_point_cloud(tmp_path / "c.npz")
    np.testing.assert_array_equal(c.points, pts)
    np.testing.assert_allclose(c.normals, nrm, atol=1e-12)
    np.savez_compressed(tmp_path / "d.npz", whatever=pts)  # a single array, any key
    np.testing.assert_array_equal(load_point_cloud(tmp_path / "d.npz").points, pts)
    np.save(tmp_path / "i.npy", np.round(pts * 1000).astype(np.int32))  # integers are fine
    # scale=1: these millimetre-like integers would otherwise be recognised as millimetres
    np.testing.assert_array_equal(
        load_point_cloud(tmp_path / "i.npy", scale=1.0).points, np.round(pts * 1000)
    )


def test_bytes_loader_matches_path_loader(tmp_path):
    pts, nrm = known_cloud()
    p = tmp_path / "c.ply"
    write_ply(p, pts, nrm, fmt="binary_big_endian")
    a = load_point_cloud(p)
    b = load_point_cloud_bytes(p.read_bytes(), "upload.ply")
    np.testing.assert_array_equal(a.points, b.points)
    np.testing.assert_array_equal(a.normals, b.normals)
    assert b.source == "upload.ply" and a.source == str(p)


def test_cloud_subsampled_to_n_points(tmp_path):
    pts, _ = known_cloud(500)
    np.save(tmp_path / "a.npy", pts)
    a = load_point_cloud(tmp_path / "a.npy", n_points=100, seed=3)
    b = load_point_cloud(tmp_path / "a.npy", n_points=100, seed=3)
    c = load_point_cloud(tmp_path / "a.npy", n_points=100, seed=4)
    full = load_point_cloud(tmp_path / "a.npy", n_points=None)
    assert a.n_points == 100 and a.info["n_subsampled_from"] == 500 and a.info["seed"] == 3
    np.testing.assert_array_equal(a.points, b.points)
    assert not np.array_equal(a.points, c.points)
    assert full.n_points == 500
    # a subset of the original rows, in file order, without repeats
    idx = [int(np.flatnonzero((pts == p).all(axis=1))[0]) for p in a.points[:20]]
    assert idx == sorted(set(idx))


def test_scale_and_millimetre_warning(tmp_path):
    pts, _ = known_cloud()
    np.save(tmp_path / "mm.npy", pts * 1000.0)  # a 100 m "object": really millimetres
    c = load_point_cloud(tmp_path / "mm.npy")  # recognised (detect_units) and converted
    assert c.info["scale"] == 0.001
    assert any("read as millimetres and scaled by 0.001" in w for w in c.warnings)
    c = load_point_cloud(tmp_path / "mm.npy", scale=1.0)  # told metres: kept, with a warning
    assert any("looks like millimetres; pass scale=0.001 (--scale 0.001)" in w for w in c.warnings)
    c = load_point_cloud(tmp_path / "mm.npy", scale=0.001)
    np.testing.assert_allclose(c.points, pts, rtol=1e-12, atol=1e-15)
    assert c.warnings == [] and c.info["scale"] == 0.001


def test_a_millimetre_mesh_is_sampled_once_and_warned_once(tmp_path, caplog):
    """A mesh written in millimetres (a 45 mm ball's STL): read as millimetres, with the one
    notice saying so; before, the mesh was sampled twice and the first, unscaled sampling also
    logged "the cloud is 45.0 m long, which looks like millimetres; pass --scale 0.001", telling
    the user to do what the loader had done. The points are those of an explicit --scale 0.001,
    bit for bit."""
    ball = trimesh.creation.icosphere(subdivisions=3, radius=22.5)
    ball.export(tmp_path / "ball_mm.stl")
    with caplog.at_level(logging.WARNING, logger="pregrasp_core"):
        auto = load_point_cloud(tmp_path / "ball_mm.stl", n_points=4000)
    said = [r.getMessage() for r in caplog.records]
    assert auto.info["scale"] == 0.001
    assert len(said) == 1 and "read as millimetres and scaled by 0.001" in said[0], said
    assert auto.warnings == said
    told = load_point_cloud(tmp_path / "ball_mm.stl", n_points=4000, scale=0.001)
    assert np.array_equal(auto.points, told.points)
    assert np.array_equal(auto.normals, told.normals)
    assert auto.info["area"] == pytest.approx(4 * np.pi * 0.0225**2, rel=0.01)


# ------------------------------------------------------------------------------------------------
# Meshes: a cube is the analytic oracle


def _cube_files(tmp_path: Path) -> dict[str, Path]:
    cube = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    out = {}
    for name, kw in {
        "obj": {},
        "stl": {},
        "off": {},
        "glb": {},
        "ply": {"encoding": "binary"},
    }.items():
        p = tmp_path / f"cube.{name}"
        data = cube.export(file_type=name, **kw)
        p.write_bytes(data if isinstance(data, bytes) else data.encode())
        out[name] = p
    p = tmp_path / "cube_ascii.ply"
    p.write_bytes(cube.export(file_type="ply", encoding="ascii"))
    out["ply_ascii"] = p
    p = tmp_path / "cube_own.ply"  # our own PLY writer with faces (big endian)
    write_ply(p, cube.vertices, fmt="binary_big_endian", faces=cube.faces)
    out["ply_own"] = p
    return out


def _assert_on_unit_cube(points: np.ndarray, normals: np.ndarray) -> None:
    a = np.abs(points)
    assert np.all(a <= 0.5 + 1e-9)
    np.testing.assert_allclose(a.max(axis=1), 0.5, atol=1e-9)  # on a face
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-12)
    k = np.argmax(a, axis=1)  # (N,) the face's axis
    expected = np.zeros_like(points)
    expected[np.arange(len(points)), k] = np.sign(points[np.arange(len(points)), k])
    np.testing.assert_allclose(normals, expected, atol=1e-9)  # outward, along the face's axis


@pytest.mark.parametrize("kind", ["obj", "stl", "off", "glb", "ply", "ply_ascii", "ply_own"])
def test_mesh_sampled_on_cube_surface(tmp_path, kind):
    path = _cube_files(tmp_path)[kind]
    cloud = load_point_cloud(path, n_points=3000, seed=7)
    assert cloud.n_points == 3000
    assert cloud.info["kind"] == "mesh"
    assert cloud.info["area"] == pytest.approx(6.0)
    _assert_on_unit_cube(cloud.points, cloud.normals)
    same = load_point_cloud(path, n_points=3000, seed=7)
    other = load_point_cloud(path, n_points=3000, seed=8)
    np.testing.assert_array_equal(cloud.points, same.points)
    np.testing.assert_array_equal(cloud.normals, same.normals)
    assert not np.allclose(cloud.points, other.points)
    gltf_note = [w for w in cloud.info["warnings"] if "glTF is Y-up" in w]
    assert len(gltf_note) == (kind == "glb")  # a glTF says how its up is read
    if gltf_note:
        assert gltf_note[0].startswith(f"{path}: ") and "--up 0 1 0" in gltf_note[0]


def test_mesh_sampling_is_area_uniform_and_rigid_motion_invariant(tmp_path):
    """A box 0.3 x 0.2 x 0.1 under a seeded rigid motion: samples lie on its surface (checked in
    its own frame) and each face gets a share of the points proportional to its area."""
    rng = np.random.default_rng(42)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.linalg.det(q))
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = q, rng.uniform(-1, 1, 3)
    ext = np.array([0.3, 0.2, 0.1])
    box = trimesh.creation.box(extents=ext, transform=T)
    p = tmp_path / "box.stl"
    p.write_bytes(box.export(file_type="stl"))
    n = 12000
    cloud = load_point_cloud(p, n_points=n, seed=0)
    local = (cloud.points - T[:3, 3]) @ q  # (N, 3) in the box frame
    frac = np.abs(local) / (ext / 2)  # 1 on the face's axis
    np.testing.assert_allclose(frac.max(axis=1), 1.0, atol=1e-6)
    k = np.argmax(frac, axis=1)
    areas = np.array([ext[1] * ext[2], ext[0] * ext[2], ext[0] * ext[1]])  # faces normal to x,y,z
    expect = areas / areas.sum()
    got = np.bincount(k, minlength=3) / n
    sd = np.sqrt(expect * (1 - expect) / n)
    assert np.all(np.abs(got - expect) < 5 * sd)
    n_local = cloud.normals @ q  # normals in the box frame: +-e_k, outward
    np.testing.assert_allclose(np.abs(n_local[np.arange(n), k]), 1.0, atol=1e-9)
    assert np.all(np.sign(n_local[np.arange(n), k]) == np.sign(local[np.arange(n), k]))


def test_gltf_with_external_buffer(tmp_path):
    cube = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    files = trimesh.exchange.gltf.export_gltf(trimesh.Scene(cube), embed_buffers=False)
    for name, data in files.items():
        (tmp_path / name).write_bytes(data)
    gltf = tmp_path / "model.gltf"
    cloud = load_point_cloud(gltf, n_points=500)
    _assert_on_unit_cube(cloud.points, cloud.normals)
    with pytest.raises(InputError, match=r"upload\.gltf: .*export it as \.glb"):
        load_point_cloud_bytes(gltf.read_bytes(), "upload.gltf")
    embedded = trimesh.exchange.gltf.export_gltf(trimesh.Scene(cube), embed_buffers=True)
    cloud = load_point_cloud_bytes(embedded["model.gltf"], "upload.gltf", n_points=500)
    _assert_on_unit_cube(cloud.points, cloud.normals)


def test_gltf_refuses_files_outside_its_folder(tmp_path):
    """A .gltf on disk may read the buffers beside it, nothing else (no '..', absolute paths,
    devices or URLs), checked before trimesh opens anything."""
    cube = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    files = trimesh.exchange.gltf.export_gltf(trimesh.Scene(cube), embed_buffers=False)
    (tmp_path / "sub").mkdir()
    for name, data in files.items():
        (tmp_path / "sub" / name).write_bytes(data)
        (tmp_path / name).write_bytes(data)
    doc = json.loads(files["model.gltf"])
    for uri in ("../" + doc["buffers"][0]["uri"], "/dev/zero", "file:///etc/passwd"):
        doc["buffers"][0]["uri"] = uri
        (tmp_path / "sub" / "model.gltf").write_text(json.dumps(doc))
        with pytest.raises(InputError, match=r"model\.gltf: malformed glTF: buffer 0 uri .* is not "
                           "a file beside the GLTF"):  # fmt: skip
            load_point_cloud(tmp_path / "sub" / "model.gltf", n_points=100)


def test_inside_out_mesh_gets_outward_normals(tmp_path):
    cube = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    inv = trimesh.Trimesh(cube.vertices, cube.faces[:, ::-1], process=False)
    assert inv.volume < 0  # really inside-out
    (tmp_path / "inv.obj").write_text(inv.export(file_type="obj"))
    c = load_point_cloud(tmp_path / "inv.obj", n_points=500)
    _assert_on_unit_cube(c.points, c.normals)
    assert any("1 closed part(s) of the mesh are wound inside-out" in w for w in c.warnings)


def test_one_inside_out_part_of_an_assembly(tmp_path):
    """Two cubes, the second wound inside-out and moved away: both get outward normals; an
    open part (a lone square, no inside) is left as wound."""
    a = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    b = trimesh.Trimesh(a.vertices + [3.0, 0.0, 0.0], a.faces[:, ::-1], process=False)
    sq = trimesh.Trimesh([[0, 0, 5], [1, 0, 5], [1, 1, 5], [0, 1, 5]], [[0, 1, 2], [0, 2, 3]])
    both = trimesh.util.concatenate([a, b, sq])
    (tmp_path / "ab.obj").write_text(both.export(file_type="obj"))
    c = load_point_cloud(tmp_path / "ab.obj", n_points=3000, seed=1)
    first, second = c.points[:, 0] < 1.0, (c.points[:, 0] > 2.0)
    top = c.points[:, 2] > 4.0
    first &= ~top
    assert first.sum() > 500 and second.sum() > 500 and top.sum() > 50
    _assert_on_unit_cube(c.points[first], c.normals[first])
    _assert_on_unit_cube(c.points[second] - [3.0, 0.0, 0.0], c.normals[second])
    np.testing.assert_allclose(c.normals[top], [[0.0, 0.0, 1.0]] * int(top.sum()), atol=1e-12)
    assert any("1 closed part(s)" in w for w in c.warnings)


def test_default_n_points_for_meshes(tmp_path):
    path = _cube_files(tmp_path)["obj"]
    assert load_point_cloud(path).n_points == DEFAULT_N_POINTS
    assert load_point_cloud(path, n_points=None).n_points == DEFAULT_N_POINTS


# ------------------------------------------------------------------------------------------------
# Bad input


def test_missing_empty_unknown(tmp_path):
    with pytest.raises(InputError, match=r"nope\.ply: file not found; check the path"):
        load_point_cloud(tmp_path / "nope.ply")
    with pytest.raises(InputError, match="not a regular file"):
        load_point_cloud(_mkdir(tmp_path / "d.ply"))
    (tmp_path / "e.xyz").write_bytes(b"")
    with pytest.raises(InputError, match=r"e\.xyz: the file is empty"):
        load_point_cloud(tmp_path / "e.xyz")
    (tmp_path / "a.foo").write_text("1 2 3\n")
    with pytest.raises(InputError, match=r"unknown file extension \.foo; supported: \.ply, \.pcd"):
        load_point_cloud(tmp_path / "a.foo")
    with pytest.raises(InputError, match=r"unknown file extension \(none\)"):
        load_point_cloud_bytes(b"1 2 3", "noext")
    with pytest.raises(InputError, match="the file is empty"):
        load_point_cloud_bytes(b"", "up.npy")


def _mkdir(p: Path) -> Path:
    p.mkdir()
    return p


def test_size_limit(tmp_path):
    pts, _ = known_cloud(1000)
    np.save(tmp_path / "big.npy", pts)
    with pytest.raises(InputError, match=r"big\.npy: the file is .* MiB, more than the limit"):
        load_point_cloud(tmp_path / "big.npy", max_bytes=1000)
    with pytest.raises(InputError, match="more than the limit"):
        load_point_cloud_bytes((tmp_path / "big.npy").read_bytes(), "big.npy", max_bytes=1000)
    # an NPZ whose arrays unpack to more than the limit (a zip bomb) is refused before reading
    buf = io.BytesIO()
    np.savez_compressed(buf, points=np.zeros((200_000, 3)))
    assert len(buf.getvalue()) < 100_000
    with pytest.raises(InputError, match="unpacks to .* more than the limit"):
        load_point_cloud_bytes(buf.getvalue(), "bomb.npz", max_bytes=100_000)


@pytest.mark.parametrize(
    "name,data,match",
    [
        ("h.ply", b"plx\nformat ascii 1.0\nend_header\n", "malformed PLY header: .*start with"),
        ("h.ply", b"ply\nformat ascii 1.0\nelement vertex 3\n", "malformed PLY header: no 'end"),
        ("h.ply", b"ply\nformat weird 1.0\nend_header\n", "malformed PLY header: unknown format"),
        ("h.ply", b"ply\nformat ascii 1.0\nelement vertex x\nend_header\n", "bad element line"),
        ("h.ply", b"ply\nformat ascii 1.0\nelement vertex 2\nproperty flt x\nend_header\n",
         "bad property line"),
        ("h.ply", b"ply\nelement vertex 2\nproperty float x\nend_header\n", "no 'format' line"),
        ("h.ply", b"ply\nformat ascii 1.0\nelement vertex 12\nproperty float x\nproperty float y"
         b"\nend_header\n" + b"1 2\n" * 12, r"properties \['x', 'y'\], no x, y, z"),
        ("h.pcd", b"VERSION 0.7\nFIELDS x y z\nSIZE 4 4\nTYPE F F F\nWIDTH 3\nHEIGHT 1\nDATA ascii"
         b"\n", "malformed PCD header: FIELDS .* same number"),
        ("h.pcd", b"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nWIDTH 3\nHEIGHT 1\n",
         "malformed PCD header: no DATA line"),
        ("h.pcd", b"FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nWIDTH 3\nDATA ascii\n",
         "malformed PCD header: no HEIGHT line"),
        ("h.pcd", b"FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nWIDTH three\nHEIGHT 1\nDATA ascii\n",
         "must be integers"),
        ("h.pcd", b"FIELDS x y z\nSIZE 4 4 3\nTYPE F F F\nWIDTH 3\nHEIGHT 1\nDATA ascii\n",
         "unsupported TYPE F SIZE 3"),
        ("h.pcd", b"BOGUS 1\nFIELDS x y z\n", "unexpected line 'BOGUS 1'"),
        ("h.pcd", b"FIELDS a b c\nSIZE 4 4 4\nTYPE F F F\nWIDTH 1\nHEIGHT 1\nDATA ascii\n1 2 3\n",
         r"fields \['a', 'b', 'c'\], no 'x'"),
        ("h.pcd", b"FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nWIDTH 3\nHEIGHT 1\nDATA lzma\n",
         "unknown DATA mode 'lzma'"),
    ],
)  # fmt: skip
def test_malformed_headers(name, data, match):
    with pytest.raises(InputError, match=match):
        load_point_cloud_bytes(data, name)


@pytest.mark.parametrize("organised", [False, True])
def test_pcd_binary_compressed_written_by_pypcd4(tmp_path, organised):
    """``DATA binary_compressed`` as another implementation writes it (pypcd4, its LZF from
    liblzf): x y z, the normals and an rgb field between them, every float32 read exactly; an
    organised cloud (WIDTH x HEIGHT, NaN where the sensor saw nothing) loses its NaN rows."""
    from pypcd4 import Encoding
    from pypcd4 import PointCloud as Pcd

    u, v = np.meshgrid(np.arange(40), np.arange(30))  # a depth camera's 40 x 30 pixels
    pts = np.column_stack([u.ravel() * 0.002, v.ravel() * 0.002, np.full(1200, 0.6)])
    pts[(u.ravel() - 20) ** 2 + (v.ravel() - 15) ** 2 < 60, 2] = 0.55  # a box on the table
    nrm = np.tile([0.0, 0.0, -1.0], (1200, 1))
    if organised:
        pts[::5] = np.nan
    rgb = np.full(1200, 0x808080, dtype=np.uint32)  # (random floats do not compress: pypcd4
    # would write them as DATA binary)
    cols = [*pts.astype(np.float32).T, rgb, *nrm.astype(np.float32).T]
    names = ("x", "y", "z", "rgb", "normal_x", "normal_y", "normal_z")
    pc = Pcd.from_points(cols, names, (np.float32,) * 3 + (np.uint32,) + (np.float32,) * 3)
    if organised:
        pc.metadata.width, pc.metadata.height = 40, 30
    path = tmp_path / "c.pcd"
    pc.save(path, encoding=Encoding.BINARY_COMPRESSED)
    assert b"DATA binary_compressed\n" in path.read_bytes()[:1000]
    cloud = load_point_cloud(path, n_points=None)
    keep = np.isfinite(pts).all(axis=1)
    np.testing.assert_array_equal(cloud.points, f32(pts[keep]))
    np.testing.assert_allclose(cloud.normals, nrm[keep], atol=1e-6)
    assert cloud.info["n_dropped_nonfinite"] == (240 if organised else 0)


def test_pcd_binary_compressed_fields_with_counts_and_padding():
    """Fields of COUNT 2 and PCL's padding field ``_`` (each stored field after field, for every
    point), x y z after them; the stream from liblzf's compressor (python-neo-lzf)."""
    import struct

    import lzf

    pts, _ = known_cloud(300)
    blocks = [np.arange(600, dtype="<i2").tobytes(), np.zeros(300, "<u4").tobytes()]
    blocks += [np.ascontiguousarray(pts[:, i], dtype="<f8").tobytes() for i in range(3)]
    raw = b"".join(blocks)
    packed = lzf.compress(raw, 2 * len(raw))
    head = (b"VERSION 0.7\nFIELDS h _ x y z\nSIZE 2 4 8 8 8\nTYPE I U F F F\nCOUNT 2 1 1 1 1\n"
            b"WIDTH 300\nHEIGHT 1\nPOINTS 300\nDATA binary_compressed\n")  # fmt: skip
    data = head + struct.pack("<II", len(packed), len(raw)) + packed
    cloud = load_point_cloud_bytes(data, "c.pcd", n_points=None)
    np.testing.assert_array_equal(cloud.points, pts)


@settings(max_examples=60, deadline=None)
@given(
    st.lists(
        st.tuples(st.binary(min_size=1, max_size=40), st.integers(1, 300)), min_size=1, max_size=12
    )
)
def test_lzf_decodes_what_liblzf_encodes(pieces):
    """Any bytes (pieces repeated up to 300 times: long and overlapping back references)
    compressed by liblzf (python-neo-lzf) decode to themselves."""
    import lzf

    from pregrasp_core.io.lzf import lzf_decompress

    raw = b"".join(p * k for p, k in pieces)
    packed = lzf.compress(raw, len(raw) + len(raw) // 16 + 64)
    assert lzf_decompress(packed, len(raw), "x.pcd") == raw


@pytest.mark.parametrize(
    ("stream", "size", "match"),
    [(b"\x03ab", 4, "ends inside a token"),
     (b"\x02abc", 2, "holds more than the 2 bytes declared"),
     (b"\x00a\x20\x01", 9, "a back reference points before its start"),
     (b"\x00a\xe0", 9, "ends inside a token"),
     (b"\x00a\x20\x00", 9, "holds 4 bytes, the header declares 9"),
     (b"\x00a", 10**6, "cannot hold the 1000000 bytes")],
)  # fmt: skip
def test_lzf_malformed_streams(stream, size, match):
    from pregrasp_core.io.lzf import lzf_decompress

    with pytest.raises(InputError, match=f"^x.pcd: .*{match}"):
        lzf_decompress(stream, size, "x.pcd")


def test_truncated_binary(tmp_path):
    pts, _ = known_cloud(100)
    write_ply(tmp_path / "t.ply", pts, fmt="binary_little_endian")
    data = (tmp_path / "t.ply").read_bytes()[:-10]
    with pytest.raises(InputError, match="truncated PLY: the header promises 100 vertices"):
        load_point_cloud_bytes(data, "t.ply")
    write_pcd(tmp_path / "t.pcd", pts, mode="binary")
    data = (tmp_path / "t.pcd").read_bytes()[:-10]
    with pytest.raises(InputError, match="truncated PCD: the header declares 100 points"):
        load_point_cloud_bytes(data, "t.pcd")
    write_ply(tmp_path / "a.ply", pts, fmt="ascii")
    lines = (tmp_path / "a.ply").read_bytes().splitlines(keepends=True)
    with pytest.raises(InputError, match="truncated PLY: the header promises 100 vertices, the "
                       "file holds 90"):  # fmt: skip
        load_point_cloud_bytes(b"".join(lines[:-10]), "a.ply")


@pytest.mark.parametrize(
    "name,text,match",
    [
        ("a.xyz", " ".join(["1"] * 65) + "\n" * 20, "wrong column count 65; expected 3"),
        ("a.txt", "1,2\n" * 20, "wrong column count 2; expected 3"),
        ("a.xyz", "1 2 3\n" * 5 + "1 2\n", "different numbers of columns"),
        ("a.xyz", "x y z\n1 2 3\n" + "4 5 six\n" * 12, "non-numeric data"),
        ("a.xyz", "1 2 3\n" * 12 + "x y z\n", "non-numeric data"),
        ("a.csv", "0.1,0.2,abc\n" * 20, "non-numeric data"),
        ("a.xyz", "# only a comment\n\n", "no data rows"),
        ("a.xyz", "1 2 3\n4 5 6\n7 8 10\n", r"only 3 finite points; at least 16 are needed"),
        ("a.pcd", "FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nWIDTH 2\nHEIGHT 1\nDATA ascii\n"
         "1 2 3 4\n5 6 7 8\n", "wrong column count in the ascii PCD: 4 numbers per row"),
        ("a.pcd", "FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nWIDTH 3\nHEIGHT 1\nDATA ascii\n"
         "1 2 3\n5 6 7\n", "declares 3 points, the data has 2 rows"),
        ("a.ply", "ply\nformat ascii 1.0\nelement vertex 12\nproperty float x\nproperty float y\n"
         "property float z\nend_header\n" + "1 2 3 4\n" * 12,
         "wrong column count in the ascii PLY: 4 numbers per vertex, the header declares 3"),
        ("a.ply", "ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\nproperty float y\n"
         "property float z\nend_header\n", "0 vertices"),
    ],
)  # fmt: skip
def test_bad_rows(name, text, match):
    with pytest.raises(InputError, match=match):
        load_point_cloud_bytes(text.encode(), name)


def test_binary_data_in_text_format():
    with pytest.raises(InputError, match=r"b\.xyz: contains binary data"):
        load_point_cloud_bytes(b"\x00\x01\x02" * 10, "b.xyz")
    with pytest.raises(InputError, match="is not UTF-8/ASCII text"):
        load_point_cloud_bytes(b"\xff\xfe\xfa 1 2 3", "b.txt")


def test_nan_rows_dropped_or_too_few(tmp_path, caplog):
    pts, _ = known_cloud(30)
    pts[:5, 1] = np.inf
    pts[5:8, 0] = np.nan
    np.savetxt(tmp_path / "n.xyz", pts, fmt="%.17g")  # writes 'inf' and 'nan'
    with caplog.at_level(logging.WARNING, logger="pregrasp_core.io"):
        c = load_point_cloud(tmp_path / "n.xyz")
    assert c.n_points == 22 and c.info["n_dropped_nonfinite"] == 8
    assert "dropped 8 of 30 rows with NaN or infinite" in caplog.text
    np.testing.assert_array_equal(c.points, pts[8:])
    pts[:25] = np.nan
    np.savetxt(tmp_path / "m.xyz", pts, fmt="%.17g")
    with pytest.raises(InputError, match=r"only 5 finite points \(25 NaN/inf rows dropped\)"):
        load_point_cloud(tmp_path / "m.xyz")


def test_degenerate_geometry(tmp_path):
    same = np.tile([[0.1, 0.2, 0.3]], (50, 1))
    with pytest.raises(DegenerateGeometryError, match=r"same\.npy: all 50 points are identical"):
        load_point_cloud_bytes(_npy(same), "same.npy")
    t = np.linspace(0, 1, 50)[:, None]
    line = np.array([0.1, 0.2, 0.3]) + t * np.array([0.3, -0.1, 0.2])
    with pytest.raises(DegenerateGeometryError, match=r"line\.npy: all points lie on one line"):
        load_point_cloud_bytes(_npy(line), "line.npy")
    # coplanar in a tilted plane: valid, with a warning
    rng = np.random.default_rng(0)
    uv = rng.uniform(-0.1, 0.1, size=(100, 2))
    e1, e2 = np.array([1.0, 1.0, 0.0]) / np.sqrt(2), np.array([0.0, 0.0, 1.0])
    plane = uv[:, :1] * e1 + uv[:, 1:] * e2 + 0.3
    c = load_point_cloud_bytes(_npy(plane), "plane.npy")
    assert c.n_points == 100
    assert any("all points lie in one plane" in w and "valid answer" in w for w in c.warnings)


def _npy(a: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, a)
    return buf.getvalue()


def test_npy_npz_refusals():
    obj = np.empty(12, dtype=object)
    buf = io.BytesIO()
    np.save(buf, obj, allow_pickle=True)
    with pytest.raises(InputError, match="not a readable NPY file .*object arrays are refused"):
        load_point_cloud_bytes(buf.getvalue(), "o.npy")
    with pytest.raises(InputError, match=r"has shape \(20, 4\), expected \(N, 3\) or \(N, 6\)|"
                       "wrong column count 4"):  # fmt: skip
        load_point_cloud_bytes(_npy(np.zeros((20, 4))), "w.npy")
    with pytest.raises(InputError, match=r"has shape \(60,\), expected \(N, 3\)"):
        load_point_cloud_bytes(_npy(np.zeros(60)), "w.npy")
    with pytest.raises(InputError, match="dtype <U1, expected a float or integer"):
        load_point_cloud_bytes(_npy(np.array([["a", "b", "c"]] * 12)), "s.npy")
    buf = io.BytesIO()
    np.savez(buf, a=np.zeros((20, 3)), b=np.zeros((20, 3)))
    with pytest.raises(InputError, match=r"NPZ holds arrays \['a', 'b'\] but none is named"):
        load_point_cloud_bytes(buf.getvalue(), "two.npz")
    buf = io.BytesIO()
    np.savez(buf, points=np.zeros((20, 3)), normals=np.zeros((19, 3)))
    with pytest.raises(InputError, match=r"'normals' has shape \(19, 3\), expected \(20, 3\)"):
        load_point_cloud_bytes(buf.getvalue(), "n.npz")
    with pytest.raises(InputError, match="not a readable NPZ archive"):
        load_point_cloud_bytes(b"PK\x03\x04garbage", "g.npz")


def test_mesh_without_faces_or_area(tmp_path):
    (tmp_path / "v.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\n")
    with pytest.raises(InputError, match=r"v\.obj: no triangles could be read from the OBJ"):
        load_point_cloud(tmp_path / "v.obj")
    (tmp_path / "z.obj").write_text("v 0 0 0\nv 1 0 0\nv 2 0 0\nv 3 0 0\nf 1 2 3\nf 2 3 4\n")
    with pytest.raises(InputError, match=r"z\.obj: the mesh has zero surface area"):
        load_point_cloud(tmp_path / "z.obj")
    with pytest.raises(InputError, match=r"x\.stl: malformed ascii STL: no 'endsolid'"):
        load_point_cloud_bytes(b"solid x\nfacet normal 0 0 1\nouter loop\nvertex 0 0\n", "x.stl")
    stl_cut = bytes(80) + (1000).to_bytes(4, "little") + bytes(100)  # promises 1000 triangles
    with pytest.raises(InputError, match=r"y\.stl: not an STL: a binary STL of 184 bytes would "
                       r"declare 2 triangles, its header says 1000"):  # fmt: skip
        load_point_cloud_bytes(stl_cut, "y.stl")
    with pytest.raises(InputError, match=r"x\.glb: malformed GLB: 15 bytes, shorter"):
        load_point_cloud_bytes(b"glTF\x02\x00\x00\x00garbage", "x.glb")


def test_flat_mesh_is_valid_with_warning(tmp_path):
    square = "v 0 0 0\nv 0.1 0 0\nv 0.1 0.1 0\nv 0 0.1 0\nf 1 2 3\nf 1 3 4\n"
    (tmp_path / "sq.obj").write_text(square)
    c = load_point_cloud(tmp_path / "sq.obj", n_points=200)
    assert np.all(c.points[:, 2] == 0.0)
    np.testing.assert_allclose(np.abs(c.normals[:, 2]), 1.0)
    assert any("one plane" in w for w in c.warnings)


def test_bad_options(tmp_path):
    np.save(tmp_path / "a.npy", known_cloud()[0])
    with pytest.raises(InputError, match="scale must be a positive finite number, got -1"):
        load_point_cloud(tmp_path / "a.npy", scale=-1)
    with pytest.raises(InputError, match="scale must be a number"):
        load_point_cloud(tmp_path / "a.npy", scale="big")
    with pytest.raises(InputError, match=f"n_points must be between {MIN_POINTS} and"):
        load_point_cloud(tmp_path / "a.npy", n_points=3)
    with pytest.raises(InputError, match="n_points must be an integer"):
        load_point_cloud(tmp_path / "a.npy", n_points=2.5)
    with pytest.raises(InputError, match="seed must be a non-negative integer, got -2"):
        load_point_cloud(tmp_path / "a.npy", seed=-2)


# ------------------------------------------------------------------------------------------------
# PointCloud.from_array


def test_from_array():
    pts, nrm = known_cloud()
    c = PointCloud.from_array(pts, normals=3.0 * nrm, source="mine")
    np.testing.assert_array_equal(c.points, pts)
    np.testing.assert_allclose(c.normals, nrm, atol=1e-12)  # normalised
    assert c.source == "mine" and c.n_points == len(pts)
    np.testing.assert_allclose(c.extents, np.ptp(pts, axis=0))
    with pytest.raises(ValueError, match="read-only"):
        c.points[0, 0] = 1.0
    with pytest.raises(ValueError, match=r"points must have shape \(N, 3\), got \(200, 2\)"):
        PointCloud.from_array(pts[:, :2])
    with pytest.raises(ValueError, match=r"normals must have shape \(200, 3\) like points"):
        PointCloud.from_array(pts, normals=nrm[:10])
    with pytest.raises(InputError, match="only 5 finite points"):
        PointCloud.from_array(pts[:5])
    bad = pts.copy()
    bad[0] = np.nan
    c = PointCloud.from_array(bad, normals=nrm)
    assert c.n_points == len(pts) - 1 and c.normals.shape == (len(pts) - 1, 3)


def test_huge_coordinates_refused():
    pts, _ = known_cloud()
    with pytest.raises(InputError, match=r"array: coordinates reach 4.99e\+11 m .* not in metres"):
        PointCloud.from_array(pts * 1e13)
    with pytest.raises(InputError, match=r"coordinates reach inf m \(after scale 1e\+300\)"):
        load_point_cloud_bytes(_npy(pts * 1e10), "big.npy", scale=1e300)
    obj = b"v 0 0 0\nv 1e200 0 0\nv 0 1e200 0\nf 1 2 3\n"
    with pytest.raises(InputError, match=r"huge\.obj: vertex coordinates reach 1e\+200 m"):
        load_point_cloud_bytes(obj, "huge.obj")


@pytest.mark.parametrize("far", [1.0, 1e6])
def test_a_stray_point_is_dropped_and_the_plan_is_the_clean_clouds(far, caplog):
    """A scanner's stray return (one point 1 m or 10^6 m away from a mug): dropped with a
    notice naming it, and the pipeline's pre-grasps are those of the cloud without it (before,
    the point at 10^6 m crashed the pool stage with "negative dimensions not allowed")."""
    from pregrasp_core.pipeline import run_pipeline

    clean = load_point_cloud(DEFAULT_OBJECT, n_points=3000, seed=0).points
    stray = np.vstack([clean[:1500], [[far, far, far]], clean[1500:]])
    with caplog.at_level(logging.WARNING, logger="pregrasp_core.io.cloud"):
        got = PointCloud.from_array(stray, source="scan.ply")
    assert np.array_equal(got.points, clean)
    assert got.info["n_dropped_strays"] == 1
    assert "scan.ply: dropped 1 stray point(s) of 3001" in caplog.text
    assert f"({far:.4g}, {far:.4g}, {far:.4g})" in caplog.text
    pools = [run_pipeline(PointCloud.from_array(p), until="pool").pool for p in (clean, stray)]
    assert len(pools[0]) > 0
    assert np.array_equal(pools[0].T_world_hand, pools[1].T_world_hand)


def test_far_apart_objects_and_long_parts_keep_every_point():
    """Not strays: two equal objects a metre apart, a thin rod with 1 % of its points at a
    far end, and 2 % of the points far away (a second, small object)."""
    pts, _ = known_cloud(2000)
    two = PointCloud.from_array(np.vstack([pts, pts + [1.0, 0.0, 0.0]]))
    assert two.n_points == 4000 and "n_dropped_strays" not in two.info
    rng = np.random.default_rng(3)
    rod = np.c_[rng.uniform(0.0, 0.3, 1000), rng.normal(0.0, 0.002, (1000, 2))]
    rod[:10, 0] = rng.uniform(0.3, 0.6, 10)  # the sparse far end of a long part
    assert PointCloud.from_array(rod).n_points == 1000
    second = np.vstack([pts, pts[:40] * 0.1 + [2.0, 0.0, 0.0]])
    assert PointCloud.from_array(second).n_points == 2040


def test_the_collision_grid_of_points_a_million_metres_apart():
    """The pool's voxel grid of two points 10^6 m apart: the voxels per axis overflowed int64
    when multiplied, the product passed the size test and the grid failed; now the voxel grows
    until the grid fits, and both points are in it."""
    from pregrasp_core.pregrasps.collision_kernels import MAX_VOXELS, point_grid

    pts = np.array([[0.0, 0.0, 0.0], [1e6, 1e6, 1e6], [1.0, 2.0, 3.0]])
    grid = point_grid(pts, 0.005)
    assert 0 < np.prod(grid.dims.astype(np.float64)) <= MAX_VOXELS
    assert grid.start[-1] == 3 and np.array_equal(np.sort(grid.pts, axis=0), np.sort(pts, axis=0))


# ------------------------------------------------------------------------------------------------
# Fuzzing: nothing but a PregraspError ever escapes


@settings(max_examples=150, deadline=None)
@given(
    arr=hnp.arrays(
        np.float64,
        st.tuples(st.integers(0, 40), st.just(3)),
        elements=st.floats(allow_nan=True, allow_infinity=True, width=64),
    ),
    scale=st.one_of(st.none(), st.floats(1e-300, 1e300)),
)
def test_from_array_random_values_only_pregrasp_errors(arr, scale):
    try:
        c = PointCloud.from_array(arr, scale=scale)
    except PregraspError as exc:
        assert isinstance(exc, InputError | DegenerateGeometryError)
    else:
        assert np.isfinite(c.points).all() and c.n_points >= MIN_POINTS


_EXTS = list(SUPPORTED_EXTENSIONS)
_FUZZ = settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])


@pytest.mark.parametrize("ext", _EXTS)
@_FUZZ
@given(data=st.binary(min_size=1, max_size=400))
def test_random_bytes_only_pregrasp_errors(ext, data):
    try:
        load_point_cloud_bytes(data, "fuzz" + ext, n_points=50)
    except PregraspError as exc:
        assert isinstance(exc, InputError | DegenerateGeometryError)
        assert ("fuzz" + ext) in str(exc)


@pytest.mark.parametrize("ext", _EXTS)
@_FUZZ
@given(text=st.text(alphabet="0123456789.,-+eE naifx#\n\t", min_size=1, max_size=300))
def test_random_text_only_pregrasp_errors(ext, text):
    try:
        load_point_cloud_bytes(text.encode(), "fuzz" + ext, n_points=50)
    except PregraspError as exc:
        assert isinstance(exc, InputError | DegenerateGeometryError)


def _valid_files() -> dict[str, bytes]:
    pts, nrm = known_cloud(30)
    out = {}
    import tempfile

    with tempfile.TemporaryDirectory() as d:
        dp = Path(d)
        write_ply(dp / "a.ply", pts, nrm, fmt="binary_little_endian")
        write_ply(dp / "b.ply", pts, nrm, fmt="ascii")
        write_pcd(dp / "c.pcd", pts, nrm, mode="binary")
        write_pcd(dp / "d.pcd", pts, nrm, mode="ascii")
        for p in dp.iterdir():
            out[p.name] = p.read_bytes()
    out["e.npy"] = _npy(pts)
    cube = trimesh.creation.box()
    out["f.stl"] = cube.export(file_type="stl")
    out["g.glb"] = cube.export(file_type="glb")
    out["h.ply"] = cube.export(file_type="ply")
    return out


_VALID = _valid_files()


@pytest.mark.parametrize("name", sorted(_VALID))
@_FUZZ
@given(data=st.data())
def test_corrupted_valid_files_only_pregrasp_errors(name, data):
    """Flip, cut or splice bytes of a valid file: the parser must fail cleanly or read it."""
    raw = bytearray(_VALID[name])
    n_flips = data.draw(st.integers(0, 6))
    for _ in range(n_flips):
        i = data.draw(st.integers(0, len(raw) - 1))
        raw[i] = data.draw(st.integers(0, 255))
    cut = data.draw(st.integers(1, len(raw)))
    try:
        c = load_point_cloud_bytes(bytes(raw[:cut]), name, n_points=50)
    except PregraspError as exc:
        assert isinstance(exc, InputError | DegenerateGeometryError)
    else:
        assert np.isfinite(c.points).all() and c.n_points >= MIN_POINTS


# ------------------------------------------------------------------------------------------------
# Demo objects


def _manifest() -> dict[str, np.ndarray]:
    with open(OBJECTS_DIR / "manifest.csv", newline="") as f:
        return {
            r["name"]: np.array([float(v) for v in r["extents_m"].split(",")])
            for r in csv.DictReader(f)
        }


def test_every_demo_object_in_manifest_and_attribution():
    names = {p.stem for p in demo_objects()}
    assert names == set(_manifest())
    assert "mug_handle" in names and DEFAULT_OBJECT.exists()
    attribution = (OBJECTS_DIR / "ATTRIBUTION.md").read_text()
    assert "CC BY 4.0" in attribution and "make_mug_handle.py" in attribution


@pytest.mark.parametrize("path", demo_objects(), ids=lambda p: p.stem)
def test_demo_object_loads_within_manifest_extents(path):
    ext = _manifest()[path.stem]
    c = load_point_cloud(path, n_points=2000, seed=0)
    assert c.n_points == 2000 and np.isfinite(c.points).all()
    assert c.warnings == []
    lo, hi = c.bounds
    # upright, centred in x/y, resting on z = 0 (ATTRIBUTION.md), within the manifest extents
    tol = 1e-3
    assert np.all(lo >= np.array([-ext[0] / 2, -ext[1] / 2, 0.0]) - tol)
    assert np.all(hi <= np.array([ext[0] / 2, ext[1] / 2, ext[2]]) + tol)
    assert np.all(hi - lo >= 0.8 * ext)  # 2,000 surface samples reach most of the box
    np.testing.assert_allclose(np.linalg.norm(c.normals, axis=1), 1.0, atol=1e-9)


SINGLE_CLOSED_BODIES = {
    "bowl", "box_cereal", "can_soda", "fruit_lemon", "mug_handle", "ramekin", "tool_frypan",
    "toy_teddy",
}  # fmt: skip
"""Demo objects that are one closed body; the others are assemblies of overlapping closed parts
(mug, thermos, tool_hammer, toy_car) or not closed (bottle)."""


def test_demo_object_normals_point_outwards():
    """trimesh's ray-parity inside test as the reference: 0.5 mm along the normal is outside the
    solid, 0.5 mm against it inside. Strict for single closed bodies; assemblies hide some surface
    inside other parts (docs/input.md), where the offset point stays inside, so most (not all) of
    their samples pass."""
    eps = 5e-4
    singles = set()
    for path in demo_objects():
        mesh = trimesh.load(path, force="mesh")
        c = load_point_cloud(path, n_points=400, seed=5)
        outside = ~mesh.contains(c.points + eps * c.normals)
        if mesh.is_watertight and mesh.body_count == 1:
            singles.add(path.stem)
            inside = mesh.contains(c.points - eps * c.normals)
            assert outside.mean() >= 0.99 and inside.mean() >= 0.99, path.stem
        else:
            assert outside.mean() >= 0.8, path.stem
    assert singles == SINGLE_CLOSED_BODIES


def _load_script():
    spec = importlib.util.spec_from_file_location(
        "make_mug_handle", REPO / "scripts" / "make_mug_handle.py"
    )
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_mug_handle_geometry():
    """The committed default object: one watertight body with the dimensions of the brief."""
    mug = trimesh.load(DEFAULT_OBJECT, force="mesh")
    assert mug.is_watertight and mug.body_count == 1 and mug.volume > 0
    np.testing.assert_allclose(mug.extents, [0.111, 0.080, 0.100], atol=5e-4)
    lo, hi = mug.bounds
    np.testing.assert_allclose((lo + hi)[:2], 0.0, atol=1e-9)
    assert lo[2] == pytest.approx(0.0, abs=1e-9)
    mod = _load_script()
    axis_x = hi[0] - mod.HANDLE_REACH - mod.OUTER_RADIUS  # the body's axis
    assert 0.03 <= mod.HANDLE_REACH <= 0.035
    arc = np.degrees(2 * mod.handle_end_angle())
    assert 200 <= arc <= 240
    handle_h = 2 * (mod.HANDLE_ARC_RADIUS + mod.TUBE_RADIUS)
    assert 0.04 <= handle_h <= 0.05
    # inside the wall, in the cavity, inside the handle tube, in the handle's hole
    R, t, b = mod.OUTER_RADIUS, mod.WALL, mod.BOTTOM
    cx, cz = axis_x + mod.HANDLE_CENTER_X, mod.HANDLE_CENTER_Z
    probes = np.array(
        [
            [axis_x - R + t / 2, 0.0, 0.05],  # in the wall (-x side)
            [axis_x, 0.0, b / 2],  # in the bottom
            [axis_x, 0.0, 0.05],  # cavity: empty
            [cx + mod.HANDLE_ARC_RADIUS, 0.0, cz],  # in the tube, outermost part
            [cx, 0.0, cz],  # the handle's hole: empty
            [axis_x, 0.0, 0.12],  # above: empty
        ]
    )
    np.testing.assert_array_equal(mug.contains(probes), [True, True, False, True, False, False])
    # the surface seen from outside: the area matches the sampled cloud's reported area
    c = load_point_cloud(DEFAULT_OBJECT, n_points=1000)
    assert c.info["area"] == pytest.approx(mug.area)
    assert c.info["watertight"] is True


def test_mug_script_parts_are_watertight():
    mod = _load_script()
    body, handle = mod.make_body(), mod.make_handle()
    assert body.is_watertight and handle.is_watertight
    # Pappus: volume of the revolved profile = 2 pi * (profile area) * (centroid radius)
    prof = mod.body_profile()
    r, z = prof[:, 0], prof[:, 1]
    r2, z2 = np.roll(r, -1), np.roll(z, -1)
    cross = r * z2 - r2 * z
    area = cross.sum() / 2
    r_c = ((r + r2) * cross).sum() / (6 * area)
    assert body.volume == pytest.approx(2 * np.pi * abs(area) * r_c, rel=2e-3)
    # a torus section: volume = pi r^2 * (arc length of the centre line)
    arc_len = 2 * mod.handle_end_angle() * mod.HANDLE_ARC_RADIUS
    assert handle.volume == pytest.approx(np.pi * mod.TUBE_RADIUS**2 * arc_len, rel=2e-2)
