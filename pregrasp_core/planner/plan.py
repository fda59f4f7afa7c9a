"""Planning a whole pool: chunks of pre-grasps through approach and slicing, one batched
closing per chunk (and per retreat from the support), verification and quality, on a thread
pool when there is one; then the ranking (:func:`plan_grasps`)."""

from __future__ import annotations

import dataclasses
import functools
import logging
import os
import pickle
import threading
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import TYPE_CHECKING, TypeVar

import numpy as np

from ..geometry import as_points, as_points_like
from ..normals import NormalParams, estimate_normals
from .approach import Prepared, prepare
from .assumed import assumed_mask, obstacle_points
from .context import Context
from .rank import first_level, quality_frame, score_grasp, settle_exact
from .slicing import ClosedFinger, Slice, close_slices, closing_records, finger_slices
from .types import REJECTION_REASONS, Grasp, GraspSet, PlannerParams
from .verify import finish

if TYPE_CHECKING:
    from ..facemask import SupportPlane
    from ..hand import Hand
    from ..io import PointCloud
    from ..pregrasps import PreGraspPool

logger = logging.getLogger(__name__)

LIFT_STEP: float = 0.005
"""Retreat step (metres) when the support plane stops the fingers (see ``max_lift``)."""

_CHUNK: int = 64
"""Pre-grasps whose fingers are closed together in one call of the batched closing model."""

_In = TypeVar("_In")
_Out = TypeVar("_Out")

_Records = dict[int, tuple[np.ndarray, list[ClosedFinger], float]]
"""Per pre-grasp index of a chunk: the joints after closing, what each finger did, and how far
back along the approach the hand closed (see :func:`_lift_retries`)."""


def _n_threads(threads: int) -> int:
    """Threads of the planner (``PlannerParams.threads``; 0 = the usable CPUs)."""
    if threads:
        return int(threads)
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # not on Linux
        return os.cpu_count() or 1


def _lift_retries(
    ctx: Context,
    todo: list[Prepared],
    records: _Records,
    each: Callable[[Callable[[Prepared], list[Slice]], list[Prepared]], list[list[Slice]]],
) -> None:
    """Retreats from the support (``PlannerParams.max_lift``) for the pre-grasps of a chunk:
    when the table, not the object, ended the approach and some finger closed on the table (or
    could not move), the hand closes again from ``k * LIFT_STEP`` higher up (back along the
    approach), k = 1, 2, ..., and keeps the height where the most fingers touch the object. It
    stops when every finger touches the object or when no finger is held by the table any more
    (going higher cannot help). Round k closes the fingers of every pre-grasp still retreating
    in one call of the batched closing model. ``records`` (pre-grasp -> (q, closings, lift)) is
    updated in place."""
    prm = ctx.params
    if ctx.support is None or prm.max_lift <= 0.0:
        return
    active = [p for p in todo if p.stop in ("support", "start")]
    best = {p.i: sum(bool(c.touched) for c in records[p.i][1]) for p in active}  # fingers on object
    for k in range(1, int(round(prm.max_lift / LIFT_STEP)) + 1):  # <= ~8 retreats
        active = [p for p in active if best[p.i] != len(records[p.i][1])]
        if not active:
            break
        up = k * LIFT_STEP

        def slices_up(p: Prepared, up: float = up) -> list[Slice]:
            T_up = p.T.copy()
            T_up[:3, 3] -= up * p.T0[:3, 2]
            return finger_slices(ctx, T_up, p.view.moved(up), p.q0, p.gt, p.spread)

        sls = each(slices_up, active)
        cls = close_slices(ctx, [sl for ss in sls for sl in ss])
        going, j = [], 0
        for p, ss in zip(active, sls, strict=True):  # loop over the retreating pre-grasps
            q_up, cl_up = closing_records(p.q0, ss, cls[j : j + len(ss)])
            j += len(ss)
            n_up = sum(bool(c.touched) for c in cl_up)
            if n_up > best[p.i]:
                best[p.i] = n_up
                records[p.i] = (q_up, cl_up, up)
            if any(
                c.on_table and not c.touched for c in cl_up
            ):  # a finger is still held by the table
                going.append(p)
        active = going


def _finish_or_keep(ctx: Context, records: _Records, p: Prepared | Grasp) -> Grasp:
    """:func:`~pregrasp_core.planner.verify.finish` for a prepared pre-grasp (its closing in
    ``records``); a rejection as it is."""
    return finish(ctx, p, *records[p.i]) if isinstance(p, Prepared) else p


def _plan_chunks(
    ctx: Context,
    pool: PreGraspPool,
    P: int,
    ex: ThreadPoolExecutor | None,
    grasps: list[Grasp],
    progress: Callable[[int, int], None] | None,
    starts: Sequence[int] | None = None,
) -> None:
    """Plan the pre-grasps of ``pool`` chunk by chunk into ``grasps`` (see :func:`plan_grasps`).
    The per-pre-grasp phases run on the thread pool ``ex`` when there is one (numpy and qhull
    release Python's global lock for most of their work); every pre-grasp is planned
    independently, so the results never depend on the threads. ``starts``: the first
    pre-grasp of each chunk to plan (default: every chunk, ``range(0, P, _CHUNK)``)."""

    def each(fn: Callable[[_In], _Out], items: list[_In]) -> list[_Out]:
        return (
            list(ex.map(fn, items)) if ex is not None and len(items) > 1 else list(map(fn, items))
        )

    prm, clock, done = ctx.params, ctx.clock, 0
    # GraspIt's torque origin: the object's centroid and largest radius (docs/quality.md)
    frame = quality_frame(prm.quality, ctx.points)
    score = functools.partial(score_grasp, prm.quality, frame, first_level(prm.quality, P))
    for c0 in range(0, P, _CHUNK) if starts is None else starts:  # loop over chunks
        t0 = time.perf_counter()
        preps = each(functools.partial(prepare, ctx, pool), list(range(c0, min(P, c0 + _CHUNK))))
        todo = [p for p in preps if isinstance(p, Prepared)]
        t1 = time.perf_counter()
        cls = close_slices(ctx, [sl for p in todo for sl in p.slices])
        records: _Records = {}
        k = 0
        for p in todo:  # loop over the chunk's pre-grasps
            records[p.i] = (*closing_records(p.q0, p.slices, cls[k : k + len(p.slices)]), 0.0)
            k += len(p.slices)
        _lift_retries(ctx, todo, records, each)
        t2 = time.perf_counter()
        if records:  # the link boxes of every closed hand of the chunk: one batched FK
            ctx.prefetch_boxes(np.array([r[0] for r in records.values()]))
        chunk = each(functools.partial(_finish_or_keep, ctx, records), preps)
        t3 = time.perf_counter()
        # 5. quality of the kept grasps: bounds, or a 6D hull (planner/rank.py)
        kept = [k for k, g in enumerate(chunk) if g.kept]
        scored = each(score, [chunk[k] for k in kept])
        for k, g in zip(kept, scored, strict=True):
            chunk[k] = g
        t4 = time.perf_counter()
        clock["approach_slicing"] += t1 - t0
        clock["closing"] += t2 - t1
        clock["verification"] += t3 - t2
        clock["quality"] += t4 - t3
        grasps.extend(chunk)
        done += len(chunk)
        if progress is not None:
            progress(done, P)


def _can_fork() -> bool:
    """Whether this process may plan chunks in forked copies of itself: a POSIX fork, from a
    process running one thread only (a fork copies no other thread, so a lock another thread
    held would stay locked in the copy: the viewer's server, the test runners with threads and
    any caller with a thread pool use threads instead)."""
    return hasattr(os, "fork") and threading.active_count() == 1


def _plan_forked(
    ctx: Context,
    pool: PreGraspPool,
    P: int,
    n_proc: int,
    grasps: list[Grasp],
    progress: Callable[[int, int], None] | None,
) -> None:
    """:func:`_plan_chunks` of every chunk on ``n_proc`` processes: this one and ``n_proc - 1``
    forked copies of it (all of the context inherited, nothing rebuilt), chunk ``c`` planned by
    process ``c % n_proc`` (this one: the last of them); each copy sends back its grasps
    (pickled, which keeps every float's bits) and its phase clocks, and ``grasps`` gets every
    chunk in pool order. The chunks are
    those of one process, and every pre-grasp is planned independently, so the grasps are
    those of a single process, bit for bit. A copy that dies without an answer has its chunks
    planned here; an exception in a copy is raised here."""
    starts = list(range(0, P, _CHUNK))
    # this process takes the last share (never more chunks than a copy's): the exact settling
    # and the ranking come after it
    mine = [starts[w::n_proc] for w in range(n_proc)][::-1]
    children: list[tuple[int, int, list[int]]] = []  # (pid, read end, chunks)
    for w in range(1, n_proc):  # fork the copies before this process starts working
        r, wfd = os.pipe()
        pid = os.fork()
        if pid == 0:  # the copy: plan its chunks, send them, leave without any clean-up
            code = 0
            try:
                os.close(r)
                out: list[Grasp] = []
                _plan_chunks(ctx, pool, P, None, out, None, mine[w])
                payload = pickle.dumps((True, out, ctx.clock), pickle.HIGHEST_PROTOCOL)
            except BaseException as exc:  # noqa: BLE001 - sent to the parent, raised there
                try:
                    payload = pickle.dumps((False, exc, None), pickle.HIGHEST_PROTOCOL)
                except Exception:  # noqa: BLE001 - an exception that does not pickle
                    payload = pickle.dumps((False, RuntimeError(repr(exc)), None))
            try:
                with os.fdopen(wfd, "wb") as fh:
                    fh.write(payload)
            except BaseException:  # noqa: BLE001
                code = 1
            os._exit(code)
        os.close(wfd)
        children.append((pid, r, mine[w]))
    by_start: dict[int, list[Grasp]] = {}
    results: list[tuple[bool, object, dict[str, float] | None]] = []
    try:
        own: list[Grasp] = []
        _plan_chunks(ctx, pool, P, None, own, progress, mine[0])
        _split_chunks(own, mine[0], P, by_start)
    finally:  # always collect the copies (no zombie, no open pipe)
        for pid, r, _ in children:
            with os.fdopen(r, "rb") as fh:
                data = fh.read()
            os.waitpid(pid, 0)
            results.append(pickle.loads(data) if data else (False, None, None))
    for (_, _, chunks), (ok, value, clock) in zip(children, results, strict=True):
        if ok:
            assert isinstance(value, list) and clock is not None
            _split_chunks(value, chunks, P, by_start)
            for k, v in clock.items():
                ctx.clock[k] += v
        elif value is not None:
            raise value if isinstance(value, BaseException) else RuntimeError(str(value))
        else:  # the copy died (e.g. killed): plan its chunks here
            logger.warning("a planner process ended without an answer; planning its chunks here")
            redo: list[Grasp] = []
            _plan_chunks(ctx, pool, P, None, redo, None, chunks)
            _split_chunks(redo, chunks, P, by_start)
    for c0 in starts:
        grasps.extend(by_start[c0])
    if progress is not None:
        progress(P, P)


def _split_chunks(
    got: list[Grasp], chunks: list[int], P: int, by_start: dict[int, list[Grasp]]
) -> None:
    """The grasps of the chunks ``chunks`` (first pre-grasps, planned in this order) into
    ``by_start``."""
    k = 0
    for c0 in chunks:
        n = min(P, c0 + _CHUNK) - c0
        by_start[c0] = got[k : k + n]
        k += n
    if k != len(got):
        raise RuntimeError(f"a planner process returned {len(got)} grasps for {k} pre-grasps")


def rank_grasps(grasps: list[Grasp] | tuple[Grasp, ...]) -> np.ndarray:
    """(K,) indices of the kept grasps, best first: epsilon, then volume, then contacts (all
    descending), ties by pre-grasp index."""
    kept = [k for k, g in enumerate(grasps) if g.kept]
    if not kept:
        return np.zeros(0, dtype=np.int64)
    eps = np.array([grasps[k].epsilon for k in kept])
    vol = np.array([grasps[k].volume for k in kept])
    nc = np.array([grasps[k].n_contacts for k in kept])
    order = np.lexsort((np.array(kept), -nc, -vol, -eps))
    return np.asarray(kept, dtype=np.int64)[order]


def plan_grasps(
    points: np.ndarray,
    normals: np.ndarray,
    pool: PreGraspPool,
    hand: Hand,
    params: PlannerParams | None = None,
    support: SupportPlane | None = None,
    progress: Callable[[int, int], None] | None = None,
    assumed: np.ndarray | None = None,
) -> GraspSet:
    """Plan every pre-grasp of ``pool`` against the cloud.

    points: (N, 3) metres, world; normals: (N, 3) unit outward normals of the cloud (see
    :func:`cloud_normals`); pool: a ``PreGraspPool`` (``T_world_hand`` (P, 4, 4), ``q`` (P, J),
    ``spread`` (P,), ``grasp_type`` (P,)); hand: ``pregrasp_core.hand.Hand``; support: the
    ``SupportPlane`` (normal, height) or None; progress: called as ``progress(done, total)``;
    assumed: (N,) bool, the points a single view's completion assumed (the hand keeps
    ``params.assumed_clearance`` from them, ``planner/assumed.py``), or None.
    """
    prm = PlannerParams() if params is None else params
    pts = as_points(points)
    nrm = as_points_like(normals, pts)
    P = len(pool)
    joint_names = tuple(hand.joint_names)
    if P and np.shape(pool.q)[1] != len(joint_names):
        raise ValueError(
            f"pool.q has {np.shape(pool.q)[1]} joints, the hand has {len(joint_names)}"
        )
    am = assumed_mask(assumed, len(pts))
    geom = obstacle_points(pts, nrm, am, prm.assumed_clearance)
    ctx = Context(geom, nrm, hand, prm, support, surface=pts, assumed=am)
    grasps: list[Grasp] = []
    # chunks of pre-grasps: approach and slicing per pre-grasp, the closing of every finger of
    # the chunk in one call of the batched closing model, verification and quality per
    # pre-grasp; the per-pre-grasp phases on a thread pool when prm.threads allows one
    n_threads = min(_n_threads(prm.threads), _CHUNK)
    n_proc = min(n_threads, -(-P // _CHUNK))  # forked processes: at most one per chunk
    fork = n_proc > 1 and _can_fork()
    ex = ThreadPoolExecutor(n_threads) if n_threads > 1 and P > 1 and not fork else None
    try:
        if fork:
            _plan_forked(ctx, pool, P, n_proc, grasps, progress)
            if n_threads > 1:  # the copies are gone: threads for the exact scores
                ex = ThreadPoolExecutor(n_threads)
        else:
            _plan_chunks(ctx, pool, P, ex, grasps, progress)
        t0 = time.perf_counter()  # exact scores wherever they decide the ranking's top
        grasps, _ = settle_exact(grasps, prm.quality, quality_frame(prm.quality, pts), ex)
        ctx.clock["quality"] += time.perf_counter() - t0
    finally:
        if ex is not None:
            ex.shutdown()
    order = rank_grasps(grasps)
    ranked = list(grasps)
    for r, k in enumerate(order):
        g = ranked[k]
        ranked[k] = dataclasses.replace(g, rank=r)
    rejected = {key: 0 for key in REJECTION_REASONS}
    for g in ranked:
        if g.rejection is not None:
            rejected[g.rejection] += 1
    logger.info(
        "planned %d pre-grasps: %d kept, %d force closure, rejected %s",
        P,
        len(order),
        sum(g.epsilon > 0 for g in ranked),
        rejected,
    )
    return GraspSet(tuple(ranked), order, joint_names, rejected, dict(ctx.clock))


def cloud_normals(cloud: PointCloud, params: NormalParams | None = None) -> np.ndarray:
    """(N, 3) outward unit normals of a ``PointCloud`` by local PCA, oriented by its own normals
    when it has them (mesh-sampled clouds), else by propagation (:mod:`pregrasp_core.normals`)."""
    prm = NormalParams() if params is None else params
    return estimate_normals(cloud.points, prm, reference=cloud.normals).normals
