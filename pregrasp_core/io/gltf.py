"""glTF 2.0 meshes (GLB, and GLTF with embedded or beside-the-file buffers): the container and
the JSON are checked here (chunk sizes, every index into buffers, views, accessors, meshes and
nodes, accessor sizes within their views, a node tree without cycles), then trimesh reads it;
the face indices themselves are checked after reading."""

from __future__ import annotations

import json
import struct
from urllib.parse import unquote

import numpy as np

from ..errors import InputError
from .cloud import FileData
from .mesh import TriangleMesh, read_mesh

GLB_MAGIC: bytes = b"glTF"
CHUNK_JSON: int = 0x4E4F534A
CHUNK_BIN: int = 0x004E4942

COMPONENT_BYTES: dict[int, int] = {5120: 1, 5121: 1, 5122: 2, 5123: 2, 5125: 4, 5126: 4}
"""glTF componentType -> bytes."""

TYPE_COMPONENTS: dict[str, int] = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4,
                                   "MAT3": 9, "MAT4": 16}  # fmt: skip
"""glTF accessor type -> components."""


MAX_GLTF_TRIANGLES: int = 10_000_000
"""Most triangles a glTF scene may expand to (nodes instancing meshes multiply them; about
100 bytes of memory each once read)."""


def read_glb(file: FileData) -> TriangleMesh:
    """Check the GLB container and its JSON, then read the triangles with trimesh."""
    doc, bin_len = _glb_parts(file.data, file.source)
    check_gltf_json(doc, bin_len, file.source)
    return read_mesh(file, "glb")


def read_gltf(file: FileData) -> TriangleMesh:
    """Check the GLTF JSON, then read the triangles with trimesh."""
    doc = _json(file.data, file.source, "GLTF")
    check_gltf_json(doc, None, file.source)
    return read_mesh(file, "gltf")


def _json(raw: bytes, source: str, what: str) -> dict[str, object]:
    try:
        doc = json.loads(raw.decode("utf-8"))
    except (UnicodeDecodeError, ValueError, RecursionError) as exc:
        raise InputError(
            f"{source}: the {what} JSON cannot be read ({type(exc).__name__}); re-export the mesh"
        ) from None
    if not isinstance(doc, dict):
        raise InputError(f"{source}: the {what} JSON is not an object; re-export the mesh")
    return doc


def _glb_parts(data: bytes, source: str) -> tuple[dict[str, object], int]:
    """The JSON document and the BIN chunk's length of a GLB."""

    def bad(problem: str) -> InputError:
        return InputError(f"{source}: malformed GLB: {problem}; re-export the mesh as GLB")

    if data[:4] != GLB_MAGIC:
        raise bad("it does not start with the 'glTF' header")
    if len(data) < 20:
        raise bad(f"{len(data)} bytes, shorter than a GLB header and its first chunk")
    version, length = struct.unpack_from("<II", data, 4)
    if version != 2:
        raise bad(f"version {version} (only glTF 2 is read)")
    if length != len(data):
        raise bad(f"the header declares {length} bytes, the file has {len(data)}")
    pos = 12
    doc: dict[str, object] | None = None
    bin_len = 0
    while pos < len(data):
        if pos + 8 > len(data):
            raise bad("a chunk header is cut off")
        size, kind = struct.unpack_from("<II", data, pos)
        if pos + 8 + size > len(data):
            raise bad(f"a chunk of {size} bytes runs past the end of the file")
        if doc is None:
            if kind != CHUNK_JSON:
                raise bad("the first chunk is not JSON")
            doc = _json(data[pos + 8 : pos + 8 + size], source, "GLB")
        elif kind == CHUNK_BIN and bin_len == 0:
            bin_len = size
        pos += 8 + size
    if doc is None:
        raise bad("no JSON chunk")
    return doc, bin_len


def _items(doc: dict[str, object], key: str, source: str) -> list[dict[str, object]]:
    value = doc.get(key, [])
    if not isinstance(value, list) or not all(isinstance(v, dict) for v in value):
        raise InputError(f"{source}: glTF '{key}' is not a list of objects; re-export the mesh")
    return value


def _is_local_file(uri: str) -> bool:
    """A relative path inside the file's folder: no scheme, no absolute path, no '..'."""
    path = unquote(uri).replace("\\", "/")
    return (
        bool(path) and ":" not in path and not path.startswith("/") and ".." not in path.split("/")
    )


def check_gltf_json(doc: dict[str, object], bin_len: int | None, source: str) -> None:
    """Indices and sizes of a glTF document; ``bin_len``: the GLB's BIN chunk (None: GLTF)."""

    def bad(problem: str) -> InputError:
        return InputError(f"{source}: malformed glTF: {problem}; re-export the mesh")

    def index(obj: dict[str, object], key: str, n: int, what: str, required: bool) -> int | None:
        value = obj.get(key)
        if value is None and not required:
            return None
        if not isinstance(value, int) or isinstance(value, bool) or not 0 <= value < n:
            raise bad(f"{what} '{key}' is {value!r}, expected an index below {n}")
        return value

    def size(obj: dict[str, object], key: str, what: str, default: int | None = None) -> int:
        value = obj.get(key, default)
        if not isinstance(value, int) or isinstance(value, bool) or value < 0:
            raise bad(f"{what} '{key}' is {value!r}, expected a non-negative integer")
        return value

    for key in ("buffers", "images"):  # only embedded data or files beside the .gltf
        for i, item in enumerate(_items(doc, key, source)):
            uri = item.get("uri")
            if uri is None or (isinstance(uri, str) and uri.startswith("data:")):
                continue
            if not isinstance(uri, str) or not _is_local_file(uri):
                shown = str(uri)[:60]
                raise bad(f"{key[:-1]} {i} uri {shown!r} is not a file beside the GLTF")
    buffers = _items(doc, "buffers", source)
    views = _items(doc, "bufferViews", source)
    accessors = _items(doc, "accessors", source)
    meshes = _items(doc, "meshes", source)
    nodes = _items(doc, "nodes", source)
    buffer_len = []
    for i, b in enumerate(buffers):
        n = size(b, "byteLength", f"buffer {i}")
        if bin_len is not None and i == 0 and "uri" not in b and n > bin_len:
            raise bad(f"buffer 0 declares {n} bytes, the BIN chunk has {bin_len}")
        buffer_len.append(n)
    view_len = []
    for i, view in enumerate(views):
        bi = index(view, "buffer", len(buffers), f"bufferView {i}", True)
        off = size(view, "byteOffset", f"bufferView {i}", 0)
        n = size(view, "byteLength", f"bufferView {i}")
        if bi is not None and off + n > buffer_len[bi]:
            raise bad(f"bufferView {i} ({off} + {n} bytes) runs past buffer {bi}")
        view_len.append((n, view.get("byteStride")))
    for i, a in enumerate(accessors):
        what = f"accessor {i}"
        count = size(a, "count", what)
        ctype = a.get("componentType")
        atype = a.get("type")
        if ctype not in COMPONENT_BYTES or atype not in TYPE_COMPONENTS:
            raise bad(f"{what} has componentType {ctype!r} and type {atype!r}")
        elem = COMPONENT_BYTES[int(str(ctype))] * TYPE_COMPONENTS[str(atype)]
        vi = index(a, "bufferView", len(views), what, False)
        if vi is None:
            if "sparse" not in a and count:
                raise bad(f"{what} has no bufferView")
            continue
        off = size(a, "byteOffset", what, 0)
        n_view, stride = view_len[vi]
        step = stride if isinstance(stride, int) and stride > 0 else elem
        if count and off + step * (count - 1) + elem > n_view:
            raise bad(f"{what} ({count} x {elem} bytes) runs past bufferView {vi}")
    mesh_triangles = [0] * len(meshes)  # (M,) triangles of each mesh
    for i, m in enumerate(meshes):
        prims = m.get("primitives")
        if not isinstance(prims, list) or not all(isinstance(p, dict) for p in prims):
            raise bad(f"mesh {i} has no list of primitives")
        for p in prims:
            attrs = p.get("attributes")
            if not isinstance(attrs, dict) or "POSITION" not in attrs:
                raise bad(f"a primitive of mesh {i} has no POSITION attribute")
            for key in attrs:
                index(attrs, key, len(accessors), f"mesh {i} attribute", True)
            pos = accessors[int(str(attrs["POSITION"]))]
            if pos.get("type") != "VEC3" or pos.get("componentType") != 5126:
                raise bad(f"mesh {i} POSITION is not float VEC3")
            ind = index(p, "indices", len(accessors), f"mesh {i} primitive", False)
            counted = accessors[ind] if ind is not None else pos
            mesh_triangles[i] += int(str(counted.get("count", 0))) // 3
            if ind is not None:
                acc = accessors[ind]
                unsigned = acc.get("componentType") in (5121, 5123, 5125)
                if acc.get("type") != "SCALAR" or not unsigned:
                    raise bad(f"mesh {i} indices are not unsigned integer scalars")
    instanced = 0
    for i, nd in enumerate(nodes):
        mi = index(nd, "mesh", len(meshes), f"node {i}", False)
        instanced += mesh_triangles[mi] if mi is not None else 0
    if instanced > MAX_GLTF_TRIANGLES:
        raise bad(
            f"its nodes place {instanced} triangles, more than {MAX_GLTF_TRIANGLES}; "
            "simplify the scene"
        )
    parent = np.full(len(nodes), -1, dtype=np.int64)
    kids: list[list[int]] = []  # children of each node
    for i, nd in enumerate(nodes):
        children = nd.get("children", [])
        if not isinstance(children, list):
            raise bad(f"node {i} 'children' is not a list")
        for c in children:
            if not isinstance(c, int) or isinstance(c, bool) or not 0 <= c < len(nodes):
                raise bad(f"node {i} has child {c!r}, expected an index below {len(nodes)}")
            if parent[c] >= 0 or c == i:
                raise bad(f"node {c} has two parents or is its own child (not a tree)")
            parent[c] = i
        kids.append(children)
    # each node has at most one parent: the nodes not reached from the roots are in cycles
    stack = [int(i) for i in np.flatnonzero(parent < 0)]
    seen = len(stack)
    while stack:
        for c in kids[stack.pop()]:
            stack.append(int(c))
            seen += 1
    if seen != len(nodes):
        raise bad(f"{len(nodes) - seen} nodes are in a cycle of children (not a tree)")
    for i, sc in enumerate(_items(doc, "scenes", source)):
        roots = sc.get("nodes", [])
        if not isinstance(roots, list) or not all(
            isinstance(r, int) and not isinstance(r, bool) and 0 <= r < len(nodes) for r in roots
        ):
            raise bad(f"scene {i} lists nodes {roots!r}, expected indices below {len(nodes)}")
