"""Fuzz suite of the readers (issue 16): generated valid files must load with the points they
were written with, every generated mutation that breaks a format must be rejected with a
``PregraspError`` naming the file (and the check that catches it), random byte damage may only
end in a cloud or such an error, headers claiming huge counts stay far below 2 GiB of memory,
and the hand-made corpus in ``tests/data/bad/`` gives the errors its README lists.

Every file is built here by small writers that do not use the code under test (GLB by trimesh's
exporter); every load goes through ``load_point_cloud_bytes``, the upload path (the corpus is
also read from disk). Deterministic: hypothesis runs with ``derandomize=True``; each case must
end within ``CASE_SECONDS``.
"""

from __future__ import annotations

import io
import json
import re
import struct
import subprocess
import sys
import time
import tracemalloc
import zipfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import lzf
import numpy as np
import pytest
import trimesh
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from pregrasp_core.errors import DegenerateGeometryError, InputError, PregraspError
from pregrasp_core.io import MIN_POINTS, SUPPORTED_EXTENSIONS, PointCloud, load_point_cloud
from pregrasp_core.io import load_point_cloud_bytes as load_bytes

REPO = Path(__file__).resolve().parents[2]
BAD = REPO / "tests" / "data" / "bad"

CASE_SECONDS = 30.0
"""A single load slower than this is a failure (a hang)."""

N_SAMPLES = 40
"""Points sampled on generated meshes (small: the readers are under test, not the sampler)."""

FUZZ = settings(
    derandomize=True,
    deadline=None,
    database=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)

CASES = {"count": 0}
"""Cases run by the hypothesis tests of this module (checked by the last test)."""


# ------------------------------------------------------------------------------------------------
# Loading under a time bound


def timed_load(data: bytes, name: str) -> PointCloud:
    CASES["count"] += 1
    t0 = time.perf_counter()
    try:
        return load_bytes(data, name, n_points=N_SAMPLES)
    finally:
        elapsed = time.perf_counter() - t0
        assert elapsed < CASE_SECONDS, f"{name}: a load took {elapsed:.1f} s"


def assert_rejected(data: bytes, name: str, match: str) -> PregraspError:
    """The load raises a PregraspError: one line, naming the file, from the check ``match``."""
    with pytest.raises(PregraspError) as info:
        timed_load(data, name)
    msg = str(info.value)
    assert isinstance(info.value, InputError | DegenerateGeometryError)
    assert msg.startswith(name + ":"), msg
    assert "\n" not in msg, msg
    assert re.search(match, msg), f"expected /{match}/, got: {msg}"
    return info.value


def assert_loads_or_rejects(data: bytes, name: str) -> None:
    """Damaged bytes: either a usable cloud or a PregraspError naming the file."""
    try:
        cloud = timed_load(data, name)
    except PregraspError as exc:
        assert isinstance(exc, InputError | DegenerateGeometryError)
        assert str(exc).startswith(name + ":"), str(exc)
    else:
        assert np.isfinite(cloud.points).all() and cloud.n_points >= MIN_POINTS
        assert cloud.normals is None or np.isfinite(cloud.normals).all()


# ------------------------------------------------------------------------------------------------
# Generated objects


@dataclass(frozen=True)
class Cloud:
    points: np.ndarray
    """(N, 3) float64 in a 0.2 m box."""
    normals: np.ndarray
    """(N, 3) unit vectors."""


@dataclass(frozen=True)
class Mesh:
    vertices: np.ndarray
    """(V, 3) float64."""
    faces: np.ndarray
    """(F, 3) int64."""

    @property
    def area(self) -> float:
        tri = self.vertices[self.faces]
        return 0.5 * float(np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]),
                                          axis=1).sum())  # fmt: skip


def make_cloud(seed: int, n: int) -> Cloud:
    rng = np.random.default_rng(seed)
    pts = rng.uniform(-0.1, 0.1, size=(n, 3))
    nrm = rng.normal(size=(n, 3))
    return Cloud(pts, nrm / np.linalg.norm(nrm, axis=1, keepdims=True))


def make_mesh(seed: int, subdivisions: int) -> Mesh:
    """An icosphere under a random scale, rotation and translation (a closed surface)."""
    rng = np.random.default_rng(seed)
    sphere = trimesh.creation.icosphere(subdivisions=subdivisions)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.linalg.det(q))
    v = (np.asarray(sphere.vertices) * rng.uniform(0.02, 0.1, 3)) @ q.T + rng.uniform(-0.1, 0.1, 3)
    return Mesh(v, np.asarray(sphere.faces, dtype=np.int64))


clouds = st.builds(make_cloud, st.integers(0, 10_000), st.integers(MIN_POINTS, N_SAMPLES))
meshes = st.builds(make_mesh, st.integers(0, 10_000), st.integers(0, 1))


# ------------------------------------------------------------------------------------------------
# Writers (independent of pregrasp_core.io)


def g17(a: np.ndarray) -> list[str]:
    return [" ".join(f"{v:.17g}" for v in row) for row in np.atleast_2d(a)]


def ply_cloud(c: Cloud, fmt: str = "ascii", dtype: str = "f8", normals: bool = True,
              extra: bool = False, perm: list[int] | None = None) -> bytes:  # fmt: skip
    """perm: the order of the properties (x y z [nx ny nz] [quality]) in the file."""
    names = ["x", "y", "z"] + (["nx", "ny", "nz"] if normals else []) + (["quality"] * extra)
    typename = {"f4": "float", "f8": "double"}[dtype]
    cols = np.hstack([c.points] + ([c.normals] if normals else []) +
                     ([np.ones((len(c.points), 1))] if extra else []))  # fmt: skip
    if perm is not None:
        names, cols = [names[i] for i in perm], cols[:, perm]
    head = ["ply", f"format {fmt} 1.0", "comment fuzz", f"element vertex {len(cols)}"]
    head += [f"property {typename} {n}" for n in names] + ["end_header"]
    out = ("\n".join(head) + "\n").encode()
    if fmt == "ascii":
        return out + ("\n".join(g17(cols)) + "\n").encode()
    order = "<" if fmt == "binary_little_endian" else ">"
    return out + cols.astype(order + dtype).tobytes()


def ply_mesh(m: Mesh, fmt: str = "ascii") -> bytes:
    head = ["ply", f"format {fmt} 1.0", f"element vertex {len(m.vertices)}",
            "property float x", "property float y", "property float z",
            f"element face {len(m.faces)}", "property list uchar int vertex_indices",
            "end_header"]  # fmt: skip
    out = ("\n".join(head) + "\n").encode()
    if fmt == "ascii":
        rows = g17(m.vertices.astype(np.float32)) + [f"3 {a} {b} {c}" for a, b, c in m.faces]
        return out + ("\n".join(rows) + "\n").encode()
    order = "<" if fmt == "binary_little_endian" else ">"
    rec = np.zeros(len(m.faces), dtype=[("n", "u1"), ("v", order + "i4", (3,))])
    rec["n"], rec["v"] = 3, m.faces
    return out + m.vertices.astype(order + "f4").tobytes() + rec.tobytes()


def pcd(c: Cloud, mode: str = "ascii", normals: bool = True, rgb: bool = False,
        size: int = 4, perm: list[int] | None = None) -> bytes:  # fmt: skip
    """perm: the order of the fields (x y z [normal_x normal_y normal_z] [rgb]) in the file."""
    if perm is not None:  # each field as a column of its own, written in the order perm gives
        cols = [c.points[:, i] for i in range(3)] + (
            [c.normals[:, i] for i in range(3)] if normals else [])  # fmt: skip
        names = ["x", "y", "z"] + (["normal_x", "normal_y", "normal_z"] if normals else [])
        specs = [(nm, f"<f{size}", col) for nm, col in zip(names, cols, strict=True)]
        if rgb:
            specs.append(("rgb", "<u4", np.full(len(c.points), 255)))
        return _pcd_columns([specs[i] for i in perm], mode)
    fields = ["x", "y", "z"] + (["normal_x", "normal_y", "normal_z"] if normals else [])
    sizes, types = [str(size)] * len(fields), ["F"] * len(fields)
    if rgb:
        fields, sizes, types = fields + ["rgb"], sizes + ["4"], types + ["U"]
    n = len(c.points)
    head = ["# .PCD v0.7", "VERSION 0.7", "FIELDS " + " ".join(fields),
            "SIZE " + " ".join(sizes), "TYPE " + " ".join(types),
            "COUNT " + " ".join(["1"] * len(fields)), f"WIDTH {n}", "HEIGHT 1",
            "VIEWPOINT 0 0 0 1 0 0 0", f"POINTS {n}", f"DATA {mode}"]  # fmt: skip
    out = ("\n".join(head) + "\n").encode()
    floats = np.hstack([c.points] + ([c.normals] if normals else []))
    if mode == "ascii":
        cols = np.hstack([floats] + ([np.full((n, 1), 255.0)] if rgb else []))
        return out + ("\n".join(g17(cols)) + "\n").encode()
    dt = [(f, f"<f{size}") for f in fields[: floats.shape[1]]] + ([("rgb", "<u4")] if rgb else [])
    rec = np.zeros(n, dtype=dt)
    for i, f in enumerate(fields[: floats.shape[1]]):
        rec[f] = floats[:, i]
    return out + pcd_body(rec, mode)


def pcd_body(rec: np.ndarray, mode: str) -> bytes:
    """The binary body of the records ``rec``: as they are for ``binary``; for
    ``binary_compressed``, field after field (each for every point) compressed by liblzf
    (python-neo-lzf, the reference compressor), after the two sizes, as PCL writes it."""
    if mode == "binary":
        return rec.tobytes()
    raw = b"".join(np.ascontiguousarray(rec[f]).tobytes() for f in rec.dtype.names)
    packed = lzf.compress(raw, len(raw) + len(raw) // 16 + 64)  # liblzf's worst case
    return struct.pack("<II", len(packed), len(raw)) + packed


def _pcd_columns(specs: list[tuple[str, str, np.ndarray]], mode: str) -> bytes:
    """A PCD of fields (name, numpy type, (N,) values) in the given order."""
    n = len(specs[0][2])
    head = ["VERSION 0.7", "FIELDS " + " ".join(nm for nm, _, _ in specs),
            "SIZE " + " ".join(t[2:] for _, t, _ in specs),
            "TYPE " + " ".join({"f": "F", "u": "U"}[t[1]] for _, t, _ in specs),
            "COUNT " + " ".join("1" for _ in specs), f"WIDTH {n}", "HEIGHT 1",
            f"POINTS {n}", f"DATA {mode}"]  # fmt: skip
    out = ("\n".join(head) + "\n").encode()
    if mode == "ascii":
        cols = np.column_stack([v.astype(np.float64) for _, _, v in specs])
        return out + ("\n".join(g17(cols)) + "\n").encode()
    rec = np.zeros(n, dtype=[(nm, t) for nm, t, _ in specs])
    for nm, _, v in specs:
        rec[nm] = v
    return out + pcd_body(rec, mode)


def text(c: Cloud, delim: str = " ", normals: bool = False, header: bool = False,
         comment: bool = False) -> bytes:  # fmt: skip
    cols = np.hstack([c.points, c.normals]) if normals else c.points
    rows = [delim.join(f"{v:.17g}" for v in r) for r in cols]
    if header:
        rows.insert(0, delim.join(["x", "y", "z"] + (["nx", "ny", "nz"] if normals else [])))
    if comment:
        rows.insert(0, "# written by the fuzz suite")
    return ("\n".join(rows) + "\n").encode()


def npy(a: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, a, allow_pickle=a.dtype.hasobject)
    return buf.getvalue()


def npz(compressed: bool = False, **arrays: np.ndarray) -> bytes:
    buf = io.BytesIO()
    (np.savez_compressed if compressed else np.savez)(buf, **arrays)
    return buf.getvalue()


def obj(m: Mesh, refs: str = "v", comment: bool = False) -> bytes:
    rows = ["# fuzz"] if comment else []
    rows += ["o part"] + ["v " + r for r in g17(m.vertices)]
    if refs != "v":
        rows += ["vn 0 0 1", "vt 0.5 0.5"]
    fmt = {"v": "{}", "v//n": "{}//1", "v/t/n": "{}/1/1"}[refs]
    rows += ["f " + " ".join(fmt.format(i + 1) for i in f) for f in m.faces]
    return ("\n".join(rows) + "\n").encode()


def off(m: Mesh) -> bytes:
    rows = ["OFF", f"{len(m.vertices)} {len(m.faces)} 0"] + g17(m.vertices)
    rows += [f"3 {a} {b} {c}" for a, b, c in m.faces]
    return ("\n".join(rows) + "\n").encode()


def stl_binary(m: Mesh) -> bytes:
    rec = np.zeros(len(m.faces), dtype=[("n", "<f4", (3,)), ("v", "<f4", (3, 3)), ("a", "<u2")])
    rec["v"] = m.vertices[m.faces]
    return bytes(80) + struct.pack("<I", len(m.faces)) + rec.tobytes()


def stl_ascii(m: Mesh) -> bytes:
    rows = ["solid fuzz"]
    for tri in m.vertices[m.faces]:
        rows += ["facet normal 0 0 0", "outer loop"] + ["vertex " + r for r in g17(tri)]
        rows += ["endloop", "endfacet"]
    rows.append("endsolid fuzz")
    return ("\n".join(rows) + "\n").encode()


def glb(m: Mesh) -> bytes:
    return trimesh.Trimesh(m.vertices, m.faces, process=False).export(file_type="glb")


def glb_parts(data: bytes) -> tuple[dict, bytearray]:
    n = struct.unpack_from("<I", data, 12)[0]
    doc = json.loads(data[20 : 20 + n])
    m = struct.unpack_from("<I", data, 20 + n)[0]
    return doc, bytearray(data[28 + n : 28 + n + m])


def glb_pack(doc: dict, binary: bytes, version: int = 2, extra_length: int = 0) -> bytes:
    j = json.dumps(doc).encode()
    j += b" " * (-len(j) % 4)
    b = bytes(binary) + bytes(-len(binary) % 4)
    body = struct.pack("<II", len(j), 0x4E4F534A) + j + struct.pack("<II", len(b), 0x004E4942) + b
    return b"glTF" + struct.pack("<II", version, 12 + len(body) + extra_length) + body


# ------------------------------------------------------------------------------------------------
# Valid files load with the points they were written with


def check_cloud(cloud: PointCloud, pts: np.ndarray, atol: float = 0.0) -> None:
    assert cloud.info["kind"] == "cloud" and cloud.n_points == len(pts)
    np.testing.assert_allclose(cloud.points, pts, rtol=0, atol=atol)


def check_mesh(cloud: PointCloud, m: Mesh, area_rtol: float = 1e-9) -> None:
    assert cloud.info["kind"] == "mesh" and cloud.n_points == N_SAMPLES
    assert cloud.info["area"] == pytest.approx(m.area, rel=area_rtol)
    lo, hi = m.vertices.min(axis=0) - 1e-6, m.vertices.max(axis=0) + 1e-6
    assert np.all((cloud.points >= lo) & (cloud.points <= hi))


def f32(a: np.ndarray) -> np.ndarray:
    return a.astype(np.float32).astype(np.float64)


@dataclass(frozen=True)
class Reader:
    name: str
    """File name given to the loader (its extension picks the reader)."""
    valid: Callable[[st.DataObject], tuple[bytes, Callable[[PointCloud], None]]]
    """Draws a valid file and the check of its loaded cloud."""
    base: Callable[[st.DataObject], bytes]
    """Draws a valid file to be broken."""


def _perm(d: st.DataObject, permute: bool, n: int) -> list[int] | None:
    return d.draw(st.permutations(range(n))) if permute else None


def _ply_ascii(permute: bool):
    def gen(d: st.DataObject):
        c = d.draw(clouds)
        nrm, extra = d.draw(st.booleans()), d.draw(st.booleans())
        perm = _perm(d, permute, 3 + 3 * nrm + extra)
        data = ply_cloud(c, "ascii", normals=nrm, extra=extra, perm=perm)
        return data, lambda x: check_cloud(x, c.points)

    return gen


def _ply_binary(permute: bool):
    def gen(d: st.DataObject):
        c = d.draw(clouds)
        fmt = d.draw(st.sampled_from(["binary_little_endian", "binary_big_endian"]))
        dtype, nrm = d.draw(st.sampled_from(["f4", "f8"])), d.draw(st.booleans())
        ref = f32(c.points) if dtype == "f4" else c.points
        perm = _perm(d, permute, 3 + 3 * nrm)
        return ply_cloud(c, fmt, dtype, normals=nrm, perm=perm), lambda x: check_cloud(x, ref)

    return gen


def _ply_mesh(d: st.DataObject):
    m = d.draw(meshes)
    m32 = Mesh(f32(m.vertices), m.faces)
    fmt = d.draw(st.sampled_from(["ascii", "binary_little_endian", "binary_big_endian"]))
    return ply_mesh(m, fmt), lambda x: check_mesh(x, m32, 1e-6)


def _pcd(mode: str, permute: bool = False):
    def gen(d: st.DataObject):
        c = d.draw(clouds)
        size, nrm, rgb = (
            d.draw(st.sampled_from([4, 8])),
            d.draw(st.booleans()),
            d.draw(st.booleans()),
        )
        ref = c.points if (mode == "ascii" or size == 8) else f32(c.points)
        perm = _perm(d, permute, 3 + 3 * nrm + rgb)
        return pcd(c, mode, nrm, rgb, size, perm), lambda x: check_cloud(x, ref)

    return gen


def _text(delims: list[str]):
    def gen(d: st.DataObject):
        c = d.draw(clouds)
        delim = d.draw(st.sampled_from(delims))
        kw = {k: d.draw(st.booleans()) for k in ("normals", "header", "comment")}
        return text(c, delim, **kw), lambda x: check_cloud(x, c.points)

    return gen


def _npy(d: st.DataObject):
    c = d.draw(clouds)
    dtype = d.draw(st.sampled_from([np.float64, np.float32]))
    arr = np.hstack([c.points, c.normals]) if d.draw(st.booleans()) else c.points
    ref = c.points.astype(dtype).astype(np.float64)
    return npy(arr.astype(dtype)), lambda x: check_cloud(x, ref)


def _npz(d: st.DataObject):
    c = d.draw(clouds)
    key = d.draw(st.sampled_from(["points", "cloud"]))
    arrays = {key: c.points} | ({"normals": c.normals} if key == "points" else {})
    return npz(d.draw(st.booleans()), **arrays), lambda x: check_cloud(x, c.points)


def _mesh(writer: Callable[..., bytes], rtol: float, **choices: list):
    def gen(d: st.DataObject):
        m = d.draw(meshes)
        kw = {k: d.draw(st.sampled_from(v)) for k, v in choices.items()}
        ref = Mesh(f32(m.vertices), m.faces) if rtol > 1e-9 else m
        return writer(m, **kw), lambda x: check_mesh(x, ref, rtol)

    return gen


def _base(gen):
    return lambda d: gen(d)[0]


_BASES = {  # the files the breaking mutations start from: fields in the usual order
    "ply_ascii": _ply_ascii(False),
    "ply_binary": _ply_binary(False),
    "pcd_ascii": _pcd("ascii"),
    "pcd_binary": _pcd("binary"),
    "pcd_compressed": _pcd("binary_compressed"),
}
_VALID = {  # valid files; PLY and PCD with their properties / fields in any order
    "ply_ascii": ("c.ply", _ply_ascii(True)),
    "ply_binary": ("c.ply", _ply_binary(True)),
    "ply_mesh": ("m.ply", _ply_mesh),
    "pcd_ascii": ("c.pcd", _pcd("ascii", True)),
    "pcd_binary": ("c.pcd", _pcd("binary", True)),
    "pcd_compressed": ("c.pcd", _pcd("binary_compressed", True)),
    "xyz": ("c.xyz", _text([" ", "\t", "  "])),
    "txt": ("c.txt", _text([" ", ","])),
    "csv": ("c.csv", _text([",", ", "])),
    "npy": ("c.npy", _npy),
    "npz": ("c.npz", _npz),
    "obj": ("m.obj", _mesh(obj, 1e-9, refs=["v", "v//n", "v/t/n"], comment=[False, True])),
    "off": ("m.off", _mesh(off, 1e-9)),
    "stl_ascii": ("m.stl", _mesh(stl_ascii, 1e-9)),
    "stl_binary": ("m.stl", _mesh(stl_binary, 1e-6)),
    "glb": ("m.glb", _mesh(glb, 1e-6)),
}
READERS = {k: Reader(name, gen, _base(_BASES.get(k, gen))) for k, (name, gen) in _VALID.items()}


@pytest.mark.parametrize("kind", sorted(READERS))
@settings(FUZZ, max_examples=30)
@given(d=st.data())
def test_valid_files_load(kind, d):
    reader = READERS[kind]
    data, check = reader.valid(d)
    check(timed_load(data, reader.name))


# ------------------------------------------------------------------------------------------------
# Mutations that break a format: each must be rejected by the check it names


def lines_of(data: bytes) -> list[bytes]:
    return data.split(b"\n")


def replace_once(data: bytes, old: bytes, new: bytes) -> bytes:
    assert old in data, old
    return data.replace(old, new, 1)


def header_end(data: bytes) -> int:
    return data.index(b"end_header\n") + len(b"end_header\n")


def _sub_count(data: bytes, key: bytes, delta: int) -> bytes:
    m = re.search(rb"(" + key + rb" )(\d+)", data)
    assert m
    return data[: m.start(2)] + str(int(m.group(2)) + delta).encode() + data[m.end(2) :]


def _set_count(data: bytes, key: bytes, value: int) -> bytes:
    m = re.search(rb"(" + key + rb" )(\d+)", data)
    assert m
    return data[: m.start(2)] + str(value).encode() + data[m.end(2) :]


Mutation = Callable[[bytes, st.DataObject], bytes]
k_small = st.integers(1, 5)
huge = st.sampled_from([10**9, 2**31, 2**32 + 3, 10**12, 2**63 - 1, 10**15])

PLY_BREAKS: list[tuple[str, Mutation, str]] = [
    (
        "property twice",
        lambda b, d: (
            replace_once(b, b"property double y\n", b"property double y\nproperty double y\n")
            if b"double y" in b
            else replace_once(b, b"property float y\n", b"property float y\nproperty float y\n")
        ),
        "property 'y' of element 'vertex' twice",
    ),
    (
        "element twice",
        lambda b, d: replace_once(
            b, b"end_header", b"element vertex 1\nproperty float x\nend_header"
        ),
        "element 'vertex' declared twice",
    ),
    (
        "count too big",
        lambda b, d: _sub_count(b, b"element vertex", d.draw(k_small)),
        "truncated PLY",
    ),
    (
        "count too small",
        lambda b, d: _sub_count(b, b"element vertex", -d.draw(k_small)),
        "after the last item",
    ),
    ("huge count", lambda b, d: _set_count(b, b"element vertex", d.draw(huge)), "truncated PLY"),
    ("body cut", lambda b, d: b[: len(b) - d.draw(st.integers(1, 30))], "truncated PLY"),
    (
        "bytes appended",
        lambda b, d: b + b"\x00\x01\x02\x03" * d.draw(k_small),
        "after the last item|contains binary data",
    ),
    (
        "unknown type",
        lambda b, d: replace_once(b, b"property ", b"property quad "),
        "bad property line",
    ),
    ("no end_header", lambda b, d: b[: header_end(b) - len(b"end_header\n")], "no 'end_header'"),
    (
        "format version",
        lambda b, d: re.sub(rb" 1\.0\n", b" 2.0\n", b, count=1),
        "unknown format line",
    ),
    (
        "two formats",
        lambda b, d: replace_once(b, b"ply\n", b"ply\nformat ascii 1.0\n"),
        "two 'format' lines",
    ),
    (
        "non-ascii header",
        lambda b, d: replace_once(b, b"ply\n", b"ply\ncomment caf\xc3\xa9\n"),
        "non-ASCII bytes in the header",
    ),
    (
        "property first",
        lambda b, d: replace_once(b, b"ply\n", b"ply\nproperty float w\n"),
        "a property before any element",
    ),
    ("no ply magic", lambda b, d: b"plx" + b[3:], "does not start with 'ply'"),
]
PLY_ASCII_BREAKS = PLY_BREAKS[:5] + PLY_BREAKS[7:] + [
    ("lines cut", lambda b, d: b"\n".join(lines_of(b)[: -1 - d.draw(k_small)]) + b"\n",
     "truncated PLY"),
    ("non-numeric", lambda b, d: _first_row(b, header_end(b), lambda r: b"0.1 zero " + r),
     "non-numeric|different numbers of columns|wrong column count"),
    ("row short", lambda b, d: _first_row(b, header_end(b), lambda r: b"0.5 0.5"),
     "different numbers of columns|wrong column count"),
    ("extra line", lambda b, d: b + b"0 0 0\n", "lines after the last item"),
]  # fmt: skip
PLY_MESH_BREAKS = [
    ("face index past vertices", lambda b, d: _face_value(b, d, lambda nv: nv + d.draw(k_small)),
     "face uses vertex"),
    ("negative face index", lambda b, d: _face_value(b, d, lambda nv: -d.draw(k_small)),
     "face uses vertex -"),
    ("face count too big", lambda b, d: _sub_count(b, b"element face", d.draw(k_small)),
     "truncated PLY"),
    ("face count too small", lambda b, d: _sub_count(b, b"element face", -d.draw(k_small)),
     "after the last item"),
    ("huge face count", lambda b, d: _set_count(b, b"element face", d.draw(huge)),
     "truncated PLY"),
    ("vertex twice", PLY_BREAKS[1][1], "element 'vertex' declared twice"),
    ("float list length", lambda b, d: replace_once(b, b"list uchar", b"list float"),
     "list length must be an integer"),
    ("body cut", lambda b, d: _cut_mesh_body(b, d.draw(st.integers(1, 30))), "truncated PLY"),
]  # fmt: skip


def _cut_mesh_body(data: bytes, k: int) -> bytes:
    """Cut k bytes off a binary body, or k lines off an ascii one (bytes could leave a valid
    file: '3 0 1 12' cut by one digit still reads)."""
    if b"format ascii" in data:
        return b"\n".join(data.rstrip(b"\n").split(b"\n")[:-k]) + b"\n"
    return data[:-k]


def _first_row(data: bytes, start: int, edit: Callable[[bytes], bytes]) -> bytes:
    """Replace the first body line (from byte ``start``) by ``edit(line)``."""
    end = data.index(b"\n", start)
    return data[:start] + edit(data[start:end]) + data[end:]


def _face_value(data: bytes, d: st.DataObject, value: Callable[[int], int]) -> bytes:
    """Set one vertex index of one face of a PLY mesh written by ``ply_mesh``."""
    nv = int(re.search(rb"element vertex (\d+)", data).group(1))
    nf = int(re.search(rb"element face (\d+)", data).group(1))
    i, j = d.draw(st.integers(0, nf - 1)), d.draw(st.integers(0, 2))
    v = value(nv)
    start = header_end(data)
    if b"format ascii" in data:
        rows = data[start:].split(b"\n")
        tok = rows[nv + i].split()
        tok[1 + j] = str(v).encode()
        rows[nv + i] = b" ".join(tok)
        return data[:start] + b"\n".join(rows)
    order = "<" if b"little" in data else ">"
    at = start + nv * 12 + i * 13 + 1 + 4 * j
    return data[:at] + struct.pack(order + "i", v) + data[at + 4 :]


def _pcd_fields(data: bytes, fields: bytes, sizes: bytes, types: bytes, counts: bytes) -> bytes:
    out = re.sub(rb"FIELDS [^\n]*", b"FIELDS " + fields, data, count=1)
    out = re.sub(rb"SIZE [^\n]*", b"SIZE " + sizes, out, count=1)
    out = re.sub(rb"TYPE [^\n]*", b"TYPE " + types, out, count=1)
    return re.sub(rb"COUNT [^\n]*", b"COUNT " + counts, out, count=1)


def _pcd_data_start(data: bytes) -> int:
    return data.index(b"\n", data.index(b"DATA ")) + 1


PCD_BREAKS: list[tuple[str, Mutation, str]] = [
    ("key twice", lambda b, d: replace_once(b, b"HEIGHT 1\n", b"HEIGHT 1\nHEIGHT 1\n"),
     "HEIGHT given twice"),
    ("field twice", lambda b, d: _pcd_fields(b, b"x y z z", b"4 4 4 4", b"F F F F", b"1 1 1 1"),
     "field 'z' named twice"),
    ("sizes short", lambda b, d: re.sub(rb"SIZE (\S+) ", b"SIZE ", b, count=1),
     "same number of entries"),
    ("huge COUNT", lambda b, d: re.sub(rb"COUNT 1", b"COUNT " + str(d.draw(huge)).encode(), b,
                                        count=1), "has COUNT"),
    ("huge POINTS", lambda b, d: _set_count(_set_count(b, b"POINTS", v := d.draw(huge)), b"WIDTH",
                                            v), "truncated PCD|declares .* points, the data has"),
    ("WIDTH x HEIGHT", lambda b, d: _sub_count(b, b"WIDTH", d.draw(k_small)),
     "differs from POINTS"),
    ("points too many", lambda b, d: _sub_count(_sub_count(b, b"POINTS", k := d.draw(k_small)),
                                                b"WIDTH", k),
     "truncated PCD|declares .* points, the data has"),
    ("points too few", lambda b, d: _sub_count(_sub_count(b, b"POINTS", -(k := d.draw(k_small))),
                                               b"WIDTH", -k),
     "bytes after the|declares .* points, the data has"),
    ("unknown DATA", lambda b, d: replace_once(b, b"DATA ", b"DATA lz4_"), "unknown DATA mode"),
    ("TYPE F SIZE 2", lambda b, d: re.sub(rb"SIZE \d", b"SIZE 2", b, count=1),
     "unsupported TYPE F SIZE 2"),
    ("no DATA", lambda b, d: b[: b.index(b"DATA ")], "no DATA line"),
    ("VIEWPOINT", lambda b, d: replace_once(b, b"VIEWPOINT 0 0 0 1 0 0 0", b"VIEWPOINT 0 0 0"),
     "VIEWPOINT must be 7 numbers"),
    ("WIDTH text", lambda b, d: re.sub(rb"WIDTH \d+", b"WIDTH many", b, count=1),
     "must be integers"),
    ("no z", lambda b, d: re.sub(rb"FIELDS x y z", b"FIELDS x y q", b, count=1), "no 'z'"),
    ("unknown key", lambda b, d: replace_once(b, b"VERSION", b"VERSIOM"), "unexpected line"),
    ("no HEIGHT", lambda b, d: re.sub(rb"HEIGHT 1\n", b"", b, count=1), "no HEIGHT line"),
]  # fmt: skip
PCD_BINARY_BREAKS = PCD_BREAKS + [
    ("body cut", lambda b, d: b[: len(b) - d.draw(st.integers(1, 30))], "truncated PCD"),
    ("bytes appended", lambda b, d: b + bytes(d.draw(k_small)), "bytes after the"),
    (
        "read as compressed",
        lambda b, d: re.sub(rb"DATA \w+", b"DATA binary_compressed", b, count=1),
        "once decompressed|truncated PCD|bytes after the data",
    ),
]


def _pcd_sizes(data: bytes, n_comp: int | None = None, n_raw: int | None = None) -> bytes:
    """A compressed PCD with the sizes before its stream replaced."""
    at = _pcd_data_start(data)
    old = struct.unpack_from("<II", data, at)
    new = (old[0] if n_comp is None else n_comp, old[1] if n_raw is None else n_raw)
    return data[:at] + struct.pack("<II", *new) + data[at + 8 :]


def _first_token(data: bytes) -> bytes:
    """A compressed PCD whose stream starts with a back reference (before the start)."""
    at = _pcd_data_start(data) + 8
    return data[:at] + b"\x20\x05" + data[at + 2 :]


PCD_COMPRESSED_BREAKS = PCD_BREAKS + [
    ("stream cut", lambda b, d: b[: len(b) - d.draw(st.integers(1, 30))], "truncated PCD"),
    ("bytes appended", lambda b, d: b + bytes(d.draw(k_small)), "bytes after the data"),
    (
        "sizes cut",
        lambda b, d: b[: _pcd_data_start(b) + d.draw(st.integers(0, 7))],
        "the compressed data has no sizes",
    ),
    (
        "raw size",
        lambda b, d: _pcd_sizes(
            b,
            n_raw=struct.unpack_from("<I", b, _pcd_data_start(b) + 4)[0]
            + d.draw(st.integers(-8, 8).filter(bool)),
        ),
        "declares .* points, the data has .* bytes once decompressed \\(.* needed\\)",
    ),
    (
        "stream shortened",
        lambda b, d: (lambda k: _pcd_sizes(b[:-k], n_comp=len(b[:-k]) - _pcd_data_start(b) - 8))(
            d.draw(st.integers(1, 8))
        ),
        "corrupt compressed PCD data",
    ),
    (
        "reference before start",
        lambda b, d: _first_token(b),
        "corrupt compressed PCD data \\(a back reference points before its start",
    ),
]
PCD_ASCII_BREAKS = PCD_BREAKS + [
    ("rows cut", lambda b, d: b"\n".join(lines_of(b)[: -1 - d.draw(k_small)]) + b"\n",
     "declares .* points, the data has"),
    ("row added", lambda b, d: b + b" ".join([b"0.01"] * len(
        re.search(rb"FIELDS ([^\n]*)", b).group(1).split())) + b"\n",
     "declares .* points, the data has"),
    ("row short", lambda b, d: _first_row(b, _pcd_data_start(b), lambda r: b"0.5 0.5"),
     "different numbers of columns|wrong column count"),
    ("non-numeric", lambda b, d: _first_row(b, _pcd_data_start(b), lambda r: b"a" + r[1:]),
     "non-numeric"),
    ("binary bytes", lambda b, d: b + b"\x00\x00", "contains binary data"),
]  # fmt: skip


def _text_rows(data: bytes) -> list[bytes]:
    return [r for r in data.split(b"\n") if r and not r.startswith(b"#") and r[:1] not in b"xn"]


TEXT_BREAKS: list[tuple[str, Mutation, str]] = [
    ("row short", lambda b, d: b + b"0.5 0.5\n", "different numbers of columns"),
    ("non-numeric", lambda b, d: b + b"0.5 zero 0.5\n" if b"," not in b else b + b"0.5,zero,0.5\n",
     "non-numeric data|different numbers of columns"),
    ("NUL bytes", lambda b, d: b[:10] + b"\x00" + b[10:], "contains binary data"),
    ("bad UTF-8", lambda b, d: b[:10] + b"\xff\xfe\xfd" + b[10:], "not UTF-8"),
    ("UTF-16", lambda b, d: b.decode().encode("utf-16"), "UTF-16"),
    ("too few points", lambda b, d: b"\n".join(_text_rows(b)[: d.draw(st.integers(1, MIN_POINTS -
                                                                                  1))]) + b"\n",
     f"at least {MIN_POINTS} are needed"),
    ("all identical", lambda b, d: b"\n".join([_text_rows(b)[0]] * 30) + b"\n",
     "points are identical"),
    ("collinear", lambda b, d: "\n".join(f"{t:.17g} {2 * t:.17g} {-t:.17g}" for t in np.linspace(
        0, 0.1, d.draw(st.integers(MIN_POINTS, 40)))).encode() + b"\n", "lie on one line"),
    ("all NaN", lambda b, d: b"nan nan nan\n" * d.draw(st.integers(1, 40)), "only 0 finite points"),
    ("65 columns", lambda b, d: "\n".join(" ".join(["0.1"] * 65) for _ in range(20)).encode(),
     "wrong column count 65"),
    ("only comments", lambda b, d: b"# nothing\n\n# here\n", "no data rows"),
]  # fmt: skip


def _npy_header_shape(data: bytes, shape: str) -> bytes:
    """An NPY whose header declares ``shape`` (the header is re-padded to its length)."""
    n = struct.unpack_from("<H", data, 8)[0]
    head = data[10 : 10 + n].decode("latin1")
    new = re.sub(r"'shape': \([^)]*\)", f"'shape': {shape}", head).rstrip()
    new = new + " " * (n - 1 - len(new)) + "\n"
    assert len(new) == n
    return data[:10] + new.encode("latin1") + data[10 + n :]


NPY_BREAKS: list[tuple[str, Mutation, str]] = [
    ("shape larger", lambda b, d: _npy_header_shape(b, f"({d.draw(st.integers(61, 200))}, 3)"),
     "the header declares shape"),
    ("huge shape", lambda b, d: _npy_header_shape(b, f"({d.draw(huge)}, 3)"),
     "the header declares shape"),
    ("data cut", lambda b, d: b[: len(b) - d.draw(st.integers(1, 64))], "the header declares shape"
     "|not a readable NPY"),
    ("bytes appended", lambda b, d: b + bytes(d.draw(st.integers(1, 64))),
     "the header declares shape"),
    ("object array", lambda b, d: npy(np.array([[0.1, 0.2, "z"]] * 20, dtype=object)),
     "holds Python objects"),
    ("4 columns", lambda b, d: npy(np.zeros((20, 4))), "wrong column count 4"),
    ("1-D", lambda b, d: npy(np.zeros(60)), r"expected \(N, 3\)"),
    ("strings", lambda b, d: npy(np.array([["a", "b", "c"]] * 20)), "dtype <U1"),
    ("bad magic", lambda b, d: b"\x93NUMPX" + b[6:], "not a readable NPY"),
    ("too few rows", lambda b, d: npy(np.random.default_rng(0).random((d.draw(st.integers(
        1, MIN_POINTS - 1)), 3))), f"at least {MIN_POINTS} are needed"),
    ("an NPZ", lambda b, d: npz(points=np.zeros((20, 3))), "an NPZ archive"),
]  # fmt: skip


def _zip_with(name: str, payload: bytes) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        zf.writestr(name, payload)
    return buf.getvalue()


NPZ_BREAKS: list[tuple[str, Mutation, str]] = [
    ("no points key", lambda b, d: npz(a=np.zeros((20, 3)), b=np.ones((20, 3))),
     "none is named 'points'"),
    ("normals mismatch", lambda b, d: npz(points=np.random.default_rng(1).random((20, 3)),
                                          normals=np.ones((19, 3))), "'normals' has shape"),
    ("garbage", lambda b, d: b"PK\x03\x04" + bytes(d.draw(st.binary(min_size=1, max_size=60))),
     "not a readable NPZ"),
    ("zip cut", lambda b, d: b[: len(b) - d.draw(st.integers(1, 40))], "not a readable NPZ"),
    ("member claims huge shape", lambda b, d: _zip_with("points.npy", _npy_header_shape(
        npy(np.zeros((20, 3))), f"({d.draw(huge)}, 3)")), "the header declares shape"),
    ("member object array", lambda b, d: _zip_with("points.npy", npy(np.array([[1, 2, "a"]] * 20,
                                                                              dtype=object))),
     "holds Python objects"),
    ("member not NPY", lambda b, d: _zip_with("points.npy", b"hello"), "not a readable NPY"),
    ("4 columns", lambda b, d: npz(points=np.zeros((20, 4))), "wrong column count 4"),
]  # fmt: skip


def _obj_lines(data: bytes, kind: bytes) -> list[int]:
    rows = data.split(b"\n")
    return [i for i, r in enumerate(rows) if r.startswith(kind + b" ")]


def _obj_edit(data: bytes, d: st.DataObject, kind: bytes, edit: Callable[[bytes], bytes]) -> bytes:
    rows = data.split(b"\n")
    i = d.draw(st.sampled_from(_obj_lines(data, kind)))
    rows[i] = edit(rows[i])
    return b"\n".join(rows)


def _obj_face_ref(data: bytes, d: st.DataObject, value: Callable[[int], int]) -> bytes:
    nv = len(_obj_lines(data, b"v"))

    def edit(row: bytes) -> bytes:
        tok = row.split()
        j = d.draw(st.integers(1, len(tok) - 1))
        rest = tok[j][tok[j].index(b"/") :] if b"/" in tok[j] else b""
        tok[j] = str(value(nv)).encode() + rest
        return b" ".join(tok)

    return _obj_edit(data, d, b"f", edit)


OBJ_BREAKS: list[tuple[str, Mutation, str]] = [
    ("vertex of 2", lambda b, d: _obj_edit(b, d, b"v", lambda r: b" ".join(r.split()[:3])),
     "a vertex with 2 coordinates"),
    ("vertex of 4 among 3", lambda b, d: _obj_edit(b, d, b"v", lambda r: r + b" 1"),
     "a vertex with 4 numbers after vertices with 3|vertices with 4"),
    ("face past vertices", lambda b, d: _obj_face_ref(b, d, lambda nv: nv + d.draw(k_small)),
     "face uses vertex"),
    ("face index 0", lambda b, d: _obj_face_ref(b, d, lambda nv: 0), "face uses vertex 0"),
    ("face index past int64", lambda b, d: _obj_face_ref(b, d, lambda nv: 10**19 + nv),
     "not an integer index"),
    ("negative past start", lambda b, d: _obj_face_ref(b, d, lambda nv: -nv - d.draw(k_small)),
     "face uses vertex -"),
    ("face of 2", lambda b, d: _obj_edit(b, d, b"f", lambda r: b" ".join(r.split()[:3])),
     "at least 3 vertices, got 2"),
    ("non-numeric coordinate", lambda b, d: _obj_edit(b, d, b"v", lambda r: r.replace(b" ", b" x",
                                                                                     1)),
     "non-numeric coordinate"),
    ("unknown statement", lambda b, d: replace_once(b, b"o part", b"0.1 0.2 0.3"),
     "unknown statement"),
    ("float face index", lambda b, d: _obj_edit(b, d, b"f", lambda r: re.sub(rb" (\d+)", rb" \1.5",
                                                                             r, count=1)),
     "not an integer index"),
    ("NUL bytes", lambda b, d: b[:5] + b"\x00" + b[5:], "contains binary data"),
    ("bad UTF-8", lambda b, d: b[:5] + b"\xc3\x28" + b[5:], "not UTF-8"),
    ("no faces", lambda b, d: b"\n".join(r for r in b.split(b"\n") if not r.startswith(b"f ")),
     "no triangles"),
    ("zero size", lambda b, d: re.sub(rb"(?m)^v [^\n]*", b"v 0.5 0.5 0.5", b), "zero surface area"),
]  # fmt: skip


def _off_rows(data: bytes) -> list[bytes]:
    return data.rstrip(b"\n").split(b"\n")


def _off_face(data: bytes, d: st.DataObject, value: Callable[[int], int]) -> bytes:
    rows = _off_rows(data)
    nv, nf = (int(x) for x in rows[1].split()[:2])
    i, j = 2 + nv + d.draw(st.integers(0, nf - 1)), d.draw(st.integers(1, 3))
    tok = rows[i].split()
    tok[j] = str(value(nv)).encode()
    rows[i] = b" ".join(tok)
    return b"\n".join(rows) + b"\n"


def _off_same_vertices(data: bytes) -> bytes:
    rows = _off_rows(data)
    nv = int(rows[1].split()[0])
    rows[2 : 2 + nv] = [b"0.5 0.5 0.5"] * nv
    return b"\n".join(rows) + b"\n"


def _off_counts(data: bytes, dv: int, df: int) -> bytes:
    rows = _off_rows(data)
    nv, nf, ne = (int(x) for x in rows[1].split())
    rows[1] = f"{nv + dv} {nf + df} {ne}".encode()
    return b"\n".join(rows) + b"\n"


OFF_BREAKS: list[tuple[str, Mutation, str]] = [
    ("face count too big", lambda b, d: _off_counts(b, 0, d.draw(k_small)), "the header declares"),
    ("face count too small", lambda b, d: _off_counts(b, 0, -d.draw(k_small)),
     "the header declares"),
    ("vertex count too big", lambda b, d: _off_counts(b, d.draw(k_small), 0),
     "the header declares|does not list|has 1 coordinates|has 2 coordinates"),
    ("huge counts", lambda b, d: _off_counts(b, d.draw(huge), d.draw(huge)), "the header declares"),
    ("face past vertices", lambda b, d: _off_face(b, d, lambda nv: nv + d.draw(st.integers(0, 5))),
     "face uses vertex"),
    ("negative face index", lambda b, d: _off_face(b, d, lambda nv: -d.draw(k_small)),
     "face uses vertex -"),
    ("vertex of 2", lambda b, d: _first_row(b, b.index(b"\n", 4) + 1,
                                            lambda r: b" ".join(r.split()[:2])),
     "has 2 coordinates"),
    ("no OFF line", lambda b, d: b[4:], "the first line must be 'OFF'"),
    ("counts text", lambda b, d: b.replace(b"\n", b"\nmany ", 1), "counts line"),
    ("face of 2", lambda b, d: re.sub(rb"\n3 (\d+) (\d+) (\d+)", rb"\n2 \1 \2", b, count=1),
     "at least 3 vertex indices"),
    ("extra line", lambda b, d: b + b"3 0 1 2\n", "the header declares"),
    ("zero size", lambda b, d: _off_same_vertices(b), "zero surface area"),
]  # fmt: skip

STL_BINARY_BREAKS: list[tuple[str, Mutation, str]] = [
    ("count too big", lambda b, d: b[:80] + struct.pack("<I", struct.unpack_from("<I", b, 80)[0] +
                                                        d.draw(k_small)) + b[84:], "not an STL"),
    ("count too small", lambda b, d: b[:80] + struct.pack("<I", struct.unpack_from("<I", b, 80)[
        0] - d.draw(k_small)) + b[84:], "not an STL"),
    ("huge count", lambda b, d: b[:80] + struct.pack("<I", 2**32 - d.draw(k_small)) + b[84:],
     "not an STL"),
    ("body cut", lambda b, d: b[: len(b) - d.draw(st.integers(1, 49))], "not an STL"),
    ("bytes appended", lambda b, d: b + bytes(d.draw(st.integers(1, 49))), "not an STL"),
    ("zero triangles", lambda b, d: bytes(84), "0 triangles"),
    ("zero size", lambda b, d: b[:84] + b"".join(bytes(50) for _ in range(struct.unpack_from(
        "<I", b, 80)[0])), "zero surface area"),
]  # fmt: skip
STL_ASCII_BREAKS: list[tuple[str, Mutation, str]] = [
    ("no endsolid", lambda b, d: b[: b.rindex(b"endsolid")], "no 'endsolid'"),
    ("vertex removed", lambda b, d: _drop_line(b, d, b"vertex"), "vertices of 3 coordinates"),
    ("endloop removed", lambda b, d: _drop_line(b, d, b"endloop"), "a facet is incomplete"),
    ("non-numeric", lambda b, d: b.replace(b"vertex ", b"vertex x", 1), "not a number"),
    ("vertex of 2", lambda b, d: re.sub(rb"vertex (\S+) (\S+) (\S+)", rb"vertex \1 \2", b,
                                        count=1), "vertices of 3 coordinates"),
    ("unknown line", lambda b, d: b.replace(b"outer loop", b"outer loop\ncolor 1 0 0", 1),
     "unexpected line"),
    ("cut", lambda b, d: b[: d.draw(st.integers(20, len(b) - 20))], "no 'endsolid'"),
    ("bad UTF-8", lambda b, d: b.replace(b"fuzz", b"fu\xffz", 1), "not UTF-8"),
]  # fmt: skip


def _drop_line(data: bytes, d: st.DataObject, key: bytes) -> bytes:
    rows = data.split(b"\n")
    idx = [i for i, r in enumerate(rows) if r.strip().startswith(key)]
    del rows[d.draw(st.sampled_from(idx))]
    return b"\n".join(rows)


def _glb_edit(data: bytes, edit: Callable[[dict, bytearray], None]) -> bytes:
    doc, binary = glb_parts(data)
    edit(doc, binary)
    return glb_pack(doc, binary)


def _glb_bad_index(doc: dict, binary: bytearray, value: int, which: int) -> None:
    acc = doc["accessors"][doc["meshes"][0]["primitives"][0]["indices"]]
    view = doc["bufferViews"][acc["bufferView"]]
    at = view.get("byteOffset", 0) + acc.get("byteOffset", 0) + 4 * (which % acc["count"])
    struct.pack_into("<I", binary, at, value)


def _glb_n_vertices(data: bytes) -> int:
    doc, _ = glb_parts(data)
    return doc["accessors"][doc["meshes"][0]["primitives"][0]["attributes"]["POSITION"]]["count"]


GLB_BREAKS: list[tuple[str, Mutation, str]] = [
    ("length field", lambda b, d: b[:8] + struct.pack("<I", len(b) + d.draw(k_small)) + b[12:],
     "the header declares"),
    ("cut", lambda b, d: b[: len(b) - d.draw(st.integers(1, 100))], "the header declares"),
    ("accessor count huge", lambda b, d: _glb_edit(b, lambda j, x: j["accessors"][0].update(
        count=d.draw(huge))), "runs past bufferView"),
    ("accessor count +1", lambda b, d: _glb_edit(b, lambda j, x: j["accessors"][1].update(
        count=j["accessors"][1]["count"] + d.draw(k_small))), "runs past bufferView"),
    ("view past buffer", lambda b, d: _glb_edit(b, lambda j, x: j["bufferViews"][0].update(
        byteLength=j["buffers"][0]["byteLength"] + d.draw(k_small))), "runs past buffer"),
    ("buffer past BIN", lambda b, d: _glb_edit(b, lambda j, x: j["buffers"][0].update(
        byteLength=len(x) + 4 * d.draw(k_small))), "the BIN chunk has"),
    ("missing accessor", lambda b, d: _glb_edit(b, lambda j, x: j["meshes"][0]["primitives"][
        0].update(indices=len(j["accessors"]) + d.draw(st.integers(0, 9)))),
     "expected an index below"),
    ("node cycle", lambda b, d: _glb_edit(b, lambda j, x: j["nodes"].extend(
        [{"children": [len(j["nodes"]) + 1]}, {"children": [len(j["nodes"])]}])),
     "cycle|two parents"),
    ("own child", lambda b, d: _glb_edit(b, lambda j, x: j["nodes"][0].update(children=[0])),
     "own child"),
    ("face past vertices", lambda b, d: _glb_edit(b, lambda j, x: _glb_bad_index(
        j, x, _glb_n_vertices(b) + d.draw(st.integers(0, 1000)), d.draw(st.integers(0, 59)))),
     "face uses vertex"),
    ("float indices", lambda b, d: _glb_edit(b, lambda j, x: j["accessors"][j["meshes"][0][
        "primitives"][0]["indices"]].update(componentType=5126)),
     "indices are not unsigned"),
    ("version 1", lambda b, d: b[:4] + struct.pack("<I", 1) + b[8:], "version 1"),
    ("bad JSON", lambda b, d: glb_pack({}, b"")[:20] + b"{not json" + bytes(3),
     "JSON cannot be read"),
    ("bad magic", lambda b, d: b"gltf" + b[4:], "does not start with the 'glTF' header"),
    ("buffer uri outside", lambda b, d: _glb_edit(b, lambda j, x: j["buffers"][0].update(
        uri=d.draw(st.sampled_from(["/dev/zero", "../../etc/passwd", "file:///etc/passwd",
                                    "%2e%2e/x.bin", "https://example.com/x.bin"])))),
     "is not a file beside the GLTF"),
    ("image uri outside", lambda b, d: _glb_edit(b, lambda j, x: j.update(
        images=[{"uri": "/dev/urandom"}])), "image 0 uri '/dev/urandom' is not a file beside"),
    ("no POSITION", lambda b, d: _glb_edit(b, lambda j, x: j["meshes"][0]["primitives"][0][
        "attributes"].pop("POSITION")), "no POSITION attribute"),
]  # fmt: skip

BREAKS: dict[str, list[tuple[str, Mutation, str]]] = {
    "ply_ascii": PLY_ASCII_BREAKS,
    "ply_binary": PLY_BREAKS,
    "ply_mesh": PLY_MESH_BREAKS,
    "pcd_ascii": PCD_ASCII_BREAKS,
    "pcd_binary": PCD_BINARY_BREAKS,
    "pcd_compressed": PCD_COMPRESSED_BREAKS,
    "xyz": TEXT_BREAKS,
    "txt": TEXT_BREAKS,
    "csv": TEXT_BREAKS,
    "npy": NPY_BREAKS,
    "npz": NPZ_BREAKS,
    "obj": OBJ_BREAKS,
    "off": OFF_BREAKS,
    "stl_ascii": STL_ASCII_BREAKS,
    "stl_binary": STL_BINARY_BREAKS,
    "glb": GLB_BREAKS,
}


BREAK_CASES = [(kind, i) for kind, rows in sorted(BREAKS.items()) for i in range(len(rows))]


@pytest.mark.parametrize(
    ("kind", "index"), BREAK_CASES, ids=[f"{k}-{BREAKS[k][i][0]}" for k, i in BREAK_CASES]
)
@settings(FUZZ, max_examples=8)
@given(d=st.data())
def test_breaking_mutation_rejected(kind, index, d):
    reader = READERS[kind]
    base = reader.base(d)
    label, mutate, match = BREAKS[kind][index]
    broken = mutate(base, d)
    assert broken != base, label
    assert_rejected(broken, reader.name, match)


# ------------------------------------------------------------------------------------------------
# Random damage: a cloud or a clean error, never anything else


@pytest.mark.parametrize("kind", sorted(READERS))
@settings(FUZZ, max_examples=60)
@given(d=st.data())
def test_random_damage_only_pregrasp_errors(kind, d):
    reader = READERS[kind]
    raw = bytearray(reader.base(d))
    for _ in range(d.draw(st.integers(0, 8))):
        op = d.draw(st.sampled_from(["flip", "insert", "delete", "digit"]))
        i = d.draw(st.integers(0, len(raw) - 1))
        if op == "flip":
            raw[i] = d.draw(st.integers(0, 255))
        elif op == "insert":
            raw[i:i] = d.draw(st.binary(min_size=1, max_size=8))
        elif op == "delete":
            del raw[i : i + d.draw(st.integers(1, 16))]
        else:  # a digit somewhere becomes a run of digits (huge counts, long numbers)
            raw[i:i] = b"9" * d.draw(st.integers(1, 30))
        if not raw:
            raw = bytearray(b"\x00")
    cut = d.draw(st.integers(1, len(raw)))
    assert_loads_or_rejects(bytes(raw[:cut]), reader.name)


@pytest.mark.parametrize("ext", SUPPORTED_EXTENSIONS)
@settings(FUZZ, max_examples=20)
@given(data=st.binary(min_size=1, max_size=300))
def test_upload_of_random_bytes(ext, data):
    assert_loads_or_rejects(data, "upload" + ext)


# ------------------------------------------------------------------------------------------------
# Memory: headers claiming huge counts are refused before anything is allocated


def _huge_claims() -> dict[str, bytes]:
    c = make_cloud(3, 40)
    m = make_mesh(3, 1)
    cz = pcd(c, "binary_compressed")  # x y z and normals, 4 bytes each: 24 bytes per point
    out = {
        "vertex.ply": _set_count(ply_cloud(c, "binary_little_endian"), b"element vertex", 10**12),
        "vertex_ascii.ply": _set_count(ply_cloud(c), b"element vertex", 2**40),
        "face.ply": _set_count(ply_mesh(m, "binary_little_endian"), b"element face", 10**11),
        "points.pcd": _set_count(_set_count(pcd(c, "binary"), b"POINTS", 10**11), b"WIDTH", 10**11),
        "count.pcd": re.sub(rb"COUNT 1", b"COUNT 1000000000", pcd(c, "binary"), count=1),
        "compressed.pcd": _pcd_sizes(
            _set_count(_set_count(cz, b"POINTS", 10**8), b"WIDTH", 10**8), n_raw=10**8 * 24
        ),
        "ratio.pcd": _pcd_sizes(
            _set_count(_set_count(cz, b"POINTS", 10**7), b"WIDTH", 10**7), n_raw=10**7 * 24
        ),
        "shape.npy": _npy_header_shape(npy(c.points), "(100000000000, 3)"),
        "member.npz": _zip_with("points.npy", _npy_header_shape(npy(c.points), "(10000000000, 3)")),
        "counts.off": _off_counts(off(m), 10**10, 10**10),
        "count.stl": stl_binary(m)[:80] + struct.pack("<I", 2**32 - 1) + stl_binary(m)[84:],
        "count.glb": _glb_edit(glb(m), lambda j, x: j["accessors"][1].update(count=10**11)),
    }
    return out


def test_huge_counts_allocate_little():
    """tracemalloc (numpy reports its buffers to it): every huge claim is refused with at most a
    few MiB allocated."""
    claims = _huge_claims()
    tracemalloc.start()
    try:
        for name, data in claims.items():
            tracemalloc.reset_peak()
            with pytest.raises(InputError, match=re.escape(name)):
                load_bytes(data, name, n_points=N_SAMPLES)
            _, peak = tracemalloc.get_traced_memory()
            assert peak < 8 * 2**20, f"{name}: {peak / 2**20:.1f} MiB"
    finally:
        tracemalloc.stop()


_RSS_SCRIPT = r"""
import sys
import numpy as np

def peak():  # this process's own peak RSS, KiB (VmHWM; ru_maxrss keeps the parent's across exec)
    return int([ln for ln in open("/proc/self/status") if ln.startswith("VmHWM:")][0].split()[1])

from pregrasp_core.io import load_point_cloud_bytes
from pregrasp_core.errors import PregraspError
n = 4_000_000  # a 48 MiB binary PLY whose header claims 2**40 vertices, and the valid one
head = b"ply\nformat binary_little_endian 1.0\nelement vertex %d\nproperty float x\n" \
       b"property float y\nproperty float z\nend_header\n"
body = np.random.default_rng(0).random((n, 3), dtype=np.float32).tobytes()
before = peak()
try:
    load_point_cloud_bytes(head % 2**40 + body, "huge.ply")
    sys.exit("accepted")
except PregraspError as exc:
    assert "huge.ply: truncated PLY" in str(exc), exc
claimed = peak()
cloud = load_point_cloud_bytes(head % n + body, "big.ply", n_points=20000)
assert cloud.n_points == 20000
valid = peak()
print(before, claimed, valid)  # KiB (Linux)
"""


def test_peak_memory_of_a_50_mib_input():
    """A fresh interpreter: growth of its peak RSS (VmHWM, KiB) for a 48 MiB binary PLY claiming
    2**40 vertices stays near the input's own size, and reading the valid 48 MiB file stays far
    below 2 GiB."""
    proc = subprocess.run(
        [sys.executable, "-c", _RSS_SCRIPT],
        capture_output=True, text=True, cwd=REPO, timeout=120,
        env={"PYTHONPATH": str(REPO), "OPENBLAS_NUM_THREADS": "1", "PATH": ""},
    )  # fmt: skip
    assert proc.returncode == 0, proc.stdout + proc.stderr
    before, claimed, valid = (int(v) for v in proc.stdout.split())
    assert (claimed - before) * 1024 < 200 * 2**20
    assert (valid - before) * 1024 < 2**30


def test_glb_instancing_bounded(monkeypatch):
    """Nodes instancing one mesh multiply its triangles: past the bound the GLB is refused
    before trimesh expands it (the bound lowered here so that a small file reaches it)."""
    from pregrasp_core.io import gltf

    m = make_mesh(1, 0)  # 20 triangles

    def ten(doc: dict, binary: bytearray) -> None:
        n = len(doc["nodes"])
        doc["nodes"].extend({"mesh": 0, "translation": [0.3 * k, 0.0, 0.0]} for k in range(1, 10))
        doc["scenes"][0]["nodes"].extend(range(n, n + 9))

    many = _glb_edit(glb(m), ten)
    monkeypatch.setattr(gltf, "MAX_GLTF_TRIANGLES", 200)
    copies = Mesh(
        np.vstack([m.vertices + [0.3 * k, 0.0, 0.0] for k in range(10)]),
        np.vstack([m.faces + k * len(m.vertices) for k in range(10)]),
    )
    check_mesh(timed_load(many, "ten.glb"), copies, 1e-6)
    monkeypatch.setattr(gltf, "MAX_GLTF_TRIANGLES", 199)
    assert_rejected(many, "ten.glb", "its nodes place 200 triangles, more than 199")


# ------------------------------------------------------------------------------------------------
# The hand-made corpus: tests/data/bad/README.md lists each file and its expected error


def _corpus() -> list[tuple[str, str]]:
    rows = []
    for line in (BAD / "README.md").read_text().splitlines():
        m = re.match(r"\| `([^`]+)` \| [^|]+ \| `([^`]+)` \|", line)
        if m:
            rows.append((m.group(1), m.group(2)))
    return rows


def test_corpus_readme_lists_every_file():
    listed = {name for name, _ in _corpus()}
    present = {p.name for p in BAD.iterdir() if p.name not in ("README.md", "make_bad_files.py")}
    assert listed == present
    assert len(listed) >= 20


@pytest.mark.parametrize(("name", "match"), _corpus())
def test_corpus_file_rejected(name, match):
    path = BAD / name
    with pytest.raises(PregraspError) as info:
        load_point_cloud(path, n_points=N_SAMPLES)
    msg = str(info.value)
    assert msg.startswith(str(path) + ":") and "\n" not in msg
    assert re.search(match, msg), msg
    assert_rejected(path.read_bytes(), name, match)  # the same through the upload path


# ------------------------------------------------------------------------------------------------


def test_at_least_2000_cases():
    """The hypothesis tests above ran at least 2,000 loads (when the whole module runs)."""
    if CASES["count"] < 1000:
        pytest.skip("only part of the module ran")
    print(f"\nfuzz cases: {CASES['count']}")
    assert CASES["count"] >= 2000, CASES
