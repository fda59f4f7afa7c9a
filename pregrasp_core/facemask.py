"""Face masks, the support plane and sub-faces (Sainul, Deb & Deb 2019, section III.C).

Conventions (``docs/conventions.md``, "Faces, adjacency and sub-faces"):

- Faces of a box, in its box frame (axis 0 longest): ``0: +x, 1: -x, 2: +y, 3: -y, 4: +z,
  5: -z``. Face ``f`` has the outward normal ``FACE_NORMAL[f]`` and, seen from outside, a
  ``right`` and an ``up`` direction (``FACE_RIGHT``, ``FACE_UP``; right x up = normal).
- The four adjacent faces of ``f`` are ``ADJACENT[f] = [l, d, r, u]``: the faces whose normals
  are -right, -up, +right and +up.
- The face mask of a box is a 6 x 5 matrix of 0 (free) and 1 (blocked); row ``f`` is
  ``[f, l(f), d(f), r(f), u(f)]``.
- A face is blocked by *blocker boxes* when they penetrate the slab in front of the face (the
  face's rectangle pushed outwards by ``clearance``) by more than ``overlap_tolerance`` and
  together cover at least ``min_coverage`` of the face's area (probed on a grid). It is blocked
  by the support plane when that slab reaches more than ``support_tolerance`` below the plane
  (or below the box's own lowest corner, when that is lower: a tilted box pokes below the table
  without facing it). The blockers of node ``n`` are the boxes of the current decomposition (a
  cut of the tree, the leaves by default) that are neither ``n`` nor one of its ancestors or
  descendants.
- Each face is divided into a grid of sub-faces that depends on the grasp type
  (:data:`SUBFACE_SCHEMES`): cell ``(col, row)`` with ``col`` along ``right`` from the left edge
  and ``row`` along ``up`` from the bottom edge has index ``s = row * n_cols + col``. A cell
  borders the adjacent faces of the face edges it touches; it is usable only when its own face
  and every adjacent face it borders are free.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Literal

import numpy as np

from .box import OrientedBox
from .decomposition import BoxTree
from .errors import InputError, WorkLimitError
from .geometry import as_points
from .limits import MAX_HEIGHT, MAX_LENGTH, WorkLimits, check_real
from .shape import GraspType
from .tolerances import (
    FACE_OVERLAP_TOL,
    GEOM_EPS,
    SUPPORT_PENETRATION_TOL,
)

if TYPE_CHECKING:
    from .result import JsonDocument

logger = logging.getLogger(__name__)

FACE_NAMES: tuple[str, ...] = ("+x", "-x", "+y", "-y", "+z", "-z")
"""Names of the six faces in the box frame (axis 0 = x is the longest box axis)."""

FACE_AXIS: np.ndarray = np.array([0, 0, 1, 1, 2, 2])
"""(6,) int: the box axis each face is perpendicular to."""

FACE_SIGN: np.ndarray = np.array([1.0, -1.0, 1.0, -1.0, 1.0, -1.0])
"""(6,) float: +1 for the face on the positive side of its axis, -1 otherwise."""

FACE_NORMAL: np.ndarray = np.eye(3)[FACE_AXIS] * FACE_SIGN[:, None]
"""(6, 3) outward unit normals of the faces in the box frame."""

FACE_RIGHT: np.ndarray = np.array(
    [[0, 1, 0], [0, -1, 0], [-1, 0, 0], [1, 0, 0], [1, 0, 0], [1, 0, 0]], dtype=np.float64
)
"""(6, 3) the 'right' direction of each face seen from outside (box frame)."""

FACE_UP: np.ndarray = np.array(
    [[0, 0, 1], [0, 0, 1], [0, 0, 1], [0, 0, 1], [0, 1, 0], [0, -1, 0]], dtype=np.float64
)
"""(6, 3) the 'up' direction of each face seen from outside (box frame); right x up = normal."""


def face_of_direction(direction: np.ndarray) -> np.ndarray:
    """Face index of axis-aligned unit directions (..., 3) in the box frame."""
    d = np.asarray(direction, dtype=np.float64)
    axis = np.argmax(np.abs(d), axis=-1)
    sign = np.take_along_axis(d, axis[..., None], axis=-1)[..., 0]
    return 2 * axis + (sign < 0)


ADJACENT: np.ndarray = np.stack(
    [
        face_of_direction(-FACE_RIGHT),
        face_of_direction(-FACE_UP),
        face_of_direction(FACE_RIGHT),
        face_of_direction(FACE_UP),
    ],
    axis=1,
)
"""(6, 4) int: adjacent faces [l, d, r, u] of each face."""


# ----------------------------------------------------------------------------- parameters

FACE_RULES: tuple[str, ...] = ("face", "subface")
"""Values of :attr:`FaceMaskParams.rule`: the paper's whole-face rule, or the clearance of each
sub-face."""


def _is_vector(value: object) -> bool:
    """True for a sequence or array of real numbers (not a string, not booleans)."""
    if isinstance(value, (str, bytes)):
        return False
    try:
        a = np.asarray(value)
    except (TypeError, ValueError):
        return False
    return a.dtype.kind in "iuf"


@dataclass(frozen=True)
class FaceMaskParams:
    """Parameters of the face masks and of the support plane."""

    clearance: float = 0.025
    """Metres: depth of the slab in front of a face that must stay empty for the face to be free
    (finger thickness about 0.02 m plus a 0.005 m margin)."""
    overlap_tolerance: float = FACE_OVERLAP_TOL
    """Metres: a blocker must penetrate a face's slab deeper than this to block the face (boxes
    that merely touch the slab's border, e.g. a part sitting flush on top of the face's edge,
    do not block)."""
    min_coverage: float = 0.05
    """Fraction (0..1] of a face's area that boxes in front of it (within the clearance) must
    cover for the face to be blocked; a blocker that only grazes a corner of the slab leaves
    the face free (partial contact is left to the hand's collision test)."""
    support: bool = True
    """Whether a support plane (a table under the object) blocks faces."""
    up: tuple[float, float, float] = (0.0, 0.0, 1.0)
    """World 'up' direction: the support plane's normal (normalised on use)."""
    support_height: float | None = None
    """Height of the support plane along ``up`` (metres); ``None`` = the lowest cloud point."""
    support_tolerance: float = SUPPORT_PENETRATION_TOL
    """Metres: a face's slab must reach deeper than this below the plane to be blocked by it."""
    rule: Literal["face", "subface"] = "subface"
    """Which sub-faces may carry pre-grasps. ``"face"``: the paper's rule, whole faces blocked
    by the boxes in front of them (and the support plane), a sub-face usable when its face and
    every adjacent face it borders are free. ``"subface"`` (default): the same sub-faces, each
    judged by the geometry in front of it: the cloud points of the other parts (or, without
    points, their boxes) and the support plane in the slab in front of the sub-face and in
    front of the third of each adjacent face next to it (:func:`usable_subfaces_by_cells`), so
    a handle in the corner of the body's box keeps its outer sub-faces."""

    def __post_init__(self) -> None:
        # bounds: docs/limits.md ("Face masks"); lengths up to MAX_LENGTH (10 m)
        for name in ("clearance", "overlap_tolerance", "support_tolerance"):
            v = check_real(name, getattr(self, name), 0.0, MAX_LENGTH, what="a length", unit=" m")
            object.__setattr__(self, name, v)
        mc = check_real(
            "min_coverage", self.min_coverage, 0.0, 1.0, lo_open=True, what="a fraction"
        )
        object.__setattr__(self, "min_coverage", mc)
        up = np.asarray(self.up, dtype=np.float64) if _is_vector(self.up) else np.zeros(0)
        with np.errstate(over="ignore"):  # a huge vector's norm is inf: refused below
            norm = float(np.linalg.norm(up)) if up.shape == (3,) else 0.0
        if not np.all(np.isfinite(up)) or not (GEOM_EPS <= norm < np.inf):
            raise ValueError(f"up must be a non-zero finite 3-vector, got {self.up!r}")
        object.__setattr__(self, "up", tuple(float(x) for x in up))
        if self.support_height is not None:
            h = check_real(
                "support_height",
                self.support_height,
                -MAX_HEIGHT,
                MAX_HEIGHT,
                what="a height (or None)",
                unit=" m",
            )
            object.__setattr__(self, "support_height", h)
        sup = self.support
        if not (isinstance(sup, (bool, np.bool_, int, np.integer)) and sup in (0, 1)):
            raise ValueError(f"support must be True or False, got {self.support!r}")
        object.__setattr__(self, "support", bool(self.support))
        if self.rule not in FACE_RULES:
            raise ValueError(f"rule must be one of {list(FACE_RULES)}, got {self.rule!r}")


# ----------------------------------------------------------------------------- support plane


@dataclass(frozen=True)
class SupportPlane:
    """The plane the object stands on: points ``p`` with ``normal . p = height``."""

    normal: np.ndarray
    """(3,) float64, unit, world frame: the 'up' direction (the object is on this side)."""
    height: float
    """Metres: offset of the plane along ``normal``."""

    def __post_init__(self) -> None:
        n = np.asarray(self.normal, dtype=np.float64)
        if n.shape != (3,):
            raise ValueError(f"normal must have shape (3,), got {n.shape}")
        norm = np.linalg.norm(n)
        if not np.isfinite(norm) or norm < GEOM_EPS:
            raise ValueError(f"normal must be a non-zero finite vector, got {n.tolist()}")
        object.__setattr__(self, "normal", n / norm)
        object.__setattr__(self, "height", float(self.height))

    @classmethod
    def from_points(
        cls, points: np.ndarray, up: Sequence[float] = (0.0, 0.0, 1.0), height: float | None = None
    ) -> SupportPlane:
        """The plane perpendicular to ``up`` at ``height``, or at the lowest of ``points``."""
        n = np.asarray(up, dtype=np.float64)
        n = n / np.linalg.norm(n)
        if height is None:
            pts = as_points(points)
            if pts.shape[0] == 0:
                raise InputError("the support plane needs at least one cloud point, got none")
            height = float(np.min(pts @ n))
        return cls(normal=n, height=float(height))

    def signed_distance(self, points: np.ndarray) -> np.ndarray:
        """(N,) metres above the plane (negative below) of world ``points`` (N, 3)."""
        return as_points(points) @ self.normal - self.height

    def to_dict(self) -> JsonDocument:
        """JSON-ready dict (normal, height)."""
        return {"normal": self.normal.tolist(), "height": self.height}


def support_plane(points: np.ndarray, params: FaceMaskParams) -> SupportPlane | None:
    """The support plane the parameters ask for, or ``None`` when it is turned off."""
    if not params.support:
        return None
    return SupportPlane.from_points(points, params.up, params.support_height)


# ----------------------------------------------------------------------------- geometry


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


@dataclass(frozen=True)
class FaceMasks:
    """Face masks of every node of a decomposition tree (indexed by node id)."""

    blocked: np.ndarray
    """(K, 6) bool: face ``f`` of node ``k`` is blocked (by a box or by the support plane)."""
    by_support: np.ndarray
    """(K, 6) bool: the support plane blocks face ``f`` of node ``k``."""
    blockers: tuple[tuple[tuple[int, ...], ...], ...]
    """``blockers[k][f]``: ids of the boxes in front of face ``f`` of node ``k`` (ascending;
    they block it when together they cover ``min_coverage`` of it)."""
    cut: tuple[int, ...]
    """Ids of the boxes of the current decomposition (the possible blockers)."""
    support: SupportPlane | None
    """The support plane, or ``None`` when it is turned off."""
    params: FaceMaskParams = field(default_factory=FaceMaskParams)
    """The parameters the masks were computed with."""
    covered: np.ndarray | None = None
    """(K, 6, G, G) bool, ``G = SUBFACE_GRID``, under the ``subface`` rule (else ``None``): cell
    ``(col, row)`` of face ``f`` of node ``k`` (``col`` along the face's right, ``row`` along its
    up) has another part's point (or box) or the support plane in front of it, within the
    clearance."""

    def usable(self, node: int, grasp_type: GraspType | str) -> list[np.ndarray]:
        """The usable sub-faces of a node for a grasp type under the masks' rule (a list of 6
        bool arrays, as :func:`usable_subfaces`)."""
        if self.covered is None:
            return usable_subfaces(self.blocked[node], grasp_type)
        return usable_subfaces_by_cells(self.covered[node], grasp_type, self.params.min_coverage)

    @property
    def masks(self) -> np.ndarray:
        """(K, 6, 5) int8: row f of node k = blocked state of [f, l(f), d(f), r(f), u(f)]."""
        return face_mask_matrix(self.blocked)

    def mask(self, node: int) -> np.ndarray:
        """(6, 5) int8: the face mask of one node."""
        return face_mask_matrix(self.blocked[node])


def face_mask_matrix(blocked: np.ndarray) -> np.ndarray:
    """(..., 6, 5) int8 face mask(s) from the blocked state of the faces (..., 6) bool."""
    b = np.asarray(blocked, dtype=bool)
    if b.shape[-1:] != (6,):
        raise ValueError(f"blocked must have shape (..., 6), got {b.shape}")
    cols = np.concatenate([np.arange(6)[:, None], ADJACENT], axis=1)  # (6, 5)
    return b[..., cols].astype(np.int8)


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


def compute_face_masks(
    tree: BoxTree,
    support: SupportPlane | None = None,
    params: FaceMaskParams | None = None,
    cut: Sequence[int] | None = None,
    limits: WorkLimits | None = None,
    points: np.ndarray | None = None,
) -> FaceMasks:
    """Face masks of every node of ``tree``.

    support: the support plane (see :func:`support_plane`) or ``None`` for a free-floating
    object. cut: ids of the boxes forming the current decomposition (the possible blockers);
    default the leaves. The blockers of node ``n`` are the boxes of ``cut`` that are neither
    ``n`` nor an ancestor or descendant of ``n``. limits: ``max_face_mask_pairs`` bounds
    ``nodes x cut boxes`` (``WorkLimitError`` past it, before any work). points: (N, 3) the
    cloud the tree was built from; under the ``subface`` rule the blockers' points decide each
    sub-face's clearance (without points, their boxes do).

    The pairs are screened in chunks of :data:`PAIR_CHUNK` (world-axis bounding boxes, then the
    node's three face axes), and only the pairs that may still block get the full
    separating-axis test: the results are those of testing every pair, in O(nodes + chunk)
    memory.
    """
    params = FaceMaskParams() if params is None else params
    limits = WorkLimits() if limits is None else limits
    cut_ids = tuple(tree.leaves() if cut is None else (int(c) for c in cut))
    for c in cut_ids:
        tree.node(c)  # raises IndexError for a bad id
    K = len(tree.nodes)
    if K * len(cut_ids) > limits.max_face_mask_pairs:
        raise WorkLimitError(
            f"face masks of {K:,} nodes against {len(cut_ids):,} boxes are "
            f"{K * len(cut_ids):,} pairs, more than the limit {limits.max_face_mask_pairs:,} "
            "(max_face_mask_pairs): decompose into fewer parts (larger min_points, smaller "
            "max_depth or volume_ratio) or raise max_face_mask_pairs"
        )
    blocked = np.zeros((K, 6), dtype=bool)
    hits: list[list[list[int]]] = [[[] for _ in range(6)] for _ in range(K)]
    near_pairs: list[tuple[np.ndarray, np.ndarray]] = []
    if cut_ids and K > 1:
        slab_c = np.empty((K, 6, 3))
        slab_h = np.empty((K, 6, 3))
        for nd in tree.nodes:  # loop over nodes
            slab_c[nd.id], slab_h[nd.id] = face_slabs(nd.box, params.clearance)
        R = np.stack([nd.box.rotation for nd in tree.nodes])  # (K, 3, 3)
        C = np.stack([nd.box.center for nd in tree.nodes])  # (K, 3)
        H = np.stack([nd.box.half_extents for nd in tree.nodes])  # (K, 3)
        cb = np.asarray(cut_ids, dtype=np.int64)  # (B,)
        tin, tout = tree_intervals(tree)
        # world-axis half extents of the slabs (K, 6, 3) and of the cut's boxes (B, 3)
        slab_w = np.einsum("kij,kfj->kfi", np.abs(R), slab_h)
        box_w = np.einsum("bij,bj->bi", np.abs(R[cb]), H[cb])
        scale = float(np.abs(slab_c).max() + np.abs(slab_w).max() + np.abs(C).max() + 1.0)
        margin = GEOM_EPS * scale  # far above the round-off of the tests, far below any overlap
        rows = max(1, PAIR_CHUNK // len(cut_ids))
        for start in range(0, K, rows):  # loop over chunks of nodes
            nodes = np.arange(start, min(K, start + rows))  # (r,)
            t_n, t_b = tin[nodes][:, None], tin[cb][None, :]
            related = ((t_n <= t_b) & (t_b < tout[nodes][:, None])) | (
                (t_b <= t_n) & (t_n < tout[cb][None, :])
            )  # (r, B)
            gap = np.abs(slab_c[nodes][:, :, None, :] - C[cb][None, None]) - (
                slab_w[nodes][:, :, None, :] + box_w[None, None]
            )  # (r, 6, B, 3): > 0 on some axis = the world-axis boxes are apart
            near = np.all(gap <= margin, axis=-1).any(axis=1) & ~related  # (r, B)
            pi, bi = np.nonzero(near)
            pn, pb = nodes[pi], cb[bi]  # (P,) node and blocker ids, by node then cut order
            near_pairs.append((pn, pb))  # the sub-face rule's candidates (touching included)
            # The separating-axis test on the node's own three axes alone: a blocker whose
            # overlap with every slab is at most overlap_tolerance on one of them cannot block
            # (the full test's depth is the minimum over these and 12 more axes).
            Rn = R[pn]  # (P, 3, 3)
            M = np.abs(np.matmul(Rn.transpose(0, 2, 1), R[pb]))  # (P, 3, 3) |R_n^T R_b|
            rb = np.matmul(M, H[pb][:, :, None])[:, :, 0]  # (P, 3) blocker radii on node axes
            q = np.matmul(C[pb][:, None, :] - slab_c[pn], Rn)  # (P, 6, 3) in the node frame
            overlap = slab_h[pn] + rb[:, None, :] - np.abs(q)  # (P, 6, 3)
            keep = np.all(overlap > params.overlap_tolerance - margin, axis=-1).any(axis=1)
            pn, pb = pn[keep], pb[keep]
            hit = np.zeros((len(pn), 6), dtype=bool)
            for s in range(0, len(pn), SAT_CHUNK):  # loop over batches of pairs
                n, b = pn[s : s + SAT_CHUNK], pb[s : s + SAT_CHUNK]
                depth = obb_penetration(  # (p, 6)
                    slab_c[n],
                    R[n][:, None],
                    slab_h[n],
                    C[b][:, None],
                    R[b][:, None],
                    H[b][:, None],
                )
                hit[s : s + SAT_CHUNK] = depth > params.overlap_tolerance  # slab penetrated
            # coverage of each (node, face) by its penetrating blockers, on a probe grid
            hp, hf = np.nonzero(hit)  # ordered by pair, then face
            key = pn[hp] * 6 + hf
            order = np.argsort(key, kind="stable")  # by (node, face), pairs in cut order
            hp, key = hp[order], key[order]
            for group in np.split(np.arange(len(key)), np.flatnonzero(np.diff(key)) + 1):
                if len(group) == 0:
                    continue
                n0, f0 = divmod(int(key[group[0]]), 6)
                cands = pb[hp[group]].tolist()
                cov = face_coverage(
                    tree.nodes[n0].box, f0, [tree.nodes[c].box for c in cands], params.clearance
                )
                hits[n0][f0] = [c for c, v in zip(cands, cov[:-1], strict=True) if v > 0]
                blocked[n0, f0] = cov[-1] >= params.min_coverage
    if support is not None:
        by_support = blocked_by_support([nd.box for nd in tree.nodes], support, params)
    else:
        by_support = np.zeros((K, 6), dtype=bool)
    blocked |= by_support
    blockers = tuple(tuple(tuple(sorted(h)) for h in node_hits) for node_hits in hits)
    covered = None
    if params.rule == "subface":
        pn_all = np.concatenate([p[0] for p in near_pairs] + [np.zeros(0, dtype=np.int64)])
        pb_all = np.concatenate([p[1] for p in near_pairs] + [np.zeros(0, dtype=np.int64)])
        order = np.argsort(pn_all, kind="stable")  # by node, blockers in cut order
        bounds = np.searchsorted(pn_all[order], np.arange(K + 1))
        near_of = [pb_all[order[bounds[k] : bounds[k + 1]]].tolist() for k in range(K)]
        covered = _covered_cells(tree, near_of, support, params, points)
        # a face is blocked when its own cells are covered as much as min_coverage of it
        blocked = covered.mean(axis=(2, 3)) >= params.min_coverage
    return FaceMasks(
        blocked=blocked,
        by_support=by_support,
        blockers=blockers,
        cut=cut_ids,
        support=support,
        params=params,
        covered=covered,
    )


# ----------------------------------------------------------------------------- sub-faces


@dataclass(frozen=True)
class SubfaceScheme:
    """How the faces of a box are divided into sub-faces for one grasp type."""

    grid: tuple[tuple[int, int], ...]
    """Per face (6): ``(n_cols, n_rows)`` of the sub-face grid; ``(0, 0)`` = face not used."""

    @property
    def n_subfaces(self) -> np.ndarray:
        """(6,) int: number of sub-faces of each face (0 for unused faces)."""
        return np.array([c * r for c, r in self.grid])

    def borders(self, face: int) -> np.ndarray:
        """(S, 4) bool: which adjacent faces [l, d, r, u] each sub-face of ``face`` borders."""
        nc, nr = self.grid[face]
        s = np.arange(nc * nr)
        col, row = s % max(nc, 1), s // max(nc, 1)
        return np.stack([col == 0, row == 0, col == nc - 1, row == nr - 1], axis=1)

    def cell(
        self, face: int, right: np.ndarray, up: np.ndarray, half_r: float, half_u: float
    ) -> np.ndarray:
        """Sub-face index (...,) of face coordinates ``right``, ``up`` (metres from the face
        centre) on a face of half sizes ``half_r``, ``half_u``."""
        nc, nr = self.grid[face]
        fr = (np.asarray(right) + half_r) / max(2.0 * half_r, GEOM_EPS)
        fu = (np.asarray(up) + half_u) / max(2.0 * half_u, GEOM_EPS)
        col = np.clip(np.floor(fr * nc), 0, nc - 1).astype(np.int64)
        row = np.clip(np.floor(fu * nr), 0, nr - 1).astype(np.int64)
        return row * nc + col


SUBFACE_SCHEMES: dict[str, SubfaceScheme] = {
    # 3 x 3 grid on every face: centre cell bound to nothing, edge cells to one adjacent face,
    # corner cells to two (the paper's Fig. 5e)
    "spherical": SubfaceScheme(grid=((3, 3),) * 6),
    "two_finger_tip": SubfaceScheme(grid=((3, 3),) * 6),
    # cylinder axis = box axis 0: the four side faces have 'right' along it and are cut into three
    # strips along the axis (each strip spans the face across the axis, so it is bound to the two
    # side faces the fingers wrap towards, and the end strips to their cap); the caps (axial
    # approach) are one sub-face bound to all four side faces (the paper's Fig. 5d)
    "cylindrical": SubfaceScheme(grid=((1, 1), (1, 1), (3, 1), (3, 1), (3, 1), (3, 1))),
    # flat part in the plane of axes 0, 1: the hand approaches the rim faces (0..3) in that plane
    # (the circle's samples all lie in the middle row); 3 x 3 like the sphere, so the middle row
    # is bound only to the neighbouring rim faces and the outer rows to the flat faces as well
    "three_finger_tip": SubfaceScheme(grid=((3, 3), (3, 3), (3, 3), (3, 3), (0, 0), (0, 0))),
}
"""Sub-face scheme of each grasp type (keys are the :class:`~pregrasp_core.shape.GraspType`
values)."""


def subface_scheme(grasp_type: GraspType | str) -> SubfaceScheme:
    """The sub-face scheme of a grasp type (a ``GraspType`` or its string value)."""
    key = getattr(grasp_type, "value", grasp_type)
    try:
        return SUBFACE_SCHEMES[str(key)]
    except KeyError:
        raise ValueError(
            f"unknown grasp type {grasp_type!r}; expected one of {sorted(SUBFACE_SCHEMES)}"
        ) from None


def usable_subfaces(blocked: np.ndarray, grasp_type: GraspType | str) -> list[np.ndarray]:
    """Which sub-faces of a box may carry pre-grasps.

    blocked: (6,) bool, the blocked state of the box's faces. Returns a list of 6 arrays
    ``(S_f,) bool``: sub-face ``s`` of face ``f`` is usable when face ``f`` is free and every
    adjacent face the sub-face borders is free.
    """
    b = np.asarray(blocked, dtype=bool)
    if b.shape != (6,):
        raise ValueError(f"blocked must have shape (6,), got {b.shape}")
    scheme = subface_scheme(grasp_type)
    out = []
    for f in range(6):
        borders = scheme.borders(f)  # (S, 4)
        adj_blocked = b[ADJACENT[f]]  # (4,)
        out.append(~b[f] & ~np.any(borders & adj_blocked, axis=1))
    return out


def subface_rectangles(box: OrientedBox, grasp_type: GraspType | str) -> list[np.ndarray]:
    """World corners of every sub-face of ``box`` for drawing: a list of 6 arrays (S_f, 4, 3),
    corners counter-clockwise seen from outside (bottom-left, bottom-right, top-right, top-left).
    """
    scheme = subface_scheme(grasp_type)
    h = box.half_extents
    out = []
    for f in range(6):
        nc, nr = scheme.grid[f]
        if nc * nr == 0:
            out.append(np.zeros((0, 4, 3)))
            continue
        r_ax, u_ax = FACE_RIGHT[f], FACE_UP[f]
        hr, hu = float(np.abs(r_ax) @ h), float(np.abs(u_ax) @ h)
        centre = FACE_NORMAL[f] * h[FACE_AXIS[f]]
        s = np.arange(nc * nr)
        col, row = s % nc, s // nc
        r0 = -hr + 2 * hr * col / nc
        r1 = -hr + 2 * hr * (col + 1) / nc
        u0 = -hu + 2 * hu * row / nr
        u1 = -hu + 2 * hu * (row + 1) / nr
        rs = np.stack([r0, r1, r1, r0], axis=1)  # (S, 4)
        us = np.stack([u0, u0, u1, u1], axis=1)
        p_box = centre + rs[..., None] * r_ax + us[..., None] * u_ax  # (S, 4, 3)
        out.append(box.to_world(p_box.reshape(-1, 3)).reshape(-1, 4, 3))
    return out


# ----------------------------------------------------------------------------- sub-face clearance

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


def _covered_cells(
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


def usable_subfaces_by_cells(
    covered: np.ndarray, grasp_type: GraspType | str, min_coverage: float
) -> list[np.ndarray]:
    """The usable sub-faces of one box under the ``subface`` rule: a list of 6 arrays
    ``(S_f,) bool``. covered: (6, G, G) bool, the box's :attr:`FaceMasks.covered`. A sub-face is
    usable when none of its regions (:func:`subface_regions`: its own cells, the bands of the
    adjacent faces it borders) has ``min_coverage`` of its cells covered."""
    cov = np.asarray(covered, dtype=bool)
    G = SUBFACE_GRID
    if cov.shape != (6, G, G):
        raise ValueError(f"covered must have shape (6, {G}, {G}), got {cov.shape}")
    out = []
    for per in subface_regions(grasp_type):  # six faces
        ok = np.zeros(len(per), dtype=bool)
        for s, reg in enumerate(per):  # (R, 6, G, G) regions of sub-face s
            n = reg.sum(axis=(1, 2, 3))  # (R,) cells per region
            hit = (reg & cov).sum(axis=(1, 2, 3))
            ok[s] = bool(np.all(hit < min_coverage * np.maximum(n, 1)))
        out.append(ok)
    return out
