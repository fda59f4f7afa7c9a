"""Planning a whole pool: chunks of pre-grasps through approach and slicing, one batched
closing per chunk (and per retreat from the support), verification and quality, on a thread
pool when there is one; then the ranking (:func:`plan_grasps`)."""

from __future__ import annotations

import atexit
import dataclasses
import fcntl
import functools
import gc
import logging
import os
import pickle
import select
import tempfile
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from typing import TYPE_CHECKING, Any, TypeVar

import numpy as np

from ..geometry import as_points, as_points_like
from ..normals import NormalParams, estimate_normals
from ..quality import LEVEL_EXACT, GraspQuality
from .approach import Prepared, prepare
from .assumed import obstacle_points, point_mask
from .context import Context
from .packing import pack_grasps, unpack_grasps
from .rank import (
    Qualities,
    QualityJob,
    first_level,
    quality_frame,
    run_quality_job,
    score_grasp,
    settle_exact,
)
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
    chunks: Iterable[tuple[int, int]] | None = None,
) -> None:
    """Plan the pre-grasps of ``pool`` chunk by chunk into ``grasps`` (see :func:`plan_grasps`).
    The per-pre-grasp phases run on the thread pool ``ex`` when there is one (numpy releases
    Python's global lock for some of their work); every pre-grasp is planned independently,
    so the results never depend on the threads or on the chunks. ``chunks``: the pre-grasp
    ranges ``[c0, c1)`` to plan, in this order (default: every chunk of ``_CHUNK``)."""

    def each(fn: Callable[[_In], _Out], items: list[_In]) -> list[_Out]:
        return (
            list(ex.map(fn, items)) if ex is not None and len(items) > 1 else list(map(fn, items))
        )

    prm, clock, done = ctx.params, ctx.clock, 0
    # GraspIt's torque origin: the object's centroid and largest radius (docs/quality.md)
    frame = quality_frame(prm.quality, ctx.points)
    score = functools.partial(score_grasp, prm.quality, frame, first_level(prm.quality, P))
    if chunks is None:
        chunks = ((c0, min(P, c0 + _CHUNK)) for c0 in range(0, P, _CHUNK))
    for c0, c1 in chunks:  # loop over chunks
        t0 = time.perf_counter()
        preps = each(functools.partial(prepare, ctx, pool), list(range(c0, c1)))
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


_MIN_FORK_CHUNK: int = 8
"""The smallest chunk of a forked plan (:func:`_fork_chunks`)."""


def _fork_chunks(P: int, n_proc: int) -> list[tuple[int, int]]:
    """The chunks ``[c0, c1)`` of a plan on ``n_proc`` processes, in pool order: each
    ``1 / (2 n_proc)`` of the pre-grasps left after it, between :data:`_MIN_FORK_CHUNK` and
    :data:`_CHUNK` (guided scheduling: large chunks first, small ones at the end, so that the
    processes taking them one by one finish together)."""
    out, c0 = [], 0
    while c0 < P:
        c1 = min(P, c0 + min(_CHUNK, max(_MIN_FORK_CHUNK, -(-(P - c0) // (2 * n_proc)))))
        out.append((c0, c1))
        c0 = c1
    return out


class _ChunkQueue:
    """The index of the next chunk to plan, shared by a process and its forked copies: a
    counter in an unnamed temporary file, read and advanced under a POSIX record lock (the
    kernel releases it when its holder dies, so a killed copy never blocks the others)."""

    def __init__(self) -> None:
        self._file = tempfile.TemporaryFile()
        self._fd = self._file.fileno()
        os.pwrite(self._fd, bytes(8), 0)

    def take(self) -> int:
        """The next index (0, 1, 2, ... over all the processes, each once)."""
        fcntl.lockf(self._fd, fcntl.LOCK_EX)
        try:
            k = int.from_bytes(os.pread(self._fd, 8, 0), "little")
            os.pwrite(self._fd, (k + 1).to_bytes(8, "little"), 0)
        finally:
            fcntl.lockf(self._fd, fcntl.LOCK_UN)
        return k

    def close(self) -> None:
        self._file.close()


def _send(fd: int, obj: object) -> None:
    """``obj`` pickled (every float's bits kept) down the pipe ``fd``, its length first."""
    data = pickle.dumps(obj, pickle.HIGHEST_PROTOCOL)
    view = memoryview(len(data).to_bytes(8, "little") + data)
    while view:
        view = view[os.write(fd, view) :]


def _recv(fd: int) -> Any:
    """The next object :func:`_send` put into the pipe ``fd``; None when the pipe was closed
    before a whole one (its writer ended)."""
    head = _read_exactly(fd, 8)
    if head is None:
        return None
    data = _read_exactly(fd, int.from_bytes(head, "little"))
    return None if data is None else pickle.loads(data)


_PIPE_SIZE: int = 1 << 20
"""Bytes a copy's answer pipe holds (Linux's default largest, ``/proc/sys/fs/pipe-max-size``):
a chunk's grasps, about 1.3 kB each, go in without waiting for the parent to read them."""


def _widen_pipe(fd: int) -> None:
    """The pipe ``fd`` made to hold :data:`_PIPE_SIZE` bytes where the system allows it."""
    try:
        fcntl.fcntl(fd, fcntl.F_SETPIPE_SZ, _PIPE_SIZE)
    except (AttributeError, OSError):  # not Linux, or a lower limit: the default size
        pass


def _readable(fd: int) -> bool:
    """Whether reading the pipe ``fd`` would not block (data, or its writer gone)."""
    return bool(select.select([fd], [], [], 0.0)[0])


def _read_exactly(fd: int, n: int) -> bytes | None:
    parts, left = [], n
    while left:
        part = os.read(fd, min(left, 1 << 20))
        if not part:
            return None
        parts.append(part)
        left -= len(part)
    return b"".join(parts)


@dataclasses.dataclass
class _Copy:
    """A forked copy of the planning process: its pid and pipes (its answers, our requests)."""

    pid: int
    answers: int
    requests: int
    alive: bool = True
    """It can still score quality jobs."""
    working: bool = True
    """It may still send chunks."""


def _serve_copy(
    ctx: Context,
    pool: PreGraspPool,
    P: int,
    chunks: list[tuple[int, int]],
    queue: _ChunkQueue,
    answers: int,
    requests: int,
) -> None:
    """The work of a forked copy: plan the chunks it takes from ``queue``, sending each one's
    grasps as soon as they are planned (``("chunk", index, packed grasps)``,
    :func:`~pregrasp_core.planner.packing.pack_grasps`), then
    ``("done", phase clocks)`` (or ``("error", exception)``); then score the quality jobs the
    parent sends (:func:`_shared_qualities`) until it closes the pipe."""
    taken: list[int] = []
    out: list[Grasp] = []

    def claimed() -> Iterator[tuple[int, int]]:
        while (k := queue.take()) < len(chunks):
            taken.append(k)
            yield chunks[k]

    sent = [0]

    def send_chunk(done: int, total: int) -> None:  # called after each chunk
        _send(answers, ("chunk", taken[-1], pack_grasps(out[sent[0] : done])))
        sent[0] = done

    try:
        _plan_chunks(ctx, pool, P, None, out, send_chunk, claimed())
        msg: tuple[Any, ...] = ("done", ctx.clock)
    except BaseException as exc:  # noqa: BLE001 - sent to the parent, raised there
        msg = ("error", exc)
    try:
        _send(answers, msg)
    except Exception:  # noqa: BLE001 - an exception that does not pickle
        _send(answers, ("error", RuntimeError(repr(msg[1]))))
    if msg[0] != "done":
        return
    while (jobs := _recv(requests)) is not None:  # the parent's quality jobs
        try:
            reply: object = (True, [run_quality_job(j) for j in jobs])
        except BaseException as exc:  # noqa: BLE001 - raised in the parent
            reply = (False, exc)
        _send(answers, reply)


def _job_cost(job: QualityJob) -> float:
    """A rough relative cost of a quality job (measured: an exact 6D hull grows as about the
    1.7th power of its wrenches; the half-cone bounds take about a third of it)."""
    return len(job[0]) ** 1.7 * (1.0 if job[3] == LEVEL_EXACT else 0.35)


def _shared_qualities(copies: list[_Copy]) -> Qualities:
    """:func:`~pregrasp_core.planner.rank.settle_exact`'s quality jobs shared between this
    process and its live copies (the largest first, each to the least loaded; this process
    scores its share while the copies score theirs). A copy that ends without an answer has its
    share scored here; an exception in a copy is raised here."""

    def qualities(jobs: list[QualityJob]) -> list[GraspQuality]:
        live = [c for c in copies if c.alive]
        if len(jobs) < 2 or not live:
            return [run_quality_job(j) for j in jobs]
        shares: list[list[int]] = [[] for _ in range(len(live) + 1)]
        loads = [0.0] * len(shares)
        for i in sorted(range(len(jobs)), key=lambda i: -_job_cost(jobs[i])):
            w = loads.index(min(loads))
            shares[w].append(i)
            loads[w] += _job_cost(jobs[i])
        sent = []
        for c, share in zip(live, shares[1:], strict=True):
            if share:
                try:
                    _send(c.requests, [jobs[i] for i in share])
                    sent.append((c, share))
                except OSError:  # the copy is gone
                    c.alive = False
                    shares[0].extend(share)
        done: list[GraspQuality | None] = [None] * len(jobs)
        for i in shares[0]:
            done[i] = run_quality_job(jobs[i])
        for c, share in sent:
            reply = _recv(c.answers)
            if reply is None:  # the copy ended: its share here
                c.alive = False
                reply = (True, [run_quality_job(jobs[i]) for i in share])
            ok, value = reply
            if not ok:
                raise value
            for i, q in zip(share, value, strict=True):
                done[i] = q
        return [q for q in done if q is not None]

    return qualities


def _plan_forked(
    ctx: Context,
    pool: PreGraspPool,
    P: int,
    n_proc: int,
    grasps: list[Grasp],
    progress: Callable[[int, int], None] | None,
) -> Callable[[], None]:
    """:func:`_plan_chunks` of every chunk, then the exact settling, on ``n_proc`` processes:
    this one and ``n_proc - 1`` forked copies of it (all of the context inherited, nothing
    rebuilt). The chunks (:func:`_fork_chunks`) are taken one by one from a shared queue by
    whichever process is free; each copy sends back the grasps of each chunk as soon as it is
    planned (packed, ``planner/packing.py``, and pickled, which keeps every float's bits; this
    process reads them between its own chunks), then its phase clocks, and ``grasps`` gets every
    chunk in pool order; the copies then score their share of the exact settling's quality jobs
    (:func:`_shared_qualities`). Every pre-grasp is planned independently of its chunk, and
    every quality job is the same call wherever it runs, so the grasps are those of a single
    process, bit for bit. The chunks of a copy that dies without an answer are planned here; an
    exception in a copy is raised here. Returns the call that lets the copies go (:func:`_reap`;
    they leave as this returns, and free their memory while the caller ranks the grasps)."""
    chunks = _fork_chunks(P, n_proc)
    queue = _ChunkQueue()
    copies: list[_Copy] = []
    handed = False  # the copies' end handed to the caller
    gc.freeze()  # the collector of a copy then leaves the inherited objects' pages shared
    try:
        for _ in range(1, n_proc):  # fork the copies before this process starts working
            answers_r, answers_w = os.pipe()
            _widen_pipe(answers_w)
            requests_r, requests_w = os.pipe()
            pid = os.fork()
            if pid == 0:  # the copy: plan, answer, then leave without any clean-up
                code = 0
                try:
                    os.close(answers_r)
                    os.close(requests_w)
                    for c in copies:  # the other copies' pipes of this process
                        os.close(c.answers)
                        os.close(c.requests)
                    _serve_copy(ctx, pool, P, chunks, queue, answers_w, requests_r)
                except BaseException:  # noqa: BLE001
                    code = 1
                os._exit(code)
            os.close(answers_w)
            os.close(requests_r)
            copies.append(_Copy(pid, answers_r, requests_w))
        by_chunk: dict[int, list[Grasp]] = {}
        taken: list[int] = []
        error: list[BaseException] = []

        def collect(block: bool) -> None:
            """The copies' answers so far (``block``: every answer, until each is done)."""
            for c in copies:
                while c.working and (block or _readable(c.answers)):
                    msg = _recv(c.answers)
                    if msg is None:  # the copy ended
                        c.working = c.alive = False
                    elif msg[0] == "chunk":
                        _split_chunks(unpack_grasps(msg[2]), [msg[1]], chunks, by_chunk)
                    elif msg[0] == "done":
                        c.working = False
                        for k, v in msg[1].items():
                            ctx.clock[k] += v
                    else:
                        c.working = c.alive = False
                        error.append(msg[1])

        def own_chunk(done: int, total: int) -> None:  # after each chunk of this process
            collect(False)  # (the copies' grasps unpickled while they still plan)
            if progress is not None:
                progress(
                    done + sum(c1 - c0 for k, (c0, c1) in enumerate(chunks) if k in by_chunk), P
                )

        def claimed() -> Iterator[tuple[int, int]]:
            while (k := queue.take()) < len(chunks):
                taken.append(k)
                yield chunks[k]

        own: list[Grasp] = []
        _plan_chunks(ctx, pool, P, None, own, own_chunk, claimed())
        _split_chunks(own, taken, chunks, by_chunk)
        collect(True)
        if error:
            raise error[0]
        missing = [k for k in range(len(chunks)) if k not in by_chunk]
        if missing:  # a copy died (e.g. killed): plan its chunks here
            logger.warning("a planner process ended without an answer; planning its chunks here")
            redo: list[Grasp] = []
            _plan_chunks(ctx, pool, P, None, redo, None, [chunks[k] for k in missing])
            _split_chunks(redo, missing, chunks, by_chunk)
        for k in range(len(chunks)):
            grasps.extend(by_chunk[k])
        if progress is not None:
            progress(P, P)
        t0 = time.perf_counter()  # exact scores wherever they decide the ranking's top
        prm = ctx.params
        grasps[:], _ = settle_exact(
            grasps,
            prm.quality,
            quality_frame(prm.quality, ctx.surface),
            None,
            _shared_qualities(copies),
        )
        ctx.clock["quality"] += time.perf_counter() - t0
        for c in copies:  # no more jobs: the copies leave (their memory freed meanwhile)
            os.close(c.requests)
        handed = True
    finally:  # on an exception: end the copies now (no open pipe; reaped by _reap)
        if not handed:
            for c in copies:
                os.close(c.requests)
            _reap(copies, queue)
    return functools.partial(_reap, copies, queue)


_LEAVING: list[int] = []
"""Forked copies told to leave (their pipes closed) that had not ended when last looked at:
reaped without waiting by the next plan's end (:func:`_reap_leaving`), and waited for when
this process exits."""


def _reap(copies: list[_Copy], queue: _ChunkQueue) -> None:
    """Let the ``copies`` go (their request pipes closed: they are leaving; with their answer
    pipes closed too, a copy still planning ends at its next chunk) and release what
    :func:`_plan_forked` holds. Not waited for: a copy's exit (the kernel freeing its
    copy-on-write pages, 10-15 ms on the default object) overlaps the caller's ranking and
    result; it is reaped later (:data:`_LEAVING`)."""
    for c in copies:
        os.close(c.answers)
        _LEAVING.append(c.pid)
    _reap_leaving(block=False)
    queue.close()
    gc.unfreeze()


def _reap_leaving(block: bool) -> None:
    """Reap the copies of :data:`_LEAVING` that have ended (``block``: wait for each)."""
    for pid in list(_LEAVING):  # loop over the copies (one per plan)
        try:
            done, _ = os.waitpid(pid, 0 if block else os.WNOHANG)
        except ChildProcessError:  # already reaped (or not ours: a forked copy's view)
            done = pid
        if done:
            _LEAVING.remove(pid)


atexit.register(_reap_leaving, True)


def _split_chunks(
    got: list[Grasp],
    taken: list[int],
    chunks: list[tuple[int, int]],
    by_chunk: dict[int, list[Grasp]],
) -> None:
    """The grasps ``got`` of the chunks ``taken`` (indices into ``chunks``, planned in this
    order) into ``by_chunk``."""
    k = 0
    for c in taken:
        c0, c1 = chunks[c]
        by_chunk[c] = got[k : k + c1 - c0]
        k += c1 - c0
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
    crest: np.ndarray | None = None,
) -> GraspSet:
    """Plan every pre-grasp of ``pool`` against the cloud.

    points: (N, 3) metres, world; normals: (N, 3) unit outward normals of the cloud (see
    :func:`cloud_normals`); pool: a ``PreGraspPool`` (``T_world_hand`` (P, 4, 4), ``q`` (P, J),
    ``spread`` (P,), ``grasp_type`` (P,)); hand: ``pregrasp_core.hand.Hand``; support: the
    ``SupportPlane`` (normal, height) or None; progress: called as ``progress(done, total)``;
    assumed: (N,) bool, the points a single view's completion assumed (the hand keeps
    ``params.assumed_clearance`` from them, ``planner/assumed.py``), or None; crest: (N,) bool,
    the points whose normal is the crest rule's (``CloudNormals.crest``: their contacts' normals
    also follow the touching link, :func:`~pregrasp_core.planner.verify.crest_contact_normals`),
    or None.
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
    am = point_mask(assumed, len(pts))
    geom = obstacle_points(pts, nrm, am, prm.assumed_clearance)
    cm = point_mask(crest, len(pts), "crest")
    ctx = Context(geom, nrm, hand, prm, support, surface=pts, assumed=am, crest=cm)
    grasps: list[Grasp] = []
    # chunks of pre-grasps: approach and slicing per pre-grasp, the closing of every finger of
    # the chunk in one call of the batched closing model, verification and quality per
    # pre-grasp; the per-pre-grasp phases on a thread pool when prm.threads allows one
    n_threads = min(_n_threads(prm.threads), _CHUNK)
    n_proc = min(n_threads, -(-P // _CHUNK))  # forked processes: at most one per chunk
    fork = n_proc > 1 and _can_fork()
    ex = ThreadPoolExecutor(n_threads) if n_threads > 1 and P > 1 and not fork else None
    end: Callable[[], None] | None = None  # lets the forked copies go
    try:
        if fork:  # with the exact settling shared by the processes
            end = _plan_forked(ctx, pool, P, n_proc, grasps, progress)
        else:
            _plan_chunks(ctx, pool, P, ex, grasps, progress)
            t0 = time.perf_counter()  # exact scores wherever they decide the ranking's top
            grasps, _ = settle_exact(grasps, prm.quality, quality_frame(prm.quality, pts), ex)
            ctx.clock["quality"] += time.perf_counter() - t0
    finally:
        if ex is not None:
            ex.shutdown()
    try:
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
    finally:
        if end is not None:  # the copies leave while the grasps are ranked
            end()


def cloud_normals(
    cloud: PointCloud, params: NormalParams | None = None, threads: int = 0
) -> np.ndarray:
    """(N, 3) outward unit normals of a ``PointCloud`` by local PCA, oriented by its own normals
    when it has them (mesh-sampled clouds), else by propagation (:mod:`pregrasp_core.normals`);
    ``threads``: those of the compiled kernels (0: the usable CPUs; the normals do not depend
    on it)."""
    prm = NormalParams() if params is None else params
    return estimate_normals(cloud.points, prm, reference=cloud.normals, threads=threads).normals
