"""Write the hand-made bad input files of this folder (each small, one per known failure of
issue 16; README.md lists what each one is and the error it must give). Run from the repository
root: ``python tests/data/bad/make_bad_files.py``. Uses numpy only, never pregrasp_core."""

from __future__ import annotations

import io
import json
import struct
import zipfile
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
RNG = np.random.default_rng(16)
PTS = RNG.uniform(-0.05, 0.05, size=(20, 3))
ROWS = "".join(f"{x:.6f} {y:.6f} {z:.6f}\n" for x, y, z in PTS)
PLY_HEAD = (
    "ply\nformat ascii 1.0\nelement vertex {n}\nproperty float x\nproperty float y\n"
    "property float z\n{extra}end_header\n"
)
PLY_BINARY_HEAD = (
    "ply\nformat binary_little_endian 1.0\nelement vertex {n}\nproperty float x\n"
    "property float y\nproperty float z\nend_header\n"
)
PLY_MESH_HEAD = (
    "ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\n"
    "property float z\nelement face {f}\nproperty list uchar int vertex_indices\nend_header\n"
)
TETRA_V = "v 0 0 0\nv 0.1 0 0\nv 0 0.1 0\nv 0 0 0.1\n"
TETRA_F = "f 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n"
OFF_V = "0 0 0\n0.1 0 0\n0 0.1 0\n0 0 0.1\n"
OFF_F = "3 0 2 1\n3 0 1 3\n3 0 3 2\n"


def pcd_head(
    n: int,
    mode: str = "ascii",
    fields: str = "x y z",
    size: str = "4 4 4",
    types: str = "F F F",
    count: str = "1 1 1",
) -> str:
    return (
        f"VERSION 0.7\nFIELDS {fields}\nSIZE {size}\nTYPE {types}\nCOUNT {count}\nWIDTH {n}\n"
        f"HEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA {mode}\n"
    )


def npy_bytes(a: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, a)
    return buf.getvalue()


def glb(doc: dict, binary: bytes) -> bytes:
    j = json.dumps(doc).encode()
    j += b" " * (-len(j) % 4)
    b = binary + bytes(-len(binary) % 4)
    body = struct.pack("<II", len(j), 0x4E4F534A) + j + struct.pack("<II", len(b), 0x004E4942) + b
    return b"glTF" + struct.pack("<II", 2, 12 + len(body)) + body


def tetra_glb(indices: list[int], count: int | None = None) -> bytes:
    """A tetrahedron as GLB with the given triangle indices (and index accessor count)."""
    verts = np.array([[0, 0, 0], [0.1, 0, 0], [0, 0.1, 0], [0, 0, 0.1]], dtype="<f4")
    idx = np.array(indices, dtype="<u4")
    binary = idx.tobytes() + verts.tobytes()
    doc = {
        "asset": {"version": "2.0"},
        "buffers": [{"byteLength": len(binary)}],
        "bufferViews": [
            {"buffer": 0, "byteOffset": 0, "byteLength": idx.nbytes},
            {"buffer": 0, "byteOffset": idx.nbytes, "byteLength": verts.nbytes},
        ],
        "accessors": [
            {"bufferView": 0, "componentType": 5125, "type": "SCALAR",
             "count": len(idx) if count is None else count},
            {"bufferView": 1, "componentType": 5126, "type": "VEC3", "count": 4,
             "min": [0, 0, 0], "max": [0.1, 0.1, 0.1]},
        ],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 1}, "indices": 0}]}],
        "nodes": [{"mesh": 0}],
        "scenes": [{"nodes": [0]}],
        "scene": 0,
    }  # fmt: skip
    return glb(doc, binary)


def main() -> None:
    with_zero = "".join(r + " 0\n" for r in ROWS.splitlines())
    npy_claim = npy_bytes(PTS).replace(b"'shape': (20, 3)", b"'shape': (99999, 3)")
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:  # an archive member whose header claims more rows
        zf.writestr("points.npy", npy_claim)
    files: dict[str, bytes | str] = {
        # PLY / PCD headers
        "ply_property_twice.ply": PLY_HEAD.format(n=20, extra="property float z\n") + with_zero,
        "ply_vertex_twice.ply": PLY_HEAD.format(
            n=20, extra="element vertex 20\nproperty float x\nproperty float y\nproperty float z\n"
        )
        + ROWS
        + ROWS,
        "ply_huge_count.ply": PLY_BINARY_HEAD.format(n=10**12),
        "ply_truncated.ply": PLY_BINARY_HEAD.format(n=20).encode()
        + PTS.astype("<f4").tobytes()[:-7],
        "pcd_field_twice.pcd": pcd_head(20, "ascii", "x y z z", "4 4 4 4", "F F F F", "1 1 1 1")
        + with_zero,
        "pcd_key_twice.pcd": pcd_head(20).replace("HEIGHT 1\n", "HEIGHT 1\nHEIGHT 2\n") + ROWS,
        "pcd_huge_count.pcd": pcd_head(20, "binary", count="1 1 1000000000").encode()
        + PTS.astype("<f4").tobytes(),
        "pcd_huge_points.pcd": pcd_head(10**11, "binary"),
        "pcd_truncated.pcd": pcd_head(20, "binary").encode() + PTS.astype("<f4").tobytes()[:-5],
        # meshes
        "obj_face_past_vertices.obj": TETRA_V + TETRA_F + "f 1 2 9\n",
        "obj_vertex_2_coordinates.obj": TETRA_V.replace("v 0 0.1 0\n", "v 0 0.1\n") + TETRA_F,
        "obj_negative_past_start.obj": TETRA_V + TETRA_F + "f -1 -2 -7\n",
        "off_face_past_vertices.off": "OFF\n4 4 0\n" + OFF_V + OFF_F + "3 1 2 7\n",
        "off_negative_index.off": "OFF\n4 4 0\n" + OFF_V + OFF_F + "3 1 2 -1\n",
        "off_more_faces_declared.off": "OFF\n4 9 0\n" + OFF_V + OFF_F + "3 1 2 3\n",
        "ply_more_faces_declared.ply": PLY_MESH_HEAD.format(f=9) + OFF_V + OFF_F + "3 1 2 3\n",
        "ply_negative_face_index.ply": PLY_MESH_HEAD.format(f=4) + OFF_V + OFF_F + "3 1 2 -1\n",
        "glb_face_past_vertices.glb": tetra_glb([0, 2, 1, 0, 1, 3, 0, 3, 2, 1, 2, 40]),
        "glb_huge_accessor.glb": tetra_glb([0, 2, 1, 0, 1, 3, 0, 3, 2, 1, 2, 3], 10**12),
        "stl_truncated.stl": bytes(80) + struct.pack("<I", 4) + bytes(50 * 3 + 20),
        "zero_area.obj": "v 0 0 0\nv 0 0 0\nv 0 0 0\nf 1 2 3\n",
        # clouds
        "too_few_points.xyz": "".join(ROWS.splitlines(keepends=True)[:12]),
        "nan_rows.xyz": "".join(ROWS.splitlines(keepends=True)[:5]) + "nan nan nan\n" * 30,
        "identical_points.xyz": "0.1 0.2 0.3\n" * 20,
        "collinear_points.csv": "".join(f"{t:.3f},{2 * t:.3f},{3 * t:.3f}\n" for t in range(20)),
        "empty.xyz": b"",
        "binary_garbage.xyz": bytes(range(256)),
        "latin1_text.txt": ("# mesure précise\n" + ROWS).encode("latin-1"),
        "utf16_text.txt": ROWS.encode("utf-16"),
        "npy_shape_past_data.npy": npy_claim,
        "npz_header_past_data.npz": buf.getvalue(),
    }
    for name, data in files.items():
        (HERE / name).write_bytes(data.encode() if isinstance(data, str) else data)


if __name__ == "__main__":
    main()
