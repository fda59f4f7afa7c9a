"""Fit-and-split decomposition of a point cloud into a binary tree of oriented boxes.

After Huebner, Ruthotto & Kragic (ICRA 2008), simplified as in Sainul, Deb & Deb (2019): start
with the minimum-volume box of all points; try to split every box by a plane parallel to one of
its faces, choosing the plane that minimises the summed volume of the two children; keep the
split only when it tightens the approximation enough. See ``docs/decomposition.md``.

Algorithm per node (n points, vectorised over points, loops over the 3 axes only):

1. ``p_box`` = the node's points in its box frame.
2. For each axis ``a``: sort ``p_box`` along ``a``; running min/max of the two other coordinates
   from the front (``np.minimum.accumulate``) and from the back give, for every cut between
   sorted positions ``i`` and ``i + 1``, the extents of both children's boxes in the parent frame,
   so their summed volume costs O(1) per cut and O(n log n) per axis in all. Only cuts between
   distinct coordinate values, with at least ``min_points`` points on each side, are candidates.
3. The best cut over the three axes is refitted: each child gets its true minimum-volume box
   (or its parent-frame box if that is smaller, which the exact MVBB never is but an
   approximate one may be).
4. The split is accepted when ``(V(child1) + V(child2)) / V(parent) < volume_ratio`` with the
   refitted volumes, each child keeps ``>= min_points`` points and the node's depth is below
   ``max_depth``. Otherwise the node is a leaf. (For speed, a split whose parent-frame ratio is
   not below the threshold first gets quick refits, ``QUICK_MVBB``; when even those are far
   from the threshold the full refits are skipped. See ``docs/decomposition.md``.)

Nodes are processed breadth-first (FIFO): node ids and ``split_order`` both follow that order.
The two children of a split are ordered by decreasing number of points (on a tie, the side
below the plane first), so the tree does not depend on the signs of the box axes.
"""

from __future__ import annotations

import logging
import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from .box import OrientedBox, canonical_axes
from .decomposition_kernels import kernels
from .errors import DegenerateGeometryError, WorkLimitError
from .geometry import as_points
from .limits import (
    MAX_MIN_POINTS,
    MAX_TREE_DEPTH,
    MIN_BOX_POINTS,
    WorkLimits,
    check_int,
    check_real,
    decomposition_bytes,
    format_bytes,
)
from .mvbb import MvbbParams, minimum_volume_box
from .tolerances import FLAT_EXTENT

logger = logging.getLogger(__name__)

QUICK_MVBB = MvbbParams(
    kernel_grid=12, n_angles=8, n_refine=3, step_min=math.radians(0.4), max_rounds=0, snap_max=0
)
"""MVBB settings of the quick first stage of the acceptance test: the same global search with a
coarser kernel and angle grid, three candidates polished, polish stopped at 0.4 degrees, no
final polish on the cloud and no snap (35-50 % of the time). On the 13 demo objects (seeds 0
and 1; 1,000, 5,000 and 20,000 points) its boxes are at most 1.27 % larger than those of the
default settings."""

QUICK_REJECT_MARGIN: float = 0.03
"""A tried split whose parent-frame ratio is not already below ``volume_ratio`` is rejected
without the full refits when even the quick refits give a ratio of at least
``volume_ratio / (1 - QUICK_REJECT_MARGIN)``: the full fits would have to be more than 3 % smaller
in sum than the quick ones (2.4 times the largest gap measured, see
``docs/decomposition.md``). Only the work changes: the tree is the one of the single-stage rule
unless that assumption fails."""


@dataclass(frozen=True)
class DecompositionParams:
    """Parameters of the fit-and-split decomposition (defaults from the paper)."""

    volume_ratio: float = 0.9
    """A split is accepted when (V(child1) + V(child2)) / V(parent) is below this, in (0, 1]."""
    min_points: int = 500
    """Each child of an accepted split keeps at least this many points, in [4, 10^9] (a box
    that is not flat needs 4 points)."""
    max_depth: int = 8
    """Nodes at this depth are never split (root depth 0; 0 = no split at all); in [0, 64]."""

    def __post_init__(self) -> None:
        # bounds: pregrasp_core.limits and docs/limits.md ("Decomposition")
        vr = check_real("volume_ratio", self.volume_ratio, 0.0, 1.0, lo_open=True)
        mp = check_int("min_points", self.min_points, MIN_BOX_POINTS, MAX_MIN_POINTS)
        md = check_int("max_depth", self.max_depth, 0, MAX_TREE_DEPTH)
        object.__setattr__(self, "volume_ratio", vr)
        object.__setattr__(self, "min_points", mp)
        object.__setattr__(self, "max_depth", md)


@dataclass(frozen=True, eq=False)
class BoxNode:
    """One box of the decomposition tree (compared by identity: it holds arrays)."""

    id: int
    """Position of this node in ``BoxTree.nodes`` (root 0)."""
    parent: int
    """Id of the parent node, -1 for the root."""
    children: tuple[int, ...]
    """Ids of the two children (the one with more points first), or ``()`` for a leaf."""
    depth: int
    """Number of edges from the root (root 0)."""
    indices: np.ndarray
    """(n,) int64, sorted ascending: indices of this node's points into the cloud."""
    box: OrientedBox
    """The box around this node's points (world frame)."""
    split_order: int
    """Index of the accepted split that created this node (root 0, then 1, 2, ...); the two
    children of one split share it."""

    def __post_init__(self) -> None:
        idx = np.asarray(self.indices)
        if idx.ndim != 1 or not (idx.dtype.kind in "iu" or idx.size == 0):
            raise ValueError(
                f"indices must be a 1-D integer array, got shape {idx.shape} dtype {idx.dtype}"
            )
        view = idx.astype(np.int64, copy=False).view()
        view.setflags(write=False)  # read-only: the tree is immutable
        object.__setattr__(self, "indices", view)

    @property
    def n_points(self) -> int:
        """Number of points of this node."""
        return int(self.indices.shape[0])

    @property
    def is_leaf(self) -> bool:
        """True when the node has no children."""
        return not self.children


@dataclass(frozen=True, eq=False)
class BoxTree:
    """A binary tree of oriented boxes over a cloud of ``n_points`` points (compared by
    identity)."""

    nodes: tuple[BoxNode, ...]
    """All nodes; ``nodes[i].id == i``; breadth-first order, root first."""
    n_points: int
    """Number of points of the decomposed cloud."""

    def __post_init__(self) -> None:
        if not self.nodes:
            raise ValueError("a BoxTree needs at least a root node, got 0 nodes")
        for i, nd in enumerate(self.nodes):
            if nd.id != i:
                raise ValueError(f"node at position {i} has id {nd.id}; ids must be positions")
            if (i == 0) != (nd.parent == -1):
                raise ValueError(f"node {i}: only the root (id 0) has parent -1")
            if len(nd.children) not in (0, 2):
                raise ValueError(f"node {i} has {len(nd.children)} children, expected 0 or 2")
            for c in nd.children:
                if not (0 < c < len(self.nodes)) or self.nodes[c].parent != i:
                    raise ValueError(f"node {i} lists child {c} whose parent is not {i}")

    @property
    def root(self) -> BoxNode:
        """The root node (all points, the minimum-volume box of the cloud)."""
        return self.nodes[0]

    @property
    def n_splits(self) -> int:
        """Number of accepted splits (= number of leaves - 1)."""
        return max(nd.split_order for nd in self.nodes)

    def node(self, i: int) -> BoxNode:
        """The node with id ``i``."""
        if not 0 <= i < len(self.nodes):
            raise IndexError(f"node id {i} out of range [0, {len(self.nodes) - 1}]")
        return self.nodes[i]

    def leaves(self) -> list[int]:
        """Ids of the leaves, ascending."""
        return [nd.id for nd in self.nodes if not nd.children]

    def is_ancestor(self, a: int, b: int) -> bool:
        """True when node ``a`` is a strict ancestor of node ``b`` (a node is not its own)."""
        self.node(a)
        p = self.node(b).parent
        while p != -1:
            if p == a:
                return True
            p = self.nodes[p].parent
        return False

    def is_related(self, a: int, b: int) -> bool:
        """True when ``a == b`` or one is an ancestor of the other."""
        return a == b or self.is_ancestor(a, b) or self.is_ancestor(b, a)

    def descendants(self, i: int) -> list[int]:
        """Ids of all strict descendants of node ``i``, breadth-first."""
        out: list[int] = []
        queue = deque(self.node(i).children)
        while queue:
            c = queue.popleft()
            out.append(c)
            queue.extend(self.nodes[c].children)
        return out

    def cut_at_level(self, k: int) -> list[int]:
        """Ids of the boxes that partition the cloud after the first ``k`` accepted splits.

        ``cut_at_level(0) == [0]`` (the root) and ``cut_at_level(n_splits) == leaves()``.
        Raises ``ValueError`` when ``k`` is outside ``[0, n_splits]``.
        """
        if isinstance(k, bool) or not isinstance(k, (int, np.integer)):
            raise ValueError(f"level must be an integer in [0, {self.n_splits}], got {k!r}")
        if not 0 <= k <= self.n_splits:
            raise ValueError(f"level must be in [0, {self.n_splits}], got {k}")
        return [
            nd.id
            for nd in self.nodes
            if nd.split_order <= k
            and (not nd.children or self.nodes[nd.children[0]].split_order > k)
        ]

    def point_labels(self, node_ids: list[int] | None = None) -> np.ndarray:
        """(n_points,) int64: for each point, the id of the node of ``node_ids`` holding it.

        ``node_ids`` defaults to the leaves; it must partition the cloud (e.g. a
        ``cut_at_level``); points in none of them get -1.
        """
        ids = self.leaves() if node_ids is None else node_ids
        labels = np.full(self.n_points, -1, dtype=np.int64)
        for i in ids:
            labels[self.node(i).indices] = i
        return labels


def best_cut(p_box: np.ndarray, min_points: int) -> tuple[int, int, np.ndarray, float] | None:
    """Exact best face-parallel cut of points given in their box frame.

    p_box: (n, 3) float64. Returns ``(axis, i, order, volume)``: sorting along ``axis`` with
    ``order`` (n,), the first ``i + 1`` sorted points form one child and the rest the other;
    ``volume`` is the minimal summed volume of the two parent-frame child boxes. ``None`` when no
    cut leaves ``min_points`` on each side between distinct coordinate values.
    """
    p = as_points(p_box, "p_box")
    n = p.shape[0]
    if isinstance(min_points, bool) or not isinstance(min_points, (int, np.integer)):
        raise ValueError(f"min_points must be an integer >= 1, got {min_points!r}")
    if min_points < 1:
        raise ValueError(f"min_points must be an integer >= 1, got {min_points!r}")
    if n < 2 * min_points:
        return None
    best: tuple[int, int, np.ndarray, float] | None = None
    lo, hi = min_points - 1, n - min_points - 1  # cut after sorted position i, lo <= i <= hi
    pT = np.ascontiguousarray(p.T)  # (3, n): rows are contiguous, accumulate runs fast
    cut_scan = kernels().cut_scan
    for a in range(3):
        # Ties are never cut (see below), so the unstable sort gives the same children. The
        # compiled scan does what these numpy steps did, to the bit: s = pT[:, order]; running
        # maxima and minima of the two other rows from the front (the left child s[:, : i + 1])
        # and from the back (the right child s[:, i + 1 :]); for every cut, total =
        # (x[i] - x[0]) e1 e2 + (x[-1] - x[i + 1]) f1 f2, inf where x[i + 1] <= x[i] (only
        # between distinct values); the first minimum.
        order = np.argsort(pT[a])
        j, v = cut_scan(pT, order, a, lo, hi)
        if math.isfinite(v) and (best is None or v < best[3]):
            best = (a, lo + j, order, float(v))
    return best


def _frame_box(box: OrientedBox, q: np.ndarray) -> OrientedBox:
    """The tightest box with the axes of ``box`` around points ``q`` (3, m) given in the frame
    of ``box`` (coordinates relative to its centre), canonicalised; the same box as
    ``OrientedBox.from_points_in_frame(world points, box.rotation)`` up to round-off."""
    lo, hi = q.min(axis=1), q.max(axis=1)
    Rc, ext = canonical_axes(box.rotation, hi - lo)
    return OrientedBox(
        center=box.center + box.rotation @ ((lo + hi) / 2.0), rotation=Rc, extents=ext
    )


def _refit(
    points: np.ndarray,
    R_parent: np.ndarray,
    in_frame: OrientedBox | None = None,
    mvbb_params: MvbbParams | None = None,
) -> OrientedBox:
    """Minimum-volume box of a child, never larger than its box in the parent frame.

    ``in_frame``: the child's box in the parent frame when already known; ``mvbb_params``: MVBB
    settings (default: the default ``MvbbParams``)."""
    if in_frame is None:
        in_frame = OrientedBox.from_points_in_frame(points, R_parent)
    try:
        if mvbb_params is None:
            mvbb = minimum_volume_box(points)
        else:
            mvbb = minimum_volume_box(points, mvbb_params)
    except DegenerateGeometryError as exc:
        logger.debug("child MVBB degenerate (%s); keeping the parent-frame box", exc)
        return in_frame
    return mvbb if mvbb.volume <= in_frame.volume else in_frame


def decompose(
    points: np.ndarray,
    params: DecompositionParams | None = None,
    limits: WorkLimits | None = None,
) -> BoxTree:
    """Split ``points`` (N, 3) into a binary tree of oriented boxes (see the module docstring).

    The leaves partition the points; every node's box contains its points. Raises
    ``DegenerateGeometryError`` when the cloud has fewer than ``MIN_BOX_POINTS`` points or no box
    can be fitted to it (all points identical or collinear), and ``WorkLimitError`` when the
    estimated memory passes ``limits.max_decomposition_bytes`` (before any work) or the tree
    would get more than ``limits.max_parts`` parts (as soon as a split would make one more; the
    work done is at most ``2 max_parts - 1`` nodes).
    """
    params = DecompositionParams() if params is None else params
    if not isinstance(params, DecompositionParams):
        raise TypeError(f"params must be DecompositionParams, got {type(params).__name__}")
    limits = WorkLimits() if limits is None else limits
    pts = as_points(points)
    n = pts.shape[0]
    if n < MIN_BOX_POINTS:
        raise DegenerateGeometryError(
            f"cannot decompose {n} points: a box needs at least {MIN_BOX_POINTS}; "
            "give a cloud with more points"
        )
    need = decomposition_bytes(n, params.max_depth, limits.max_parts)
    if need > limits.max_decomposition_bytes:
        raise WorkLimitError(
            f"decomposing {n:,} points needs about {format_bytes(need)}, more than the limit "
            f"{format_bytes(limits.max_decomposition_bytes)} (max_decomposition_bytes): "
            "give fewer points (sample or thin the cloud) or a smaller max_depth"
        )
    if not np.all(np.isfinite(pts)):
        raise ValueError("points contain NaN or inf; drop those rows first")

    pts_t = np.ascontiguousarray(pts.T)  # (3, N)
    parent = [-1]
    children: list[tuple[int, ...]] = [()]
    depth = [0]
    indices = [np.arange(n, dtype=np.int64)]
    boxes = [minimum_volume_box(pts)]
    split_order = [0]
    n_splits = 0
    queue = deque([0])
    while queue:
        k = queue.popleft()
        box, idx = boxes[k], indices[k]
        if depth[k] >= params.max_depth or idx.shape[0] < 2 * params.min_points:
            continue
        if box.extents[2] < FLAT_EXTENT:
            logger.debug("node %d is flat (%.3g m); not split", k, box.extents[2])
            continue
        # The node's points in its box frame, (3, n): column gathers and a 3 x 3 product are
        # much cheaper than the same work on (n, 3) rows.
        q = box.rotation.T @ (np.take(pts_t, idx, axis=1) - box.center[:, None])
        cut = best_cut(q.T, params.min_points)
        if cut is None:
            continue
        axis, i, order, v_frame = cut
        sides = [order[: i + 1], order[i + 1 :]]  # positions into idx
        if sides[1].size > sides[0].size:  # the child with more points first (invariant)
            sides.reverse()
        left, right = np.sort(idx[sides[0]]), np.sort(idx[sides[1]])
        p1, p2 = pts[left], pts[right]
        f1, f2 = (_frame_box(box, np.take(q, side, axis=1)) for side in sides)
        if not (f1.volume + f2.volume) / box.volume < params.volume_ratio:
            # Two-stage test: the full refits only when quick refits come close to the threshold.
            q_ratio = (
                _refit(p1, box.rotation, f1, QUICK_MVBB).volume
                + _refit(p2, box.rotation, f2, QUICK_MVBB).volume
            ) / box.volume
            if q_ratio >= params.volume_ratio / (1.0 - QUICK_REJECT_MARGIN):
                logger.debug(
                    "node %d: frame ratio %.3f, quick refit ratio %.3f: leaf",
                    k,
                    v_frame / box.volume,
                    q_ratio,
                )
                continue
        b1 = _refit(p1, box.rotation, f1)
        b2 = _refit(p2, box.rotation, f2)
        ratio = (b1.volume + b2.volume) / box.volume
        logger.debug(
            "node %d: best cut axis %d, %d | %d points, frame ratio %.3f, refit ratio %.3f",
            k,
            axis,
            left.size,
            right.size,
            v_frame / box.volume,
            ratio,
        )
        if not ratio < params.volume_ratio:
            continue
        if n_splits + 2 > limits.max_parts:  # leaves: n_splits + 1 now, one more after it
            raise WorkLimitError(
                f"the decomposition needs more than {limits.max_parts:,} parts (max_parts): "
                f"with volume_ratio {params.volume_ratio:g}, min_points {params.min_points} and "
                f"max_depth {params.max_depth} it keeps splitting; raise min_points, lower "
                "max_depth or volume_ratio, or raise max_parts"
            )
        n_splits += 1
        c1, c2 = len(parent), len(parent) + 1
        children[k] = (c1, c2)
        for ind, b in ((left, b1), (right, b2)):
            parent.append(k)
            children.append(())
            depth.append(depth[k] + 1)
            indices.append(ind)
            boxes.append(b)
            split_order.append(n_splits)
        queue.extend((c1, c2))

    nodes = tuple(
        BoxNode(
            id=i,
            parent=parent[i],
            children=children[i],
            depth=depth[i],
            indices=indices[i],
            box=boxes[i],
            split_order=split_order[i],
        )
        for i in range(len(parent))
    )
    logger.info("decomposed %d points into %d boxes (%d splits)", n, len(nodes), n_splits)
    return BoxTree(nodes=nodes, n_points=n)
