"""The face masks of every node: :class:`FaceMasks` and :func:`compute_face_masks`."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from ..decomposition import BoxTree
from ..errors import WorkLimitError
from ..limits import WorkLimits
from ..shape import GraspType
from ..tolerances import GEOM_EPS
from .blocking import (
    PAIR_CHUNK,
    SAT_CHUNK,
    blocked_by_support,
    face_coverage,
    face_slabs,
    obb_penetration,
    tree_intervals,
)
from .cells import covered_cells, usable_subfaces_by_cells
from .faces import ADJACENT
from .params import FaceMaskParams, SupportPlane
from .subfaces import usable_subfaces


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
        covered = covered_cells(tree, near_of, support, params, points)
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
