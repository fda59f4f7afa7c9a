"""Meshes (OBJ, STL, OFF, GLB/GLTF and PLY with faces) read by trimesh and sampled uniformly on
their surface; inside-out closed parts get their normals flipped outwards."""

from __future__ import annotations

import io
import warnings
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ..errors import InputError
from ..tolerances import GEOM_EPS
from .cloud import (
    DEFAULT_N_POINTS,
    MAX_COORDINATE,
    CloudInfo,
    FileData,
    PointCloud,
    add_warning,
    describe_error,
    finish_cloud,
)


@dataclass(frozen=True)
class TriangleMesh:
    """Every triangle of a mesh file (scene transforms applied), before validation."""

    vertices: np.ndarray
    """(V, 3) float64, the file's units."""
    faces: np.ndarray
    """(F, 3) int64 vertex indices."""
    watertight: bool
    """trimesh's ``is_watertight`` of the loaded mesh."""


def read_mesh(file: FileData, fmt: str) -> TriangleMesh:
    """The triangles of ``file`` read by trimesh as format ``fmt`` (``obj``, ``stl``, ...)."""
    import trimesh

    source = file.source
    try:
        # Numeric warnings from trimesh on absurd values: the checks after loading report them.
        with warnings.catch_warnings(), np.errstate(all="ignore"):
            warnings.simplefilter("ignore", RuntimeWarning)
            if fmt == "gltf" and file.path is not None:
                # A .gltf on disk may reference .bin/.png files beside it: let trimesh find them.
                scene = trimesh.load_scene(str(file.path), file_type="gltf")
            else:
                scene = trimesh.load_scene(io.BytesIO(file.data), file_type=fmt)
            mesh = scene.to_mesh()
    except Exception as exc:  # noqa: BLE001 - any parser failure is the input's fault
        hint = (
            "; a GLTF uploaded alone must embed its buffers, export it as .glb"
            if fmt == "gltf"
            else ""
        )
        raise InputError(
            f"{source}: cannot read it as a {fmt.upper()} mesh ({describe_error(exc)})"
            f"{hint}; check that the file is a valid {fmt.upper()} file"
        ) from exc
    if mesh is None or len(getattr(mesh, "faces", ())) == 0:
        raise InputError(
            f"{source}: no triangles could be read from the {fmt.upper()} file; check that it is "
            "a valid mesh with faces, or give a point-cloud format (PLY, PCD, XYZ, NPY)"
        )
    return check_triangles(
        TriangleMesh(
            vertices=np.asarray(mesh.vertices, dtype=np.float64),
            faces=np.asarray(mesh.faces),
            watertight=bool(getattr(mesh, "is_watertight", False)),
        ),
        source,
        fmt,
    )


def check_triangles(mesh: TriangleMesh, source: str, fmt: str) -> TriangleMesh:
    """Shapes (V, 3) and (F, 3) and every face index in [0, V), else :class:`InputError`."""
    verts, faces = mesh.vertices, mesh.faces
    if verts.ndim != 2 or verts.shape[1] != 3 or len(verts) == 0:
        raise InputError(
            f"{source}: the {fmt.upper()} vertices have shape {verts.shape}, expected (V, 3): "
            "some vertex does not have 3 coordinates; re-export the mesh"
        )
    if faces.ndim != 2 or faces.shape[1] != 3 or faces.dtype.kind not in "iu":
        raise InputError(
            f"{source}: the {fmt.upper()} faces have shape {faces.shape}, expected (F, 3) "
            "vertex indices; re-export the mesh"
        )
    faces = faces.astype(np.int64)
    lo, hi = int(faces.min()), int(faces.max())
    if lo < 0 or hi >= len(verts):
        bad = lo if lo < 0 else hi
        raise InputError(
            f"{source}: a {fmt.upper()} face uses vertex {bad}, the mesh has vertices 0 to "
            f"{len(verts) - 1}; the file is corrupt: re-export it"
        )
    return TriangleMesh(vertices=verts, faces=faces, watertight=mesh.watertight)


def sample_mesh(
    mesh: TriangleMesh,
    source: str,
    fmt: str,
    n_points: int | None,
    seed: int,
    scale: float | None,
    units: Callable[[np.ndarray, list[str]], float | None] | None = None,
) -> PointCloud:
    """Area-weighted uniform samples on the triangles, face normals as normals. With ``scale``
    None and ``units`` given, ``units(samples, warnings)`` decides the scale from the samples
    in the file's units (None: metres) and appends its notice first: one sampling, and the
    warnings of the samples as scaled (a millimetre file is not also called "45 m long")."""
    import trimesh

    warns: list[str] = []
    verts = mesh.vertices  # (V, 3)
    faces = mesh.faces  # (F, 3)
    bad_vert: np.ndarray = ~np.isfinite(verts).all(axis=1)  # (V,)
    if bad_vert.any():
        keep = ~bad_vert[faces].any(axis=1)
        add_warning(
            warns,
            f"{source}: {int(bad_vert.sum())} vertices are NaN/inf; dropped the "
            f"{int((~keep).sum())} faces using them",
        )
        faces = faces[keep]
        verts = np.where(bad_vert[:, None], 0.0, verts)
    s = 1.0 if scale is None else float(scale)
    largest = float(np.abs(verts).max()) * s if len(verts) else 0.0
    if not largest <= MAX_COORDINATE:
        raise InputError(
            f"{source}: vertex coordinates reach {largest:.3g} m (after scale {s:g}), beyond "
            f"{MAX_COORDINATE:.0e} m; the file is not in metres or is corrupt: check it, or "
            "pass a scale"
        )
    tri = verts[faces]  # (F, 3, 3)
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])  # (F, 3)
    area2 = np.linalg.norm(cross, axis=1)  # (F,) twice the areas
    total = 0.5 * float(area2.sum()) if len(faces) else 0.0
    if not total > GEOM_EPS**2:
        raise InputError(
            f"{source}: the mesh has zero surface area ({len(faces)} usable faces); "
            "give a mesh with non-degenerate triangles"
        )
    n = DEFAULT_N_POINTS if n_points is None else int(n_points)
    clean = trimesh.Trimesh(vertices=verts, faces=faces, process=False, validate=False)
    pts, face_idx = trimesh.sample.sample_surface(clean, n, face_weight=area2, seed=seed)
    pts = np.asarray(pts, dtype=np.float64)
    if scale is None and units is not None:
        notices: list[str] = []
        scale = units(pts, notices)
        s = 1.0 if scale is None else float(scale)
        warns[:0] = notices
    # Unit face normals from the winding (zero-area faces are never sampled).
    normals = cross[face_idx] / area2[face_idx, None]  # (n, 3)
    watertight = mesh.watertight and not bad_vert.any()
    flip, n_flipped = inside_out_faces(faces, tri[:, 0], cross)
    if n_flipped:
        normals = np.where(flip[face_idx, None], -normals, normals)
        add_warning(
            warns,
            f"{source}: {n_flipped} closed part(s) of the mesh are wound inside-out; "
            "their normals were flipped outwards",
        )
    if fmt in ("glb", "gltf"):
        add_warning(warns, gltf_up_notice(source))
    info = CloudInfo(
        format=fmt,
        kind="mesh",
        n_read=int(len(verts)),
        n_faces=int(len(faces)),
        area=total * s * s,
        watertight=watertight,
        warnings=warns,
    )
    return finish_cloud(pts, normals, source, info, scale=scale, n_points=None, seed=seed)


def gltf_up_notice(source: str) -> str:
    """The notice of every glTF input: its coordinates are read as they are, z up."""
    return (
        f"{source}: glTF is Y-up by its specification, and pregrasp reads every file z-up "
        "(the table below its lowest z): if the object stands along +y, plan it with --up 0 1 "
        "0 (in the viewer: 'up (table normal)' +y)"
    )


def inside_out_faces(
    faces: np.ndarray, v0: np.ndarray, cross: np.ndarray
) -> tuple[np.ndarray, int]:
    """Faces of closed, consistently wound parts with negative signed volume (inside-out).

    faces: (F, 3) vertex indices; v0: (F, 3) first vertex of each face; cross: (F, 3) the
    (unnormalised) face normals. Parts are edge-connected components; a part is closed when each
    of its edges has exactly two faces, and consistently wound when each edge is used once in
    each direction. Returns ((F,) bool: flip this face's normal, number of parts flipped).
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    n_f = len(faces)
    n_v = int(faces.max()) + 1
    directed = faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)  # (3F, 2) edges as wound
    undirected = np.sort(directed, axis=1)
    # Edges as int64 keys (a * n_v + b): 1-D unique is much faster than unique rows.
    _, edge_id, edge_count = np.unique(
        undirected[:, 0] * n_v + undirected[:, 1], return_inverse=True, return_counts=True
    )  # edge_id: (3F,) index of each face edge among the unique edges
    # Faces and edges as one bipartite graph: its components are the edge-connected parts.
    n_e = len(edge_count)
    face_of_edge = np.repeat(np.arange(n_f), 3)  # (3F,)
    graph = coo_matrix(
        (np.ones(3 * n_f), (face_of_edge, n_f + edge_id)), shape=(n_f + n_e, n_f + n_e)
    )
    _, labels = connected_components(graph, directed=False)
    _, part = np.unique(labels[:n_f], return_inverse=True)  # (F,) part of each face
    n_parts = int(part.max()) + 1
    _, dir_id, dir_count = np.unique(
        directed[:, 0] * n_v + directed[:, 1], return_inverse=True, return_counts=True
    )
    # (3F,) edge is open or non-manifold, or two faces wind it the same way
    bad_edge = (edge_count[edge_id] != 2) | (dir_count[dir_id] != 1)
    bad_face = bad_edge.reshape(n_f, 3).any(axis=1)
    bad_part = np.bincount(part, weights=bad_face, minlength=n_parts) > 0
    volume6 = np.bincount(part, weights=np.einsum("ij,ij->i", v0, cross), minlength=n_parts)
    flip_part = ~bad_part & (volume6 < 0.0)
    return flip_part[part], int(flip_part.sum())
