"""Build the pre-grasp pool of an object (:func:`build_pool`).

The samples of every candidate (:func:`~.surfaces.sample_node`) go through three filters, each
counted in ``PreGraspPool.dropped``: samples on sub-faces that are not usable are dropped; the
others are backed off along their approach line until the open hand clears the support plane
and the cloud, or dropped when it cannot within ``max_backoff``. A candidate whose own grasp type
leaves nothing may fall back to another type (``SamplingParams.fallback``).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np

from ..box import OrientedBox
from ..decomposition import BoxNode, BoxTree
from ..errors import PregraspError
from ..facemask import FaceMasks, SupportPlane
from ..geometry import as_points
from ..hand import grasp_type_name
from ..shape import GRASP_TYPES, NodeShape, ShapeParams
from .collision import (
    CellCache,
    cloud_grid,
    collision_batch_bytes,
    hand_cell_cache,
    hand_hits_points,
    hand_min_height,
)
from .params import (
    MAX_POOL_SAMPLES,
    POOL_BYTES_PER_SAMPLE,
    SAMPLING_BOUNDS,
    SamplingParams,
    TraversalPolicy,
)
from .pinch import PINCH_SURFACE, pinch_count_bound, pinch_samples
from .pool import DROP_REASONS, PreGraspPool
from .surfaces import sample_node, total_samples
from .traversal import Traversal, grip_width, traverse

if TYPE_CHECKING:
    from ..hand import Hand
    from .collision_kernels import PointGrid

logger = logging.getLogger(__name__)

FALLBACK_ORDER: tuple[str, ...] = ("cylindrical", "spherical", "three_finger_tip", "two_finger_tip")
"""Order in which other grasp types are tried when a candidate's own type gives nothing."""


def _concat_pools(pools: list[PreGraspPool], joint_names: Sequence[str]) -> PreGraspPool:
    """The pools one after the other (an empty pool when there are none)."""
    if not pools:
        return PreGraspPool.empty(joint_names)
    return PreGraspPool(
        T_world_hand=np.concatenate([p.T_world_hand for p in pools]),
        approach=np.concatenate([p.approach for p in pools]),
        grasp_type=np.concatenate([p.grasp_type for p in pools]).astype("<U16"),
        spread=np.concatenate([p.spread for p in pools]),
        q=np.concatenate([p.q for p in pools]),
        node=np.concatenate([p.node for p in pools]),
        face=np.concatenate([p.face for p in pools]),
        subface=np.concatenate([p.subface for p in pools]),
        surface=np.concatenate([p.surface for p in pools]),
        backoff=np.concatenate([p.backoff for p in pools]),
        approach_limit=np.concatenate([np.asarray(p.approach_limit) for p in pools]),
        joint_names=tuple(joint_names),
    )


def estimate_pool_bytes(n_samples: int, n_points: int = 0) -> int:
    """Bytes of peak memory the pool stage needs for ``n_samples`` samples in one pass on a
    cloud of ``n_points`` (an upper bound, checked against tracemalloc by the tests):
    :data:`POOL_BYTES_PER_SAMPLE` per sample, 64 per point (the cloud's voxel grid) and the
    collision test's bounded batch (:func:`~.collision.collision_batch_bytes`)."""
    return int(n_samples) * POOL_BYTES_PER_SAMPLE + 64 * int(n_points) + collision_batch_bytes()


def check_pool_size(
    jobs: Sequence[tuple[OrientedBox, str]],
    params: SamplingParams,
    max_samples: int = MAX_POOL_SAMPLES,
    pinch_boxes: Sequence[OrientedBox] = (),
) -> int:
    """The number of samples sampling every ``(box, grasp_type)`` of ``jobs`` at
    ``params.interval`` makes (:func:`~.surfaces.total_samples`, nothing allocated), plus a
    bound on the pinches of ``pinch_boxes`` when ``params.pinch``
    (:func:`~.pinch.pinch_count_bound`); raises ``PregraspError`` when it exceeds
    ``max_samples``, with the memory it would take and the smallest interval that fits."""
    interval = params.interval
    pinch_boxes = list(pinch_boxes) if params.pinch else []

    def count(intervals: Sequence[float]) -> np.ndarray:
        return total_samples(jobs, intervals) + pinch_count_bound(pinch_boxes, intervals)

    n = int(count([interval])[0])
    if n <= max_samples:
        return n
    head = (
        f"the pre-grasp pool would make {n:,} samples on {len(jobs)} candidate node(s) at "
        f"interval {interval:g} m (about {estimate_pool_bytes(n) / 2**30:.1f} GiB), more than "
        f"the limit of {max_samples:,}"
    )
    # the intervals of two significant digits above this one, up to the largest allowed
    hi = SAMPLING_BOUNDS["interval"][1]
    e0 = int(np.floor(np.log10(interval)))
    grid = [float(f"{k}e{e - 1}") for e in range(e0, 1) for k in range(10, 100)]
    grid = [v for v in grid if interval < v <= hi] + [hi]
    fits = np.flatnonzero(count(grid) <= max_samples)  # falls as interval grows
    if len(fits) == 0:
        raise PregraspError(
            f"{head}, even at the largest interval ({hi:g} m): the object is too large for its "
            "hand; scale it down (--scale) or sample fewer nodes (policy 'leaves')"
        )
    raise PregraspError(
        f"{head}: raise the sampling interval (SamplingParams.interval, --interval) to at least "
        f"{grid[fits[0]]:g} m, or sample fewer nodes (policy 'leaves'); see docs/limits.md"
    )


def build_pool(
    points: np.ndarray,
    tree: BoxTree,
    shapes: Sequence[NodeShape],
    masks: FaceMasks,
    hand: Hand,
    params: SamplingParams | None = None,
    traversal: Traversal | None = None,
    shape_params: ShapeParams | None = None,
    max_samples: int = MAX_POOL_SAMPLES,
) -> PreGraspPool:
    """The pre-grasp pool of an object.

    points: (N, 3) the cloud (world frame) for the collision filter; tree, shapes, masks: the
    decomposition, its shapes and face masks (``masks.support`` is the support plane or None);
    hand: the ``pregrasp_core.hand.Hand``; traversal: the candidates (computed with
    :func:`traverse` when ``None``); max_samples: the most samples one pass over the candidates
    may generate (own types, then each fallback pass): past it a ``PregraspError`` says which
    interval fits, before anything is allocated (:func:`estimate_pool_bytes`).
    """
    params = SamplingParams() if params is None else params
    pts = as_points(points)
    if traversal is None:
        traversal = traverse(tree, shapes, hand, params, shape_params)
    joint_names = tuple(hand.joint_names)
    dropped = {r: 0 for r in DROP_REASONS}
    # the cloud's voxel grid for every collision test of this pool (no k-d tree: the compiled
    # test needs only the grid, and building a tree of the cloud took longer than the grid)
    grid = cloud_grid(pts) if len(pts) else None
    # the types each candidate may use, in order: its own, then (fallback) the others that fit
    queue: dict[int, list[str]] = {}
    own_type: dict[int, str] = {}
    for i in traversal.candidates:
        own = own_type[i] = grasp_type_name(shapes[i].grasp_type)
        # a candidate too big for its own type (taken by the traversal's last resort, never
        # under the ``all`` policy, which samples every node with its own type) starts with
        # the others
        own_fits = (
            traversal.policy is TraversalPolicy.ALL
            or grip_width(tree.nodes[i].box, own)
            <= float(hand.aperture(own)) * params.aperture_scale
        )
        queue[i] = [own] if own_fits else []
        if params.fallback:
            queue[i] += [
                t
                for t in FALLBACK_ORDER
                if t != own
                and grip_width(tree.nodes[i].box, t)
                <= float(hand.aperture(t)) * params.aperture_scale
            ]
    kept: list[PreGraspPool] = []
    fallback: dict[int, str] = {}
    todo = list(traversal.candidates)
    for attempt in range(len(GRASP_TYPES)):  # own type, then up to 3 fallbacks
        jobs = [(tree.nodes[i], queue[i][attempt]) for i in todo if attempt < len(queue[i])]
        pinch_boxes = [tree.nodes[i].box for i in traversal.candidates] if attempt == 0 else []
        check_pool_size([(nd.box, gt) for nd, gt in jobs], params, max_samples, pinch_boxes)
        pools = [_node_pool(nd, gt, masks, hand, params, dropped, max_samples) for nd, gt in jobs]
        got = _clear_the_hand(
            _concat_pools(pools, joint_names), hand, pts, grid, masks.support, params, dropped
        )
        kept.append(got)
        placed = set(np.unique(got.node).tolist())
        fallback.update({i: queue[i][attempt] for i in placed if queue[i][attempt] != own_type[i]})
        todo = [i for i in todo if i not in placed and attempt + 1 < len(queue[i])]
        if not todo:
            break
    if params.pinch:
        pinches = _pinch_pool(pts, tree, traversal.candidates, masks, hand, params, dropped)
        kept.append(_clear_the_hand(pinches, hand, pts, grid, masks.support, params, dropped))
    pool = _concat_pools(kept, joint_names)
    order = np.lexsort((np.arange(len(pool)), pool.node))  # group by node, stable
    pool = replace(
        pool.select(order), candidates=traversal.candidates, dropped=dropped, fallback=fallback
    )
    logger.info("pool: %d pre-grasps, dropped %s, fallback %s", len(pool), dropped, fallback)
    return pool


def _node_pool(
    nd: BoxNode,
    gt: str,
    masks: FaceMasks,
    hand: Hand,
    params: SamplingParams,
    dropped: dict[str, int],
    max_samples: int,
) -> PreGraspPool:
    """The samples of one node for one grasp type on its usable sub-faces, as a pool."""
    every = sample_node(nd.box, gt, params, max_samples=max_samples)
    use = masks.usable(nd.id, gt)
    table = np.zeros((6, max(len(u) for u in use) or 1), dtype=bool)  # (6, S_max) usable
    for f, u in enumerate(use):
        table[f, : len(u)] = u
    keep = table[every.face, every.subface]  # (M,)
    ok = replace(
        every,
        T_box_grasp=every.T_box_grasp[keep],
        face=every.face[keep],
        subface=every.subface[keep],
        surface=every.surface[keep],
        aim=every.aim[keep],
    )
    dropped["blocked_subface"] += int(np.count_nonzero(~keep))
    M = len(ok.face)
    # the samples place the hand's grasp centre (a point of the palm plane, hand frame);
    # the hand's origin sits at -grasp_center from it
    T_grasp_hand = np.eye(4)
    T_grasp_hand[:3, 3] = -np.asarray(hand.grasp_center(gt), dtype=np.float64)
    T = nd.box.T_world_box @ ok.T_box_grasp @ T_grasp_hand  # (M, 4, 4)
    q = np.asarray(hand.preshape(gt), dtype=np.float64)
    return PreGraspPool(
        T_world_hand=T,
        approach=T[:, :3, 2].copy(),
        grasp_type=np.full(M, gt, dtype="<U16"),
        spread=np.full(M, float(hand.spread_for(gt))),
        q=np.tile(q, (M, 1)),
        node=np.full(M, nd.id, dtype=np.int64),
        face=ok.face,
        subface=ok.subface,
        surface=ok.surface,
        joint_names=tuple(hand.joint_names),
    )


def _pinch_pool(
    points: np.ndarray,
    tree: BoxTree,
    candidates: Sequence[int],
    masks: FaceMasks,
    hand: Hand,
    params: SamplingParams,
    dropped: dict[str, int],
) -> PreGraspPool:
    """The fingertip pinches (:mod:`.pinch`) of every candidate whose face they come from has
    its centre sub-face usable, as a pool (the others are counted ``blocked_subface``)."""
    pools = []
    for i in candidates:  # loop over the candidate nodes
        nd = tree.nodes[i]
        got = pinch_samples(hand, nd.box, masks.support, params, points[nd.indices])
        if got is None:
            continue
        # a pinch needs its face's centre sub-face (3 x 3 grid) usable
        use = masks.usable(i, "spherical")
        keep = np.array([use[f][4] for f in got.face], dtype=bool)
        dropped["blocked_subface"] += int(np.count_nonzero(~keep))
        M = int(keep.sum())
        if M == 0:
            continue
        pools.append(
            PreGraspPool(
                T_world_hand=got.T_world_hand[keep],
                approach=got.T_world_hand[keep, :3, 2].copy(),
                grasp_type=got.grasp_type[keep],
                spread=got.spread[keep],
                q=got.q[keep],
                node=np.full(M, i, dtype=np.int64),
                face=got.face[keep],
                subface=np.full(M, 4, dtype=np.int64),
                surface=np.full(M, PINCH_SURFACE, dtype=np.int64),
                approach_limit=got.approach_limit[keep],
                joint_names=tuple(hand.joint_names),
            )
        )
    return _concat_pools(pools, hand.joint_names)


def _clear_the_hand(
    pool: PreGraspPool,
    hand: Hand,
    points: np.ndarray,
    grid: PointGrid | None,
    support: SupportPlane | None,
    params: SamplingParams,
    dropped: dict[str, int],
) -> PreGraspPool:
    """Back every pre-grasp off along its approach line by the smallest multiple of
    ``backoff_step`` (up to ``max_backoff``) at which its open hand is above the support plane
    and holds no cloud point, provided the hand is also clear at ``max_backoff`` (where the
    approach starts from); drop it otherwise (counted in ``dropped``). Levels are tested in the
    order 0, ``max_backoff``, then the ones between, so hopeless pre-grasps cost two tests."""
    P = len(pool)
    if P == 0:
        return pool
    step, n_levels = params.backoff_step, int(np.floor(params.max_backoff / params.backoff_step))
    levels = np.arange(n_levels + 1) * step  # (K,) candidate back-offs, metres
    first = np.zeros(P, dtype=np.int64)  # first level the support allows
    if support is not None:
        low = hand_min_height(hand, pool.T_world_hand, pool.grasp_type, pool.q, support)
        low = low - params.support_margin  # (P,) above plane
        down = -(pool.approach @ support.normal)  # (P,) > 0: backing off raises the hand
        with np.errstate(divide="ignore", invalid="ignore"):
            need = np.where(low >= 0, 0.0, np.where(down > 1e-9, -low / down, np.inf))
        first = np.ceil(need / step - 1e-6).astype(np.float64)  # 1e-6: round-off
        no_room = ~(first <= n_levels)
        dropped["support"] += int(np.count_nonzero(no_room))
        first = np.where(no_room, n_levels + 1, first).astype(np.int64)
    backoff = np.full(P, np.nan)
    cells: CellCache = hand_cell_cache(hand)  # link cells per preshape, kept with the hand
    hopeless = np.zeros(P, dtype=bool)  # still colliding at the largest back-off

    def test(idx: np.ndarray, k: int) -> np.ndarray:
        T = pool.T_world_hand[idx].copy()
        T[:, :3, 3] -= levels[k] * pool.approach[idx]
        return hand_hits_points(
            hand, T, pool.grasp_type[idx], pool.q[idx], points, params.collision_margin, cells, grid
        )

    # levels in the order 0, then the last (to drop hopeless ones at once), then 1, 2, ...
    order = [0, n_levels] + list(range(1, n_levels)) if n_levels > 0 else [0]
    for k in order:  # loop over the few back-off levels
        todo = np.flatnonzero((first <= k) & np.isnan(backoff) & ~hopeless)
        if len(todo) == 0:
            continue
        hit = test(todo, k)
        if k == n_levels and n_levels > 0:
            hopeless[todo[hit]] = True
            # free at the largest back-off: placed there unless a smaller level also is
            free_last = todo[~hit]
            backoff[free_last] = -1.0  # marker: free at the last level, smaller ones untested
            continue
        done = todo[~hit]
        backoff[done] = levels[k]
    # the marked ones get the smallest free level >= their first, scanning 1 .. n_levels - 1
    marked = np.flatnonzero(backoff == -1.0)
    backoff[marked] = np.nan
    for k in range(1, n_levels):
        todo = marked[(first[marked] <= k) & np.isnan(backoff[marked])]
        if len(todo) == 0:
            continue
        backoff[todo[~test(todo, k)]] = levels[k]
    rest = marked[np.isnan(backoff[marked])]
    backoff[rest] = levels[n_levels] if n_levels > 0 else np.nan
    placed = ~np.isnan(backoff)
    dropped["object_collision"] += int(np.count_nonzero(~placed & (first <= n_levels)))
    out = pool.select(placed)
    T = out.T_world_hand.copy()
    T[:, :3, 3] -= backoff[placed][:, None] * out.approach
    # a limited approach (pinches) is measured from the pre-grasp before its back-off
    limit = np.asarray(out.approach_limit) + backoff[placed]
    return replace(out, T_world_hand=T, backoff=backoff[placed], approach_limit=limit)
