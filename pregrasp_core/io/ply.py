"""PLY: point clouds (ascii, binary little/big endian) with an own parser; a PLY with faces is a
mesh: its faces are checked here (counts, sizes, vertex indices), then trimesh reads it.

Every header field is checked before anything is allocated: a single ``format`` line of version
1.0, each element named once, each property named once per element, element counts that fit
the body (ascii: one line per item; binary: the bytes each item needs), and a body that ends
where the header says (no missing and no extra items)."""

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

PLY_FORMATS: tuple[str, ...] = ("ascii", "binary_little_endian", "binary_big_endian")
"""The three PLY encodings."""

FACE_INDEX_NAMES: tuple[str, ...] = ("vertex_indices", "vertex_index")
"""Names of the face element's list of vertex indices (trimesh reads either)."""


@dataclass(frozen=True)
class PlyProperty:
    """One property of a PLY element."""

    name: str
    dtype: str
    """numpy type code (the list's item type for a list property)."""
    is_list: bool
    count_dtype: str = "u1"
    """numpy type code of a list's length."""


@dataclass(frozen=True)
class PlyElement:
    """One element (``vertex``, ``face``, ...) of a PLY header."""

    name: str
    count: int
    props: tuple[PlyProperty, ...]

    @property
    def has_lists(self) -> bool:
        """Whether any property is a list (items of varying size)."""
        return any(p.is_list for p in self.props)

    def min_item_bytes(self) -> int:
        """Bytes of the smallest binary item (lists of length 0)."""
        return sum(np.dtype(p.count_dtype if p.is_list else p.dtype).itemsize for p in self.props)


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
        """Faces declared by the ``face`` element."""
        return sum(e.count for e in self.elements if e.name == "face")

    @property
    def order(self) -> str:
        """numpy byte order of a binary body."""
        return ">" if self.fmt == "binary_big_endian" else "<"


def _bad_header(source: str, problem: str) -> InputError:
    return InputError(
        f"{source}: malformed PLY header: {problem}; re-export the file as PLY (ascii or binary)"
    )


def parse_ply_header(data: bytes, source: str) -> PlyHeader:
    """The header of a PLY file; a malformed header raises :class:`InputError`."""
    first_nl = data.find(b"\n")
    if data[: first_nl if first_nl >= 0 else len(data)].strip() != b"ply":
        raise _bad_header(source, "it does not start with 'ply'")
    pos = first_nl + 1
    lines: list[bytes] = []
    while True:
        nl = data.find(b"\n", pos)
        if nl < 0:
            rest = data[pos:].strip()
            if rest == b"end_header":  # the body is empty
                pos = len(data)
                break
            raise _bad_header(source, "no 'end_header' line")
        line = data[pos:nl].strip()
        pos = nl + 1
        if line == b"end_header":
            break
        lines.append(line)
    data_start = pos
    fmt = None
    elements: list[tuple[str, int, list[PlyProperty]]] = []
    for raw_b in lines:
        try:
            raw = raw_b.decode("ascii")
        except UnicodeDecodeError:
            raise _bad_header(source, "non-ASCII bytes in the header") from None
        tok = raw.split()
        if not tok or tok[0] in ("comment", "obj_info"):
            continue
        if tok[0] == "format":
            if len(tok) != 3 or tok[1] not in PLY_FORMATS or tok[2] != "1.0":
                raise _bad_header(source, f"unknown format line {raw.strip()!r}")
            if fmt is not None:
                raise _bad_header(source, "two 'format' lines")
            fmt = tok[1]
        elif tok[0] == "element":
            if len(tok) != 3 or not tok[2].isdigit() or not tok[2].isascii():
                raise _bad_header(source, f"bad element line {raw.strip()!r}")
            if any(e[0] == tok[1] for e in elements):
                raise _bad_header(source, f"element {tok[1]!r} declared twice")
            elements.append((tok[1], int(tok[2]), []))
        elif tok[0] == "property":
            if not elements:
                raise _bad_header(source, "a property before any element")
            if len(tok) == 5 and tok[1] == "list":
                if tok[2] not in PLY_TYPES or tok[3] not in PLY_TYPES:
                    raise _bad_header(source, f"unknown type in {raw.strip()!r}")
                if PLY_TYPES[tok[2]][0] == "f":
                    raise _bad_header(source, f"a list length must be an integer: {raw!r}")
                prop = PlyProperty(tok[4], PLY_TYPES[tok[3]], True, PLY_TYPES[tok[2]])
            elif len(tok) == 3 and tok[1] in PLY_TYPES:
                prop = PlyProperty(tok[2], PLY_TYPES[tok[1]], False)
            else:
                raise _bad_header(source, f"bad property line {raw.strip()!r}")
            name, _, props = elements[-1]
            if any(p.name == prop.name for p in props):
                raise _bad_header(source, f"property {prop.name!r} of element {name!r} twice")
            props.append(prop)
        else:
            raise _bad_header(source, f"unexpected line {raw.strip()[:60]!r}")
    if fmt is None:
        raise _bad_header(source, "no 'format' line")
    for name, count, props in elements:
        if count > 0 and not props:
            raise _bad_header(source, f"element {name!r} has {count} items but no properties")
    header = PlyHeader(
        fmt=fmt,
        elements=tuple(PlyElement(n, c, tuple(p)) for n, c, p in elements),
        data_start=data_start,
    )
    _check_counts_fit(data, header, source)
    return header


def _check_counts_fit(data: bytes, header: PlyHeader, source: str) -> None:
    """Element counts no larger than the body can hold (before anything is allocated)."""
    body = len(data) - header.data_start
    if header.fmt == "ascii":
        need = sum(e.count for e in header.elements)  # one line (at least 2 bytes) per item
        if need * 2 > body + 1:
            raise InputError(
                f"{source}: truncated PLY: the header declares {need} items (lines), the body "
                f"has {body} bytes; re-export the file"
            )
        return
    need = sum(e.count * e.min_item_bytes() for e in header.elements)
    if need > body:
        what = ", ".join(
            f"{e.count} vertices" if e.name == "vertex" else f"{e.count} {e.name} items"
            for e in header.elements
        )
        raise InputError(
            f"{source}: truncated PLY: the header promises {what} (at least {need} "
            f"bytes), the body has {body} bytes; re-export the file"
        )


def read_ply(file: FileData) -> RawCloud | TriangleMesh:
    """A PLY with a non-empty face element is a mesh (trimesh), else a cloud (own parser)."""
    header = parse_ply_header(file.data, file.source)
    if header.n_faces > 0:
        _check_faces(file.data, header, file.source)
        return read_mesh(file, "ply")
    return _read_ply_cloud(file.data, header, file.source)


def _vertex_element(header: PlyHeader, source: str) -> tuple[int, PlyElement]:
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
    if vertex.has_lists:
        raise InputError(
            f"{source}: the PLY vertex element has list properties, which are not supported; "
            "re-export with scalar x y z (nx ny nz)"
        )
    if vertex.count == 0:
        raise InputError(f"{source}: the PLY has 0 vertices; nothing to read")
    return vi, vertex


def _ascii_rows(data: bytes, header: PlyHeader, source: str) -> list[str]:
    """The body's lines, exactly one per declared item (else truncated / extra data)."""
    text = decode_text(data[header.data_start :], source, "ascii PLY")
    lines = text.rstrip().splitlines() if text.strip() else []
    need = sum(e.count for e in header.elements)
    if len(lines) < need:
        vertex = next((e for e in header.elements if e.name == "vertex"), None)
        if vertex is not None and sum(
            e.count for e in header.elements[: header.elements.index(vertex) + 1]
        ) > len(lines):
            raise InputError(
                f"{source}: truncated PLY: the header promises {vertex.count} vertices, the "
                f"file holds {max(0, len(lines) - _items_before(header, vertex))}; re-export "
                "the file"
            )
        raise InputError(
            f"{source}: truncated PLY: the header declares {need} items (lines), the body "
            f"holds {len(lines)}; re-export the file"
        )
    if len(lines) > need:
        raise InputError(
            f"{source}: {len(lines) - need} lines after the last item the header declares "
            f"({need}); the element counts are wrong or the file is corrupt: re-export it"
        )
    return lines


def _check_ascii_elements(
    lines: list[str], header: PlyHeader, source: str, skip: tuple[str, ...]
) -> None:
    """Rows of the scalar-only elements not named in ``skip``: numbers, one per property."""
    for e in header.elements:
        if e.name in skip or e.has_lists or e.count == 0:
            continue
        start = _items_before(header, e)
        arr = parse_numbers(lines[start : start + e.count], source, f"ascii PLY {e.name} rows")
        if arr.shape != (e.count, len(e.props)):
            raise InputError(
                f"{source}: wrong column count in the ascii PLY {e.name} rows: {arr.shape[1]} "
                f"numbers per row, the header declares {len(e.props)}"
            )


def _items_before(header: PlyHeader, element: PlyElement) -> int:
    return sum(e.count for e in header.elements[: header.elements.index(element)])


def _read_ply_cloud(data: bytes, header: PlyHeader, source: str) -> RawCloud:
    """The vertex element of a PLY without faces."""
    vi, vertex = _vertex_element(header, source)
    prop_names = [p.name for p in vertex.props]
    before = header.elements[:vi]
    if header.fmt == "ascii":
        lines = _ascii_rows(data, header, source)
        skip = _items_before(header, vertex)
        _check_ascii_elements(lines, header, source, skip=("vertex",))
        arr = parse_numbers(lines[skip : skip + vertex.count], source, "ascii PLY vertices")
        if arr.shape[1] != len(prop_names):
            raise InputError(
                f"{source}: wrong column count in the ascii PLY: {arr.shape[1]} numbers per "
                f"vertex, the header declares {len(prop_names)}"
            )
        if arr.shape[0] != vertex.count:
            raise InputError(
                f"{source}: the ascii PLY has {arr.shape[0]} vertex rows of numbers, the header "
                f"declares {vertex.count} (a '#' in the body?); re-export the file"
            )
        col = {n: arr[:, i] for i, n in enumerate(prop_names)}
    else:
        order = header.order
        if any(e.has_lists for e in header.elements if e.count):
            raise InputError(
                f"{source}: binary PLY with list elements but no faces is not supported; "
                "re-export the points alone"
            )
        offset = header.data_start + sum(
            e.count * np.dtype([(p.name, order + p.dtype) for p in e.props]).itemsize
            for e in before
        )
        dt = np.dtype([(p.name, order + p.dtype) for p in vertex.props])
        need = header.data_start + sum(
            e.count * np.dtype([(p.name, order + p.dtype) for p in e.props]).itemsize
            for e in header.elements
            if e.count
        )
        if len(data) < need:
            raise InputError(
                f"{source}: truncated PLY: the header promises {vertex.count} vertices "
                f"({need} bytes), the file has {len(data)} bytes; re-export the file"
            )
        if len(data) > need:
            raise InputError(
                f"{source}: {len(data) - need} bytes after the last item the header declares; "
                "the element counts are wrong or the file is corrupt: re-export it"
            )
        rec = np.frombuffer(data, dtype=dt, count=vertex.count, offset=offset)
        col = {n: rec[n].astype(np.float64) for n in prop_names}
    pts = np.column_stack([col["x"], col["y"], col["z"]])
    nrm = None
    if {"nx", "ny", "nz"} <= set(prop_names):
        nrm = np.column_stack([col["nx"], col["ny"], col["nz"]])
    return RawCloud(pts, nrm, int(vertex.count), [])


# ----------------------------------------------------------------------------------------------
# Faces of a PLY mesh


def _face_index_position(face: PlyElement, source: str) -> int:
    lists = [i for i, p in enumerate(face.props) if p.is_list and p.name in FACE_INDEX_NAMES]
    if not lists:
        raise InputError(
            f"{source}: the PLY face element has no list property 'vertex_indices'; "
            "re-export the mesh"
        )
    prop = face.props[lists[0]]
    if prop.dtype[0] == "f":
        raise InputError(f"{source}: the PLY face indices are floats; re-export the mesh")
    return lists[0]


def _check_indices(lengths: np.ndarray, indices: np.ndarray, n_vertices: int, source: str) -> None:
    """lengths: (F,) vertices per face; indices: (sum lengths,) vertex indices."""
    if lengths.size and int(lengths.min()) < 3:
        raise InputError(
            f"{source}: a PLY face has {int(lengths.min())} vertices (at least 3 are needed); "
            "the file is corrupt: re-export it"
        )
    if indices.size and (int(indices.min()) < 0 or int(indices.max()) >= n_vertices):
        bad = int(indices.min()) if int(indices.min()) < 0 else int(indices.max())
        raise InputError(
            f"{source}: a PLY face uses vertex {bad}, the file has vertices 0 to "
            f"{n_vertices - 1}; the file is corrupt: re-export it"
        )


def _check_faces(data: bytes, header: PlyHeader, source: str) -> None:
    """The face element's sizes and vertex indices (and that the body ends where it should)."""
    _, vertex = _vertex_element(header, source)
    face = next(e for e in header.elements if e.name == "face")
    k = _face_index_position(face, source)
    if header.fmt == "ascii":
        lines = _ascii_rows(data, header, source)
        _check_ascii_elements(lines, header, source, skip=())
        skip = _items_before(header, face)
        lengths = np.empty(face.count, dtype=np.int64)
        chunks: list[list[int]] = []
        for i, line in enumerate(lines[skip : skip + face.count]):
            tok = line.split()
            at = 0
            try:
                for j, p in enumerate(face.props):
                    if p.is_list:
                        n = int(tok[at])
                        if n < 0 or at + 1 + n > len(tok):
                            raise ValueError
                        if j == k:
                            lengths[i] = n
                            chunks.append([int(t) for t in tok[at + 1 : at + 1 + n]])
                        at += 1 + n
                    else:
                        float(tok[at])
                        at += 1
            except (ValueError, IndexError):
                raise InputError(
                    f"{source}: ascii PLY face {i}: {line.strip()[:60]!r} does not match the "
                    "header's face properties; re-export the file"
                ) from None
            if at != len(tok):
                raise InputError(
                    f"{source}: ascii PLY face {i} has {len(tok) - at} numbers more than the "
                    "header's face properties; re-export the file"
                )
        flat = [v for c in chunks for v in c]
        _check_indices(lengths, np.asarray(flat, dtype=np.int64), vertex.count, source)
        return
    order = header.order
    pos = header.data_start
    for e in header.elements:
        if not e.has_lists:
            pos += e.count * np.dtype([(p.name, order + p.dtype) for p in e.props]).itemsize
            continue
        if e is face:
            lengths, indices, pos = _binary_list_element(data, pos, e, k, order, source)
            _check_indices(lengths, indices, vertex.count, source)
        else:
            _, _, pos = _binary_list_element(data, pos, e, None, order, source)
    if pos > len(data):
        raise InputError(
            f"{source}: truncated PLY: the body ends {pos - len(data)} bytes early; "
            "re-export the file"
        )
    if pos < len(data):
        raise InputError(
            f"{source}: {len(data) - pos} bytes after the last item the header declares; "
            "the element counts are wrong or the file is corrupt: re-export it"
        )


def _binary_list_element(
    data: bytes, pos: int, e: PlyElement, k: int | None, order: str, source: str
) -> tuple[np.ndarray, np.ndarray, int]:
    """Walk a binary element with lists: ((F,) lengths and flat values of list ``k``, end)."""

    def truncated() -> InputError:
        return InputError(
            f"{source}: truncated PLY: the {e.name} element ({e.count} items) runs past the end "
            "of the file; re-export the file"
        )

    if e.count == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), pos
    # Fast path: every list as long as in the first item (triangles, quads) -> one strided view.
    fields: list[tuple[str, str] | tuple[str, str, tuple[int]]] = []
    at = pos
    for j, p in enumerate(e.props):
        if p.is_list:
            csize = np.dtype(p.count_dtype).itemsize
            if at + csize > len(data):
                raise truncated()
            n = int(np.frombuffer(data, order + p.count_dtype, 1, at)[0])
            if n < 0:
                raise InputError(f"{source}: a PLY {e.name} list has length {n}; corrupt file")
            fields.append((f"n{j}", order + p.count_dtype))
            fields.append((f"v{j}", order + p.dtype, (n,)))
            at += csize + n * np.dtype(p.dtype).itemsize
        else:
            fields.append((f"s{j}", order + p.dtype))
            at += np.dtype(p.dtype).itemsize
    dt = np.dtype(fields)
    if dt.itemsize > 0 and pos + e.count * dt.itemsize <= len(data):
        rec = np.frombuffer(data, dtype=dt, count=e.count, offset=pos)
        uniform = all(
            bool((rec[f"n{j}"] == rec[f"n{j}"][0]).all())
            for j, p in enumerate(e.props)
            if p.is_list
        )
        if uniform:
            end = pos + e.count * dt.itemsize
            if k is None:
                return np.zeros(0, np.int64), np.zeros(0, np.int64), end
            lengths = rec[f"n{k}"].astype(np.int64)
            values = rec[f"v{k}"].reshape(-1).astype(np.int64)
            return lengths, values, end
    # Slow path: lists of varying length, item by item.
    lengths = np.empty(e.count, dtype=np.int64)
    chunks = []
    for i in range(e.count):
        for j, p in enumerate(e.props):
            if p.is_list:
                csize = np.dtype(p.count_dtype).itemsize
                if pos + csize > len(data):
                    raise truncated()
                n = int(np.frombuffer(data, order + p.count_dtype, 1, pos)[0])
                pos += csize
                size = n * np.dtype(p.dtype).itemsize
                if n < 0 or pos + size > len(data):
                    raise truncated()
                if j == k:
                    lengths[i] = n
                    chunks.append(np.frombuffer(data, order + p.dtype, n, pos))
                pos += size
            else:
                pos += np.dtype(p.dtype).itemsize
    values = np.concatenate(chunks).astype(np.int64) if chunks else np.zeros(0, np.int64)
    return lengths, values, pos
