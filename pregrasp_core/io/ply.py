"""PLY: point clouds (ascii, binary little/big endian) with an own parser; a PLY with faces is a
mesh, read by trimesh."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import InputError
from .cloud import FileData, RawCloud
from .mesh import TriangleMesh, read_mesh
from .text import decode_text, parse_numbers

PLY_TYPES: dict[str, str] = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}  # fmt: skip
"""PLY scalar type names -> numpy type codes (without byte order)."""


@dataclass(frozen=True)
class PlyProperty:
    """One property of a PLY element."""

    name: str
    dtype: str
    """numpy type code (the list's item type for a list property)."""
    is_list: bool


@dataclass(frozen=True)
class PlyElement:
    """One element (``vertex``, ``face``, ...) of a PLY header."""

    name: str
    count: int
    props: tuple[PlyProperty, ...]


@dataclass(frozen=True)
class PlyHeader:
    """A parsed PLY header."""

    fmt: str
    """ascii, binary_little_endian or binary_big_endian."""
    elements: tuple[PlyElement, ...]
    data_start: int
    """Byte offset of the body."""

    @property
    def n_faces(self) -> int:
        """Faces declared by every ``face`` element."""
        return sum(e.count for e in self.elements if e.name == "face")


def parse_ply_header(data: bytes, source: str) -> PlyHeader:
    """The header of a PLY file; a malformed header raises :class:`InputError`."""

    def bad(problem: str) -> InputError:
        return InputError(
            f"{source}: malformed PLY header: {problem}; re-export the file as PLY "
            "(ascii or binary)"
        )

    if not data.startswith(b"ply"):
        raise bad("it does not start with 'ply'")
    end = data.find(b"end_header")
    if end < 0:
        raise bad("no 'end_header' line")
    nl = data.find(b"\n", end)
    data_start = len(data) if nl < 0 else nl + 1
    try:
        head = data[:end].decode("ascii")
    except UnicodeDecodeError:
        raise bad("non-ASCII bytes in the header") from None
    fmt = None
    elements: list[tuple[str, int, list[PlyProperty]]] = []
    for raw in head.splitlines()[1:]:
        tok = raw.split()
        if not tok or tok[0] in ("comment", "obj_info"):
            continue
        if tok[0] == "format":
            if len(tok) < 2 or tok[1] not in (
                "ascii",
                "binary_little_endian",
                "binary_big_endian",
            ):
                raise bad(f"unknown format line {raw.strip()!r}")
            fmt = tok[1]
        elif tok[0] == "element":
            if len(tok) != 3 or not tok[2].isdigit():
                raise bad(f"bad element line {raw.strip()!r}")
            elements.append((tok[1], int(tok[2]), []))
        elif tok[0] == "property":
            if not elements:
                raise bad("a property before any element")
            if len(tok) == 5 and tok[1] == "list":
                if tok[2] not in PLY_TYPES or tok[3] not in PLY_TYPES:
                    raise bad(f"unknown type in {raw.strip()!r}")
                elements[-1][2].append(PlyProperty(tok[4], PLY_TYPES[tok[3]], True))
            elif len(tok) == 3 and tok[1] in PLY_TYPES:
                elements[-1][2].append(PlyProperty(tok[2], PLY_TYPES[tok[1]], False))
            else:
                raise bad(f"bad property line {raw.strip()!r}")
        else:
            raise bad(f"unexpected line {raw.strip()!r}")
    if fmt is None:
        raise bad("no 'format' line")
    return PlyHeader(
        fmt=fmt,
        elements=tuple(PlyElement(n, c, tuple(p)) for n, c, p in elements),
        data_start=data_start,
    )


def read_ply(file: FileData) -> RawCloud | TriangleMesh:
    """A PLY with a non-empty face element is a mesh (trimesh), else a cloud (own parser)."""
    header = parse_ply_header(file.data, file.source)
    if header.n_faces > 0:
        return read_mesh(file, "ply")
    return _read_ply_cloud(file.data, header, file.source)


def _read_ply_cloud(data: bytes, header: PlyHeader, source: str) -> RawCloud:
    """The vertex element of a PLY without faces."""
    names = [e.name for e in header.elements]
    if "vertex" not in names:
        raise InputError(f"{source}: the PLY has no 'vertex' element; nothing to read")
    vi = names.index("vertex")
    vertex = header.elements[vi]
    prop_names = [p.name for p in vertex.props]
    if not {"x", "y", "z"} <= set(prop_names):
        raise InputError(
            f"{source}: the PLY vertex element has properties {prop_names}, no x, y, z"
        )
    if any(p.is_list for p in vertex.props):
        raise InputError(
            f"{source}: the PLY vertex element has list properties, which are not supported; "
            "re-export with scalar x y z (nx ny nz)"
        )
    before = header.elements[:vi]
    if header.fmt == "ascii":
        text = decode_text(data[header.data_start :], source, "ascii PLY")
        lines = text.splitlines()
        skip = sum(e.count for e in before)
        rows = lines[skip : skip + vertex.count]
        if len(rows) < vertex.count:
            raise InputError(
                f"{source}: truncated PLY: the header promises {vertex.count} vertices, the "
                f"file holds {len(rows)}; re-export the file"
            )
        if vertex.count == 0:
            raise InputError(f"{source}: the PLY has 0 vertices; nothing to read")
        arr = parse_numbers(rows, source, "ascii PLY vertices")
        if arr.shape[1] != len(prop_names):
            raise InputError(
                f"{source}: wrong column count in the ascii PLY: {arr.shape[1]} numbers per "
                f"vertex, the header declares {len(prop_names)}"
            )
        col = {n: arr[:, i] for i, n in enumerate(prop_names)}
    else:
        order = "<" if header.fmt == "binary_little_endian" else ">"
        if any(p.is_list for e in before for p in e.props if e.count):
            raise InputError(
                f"{source}: binary PLY with list elements before the vertices is not supported; "
                "re-export with the vertex element first"
            )
        offset = header.data_start + sum(
            e.count * np.dtype([(p.name, order + p.dtype) for p in e.props]).itemsize
            for e in before
        )
        dt = np.dtype([(p.name, order + p.dtype) for p in vertex.props])
        need = offset + vertex.count * dt.itemsize
        if vertex.count == 0:
            raise InputError(f"{source}: the PLY has 0 vertices; nothing to read")
        if len(data) < need:
            raise InputError(
                f"{source}: truncated PLY: the header promises {vertex.count} vertices "
                f"({need} bytes), the file has {len(data)} bytes; re-export the file"
            )
        rec = np.frombuffer(data, dtype=dt, count=vertex.count, offset=offset)
        col = {n: rec[n].astype(np.float64) for n in prop_names}
    pts = np.column_stack([col["x"], col["y"], col["z"]])
    nrm = None
    if {"nx", "ny", "nz"} <= set(prop_names):
        nrm = np.column_stack([col["nx"], col["ny"], col["nz"]])
    return RawCloud(pts, nrm, int(vertex.count), [])
