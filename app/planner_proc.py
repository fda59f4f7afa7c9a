"""The viewer's planner process: ``plan_grasps`` on both cores from the threaded server.

``pregrasp plan`` plans on two cores by forking copies of itself
(``pregrasp_core.planner.plan``); the viewer cannot, since its server runs threads and a fork
copies none of them (a lock another thread held would stay locked in the copy), so in the
server the planner ran on threads that Python's global lock serialises. :class:`PlannerProcess`
is a worker process of one thread, started as a new interpreter (``subprocess``: no fork of
the server) once, when the app starts, and warmed up in the background; the controller sends it
each plan's inputs and it runs ``plan_grasps`` there, which forks its copy and plans on both
cores. :meth:`PlannerProcess.plan` takes ``plan_grasps``'s arguments and returns its
``GraspSet`` (packed, ``pregrasp_core/planner/packing.py``, and pickled, which keeps every
float's bits: the grasps are those of the in-process planner), so the pipeline's grasps stage
calls it in place of ``plan_grasps`` (``run_pipeline(..., planner=...)``).

- Progress: the worker reports each chunk (``("progress", job, done, total)``) and the caller's
  ``progress`` is called with it (the progress bar; a superseded request raises there).
- Cancellation: when the caller's ``check()`` raises (a newer request; checked every
  :data:`POLL_S` while the worker plans) or its progress callback raises, a cancel goes to
  the worker, which stops at its next chunk (its forked copy
  ends with it) and answers ``cancelled``; the worker then waits for the next job.
- Failure: a worker that dies (killed, out of memory) or does not answer a cancel within
  :data:`CANCEL_S` is reported through ``notice`` and ended; the plan is run in this process
  (``plan_grasps``, on threads) and a new worker is started (at most :data:`MAX_RESTARTS`
  times). A plan that comes while the worker still starts is planned here as well.
- End: :meth:`close` (``App.close``) stops the worker and waits for it; the worker also leaves
  when the viewer's end of its pipe closes (the viewer died), and its forked copies die with it
  (``PR_SET_PDEATHSIG``).
"""

from __future__ import annotations

import dataclasses
import gc
import logging
import os
import pickle
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

logger = logging.getLogger(__name__)

POLL_S: float = 0.02
"""How often a waiting plan looks at the worker's answers, its life and the caller's
``check()`` (s)."""

CANCEL_S: float = 10.0
"""Longest wait for a cancelled plan's answer before the worker is ended (s): it stops at its
next chunk, 0.1-0.3 s on the default object."""

START_S: float = 120.0
"""Longest a worker may take to start (import, hand, warm-up) before it is ended (s)."""

MAX_RESTARTS: int = 3
"""Workers started again after a failure; after that, every plan runs in this process."""

FORK_MIN: int = 128
"""Smallest pool the worker plans on two processes (``PlannerParams.threads`` as asked); a
smaller one is planned in the worker alone (``threads=1``; the grasps never depend on it): the
fork and its copy cost 0.12-0.18 s of CPU per plan, more than the second core saves on the 76
pre-grasps of the mug at 5,000 points (docs/benchmarks.md, "Session 10")."""

FORK_MODES: tuple[str, ...] = ("auto", "always", "never")
"""When the worker forks its copy (``PlannerProcess.fork``): ``auto`` = a pool of at least
:data:`FORK_MIN` pre-grasps and a free core (:func:`free_cores`); ``always`` = a pool of at
least :data:`FORK_MIN`; ``never`` = one process."""


def running_tasks(pid: int) -> int:
    """The threads of process ``pid`` that are running or runnable now (state ``R`` in
    ``/proc/<pid>/task/*/stat``); 0 when the process is gone or on a system without /proc."""
    n = 0
    try:
        tids = os.listdir(f"/proc/{pid}/task")
    except OSError:
        return 0
    for tid in tids:
        try:
            with open(f"/proc/{pid}/task/{tid}/stat", encoding="ascii", errors="replace") as fh:
                stat = fh.read()
        except OSError:
            continue  # the thread ended meanwhile
        # the state is the first field after the command name in parentheses (which may hold
        # spaces and parentheses)
        n += stat.rpartition(")")[2].split()[:1] == ["R"]
    return n


def free_cores(samples: int = 5, every: float = 0.002, exclude: int | None = None) -> int:
    """The usable CPUs that no other task is running on or waiting for, now: the CPUs less the
    median over ``samples`` readings (``every`` s apart) of the running and runnable tasks
    (``procs_running`` of ``/proc/stat``, which counts the caller too), less those of process
    ``exclude`` (:func:`running_tasks`): the worker passes the viewer's, whose drawing of the
    new scene runs beside the plan it asked for (``Controller._rerun``) and ends within it, so
    it is no reason to plan on one core. Linux; elsewhere the CPUs less one."""
    n = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    seen: list[int] = []
    try:
        for k in range(samples):
            if k:
                time.sleep(every)
            with open("/proc/stat", encoding="ascii") as fh:
                running = [int(ln.split()[1]) for ln in fh if ln.startswith("procs_running")]
            if running:  # ``exclude``'s threads read only when they can matter (~1 ms)
                r = running[0]
                seen.append(r - running_tasks(exclude) if exclude and r >= n else r)
    except OSError:
        return n - 1
    if not seen:
        return n - 1
    return n - max(1, int(sorted(seen)[len(seen) // 2]))  # the caller runs at least


def fork_copy(n_pool: int, mode: str, exclude: int | None = None) -> bool:
    """Whether the worker plans ``n_pool`` pre-grasps on two processes (``mode``: one of
    :data:`FORK_MODES`; ``exclude``: the viewer's process id, whose running threads are not
    counted, :func:`free_cores`). With both cores busy (other work on the machine), the forked
    plan's two processes wait for each other and it was no faster than one
    (docs/benchmarks.md, "Session 10")."""
    if mode == "never" or n_pool < FORK_MIN:
        return False
    return mode == "always" or free_cores(exclude=exclude) >= 1


WARM_POINTS: int = 1000
"""Points of the warm-up plan (the default object's) that loads the compiled kernels."""

WARM_PREGRASPS: int = 8
"""Pre-grasps of the warm-up plan."""


class _Cancelled(Exception):  # noqa: N818 - never leaves the worker
    """Raised in the worker's progress callback when the viewer cancelled the job."""


class _Stop(Exception):
    """Raised in the worker's progress callback when the viewer asked it to leave."""


class WorkerLost(Exception):
    """The worker ended or stopped answering during a plan (the plan runs in this process)."""


def _planner() -> Callable[..., Any]:
    from pregrasp_core.planner import plan_grasps

    return plan_grasps


def _planner_params() -> Any:
    from pregrasp_core.planner import PlannerParams

    return PlannerParams()


class PlannerProcess:
    """A worker process that runs ``plan_grasps`` for the viewer (module docstring).

    urdf_path: the hand's URDF (``None`` = ``pregrasp_core.paths.HAND_URDF``); the worker loads
    its own ``Hand`` from it once, and only plans for a hand read from the same file.
    notice: called with a sentence when the worker fails (the app shows it to the browsers).
    warm: plan a small problem at start so that the first real plan finds the kernels loaded.
    """

    def __init__(
        self,
        urdf_path: Path | str | None = None,
        notice: Callable[[str], None] | None = None,
        warm: bool = True,
    ) -> None:
        from pregrasp_core.paths import HAND_URDF

        self.urdf_path = Path(HAND_URDF if urdf_path is None else urdf_path).resolve()
        self.notice = notice
        self.warm = warm
        self._lock = threading.Lock()  # one job at a time; guards the fields below
        self._proc: subprocess.Popen[bytes] | None = None
        self._conn: Connection | None = None
        self._ready = False
        self._started = 0.0
        self._job = 0
        self._restarts = 0
        self._closed = False
        self.plans = 0
        """Plans the worker answered (tests and benchmarks read it)."""
        self.local_plans = 0
        """Plans run in this process instead (worker not ready, failed or closed)."""
        self.last_cancel: tuple[int, int] | None = None
        """(pre-grasps planned, of) when the worker stopped its last cancelled plan."""
        self.fork = "auto"
        """When the worker forks its copy (:data:`FORK_MODES`); sent with each plan."""
        with self._lock:
            self._start()

    # ------------------------------------------------------------------ the worker's life
    @property
    def pid(self) -> int | None:
        """The worker's process id (None when none runs)."""
        return None if self._proc is None else self._proc.pid

    def _start(self) -> None:
        """Start a worker (lock held). A new interpreter, not a fork of this threaded one."""
        r_req, w_req = os.pipe()  # viewer -> worker
        r_ans, w_ans = os.pipe()  # worker -> viewer
        root = str(Path(__file__).resolve().parents[1])  # the `app` package's directory
        env = dict(os.environ)
        env["PYTHONPATH"] = os.pathsep.join([root, *filter(None, [env.get("PYTHONPATH")])])
        code = (
            "import sys; from app.planner_proc import worker_main; "
            "worker_main(int(sys.argv[1]), int(sys.argv[2]), sys.argv[3], sys.argv[4] == '1')"
        )
        args = [sys.executable, "-c", code, str(r_req), str(w_ans), str(self.urdf_path)]
        try:
            self._proc = subprocess.Popen(
                [*args, "1" if self.warm else "0"],
                pass_fds=(r_req, w_ans),
                env=env,
                stdin=subprocess.DEVNULL,
            )
        except OSError as exc:  # no interpreter to start: every plan runs in this process
            logger.warning("cannot start the planner process (%s); planning in the viewer", exc)
            self._proc = None
            os.close(r_ans)
            os.close(w_req)
            return
        finally:
            os.close(r_req)
            os.close(w_ans)
        self._conn = _Duplex(r_ans, w_req)
        self._ready = False
        self._started = time.monotonic()

    def _end(self) -> None:
        """End the worker (lock held): ask it to leave, then terminate, then kill; reap it."""
        proc, conn = self._proc, self._conn
        self._proc, self._conn, self._ready = None, None, False
        if conn is not None:
            try:
                conn.send(("stop",))
            except OSError:
                pass
            conn.close()  # its pipe closed: an idle worker leaves at once
        if proc is not None:
            for step in (None, proc.terminate, proc.kill):  # 2 s for each to take effect
                if step is not None:
                    step()
                try:
                    proc.wait(timeout=2.0)
                    break
                except subprocess.TimeoutExpired:
                    continue

    def _fail(self, why: str, here: str = "this plan runs in the viewer's process") -> None:
        """The worker failed (lock held): say so (``why``, then ``here``: what happens to the
        plan), end it, start another while allowed."""
        self._end()
        if self._closed:
            return
        again = self._restarts < MAX_RESTARTS
        text = f"the planner process {why}; {here}" + (
            ", and a new planner process starts" if again else "; every plan now runs here"
        )
        logger.warning("%s", text)
        if self.notice is not None:
            try:
                self.notice(text)
            except Exception:  # noqa: BLE001 - a notice must not break the plan
                logger.debug("notice failed", exc_info=True)
        if again:
            self._restarts += 1
            self._start()

    def _check_ready(self) -> bool:
        """Whether the worker has said it is ready (lock held; never waits)."""
        if self._ready:
            return True
        if self._proc is None or self._conn is None:
            return False
        if self._proc.poll() is not None:
            self._fail(f"ended while starting (exit code {self._proc.returncode})")
            return False
        try:
            if not self._conn.poll(0.0):
                if time.monotonic() - self._started > START_S:
                    self._fail(f"did not start within {START_S:.0f} s")
                return False
            msg = self._conn.recv()
        except (EOFError, OSError):
            self._fail("ended while starting")
            return False
        if msg[0] == "ready":
            self._ready = True
            dt = time.monotonic() - self._started
            logger.info("planner process %s ready (%.1f s)", msg[1], dt)
            return True
        self._fail(f"could not start: {msg[1]}")
        return False

    def ready(self) -> bool:
        """Whether plans go to the worker now (it has started and warmed up)."""
        with self._lock:
            return self._check_ready()

    def wait_ready(self, timeout: float = START_S) -> bool:
        """Wait until the worker is ready (tests, benchmarks); False after ``timeout`` s."""
        deadline = time.monotonic() + timeout
        while not self.ready():
            if self._closed or self._proc is None or time.monotonic() > deadline:
                return False
            time.sleep(POLL_S)
        return True

    def close(self) -> None:
        """Stop the worker and wait for it (the app's end); plans after this run here. A plan
        in progress is not waited for: its worker is ended under it (it then fails)."""
        self._closed = True
        if self._lock.acquire(timeout=1.0):
            try:
                self._end()
            finally:
                self._lock.release()
            return
        proc = self._proc  # a plan holds the lock: end its worker; the plan sees it gone
        if proc is not None:
            proc.kill()
            proc.wait()

    # ------------------------------------------------------------------ planning
    def plan(
        self,
        points: Any,
        normals: Any,
        pool: Any,
        hand: Any,
        params: Any = None,
        support: Any = None,
        progress: Callable[[int, int], None] | None = None,
        assumed: Any = None,
        crest: Any = None,
        check: Callable[[], None] | None = None,
    ) -> Any:
        """``plan_grasps(points, normals, pool, hand, params, support, progress, assumed,
        crest)`` in the worker (the same ``GraspSet``, bit for bit), or here when the worker is
        not ready, has failed, or ``hand`` was not read from the worker's URDF. ``check()``:
        raises once a newer request has made this plan useless (the viewer's ``Superseded``);
        the worker's plan is then cancelled and the exception raised here."""
        args = (points, normals, pool, hand, params, support, progress, assumed, crest)
        with self._lock:
            if not self._closed and self._same_hand(hand) and self._check_ready():
                self._job += 1
                kw = {
                    "points": points,
                    "normals": normals,
                    "pool": pool,
                    "params": params,
                    "support": support,
                    "assumed": assumed,
                    "crest": crest,
                    "fork": self.fork,
                    "viewer": os.getpid(),
                }
                try:
                    gs = self._remote(self._job, kw, progress, check)
                except WorkerLost as lost:
                    self._fail(str(lost))
                    if self._closed:
                        raise RuntimeError("the viewer closed during a plan") from None
                else:
                    self.plans += 1
                    return gs
            self.local_plans += 1
        # here, outside the lock: closing, asking whether it is ready and a new worker's start
        # do not wait for this plan
        return _planner()(*args)

    def _same_hand(self, hand: Any) -> bool:
        path = getattr(hand, "urdf_path", None)
        return path is not None and Path(path).resolve() == self.urdf_path

    def _remote(
        self,
        job: int,
        kw: dict[str, Any],
        progress: Callable[[int, int], None] | None,
        check: Callable[[], None] | None,
    ) -> Any:
        """Send job ``job`` and wait for its answer (lock held), forwarding its progress."""
        conn, proc = self._conn, self._proc
        assert conn is not None and proc is not None
        if check is not None:
            check()  # already stale: no job for the worker
        try:
            conn.send(("plan", job, kw))
        except (OSError, ValueError) as exc:
            raise WorkerLost(f"could not be reached ({exc})") from None
        while True:
            msg = self._next(job, conn, proc)
            try:
                if check is not None:
                    check()
                if msg is not None and msg[0] == "progress" and progress is not None:
                    progress(msg[2], msg[3])
            except BaseException:  # a newer request: the worker stops at its next chunk
                self._cancel(job)
                raise
            if msg is None:
                continue
            kind = msg[0]
            if kind == "progress":
                continue
            elif kind == "done":
                return msg[2]
            elif kind == "error":
                raise msg[2]

    def _next(self, job: int, conn: Connection, proc: subprocess.Popen[bytes]) -> Any:
        """The worker's next message about ``job``, None after :data:`POLL_S` without one;
        :class:`WorkerLost` when it ended."""
        try:
            if not conn.poll(POLL_S):
                if proc.poll() is not None:
                    raise WorkerLost(f"ended during a plan (exit code {proc.returncode})")
                return None
            data = conn.recv_bytes()
        except (EOFError, OSError):
            proc.poll()
            raise WorkerLost(f"ended during a plan (exit code {proc.returncode})") from None
        collect = gc.isenabled()
        gc.disable()  # a GraspSet is ~10^4 small objects: no collection of the server's heap
        try:  # in the middle of them (one took 0.1 s of a 15 ms unpickling)
            msg = pickle.loads(data)
            if msg[0] == "done":  # the grasps packed by the worker (planner/packing.py)
                from pregrasp_core.planner.packing import unpack_grasp_set

                msg = (*msg[:2], unpack_grasp_set(msg[2]))
        finally:
            if collect:
                gc.enable()
        if len(msg) > 1 and msg[1] != job:
            return None  # an answer to an older job
        return msg

    def _cancel(self, job: int) -> None:
        """Cancel job ``job`` and wait until the worker is free again (lock held); a worker
        that does not answer within :data:`CANCEL_S` is ended (the next plan starts another)."""
        conn, proc = self._conn, self._proc
        assert conn is not None and proc is not None
        deadline = time.monotonic() + CANCEL_S
        try:
            conn.send(("cancel", job))
            while time.monotonic() < deadline:
                msg = self._next(job, conn, proc)
                if msg is not None and msg[0] in ("cancelled", "done", "error"):
                    if msg[0] == "cancelled":
                        self.last_cancel = (msg[2], msg[3])
                    return
        except (WorkerLost, OSError, ValueError):
            pass
        self._fail("did not stop a cancelled plan", "it is ended")


class _Duplex(Connection):
    """A ``multiprocessing`` connection over two pipe ends (read ``r``, write ``w``)."""

    def __init__(self, r: int, w: int) -> None:
        super().__init__(r)
        self._w = w

    def _send(self, buf: Any, write: Callable[..., int] = os.write) -> None:
        view = memoryview(buf)
        while view:
            view = view[write(self._w, view) :]

    def _close(self, _close: Callable[[int], None] = os.close) -> None:
        super()._close()  # type: ignore[misc]
        _close(self._w)


# ---------------------------------------------------------------------- in the worker
def _die_with_parent() -> None:
    """In a forked copy of the worker: be killed when the worker ends (Linux)."""
    if sys.platform.startswith("linux"):
        import ctypes
        import signal

        try:
            ctypes.CDLL(None, use_errno=True).prctl(1, int(signal.SIGKILL))  # PR_SET_PDEATHSIG
        except (OSError, AttributeError):
            pass


def _warm_up(hand: Any) -> None:
    """A small plan of the default object, which loads the compiled kernels."""
    import numpy as np

    from pregrasp_core import io as pio
    from pregrasp_core import pipeline as ppl
    from pregrasp_core.paths import DEFAULT_OBJECT

    cloud = pio.load_point_cloud(DEFAULT_OBJECT, n_points=WARM_POINTS)
    r = ppl.run_pipeline(cloud, hand=hand, until="pool")
    if r.pool is None or not len(r.pool):
        return
    pool = r.pool.select(np.arange(min(WARM_PREGRASPS, len(r.pool))))
    normals = ppl.view_normals(cloud, r.params.planner.normals)
    support = None if r.masks is None else r.masks.support
    _planner()(cloud.points, normals, pool, hand, r.params.planner, support)


def worker_main(r_req: int, w_ans: int, urdf_path: str, warm: bool) -> None:
    """The worker: load the hand (and warm up), say ``ready``, then plan each job it is sent
    until it is told to stop or its pipe closes. One thread only, so ``plan_grasps`` forks."""
    import signal

    # Ctrl-C in the viewer's terminal reaches its whole process group, this worker included:
    # the viewer ends the worker itself (App.close) and a viewer that dies closes the pipe, so
    # the worker ignores it (else every Ctrl-C printed its KeyboardInterrupt traceback)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    logging.basicConfig(level=logging.WARNING, format="planner process: %(message)s")
    conn = _Duplex(r_req, w_ans)
    os.register_at_fork(after_in_child=_die_with_parent)
    try:
        from pregrasp_core.hand import Hand

        hand = Hand.load(urdf_path)
        if warm:
            _warm_up(hand)
    except BaseException as exc:  # noqa: BLE001 - reported to the viewer
        conn.send(("failed", f"{type(exc).__name__}: {exc}"))
        return
    conn.send(("ready", os.getpid()))
    plan_grasps = _planner()
    from pregrasp_core.planner.packing import pack_grasp_set

    while True:
        try:
            msg = conn.recv()
        except (EOFError, OSError):
            return  # the viewer ended
        if msg[0] == "stop":
            return
        if msg[0] != "plan":
            continue  # the cancel of a job that is over
        job, kw = msg[1], msg[2]
        reached = [0, len(kw["pool"])]  # pre-grasps planned so far, of

        def progress(done: int, total: int, job: int = job, reached: list[int] = reached) -> None:
            reached[:] = [done, total]
            conn.send(("progress", job, done, total))
            while conn.poll():
                m = conn.recv()
                if m[0] == "stop":
                    raise _Stop
                if m[0] == "cancel" and m[1] == job:
                    raise _Cancelled

        reply: tuple[Any, ...]
        try:
            params = kw["params"]
            if not fork_copy(len(kw["pool"]), kw.get("fork", "auto"), kw.get("viewer")):
                # one process
                params = dataclasses.replace(params or _planner_params(), threads=1)
            gs = plan_grasps(
                kw["points"],
                kw["normals"],
                kw["pool"],
                hand,
                params,
                support=kw["support"],
                progress=progress,
                assumed=kw["assumed"],
                crest=kw.get("crest"),
            )
            reply = ("done", job, pack_grasp_set(gs))
        except _Cancelled:
            reply = ("cancelled", job, *reached)
        except (_Stop, EOFError, BrokenPipeError):
            return
        except BaseException as exc:  # noqa: BLE001 - raised in the viewer
            reply = ("error", job, exc)
        try:
            conn.send(reply)
        except (OSError, EOFError):
            return
        except Exception:  # noqa: BLE001 - an exception that does not pickle
            conn.send(("error", job, RuntimeError(repr(reply[-1]))))
