"""The viewer's planner process (``app/planner_proc.py``): the grasps of ``run_pipeline`` bit for
bit, progress forwarded, a stale plan cancelled without killing the worker, a killed worker
replaced while the plan goes on in the viewer's process, an error raised where the plan was
asked, and no process left behind by the app's end or the viewer's death."""

from __future__ import annotations

import dataclasses
import os
import signal
import struct
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import viser

from app import planner_proc
from app.planner_proc import FORK_MIN, PlannerProcess, fork_copy
from app.server import ViewerConfig, run
from pregrasp_core import pipeline as ppl
from pregrasp_core.pregrasps import SamplingParams
from tests.app.conftest import APP_POINTS

DENSE = ppl.PipelineParams(sampling=SamplingParams(interval=0.01))
"""A pool about four times the default's (sampling every 1 cm): more than ``FORK_MIN``, so the
worker forks its copy, and a plan long enough to cancel or kill in its middle."""

READY_S = 120.0
"""Longest wait for a worker's start (imports, hand, warm-up) on a loaded 2-core machine."""


def bits(x: object) -> object:
    """Every bit of a value as nested tuples (dataclasses field by field, arrays by dtype,
    shape and bytes, floats by their 64 bits); the planner's phase clocks are left out."""
    if dataclasses.is_dataclass(x) and not isinstance(x, type):
        return (type(x).__name__,) + tuple(
            (f.name, bits(getattr(x, f.name)))
            for f in dataclasses.fields(x)
            if f.name != "phase_seconds"
        )
    if isinstance(x, np.ndarray):
        return ("nd", x.dtype.str, x.shape, x.tobytes())
    if isinstance(x, (float, np.floating)):
        return ("f", struct.pack("<d", float(x)))
    if isinstance(x, (tuple, list)):
        return (type(x).__name__, *(bits(v) for v in x))
    if isinstance(x, dict):
        return ("d", *((k, bits(v)) for k, v in x.items()))
    return (type(x).__name__, x)


def descendants(pid: int) -> set[int]:
    """The live processes below ``pid`` (Linux's /proc children lists)."""
    out: set[int] = set()
    todo = [pid]
    while todo:
        p = todo.pop()
        for task in Path(f"/proc/{p}/task").glob("*"):
            try:
                kids = {int(k) for k in (task / "children").read_text().split()}
            except OSError:
                continue
            todo.extend(kids - out)
            out |= kids
    return out


def alive(pid: int) -> bool:
    """Whether ``pid`` is a process that has not ended (a zombie has ended)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat.rsplit(")", 1)[1].split()[0] != "Z"


def wait_gone(pids: set[int], timeout: float = 10.0) -> set[int]:
    """The ``pids`` still alive after at most ``timeout`` s."""
    deadline = time.monotonic() + timeout
    while (left := {p for p in pids if alive(p)}) and time.monotonic() < deadline:
        time.sleep(0.05)
    return left


def reference(app) -> ppl.PipelineResult:
    """``run_pipeline`` in this process on the app's cloud and parameters, up to the grasps."""
    s = app.controller.state
    return ppl.run_pipeline(s.result.cloud, s.params, app.controller.hand, until="grasps")


def assert_same_grasps(app) -> None:
    """The app's ranking and grasps are ``run_pipeline``'s, bit for bit."""
    got, want = app.controller.state.result.grasps, reference(app).grasps
    assert got is not None and want is not None
    assert np.array_equal(got.ranking, want.ranking)
    assert bits(got) == bits(want)


def ready_app(make_app, **kw):
    app = make_app(planner_process=True, **kw)
    assert app.controller.planner.wait_ready(READY_S), "the planner process never started"
    return app


def test_the_viewer_plans_in_its_process_with_the_grasps_of_run_pipeline(make_app):
    """Two objects planned by the worker (not here) give ``run_pipeline``'s grasps bit for
    bit, with the worker's progress on the progress bar; a threshold change re-plans there
    too. The mug's 76 pre-grasps are fewer than ``FORK_MIN``: the worker plans them alone (the
    forked path is checked by the tests below, on a pool of more than 200)."""
    app = ready_app(make_app)
    c, pp = app.controller, app.controller.planner
    shown: list[float] = []
    c.subscribe(lambda s: shown.append(s.progress) if s.busy == "plan" else None)
    copies = watch_copies(pp)
    c.plan()
    copies.stop()
    s = c.state
    assert s.planned and s.error == "", s.error
    assert (pp.plans, pp.local_plans) == (1, 0)
    assert_same_grasps(app)
    # the pipeline's fraction: 4/5 when the planner starts, then the worker's reports up to 1
    assert [p for p in shown if p > 0.8][-1:] == [1.0], shown
    assert len(s.result.pool) < FORK_MIN and not copies.seen
    app.gui.params[("decomposition", "volume_ratio")].value = 0.6  # re-plans after the edit
    assert c.state.planned and c.state.error == "", c.state.error
    assert (pp.plans, pp.local_plans) == (2, 0)
    assert_same_grasps(app)
    c.load_demo("can_soda")
    c.plan()
    assert c.state.planned and c.state.error == "", c.state.error
    assert (pp.plans, pp.local_plans) == (3, 0)
    assert len(c.state.result.grasps.ranking) > 0
    assert_same_grasps(app)


class watch_copies:  # noqa: N801 - used as a function
    """Watch the worker's children from a thread; ``on_copy()`` runs once, when the first
    appears (the worker has forked: it is in the middle of a plan)."""

    def __init__(self, pp: PlannerProcess, on_copy=None) -> None:
        self.seen: set[int] = set()
        self._done = threading.Event()
        self._pid = pp.pid
        self._on_copy = on_copy
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._done.is_set():
            kids = descendants(self._pid)
            if kids and not self.seen and self._on_copy is not None:
                self.seen |= kids
                self._on_copy(kids)
            self.seen |= kids
            time.sleep(0.002)

    def stop(self) -> None:
        self._done.set()
        self._thread.join()


def test_a_stale_plan_is_cancelled_and_the_worker_plans_the_next_one(make_app):
    """A cancel while the worker plans (its copy forked) stops it at its next chunk: the plan
    ends without a result, the worker lives on (same process) and the next plan has
    ``run_pipeline``'s grasps."""
    app = ready_app(make_app, params=DENSE)
    c, pp = app.controller, app.controller.planner
    pp.fork = "always"  # the copy forked whatever the machine's load
    assert len(c.state.result.pool) > max(200, FORK_MIN)
    pid = pp.pid
    fired: list[float] = []

    def cancel(kids) -> None:
        fired.append(time.perf_counter())
        c.cancel()

    watch = watch_copies(pp, cancel)
    c.plan()
    ended = time.perf_counter()
    watch.stop()
    assert fired, "the worker never forked its copy"
    s = c.state
    assert not s.planned and s.result.grasps is None and s.error == ""
    assert pp.plans == 0 and pp.local_plans == 0 and pp.pid == pid and alive(pid)
    # the worker answered "cancelled" (it stopped before the exact settling and the ranking;
    # on a quiet machine after 53-117 of the 276 pre-grasps, docs/app.md), not "done"
    assert pp.last_cancel is not None and pp.last_cancel[1] == len(s.result.pool)
    assert ended - fired[0] < 5.0
    c.plan()
    assert c.state.planned and pp.plans == 1 and pp.pid == pid
    assert_same_grasps(app)


def test_a_killed_worker_is_replaced_and_the_plan_goes_on_here(make_app):
    """``os.kill`` of the worker mid-plan: the browsers get a notice, the plan ends here with
    ``run_pipeline``'s grasps, the worker and its copy are gone, a new worker starts and plans
    the next request."""
    app = ready_app(make_app, params=DENSE)
    c, pp = app.controller, app.controller.planner
    pp.fork = "always"  # the copy forked whatever the machine's load
    old = pp.pid
    notices: list[str] = []
    c.notify = lambda client, title, body, color="blue": notices.append(f"{title}: {body}")
    killed: set[int] = set()

    def kill(kids) -> None:  # the worker and its copy are planning
        killed.update({old, *kids})
        os.kill(old, signal.SIGKILL)

    watch = watch_copies(pp, kill)
    c.plan()
    watch.stop()
    assert len(killed) >= 2, "the worker never forked its copy"
    s = c.state
    assert s.planned and s.error == "" and pp.local_plans == 1 and pp.plans == 0
    assert_same_grasps(app)
    assert any("Planner process" in n and "ended during a plan" in n for n in notices), notices
    assert not wait_gone(killed), "the killed worker or its copy is still running"
    assert pp.pid is not None and pp.pid != old and pp.wait_ready(READY_S)
    app.gui.params[("decomposition", "volume_ratio")].value = 0.6
    assert c.state.planned and pp.plans == 1
    assert_same_grasps(app)


def test_an_error_in_the_worker_is_raised_here_and_the_worker_goes_on(hand_pool):
    """A plan the planner refuses (one normal short) raises the planner's own ``ValueError``
    in the caller; the same worker then plans the next job, its progress reports forwarded as
    the planner in this process makes them."""
    hand, points, normals, pool, params, support = hand_pool
    pp = PlannerProcess(warm=False)
    try:
        assert pp.wait_ready(READY_S)
        pid = pp.pid
        with pytest.raises(ValueError, match=r"must have shape \(3000, 3\) like points"):
            pp.plan(points, normals[:-1], pool, hand, params, support)
        # one process (threads=1): chunks of 64, each reported as the planner here reports it
        one = dataclasses.replace(params, threads=1)
        got: list[tuple[int, int]] = []
        gs = pp.plan(points, normals, pool, hand, one, support, lambda d, t: got.append((d, t)))
        assert pp.pid == pid and pp.plans == 1 and pp.local_plans == 0
        from pregrasp_core.planner import plan_grasps

        want: list[tuple[int, int]] = []
        ref = plan_grasps(
            points, normals, pool, hand, one, support, lambda d, t: want.append((d, t))
        )
        assert bits(gs) == bits(ref)
        assert got == want and len(want) >= 2 and want[-1] == (len(pool), len(pool))
    finally:
        pp.close()
    assert pp.pid is None and not alive(pid)


def test_ctrl_c_reaches_the_viewer_not_the_worker(hand_pool, capfd):
    """A Ctrl-C in the terminal of ``pregrasp view`` is sent to its whole process group: the
    worker ignores it (no traceback on the terminal, the same worker plans on) and ends when the
    viewer closes it."""
    hand, points, normals, pool, params, support = hand_pool
    pp = PlannerProcess(warm=False)
    try:
        assert pp.wait_ready(READY_S)
        pid = pp.pid
        os.kill(pid, signal.SIGINT)
        time.sleep(0.5)
        one = dataclasses.replace(params, threads=1)
        gs = pp.plan(points, normals, pool, hand, one, support)
        assert pp.pid == pid and alive(pid) and pp.plans == 1 and pp.local_plans == 0
        assert len(gs.grasps) == len(pool)
    finally:
        pp.close()
    assert not alive(pid)
    assert "KeyboardInterrupt" not in capfd.readouterr().err


@pytest.fixture
def hand_pool():
    from pregrasp_core import io as pio
    from pregrasp_core.hand import Hand
    from pregrasp_core.paths import DEFAULT_OBJECT

    hand = Hand.load()
    cloud = pio.load_point_cloud(DEFAULT_OBJECT, n_points=APP_POINTS)
    r = ppl.run_pipeline(cloud, hand=hand, until="pool")
    normals = ppl.view_normals(cloud, r.params.planner.normals)
    pool = r.pool
    return hand, cloud.points, normals, pool, r.params.planner, r.masks.support


def test_no_process_outlives_the_app_or_the_viewer():
    """``App.close()`` and ``server.stop()`` leave no child process (the worker is stopped and
    reaped); a viewer process that dies without closing leaves no worker behind either (the
    worker leaves when its pipe closes)."""
    before = descendants(os.getpid())
    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    app = run(ViewerConfig(n_points=APP_POINTS), server)  # the default: planner process on
    pp = app.controller.planner
    assert pp is not None and pp.wait_ready(READY_S)
    app.controller.plan()
    assert pp.plans == 1
    ours = descendants(os.getpid()) - before
    assert pp.pid in ours
    app.close()
    server.stop()
    assert not wait_gone(ours), "a child process outlived the app"
    assert descendants(os.getpid()) - before == set()
    # a viewer killed without closing: its worker sees the pipe close and leaves
    script = (
        "import os, sys; from app.planner_proc import PlannerProcess; "
        "pp = PlannerProcess(warm=False); assert pp.wait_ready(120); "
        "print(pp.pid, flush=True); os._exit(0)"
    )
    root = str(Path(__file__).resolve().parents[2])
    env = {**os.environ, "PYTHONPATH": root}
    out = subprocess.run(
        [sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=180
    )
    assert out.returncode == 0, out.stderr
    worker = int(out.stdout.split()[0])
    assert not wait_gone({worker}), "the worker outlived its viewer"


def test_a_worker_that_cannot_start_leaves_every_plan_here(hand_pool, monkeypatch):
    """No interpreter to start (``sys.executable`` gone): the app's planner process plans in
    the caller, with ``plan_grasps``'s grasps, and nothing is left to end."""
    hand, points, normals, pool, params, support = hand_pool
    monkeypatch.setattr(sys, "executable", "/nonexistent/python")
    pp = PlannerProcess(warm=False)
    assert pp.pid is None and not pp.ready() and not pp.wait_ready(1.0)
    from pregrasp_core.planner import plan_grasps

    one = dataclasses.replace(params, threads=1)
    got = pp.plan(points, normals, pool, hand, one, support)
    assert (pp.plans, pp.local_plans) == (0, 1)
    assert bits(got) == bits(plan_grasps(points, normals, pool, hand, one, support))
    pp.close()


def test_the_worker_forks_for_a_large_pool_and_a_free_core(monkeypatch):
    """``fork_copy``: never below ``FORK_MIN`` pre-grasps or with ``never``; with ``auto`` only
    when a core is free (the running tasks read from /proc/stat, here replaced)."""
    for free in (-1, 0, 1):
        monkeypatch.setattr(planner_proc, "free_cores", lambda free=free, **kw: free)
        assert fork_copy(FORK_MIN, "auto") == (free >= 1)
        assert fork_copy(FORK_MIN, "always") and not fork_copy(FORK_MIN, "never")
        assert not fork_copy(FORK_MIN - 1, "always") and not fork_copy(FORK_MIN - 1, "auto")
    monkeypatch.undo()
    n = planner_proc.free_cores()
    assert n <= len(os.sched_getaffinity(0)) - 1  # this test's own process is running


def test_the_viewers_own_running_threads_do_not_keep_the_worker_on_one_core():
    """``running_tasks`` reads a process's runnable threads from /proc (a spinning process: 1;
    one asleep: 0; two spinning threads of one process: 1 or 2, the one waiting for the GIL may
    sleep), and ``free_cores(exclude=pid)`` does not count them: the viewer draws the new scene
    while the worker plans the re-plan it asked for."""
    import subprocess
    import sys

    spin = (
        "import threading\n"
        "def f():\n    while True: pass\n"
        "threading.Thread(target=f, daemon=True).start()\n"
        "import os\nwhile True: os.getpid()\n"
    )
    n = len(os.sched_getaffinity(0))
    busy = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    procs = [busy]
    try:
        time.sleep(1.0)  # started and spinning
        assert planner_proc.running_tasks(busy.pid) == 1  # R: running or runnable
        # counted, the spinner and this test (the caller) take a core each, whatever else runs
        with_it = [planner_proc.free_cores() for _ in range(5)]
        without = [planner_proc.free_cores(exclude=busy.pid) for _ in range(5)]
        assert max(with_it) <= n - 2, with_it
        # excluded, it takes none: at least as many free as with it counted, never more than
        # all but the caller's
        assert max(without) <= n - 1 and max(without) >= min(with_it), (with_it, without)
        idle = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(120)"])
        two = subprocess.Popen([sys.executable, "-c", spin])
        procs += [idle, two]
        time.sleep(1.0)
        assert planner_proc.running_tasks(idle.pid) == 0
        assert 1 <= planner_proc.running_tasks(two.pid) <= 2
        assert planner_proc.running_tasks(2**22 + 12345) == 0  # no such process
    finally:
        for p in procs:
            p.kill()
            p.wait()
