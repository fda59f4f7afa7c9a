"""The sub-face rule: a grid of cells per face, covered when another part's points, its box
or the support plane stand in front of the cell within the clearance."""

from __future__ import annotations

import functools
from collections.abc import Sequence

import numpy as np

from ..decomposition import BoxTree
from ..geometry import as_points
from ..shape import GraspType
from ..tolerances import GEOM_EPS
from .blocking import COVERAGE_DEPTHS
from .faces import ADJACENT, FACE_AXIS, FACE_NORMAL, FACE_RIGHT, FACE_SIGN, FACE_UP
from .params import FaceMaskParams, SupportPlane
from .subfaces import subface_scheme

SUBFACE_GRID: int = 12
"""Cells per side of the grid on which the ``subface`` rule measures the clearance in front of
each face (a multiple of 3, so the 3 x 3 and 3 x 1 sub-faces are whole cells)."""


def face_cell_coords() -> np.ndarray:
    """(6, G, G, 3) the centres of the ``G x G`` cells of each face of the cube ``[-1, 1]^3``
    (a box's frame divided by its half extents): ``[f, col, row]``, ``col`` along the face's
    right, ``row`` along its up."""
    G = SUBFACE_GRID
    c = (np.arange(G) + 0.5) / G * 2.0 - 1.0  # (G,)
    return (
        FACE_NORMAL[:, None, None, :]
        + c[None, :, None, None] * FACE_RIGHT[:, None, None, :]
        + c[None, None, :, None] * FACE_UP[:, None, None, :]
    )


def covered_cells(
    tree: BoxTree,
    near: Sequence[Sequence[int]],
    support: SupportPlane | None,
    params: FaceMaskParams,
    points: np.ndarray | None,
) -> np.ndarray:
    """(K, 6, G, G) bool: :attr:`FaceMasks.covered` of every node (loop over nodes).

    near: per node, the blockers whose world-axis box meets one of its slabs (the screening of
    :func:`compute_face_masks`): no other box, nor any of its points, can be in front of it."""
    G = SUBFACE_GRID
    K = len(tree.nodes)
    out = np.zeros((K, 6, G, G), dtype=bool)
    pts = None if points is None else as_points(points)
    unit = face_cell_coords()  # (6, G, G, 3)
    for nd in tree.nodes:  # loop over nodes (a small set)
        box = nd.box
        h = box.half_extents
        others = list(near[nd.id])
        if others and pts is not None:
            idx = np.concatenate([tree.nodes[c].indices for c in others])
            p_box = (pts[idx] - box.center) @ box.rotation  # (M, 3)
            for f in range(6):  # loop over the six faces
                a = FACE_AXIS[f]
                depth = FACE_SIGN[f] * p_box[:, a] - h[a]
                r, u = p_box @ FACE_RIGHT[f], p_box @ FACE_UP[f]
                hr, hu = float(np.abs(FACE_RIGHT[f]) @ h), float(np.abs(FACE_UP[f]) @ h)
                sel = (
                    (depth > GEOM_EPS)  # a neighbour's points touching the face block it
                    & (depth <= params.clearance)
                    & (np.abs(r) <= hr)
                    & (np.abs(u) <= hu)
                )
                col = np.clip(((r[sel] + hr) / max(2 * hr, GEOM_EPS) * G).astype(int), 0, G - 1)
                row = np.clip(((u[sel] + hu) / max(2 * hu, GEOM_EPS) * G).astype(int), 0, G - 1)
                out[nd.id, f, col, row] = True
        elif others:  # no points: probe each cell's column against the blocker boxes
            depths = (np.arange(COVERAGE_DEPTHS) + 0.5) / COVERAGE_DEPTHS * params.clearance
            p_box = unit[..., None, :] * h + depths[:, None] * FACE_NORMAL[:, None, None, None, :]
            p_world = box.to_world(p_box.reshape(-1, 3))  # (6 G G D, 3)
            inside = np.zeros(len(p_world), dtype=bool)
            for c in others:  # loop over the blocker boxes
                b = tree.nodes[c].box
                local = (p_world - b.center) @ b.rotation
                inside |= np.all(np.abs(local) <= b.half_extents, axis=1)
            out[nd.id] |= inside.reshape(6, G, G, COVERAGE_DEPTHS).any(axis=-1)
        if support is not None:
            # the lowest point of each cell's column (the cell's rectangle pushed out by the
            # clearance) against min(plane, the box's lowest corner), as for whole faces
            proj = np.abs(box.rotation.T @ support.normal)  # (3,) |axis . up|
            centre = unit * h + FACE_NORMAL[:, None, None, :] * (0.5 * params.clearance)
            half = (
                np.abs(FACE_RIGHT) * h / G
                + np.abs(FACE_UP) * h / G
                + np.abs(FACE_NORMAL) * (0.5 * params.clearance)
            )  # (6, 3) half sides of a column, box axes
            lowest = (box.to_world(centre.reshape(-1, 3)) @ support.normal).reshape(6, G, G)
            lowest = lowest - (half @ proj)[:, None, None]
            box_lowest = float(box.center @ support.normal - h @ proj)
            out[nd.id] |= lowest < min(support.height, box_lowest) - params.support_tolerance
    return out


def subface_regions(grasp_type: GraspType | str) -> list[list[np.ndarray]]:
    """For each face ``f`` and each of its sub-faces ``s`` (``subface_scheme``), the cells
    ``(6, G, G)`` bool whose clearance decides it: ``regions[f][s][0]`` its own cells on face
    ``f``; then, for every adjacent face ``a`` the sub-face borders, the cells of ``a`` in the
    third of ``a`` next to the shared edge, along the sub-face's own span of that edge (where
    the fingers go when they wrap round the edge). The same for every box (in the cube
    ``[-1, 1]^3``)."""
    scheme = subface_scheme(grasp_type)
    unit = face_cell_coords()  # (6, G, G, 3)
    regions: list[list[np.ndarray]] = []
    for f in range(6):
        nc, nr = scheme.grid[f]
        borders = scheme.borders(f)  # (S, 4)
        per: list[np.ndarray] = []
        for s in range(nc * nr):
            col, row = s % nc, s // nc
            r0, r1 = -1 + 2 * col / nc, -1 + 2 * (col + 1) / nc
            u0, u1 = -1 + 2 * row / nr, -1 + 2 * (row + 1) / nr
            rc, uc = unit[f] @ FACE_RIGHT[f], unit[f] @ FACE_UP[f]  # (G, G)
            own = np.zeros((6, SUBFACE_GRID, SUBFACE_GRID), dtype=bool)
            own[f] = (rc > r0) & (rc < r1) & (uc > u0) & (uc < u1)
            bands = [own]
            for j in np.flatnonzero(borders[s]):  # the adjacent faces the sub-face borders
                a = int(ADJACENT[f, j])
                # along the edge: f's up for l and r (j = 0, 2), f's right for d and u
                e_dir, lo, hi = (FACE_UP[f], u0, u1) if j in (0, 2) else (FACE_RIGHT[f], r0, r1)
                e = unit[a] @ e_dir  # (G, G)
                near = unit[a] @ FACE_NORMAL[f] > 1.0 / 3.0  # the third of a next to f
                band = np.zeros_like(own)
                band[a] = near & (e > lo) & (e < hi)
                bands.append(band)
            per.append(np.stack(bands))  # (1 + borders, 6, G, G)
        regions.append(per)
    return regions


@functools.cache
def _region_table(scheme_key: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`subface_regions` of a grasp type (its scheme's key) as flat tables, computed once:
    ``(regions (R, 6 G G) bool, cells (R,) per region, first (S,) row of each sub-face's first
    region, faces (S,) the face of each sub-face)``, the sub-faces face by face (read-only)."""
    rows: list[np.ndarray] = []
    first: list[int] = []
    faces: list[int] = []
    for f, per in enumerate(subface_regions(scheme_key)):  # six faces
        for reg in per:  # (R_s, 6, G, G) regions of one sub-face
            first.append(len(rows))
            faces.append(f)
            rows.extend(r.reshape(-1) for r in reg)
    regions = np.stack(rows)
    out = (
        regions,
        regions.sum(axis=1),
        np.asarray(first, dtype=np.int64),
        np.asarray(faces, dtype=np.int64),
    )
    for a in out:
        a.setflags(write=False)
    return out


def usable_subfaces_by_cells(
    covered: np.ndarray, grasp_type: GraspType | str, min_coverage: float
) -> list[np.ndarray]:
    """The usable sub-faces of one box under the ``subface`` rule: a list of 6 arrays
    ``(S_f,) bool``. covered: (6, G, G) bool, the box's :attr:`FaceMasks.covered`. A sub-face is
    usable when none of its regions (:func:`subface_regions`: its own cells, the bands of the
    adjacent faces it borders) has ``min_coverage`` of its cells covered (the regions of every
    grasp type are the same for every box: tabled once per type, counted in one pass)."""
    cov = np.asarray(covered, dtype=bool)
    G = SUBFACE_GRID
    if cov.shape != (6, G, G):
        raise ValueError(f"covered must have shape (6, {G}, {G}), got {cov.shape}")
    subface_scheme(grasp_type)  # a known grasp type (else ValueError)
    regions, n, first, faces = _region_table(str(getattr(grasp_type, "value", grasp_type)))
    hit = (regions & cov.reshape(-1)).sum(axis=1)  # (R,) covered cells per region
    ok = np.logical_and.reduceat(hit < min_coverage * np.maximum(n, 1), first)  # (S,)
    return [ok[faces == f] for f in range(6)]
