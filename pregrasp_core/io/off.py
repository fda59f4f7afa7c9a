"""OFF meshes: the text is checked here (the OFF line, the counts, V vertex lines of 3
coordinates, F face lines whose vertices exist, nothing after them), then trimesh reads it."""

from __future__ import annotations

import numpy as np

from ..errors import InputError
from .cloud import FileData
from .mesh import TriangleMesh, read_mesh
from .text import decode_text


def read_off(file: FileData) -> TriangleMesh:
    """Check the OFF text, then read its triangles with trimesh."""
    check_off(file.data, file.source)
    return read_mesh(file, "off")


def check_off(data: bytes, source: str) -> None:
    """Raise :class:`InputError` naming what makes the OFF malformed."""
    text = decode_text(data, source, "OFF")

    def bad(problem: str) -> InputError:
        return InputError(f"{source}: malformed OFF: {problem}; re-export the mesh")

    lines = [ln.split("#", 1)[0].split() for ln in text.splitlines()]
    lines = [t for t in lines if t]
    if not lines or lines[0][0].upper() not in ("OFF", "COFF"):
        raise bad("the first line must be 'OFF' (or 'COFF')")
    counts = lines[0][1:] if len(lines[0]) > 1 else (lines[1] if len(lines) > 1 else [])
    body = lines[1:] if len(lines[0]) > 1 else lines[2:]
    if len(counts) != 3 or not all(c.isascii() and c.isdigit() for c in counts):
        raise bad(f"the counts line must be 'vertices faces edges', got {' '.join(counts)!r}")
    n_v, n_f = int(counts[0]), int(counts[1])
    if len(body) != n_v + n_f:
        raise bad(
            f"the header declares {n_v} vertices and {n_f} faces ({n_v + n_f} lines), the "
            f"file holds {len(body)} lines after it"
        )
    vert_lines, face_lines = body[:n_v], body[n_v:]
    if any(len(t) < 3 for t in vert_lines):
        j = next(k for k, t in enumerate(vert_lines) if len(t) < 3)
        raise bad(f"vertex {j} has {len(vert_lines[j])} coordinates (3 are needed)")
    try:
        np.asarray([t[:3] for t in vert_lines], dtype=np.float64)
    except ValueError:
        raise bad("a vertex coordinate is not a number") from None
    sizes: list[int] = []
    refs: list[str] = []
    for j, t in enumerate(face_lines):
        n = int(t[0]) if t[0].isascii() and t[0].isdigit() and len(t[0]) < 9 else -1
        if n < 3 or len(t) < 1 + n:
            raise bad(f"face {j} {' '.join(t)[:40]!r} does not list at least 3 vertex indices")
        sizes.append(n)
        refs.extend(t[1 : 1 + n])
    try:
        idx = np.asarray(refs, dtype=np.int64)
    except (ValueError, OverflowError):
        raise bad("a face vertex index is not an integer") from None
    if idx.size and (int(idx.min()) < 0 or int(idx.max()) >= n_v):
        b = int(idx.min()) if int(idx.min()) < 0 else int(idx.max())
        raise bad(f"a face uses vertex {b}, the file has vertices 0 to {n_v - 1}")
