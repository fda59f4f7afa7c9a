"""What blocks a face: the slab in front of it, box penetration and coverage, the support
plane, and the tree intervals that tell related boxes apart."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from ..box import OrientedBox
from ..decomposition import BoxTree
from .faces import FACE_AXIS, FACE_NORMAL, FACE_RIGHT, FACE_UP
from .params import FaceMaskParams, SupportPlane


def face_slabs(box: OrientedBox, clearance: float) -> tuple[np.ndarray, np.ndarray]:
    """The six slabs in front of the faces of ``box``.

    Returns ``(centers (6, 3) world, half_extents (6, 3))``; every slab has the box's rotation.
    Slab ``f`` covers the face's rectangle and extends ``clearance`` outwards from the face.
    """
    h = box.half_extents
    half = np.tile(h, (6, 1))  # (6, 3)
    half[np.arange(6), FACE_AXIS] = clearance / 2.0
    offset_box = FACE_NORMAL * (h[FACE_AXIS] + clearance / 2.0)[:, None]  # (6, 3) box frame
    return box.center + offset_box @ box.rotation.T, half


def obb_penetration(
    center_a: np.ndarray,
    rotation_a: np.ndarray,
    half_a: np.ndarray,
    center_b: np.ndarray,
    rotation_b: np.ndarray,
    half_b: np.ndarray,
) -> np.ndarray:
    """Penetration depth of pairs of oriented boxes by the separating-axis test (broadcast).

    Shapes: centers (..., 3), rotations (..., 3, 3) with columns = axes, half extents (..., 3).
    Returns (...,) metres: the smallest overlap of the boxes' projections over the 15 candidate
    axes (3 + 3 face normals and 9 edge cross products), which for boxes is the minimum
    translation that separates them; negative when they are apart (then it is minus a lower
    bound of their gap).
    """
    ca, Ra, ha = (np.asarray(x, dtype=np.float64) for x in (center_a, rotation_a, half_a))
    cb, Rb, hb = (np.asarray(x, dtype=np.float64) for x in (center_b, rotation_b, half_b))
    A = np.swapaxes(Ra, -1, -2)  # (..., 3 axes, 3)
    B = np.swapaxes(Rb, -1, -2)
    A, B = np.broadcast_arrays(A, B)
    cross = np.cross(A[..., :, None, :], B[..., None, :, :])  # (..., 3, 3, 3)
    cross = cross.reshape(cross.shape[:-3] + (9, 3))
    axes = np.concatenate([A, B, cross], axis=-2)  # (..., 15, 3)
    norm = np.linalg.norm(axes, axis=-1)  # (..., 15)
    valid = norm > 1e-9
    axes = axes / np.where(valid, norm, 1.0)[..., None]
    ra = np.sum(ha[..., None, :] * np.abs(axes @ np.swapaxes(A, -1, -2)), axis=-1)  # (..., 15)
    rb = np.sum(hb[..., None, :] * np.abs(axes @ np.swapaxes(B, -1, -2)), axis=-1)
    dist = np.abs(np.einsum("...kj,...j->...k", axes, cb - ca))
    overlap = np.where(valid, ra + rb - dist, np.inf)
    return overlap.min(axis=-1)


COVERAGE_GRID: int = 10
"""Cells per side of the grid a face's coverage by blockers is measured on (1 % resolution)."""

COVERAGE_DEPTHS: int = 3
"""Depths (evenly spread through the clearance) the coverage grid is probed at."""


def face_probe_points(box: OrientedBox, face: int, clearance: float) -> np.ndarray:
    """(G * G, D, 3) world points probing the slab in front of ``face``: one column of
    ``D = COVERAGE_DEPTHS`` points in front of the centre of each of the ``G x G`` cells
    (``G = COVERAGE_GRID``) of the face."""
    h = box.half_extents
    G, D = COVERAGE_GRID, COVERAGE_DEPTHS
    hr, hu = float(np.abs(FACE_RIGHT[face]) @ h), float(np.abs(FACE_UP[face]) @ h)
    c = (np.arange(G) + 0.5) / G * 2.0 - 1.0  # (G,) cell centres in [-1, 1]
    r, u = np.meshgrid(c * hr, c * hu, indexing="ij")
    depth = h[FACE_AXIS[face]] + clearance * (np.arange(D) + 0.5) / D  # (D,)
    p_box = (
        r.reshape(-1, 1, 1) * FACE_RIGHT[face]
        + u.reshape(-1, 1, 1) * FACE_UP[face]
        + depth[None, :, None] * FACE_NORMAL[face]
    )  # (G*G, D, 3)
    return box.to_world(p_box.reshape(-1, 3)).reshape(G * G, D, 3)


def face_coverage(
    box: OrientedBox, face: int, blockers: Sequence[OrientedBox], clearance: float
) -> np.ndarray:
    """(B,) fraction of ``face``'s cells that each blocker covers within ``clearance`` in front
    of the face, and, as the last entry, the fraction covered by any of them: shape (B + 1,)."""
    probes = face_probe_points(box, face, clearance)  # (C, D, 3)
    if not blockers:
        return np.zeros(1)
    Cb = np.stack([b.center for b in blockers])  # (B, 3)
    Rb = np.stack([b.rotation for b in blockers])  # (B, 3, 3)
    Hb = np.stack([b.half_extents for b in blockers])  # (B, 3)
    local = (
        np.einsum("cdj,bjk->bcdk", probes, Rb) - np.einsum("bj,bjk->bk", Cb, Rb)[:, None, None, :]
    )  # (B, C, D, 3) probe points in each blocker's frame
    inside = np.all(np.abs(local) <= Hb[:, None, None, :], axis=-1).any(axis=-1)  # (B, C)
    return np.concatenate([inside.mean(axis=1), [inside.any(axis=0).mean()]])


# ----------------------------------------------------------------------------- face masks


def blocked_by_support(
    box: OrientedBox | Sequence[OrientedBox], support: SupportPlane, params: FaceMaskParams
) -> np.ndarray:
    """(6,) or (K, 6) bool: whether the slab in front of each face reaches below the plane.

    The depth is measured from ``min(plane, lowest corner of the box)``: a box tilted against
    the table has a corner below its lowest point, and only the faces whose slab reaches further
    down than that (the faces that look at the table) are blocked.
    """
    boxes = [box] if isinstance(box, OrientedBox) else list(box)
    out = np.zeros((len(boxes), 6), dtype=bool)
    for k, b in enumerate(boxes):  # loop over nodes
        centers, half = face_slabs(b, params.clearance)
        # lowest point of each slab along the normal: centre minus the projected half extents
        proj = np.abs(b.rotation.T @ support.normal)  # (3,) |axis . up|
        lowest = centers @ support.normal - half @ proj  # (6,)
        box_lowest = float(b.center @ support.normal - b.half_extents @ proj)
        out[k] = lowest < min(support.height, box_lowest) - params.support_tolerance
    return out[0] if isinstance(box, OrientedBox) else out


def tree_intervals(tree: BoxTree) -> tuple[np.ndarray, np.ndarray]:
    """Entry and exit times ``(tin, tout)``, (K,) int64 each, of a depth-first walk of ``tree``
    along its parent links: node ``a`` is ``b`` or an ancestor of ``b`` exactly when
    ``tin[a] <= tin[b] < tout[a]`` (so ``tree.is_related`` for all pairs at once)."""
    K = len(tree.nodes)
    kids: list[list[int]] = [[] for _ in range(K)]
    for nd in tree.nodes[1:]:  # loop over nodes
        kids[nd.parent].append(nd.id)
    order: list[int] = []  # pre-order
    stack = [0]
    while stack:
        k = stack.pop()
        order.append(k)
        stack.extend(reversed(kids[k]))
    if len(order) != K:
        raise ValueError(f"the parent links reach {len(order)} of the tree's {K} nodes")
    tin = np.empty(K, dtype=np.int64)
    tin[order] = np.arange(K)
    size = np.ones(K, dtype=np.int64)
    for k in reversed(order):  # children before their parent
        for c in kids[k]:
            size[k] += size[c]
    return tin, tin + size


PAIR_CHUNK: int = 16_384
"""(node, blocker) pairs screened at once by :func:`compute_face_masks` (about 3 MB of
temporaries): its memory is O(nodes + chunk), not O(nodes x blockers)."""

SAT_CHUNK: int = 1024
"""(node, blocker) pairs per separating-axis batch of :func:`compute_face_masks` (six faces
each; about 20 MB of temporaries)."""
