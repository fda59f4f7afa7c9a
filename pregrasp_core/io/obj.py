"""Wavefront OBJ meshes: the text is checked here (every statement known, every vertex with 3
coordinates, every face with at least 3 vertices that exist), then trimesh reads it."""

from __future__ import annotations

import numpy as np

from ..errors import InputError
from .cloud import FileData
from .mesh import TriangleMesh, read_mesh
from .text import decode_text

OBJ_STATEMENTS: frozenset[str] = frozenset(
    {"v", "vt", "vn", "vp", "f", "l", "p", "o", "g", "s", "usemtl", "mtllib"}
)
"""OBJ statements accepted (the geometry of ``v`` and ``f`` is used, the rest ignored)."""

VERTEX_VALUES: tuple[int, ...] = (3, 4, 6, 7)
"""Numbers a ``v`` line may hold: x y z, x y z w, x y z r g b, x y z r g b a."""


def read_obj(file: FileData) -> TriangleMesh:
    """Check the OBJ text, then read its triangles with trimesh."""
    check_obj(file.data, file.source)
    return read_mesh(file, "obj")


def check_obj(data: bytes, source: str) -> None:
    """Raise :class:`InputError` naming the first line that makes the OBJ malformed."""
    text = decode_text(data, source, "OBJ")

    def bad(line_no: int, problem: str) -> InputError:
        return InputError(f"{source}: OBJ line {line_no}: {problem}; re-export the mesh")

    v_values: list[str] = []  # the numbers of every v line, flat
    v_counts: list[int] = []  # (V,) numbers per v line
    v_lines: list[int] = []  # (V,) line numbers
    f_refs: list[str] = []  # the vertex part of every face reference, flat
    f_sizes: list[int] = []  # (F,) references per face
    f_lines: list[int] = []  # (F,) line numbers
    f_vertices_before: list[int] = []  # (F,) v lines before each face
    for i, raw in enumerate(text.splitlines(), start=1):
        tok = raw.split("#", 1)[0].split()
        if not tok:
            continue
        kind = tok[0]
        if kind not in OBJ_STATEMENTS:
            if raw.rstrip().endswith("\\"):
                raise bad(i, "line continuations ('\\') are not supported")
            raise bad(i, f"unknown statement {raw.strip()[:40]!r}")
        if kind == "v":
            v_values.extend(tok[1:])
            v_counts.append(len(tok) - 1)
            v_lines.append(i)
        elif kind == "f":
            if len(tok) < 4:
                raise bad(i, f"a face needs at least 3 vertices, got {len(tok) - 1}")
            f_refs.extend(t.split("/", 1)[0] for t in tok[1:])
            f_sizes.append(len(tok) - 1)
            f_lines.append(i)
            f_vertices_before.append(len(v_counts))
    n_v = len(v_counts)
    counts = np.asarray(v_counts, dtype=np.int64)
    if n_v:
        wrong = ~np.isin(counts, VERTEX_VALUES)
        if wrong.any():
            j = int(np.argmax(wrong))
            raise bad(v_lines[j], f"a vertex with {counts[j]} coordinates (3 are needed)")
        if (counts != counts[0]).any():
            j = int(np.argmax(counts != counts[0]))
            raise bad(
                v_lines[j],
                f"a vertex with {counts[j]} numbers after vertices with {counts[0]}; give every "
                "vertex the same values",
            )
        try:
            values = np.asarray(v_values, dtype=np.float64)
        except ValueError:
            j = next((k for k, t in enumerate(v_values) if not _is_float(t)), 0)
            line = v_lines[j // int(counts[0])]
            raise bad(line, f"non-numeric coordinate {v_values[j][:30]!r}") from None
        del values
    if not f_sizes:
        return  # "no triangles" is reported after reading
    try:
        refs = np.asarray(f_refs, dtype=np.int64)  # (sum sizes,)
    except (ValueError, OverflowError):
        j = next((k for k, t in enumerate(f_refs) if not _is_int(t)), 0)
        line = f_lines[int(np.searchsorted(np.cumsum(f_sizes), j, side="right"))]
        raise bad(line, f"face vertex {f_refs[j][:30]!r} is not an integer index") from None
    sizes = np.asarray(f_sizes, dtype=np.int64)
    before = np.repeat(np.asarray(f_vertices_before, dtype=np.int64), sizes)  # (sum sizes,)
    face_of = np.repeat(np.arange(len(sizes)), sizes)  # (sum sizes,)
    # 1-based positive indices reach any vertex; negative ones count back from this line
    wrong = (refs == 0) | (refs > n_v) | (refs < -before)
    if wrong.any():
        j = int(np.argmax(wrong))
        raise bad(
            f_lines[int(face_of[j])],
            f"a face uses vertex {int(refs[j])}, the file has vertices 1 to {n_v}"
            + (" (negative indices count back from the face)" if refs[j] < 0 else ""),
        )
    if (refs < 0).any() and (before[refs < 0] != n_v).any():
        j = int(np.argmax((refs < 0) & (before != n_v)))
        raise bad(
            f_lines[int(face_of[j])],
            "a relative (negative) face index before the last vertex line is not supported; "
            "re-export with positive indices",
        )


def _is_float(s: str) -> bool:
    try:
        float(s)
    except ValueError:
        return False
    return True


def _is_int(s: str) -> bool:
    """Whether ``s`` is an integer numpy reads as int64."""
    try:
        return -(2**63) <= int(s) < 2**63
    except ValueError:
        return False
