"""STL meshes: a binary STL must be exactly 84 + 50 x (its triangle count) bytes; an ascii STL
must hold complete facets of 3 vertices with 3 coordinates and end with ``endsolid``. Then
trimesh reads it."""

from __future__ import annotations

import numpy as np

from ..errors import InputError
from .cloud import FileData
from .mesh import TriangleMesh, read_mesh
from .text import decode_text


def read_stl(file: FileData) -> TriangleMesh:
    """Check the STL's size or text, then read its triangles with trimesh."""
    check_stl(file.data, file.source)
    return read_mesh(file, "stl")


def check_stl(data: bytes, source: str) -> None:
    """Raise :class:`InputError` naming what makes the STL malformed."""
    n_binary = int.from_bytes(data[80:84], "little") if len(data) >= 84 else -1
    if n_binary >= 0 and len(data) == 84 + 50 * n_binary:
        if n_binary == 0:
            raise InputError(f"{source}: the binary STL holds 0 triangles; nothing to read")
        return  # a binary STL of the size its header declares
    if not data.lstrip()[:5].lower() == b"solid":
        raise InputError(
            f"{source}: not an STL: a binary STL of {len(data)} bytes would declare "
            f"{(len(data) - 84) / 50:g} triangles, its header says {n_binary}; and it does not "
            "start with 'solid' (ascii STL); the file is truncated or corrupt: re-export it"
        )
    text = decode_text(data, source, "ascii STL")
    lines = [ln.split() for ln in text.splitlines()]
    lines = [t for t in lines if t]
    keys = [t[0].lower() for t in lines]

    def bad(problem: str) -> InputError:
        return InputError(f"{source}: malformed ascii STL: {problem}; re-export the mesh")

    if keys[-1] != "endsolid":
        raise bad("no 'endsolid' at the end (truncated?)")
    allowed = {"solid", "endsolid", "facet", "outer", "vertex", "endloop", "endfacet"}
    unknown = next((t for t, k in zip(lines, keys, strict=True) if k not in allowed), None)
    if unknown is not None:
        raise bad(f"unexpected line {' '.join(unknown)[:40]!r}")
    n_facet = keys.count("facet")
    if not n_facet:
        raise bad("no facets")
    if not keys.count("endfacet") == keys.count("outer") == keys.count("endloop") == n_facet:
        raise bad("a facet is incomplete (facet / outer loop / endloop / endfacet do not pair)")
    verts = [t for t, k in zip(lines, keys, strict=True) if k == "vertex"]
    if len(verts) != 3 * n_facet or any(len(t) != 4 for t in verts):
        raise bad(f"{n_facet} facets need {3 * n_facet} vertices of 3 coordinates each")
    try:
        np.asarray([t[1:] for t in verts], dtype=np.float64)
    except ValueError:
        raise bad("a vertex coordinate is not a number") from None
