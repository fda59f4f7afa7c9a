"""App latency: a threshold change until the updated scene, and until the new best grasp, has
reached every browser, with 1 and 4 browsers connected.

The app runs on a real ``ViserServer``; one websocket client (speaking viser's wire format: zstd
msgpack frames) stays connected like a browser. Each trial sets the volume-ratio GUI input from
Python, which runs exactly the callback a browser's edit runs (re-run the decomposition and
everything downstream, redraw, update the GUI), and stops the clock when the client has received
the frame carrying the new "boxes: N" label, which the app sends after the scene update.

Second table (``--clients``): the viewer's default object as a user gets it (the mug at
``ViewerConfig().n_points`` = 20,000 points; ``--client-points 20000 5000`` adds a 5,000-point
row), planned once; then one client sends a volume-ratio edit exactly as viser's browser client
does (a GuiUpdateMessage, handled as a browser's edit is); "scene" = until every client has
received the new "boxes: N" label (sent after the boxes, masks and pool are drawn), "best
grasp" = until every client has received the new "N force-closure of M kept" line (sent after
the re-plan is committed and drawn); "stages" = the pipeline stages the edit re-ran before the
planner (decomposition, classes, face masks, pool), "planner" = the planner's own time, and
"other" = best grasp - stages - planner: what lies between the edit and the line besides the
pipeline (the app's handling, scene and GUI updates, messages to the clients). The clients are
websocket connections speaking viser's protocol (zstd msgpack frames), as the security tests
use: every broadcast is serialised and sent to each, which is what several tabs cost the
server; headless Chromium pages would add their own rendering (software WebGL) to the
machine's load and measure that instead.

``--planner-process off on`` runs each row of the clients table with the viewer's planner
process off (the planner on the server's threads, as before session 10) and on (a worker
process that forks its copy, ``app/planner_proc.py``; the default of ``pregrasp view``),
alternating, ``--rounds`` times; the worker's start and warm-up are waited for before the
first edit. "CPU" = processor time per edit of the viewer's process and of the worker with its
forked copies (``/proc/PID/stat``), which the machine's load disturbs less than wall time.

Rows: a volume-ratio change (re-runs the decomposition and everything downstream) and a level
slider change (no pipeline stage: boxes, colours and face masks redrawn). Columns: pipeline =
the pipeline stages the change re-ran (from the result's timings, reused stages excluded);
callback = the whole callback on the server (pipeline + scene + GUI); received = the change
until the client has received the new scene (median, min and max over the trials). Timings
are wall-clock on one machine; under load they are noisy, so compare rows of one run.

    .venv/bin/python benchmarks/bench_app.py [--points 20000 200000] [--trials 7]
        [--clients 1 4] [--client-points 20000 5000] [--client-trials 5]
        [--planner-process off on] [--rounds 2]
"""

from __future__ import annotations

import os

# one BLAS thread, as the `pregrasp` console script sets (app/__init__.py); before numpy loads
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse
import platform
import re
import statistics
import sys
import threading
import time
from pathlib import Path

import msgspec
import numpy as np
import viser
import zstandard
from websockets.sync.client import connect

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from app.server import ViewerConfig, run  # noqa: E402

BOXES = re.compile(rb"boxes: (\d+)")


SCENE_STAGES = ("decompose", "classify", "facemask", "pool")
"""The stages a volume-ratio edit re-runs before the planner (all of them: the tree changes)."""

FC_LINE = re.compile(rb"\d+ force-closure of \d+ kept")


class Listener:
    """A websocket client that records when each "boxes: N" label and each force-closure line
    arrives; it registers with the server as viser's client does (its camera first)."""

    def __init__(self, port: int) -> None:
        from viser import _messages

        self.ws = connect(
            f"ws://127.0.0.1:{port}",
            subprotocols=[f"viser-v{viser.__version__}"],
            max_size=None,
            open_timeout=30,
        )
        self.send(
            _messages.ViewerCameraMessage(
                wxyz=(1.0, 0.0, 0.0, 0.0),
                position=(0.5, -0.5, 0.4),
                fov=1.0,
                near=0.01,
                far=100.0,
                image_height=480,
                image_width=640,
                look_at=(0.0, 0.0, 0.0),
                up_direction=(0.0, 0.0, 1.0),
            )
        )
        self.dctx = zstandard.ZstdDecompressor()
        self.events: list[tuple[float, bytes]] = []
        self.cond = threading.Condition()
        self.thread = threading.Thread(target=self._loop, daemon=True)
        self.thread.start()

    def _loop(self) -> None:
        try:
            for frame in self.ws:
                t = time.perf_counter()
                size = int.from_bytes(frame[0:8], "little")
                clen = int.from_bytes(frame[8:16], "little")
                inner = self.dctx.decompress(frame[16 : 16 + clen], max_output_size=size)
                msgs = msgspec.msgpack.decode(inner)["messages"]
                text = msgspec.json.encode(msgs)
                with self.cond:
                    for m in BOXES.finditer(text):
                        self.events.append((t, m.group(0)))
                    for _m in FC_LINE.finditer(text):
                        self.events.append((t, b"fc"))
                    self.cond.notify_all()
        except Exception:  # noqa: BLE001 - closed at the end of the run
            pass

    def wait_for(self, label: bytes, after: float, timeout: float = 120.0) -> float:
        """Arrival time of the first ``label`` received after ``after``."""
        deadline = time.perf_counter() + timeout
        with self.cond:
            while True:
                for t, lab in self.events:
                    if t >= after and lab == label:
                        return t
                left = deadline - time.perf_counter()
                if left <= 0:
                    raise TimeoutError(f"{label!r} never arrived")
                self.cond.wait(left)

    def send(self, message) -> None:
        self.ws.send(msgspec.msgpack.encode(message.as_serializable_dict()))

    def close(self) -> None:
        self.ws.close()


def _trials(app, listener, handle, values, trials: int) -> dict:
    """Alternate ``handle`` between ``values`` (two settings with different box counts); time
    each change until the client has received the new "boxes: N" label."""
    cb, rx, pipe = [], [], []
    stages: dict[str, list[float]] = {}
    counts = set()
    for k in range(trials + 1):
        before = app.controller.state.result
        t0 = time.perf_counter()
        handle.value = values[k % 2]
        t1 = time.perf_counter()
        s = app.controller.state
        assert s.error == "", s.error
        counts.add(app.scene.n_boxes)
        t2 = listener.wait_for(f"boxes: {app.scene.n_boxes}".encode(), after=t0)
        if k == 0:
            continue  # warm-up
        cb.append(t1 - t0)
        rx.append(t2 - t0)
        ran = s.result is not before  # a view change keeps the result: no stage ran
        for st, t in s.result.timings.items():
            if ran and st not in s.result.reused:
                stages.setdefault(st, []).append(t)
        pipe.append(
            sum(t for st, t in s.result.timings.items() if st not in s.result.reused) if ran else 0
        )
    if len(counts) < 2:
        raise SystemExit(f"{values} give the same box count; the client would wait forever")
    return {
        "pipeline": statistics.median(pipe),
        "stages": ", ".join(f"{k} {statistics.median(v) * 1e3:.0f}" for k, v in stages.items())
        or "none",
        "callback": statistics.median(cb),
        "received": statistics.median(rx),
        "min": min(rx),
        "max": max(rx),
    }


def _cpu(pid: int | None) -> float:
    """Seconds of processor time of process ``pid`` and its reaped children (0 for None)."""
    if pid is None:
        return 0.0
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return sum(int(f) for f in fields[11:15]) / os.sysconf("SC_CLK_TCK")


def bench(n_points: int, trials: int) -> list[dict]:
    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    app = run(ViewerConfig(n_points=n_points, planner_process=False), server)
    listener = Listener(server.get_port())
    try:
        time.sleep(1.0)  # let the client receive the initial scene
        rows = []
        # volume ratio 0.5 <-> 0.9: two part counts on the mug, every change re-runs the whole
        # pipeline (decomposition, classes, face masks, pool) and redraws everything
        h = app.gui.params[("decomposition", "volume_ratio")]
        r = _trials(app, listener, h, (0.5, 0.9), trials)
        rows.append({"change": "volume ratio", **r})
        # level slider root <-> leaves: no pipeline stage, redraw boxes, colours, face masks
        n = app.controller.state.tree.n_splits
        r = _trials(app, listener, app.gui.level, (0, n), trials)
        rows.append({"change": "level slider", **r})
        for row in rows:
            row.update(points=n_points, pool=len(app.controller.state.result.pool))
        return rows
    finally:
        listener.close()
        app.close()
        server.stop()


def bench_clients(n_points: int, n_clients: int, trials: int, process: bool = True) -> dict:
    """After planning, a browser's volume-ratio edit until every one of ``n_clients`` clients
    has the new scene and the new best grasp (medians over ``trials``, after one warm-up);
    ``process``: the viewer's planner process on (else the planner runs on its threads)."""
    from viser import _messages

    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    app = run(ViewerConfig(n_points=n_points, planner_process=process), server)
    clients = [Listener(server.get_port()) for _ in range(n_clients)]
    c = app.controller
    pp = c.planner
    try:
        if pp is not None and not pp.wait_ready():
            raise SystemExit("the planner process did not start")
        time.sleep(1.0)
        c.plan()
        h = app.gui.params[("decomposition", "volume_ratio")]
        scene, best, plan_s, stages_s, cpu_here, cpu_worker = [], [], [], [], [], []
        for k in range(trials + 1):
            value = (0.5, 0.9)[k % 2]
            while not (c.idle() and app.gui.settled()):
                time.sleep(0.01)
            pid = None if pp is None else pp.pid
            c0, w0 = time.process_time(), _cpu(pid)
            t0 = time.perf_counter()
            clients[0].send(_messages.GuiUpdateMessage(h._impl.uuid, {"value": value}))
            deadline = time.perf_counter() + 600
            while not (c.state.params.decomposition.volume_ratio == value and c.state.planned):
                assert time.perf_counter() < deadline, "the edit never applied"
                time.sleep(0.005)
            s = c.state
            assert s.error == "", s.error
            label = f"boxes: {len(s.tree.leaves())}".encode()
            t_scene = max(cl.wait_for(label, after=t0) for cl in clients)
            t_best = max(cl.wait_for(b"fc", after=t_scene) for cl in clients)
            c1, w1 = time.process_time(), _cpu(pid if pp is None or pp.pid == pid else None)
            if k == 0:
                continue  # warm-up
            cpu_here.append(c1 - c0)
            cpu_worker.append(w1 - w0 if w1 else float("nan"))
            scene.append(t_scene - t0)
            best.append(t_best - t0)
            plan_s.append(s.result.timings.get("grasps", float("nan")))
            stages_s.append(sum(s.result.timings.get(st, 0.0) for st in SCENE_STAGES))
        if pp is not None and pp.local_plans:
            print(f"# {pp.local_plans} plan(s) ran in the viewer's process", flush=True)
        return {
            "process": "on" if process else "off",
            "cpu_here": statistics.median(cpu_here),
            "cpu_worker": statistics.median(cpu_worker) if pp is not None else 0.0,
            "points": n_points,
            "clients": n_clients,
            "pool": len(c.state.result.pool),
            "scene": statistics.median(scene),
            "scene_max": max(scene),
            "best": statistics.median(best),
            "best_max": max(best),
            "best_min": min(best),
            "planner": statistics.median(plan_s),
            "stages": statistics.median(stages_s),
            "other": statistics.median(
                b - p - st for b, p, st in zip(best, plan_s, stages_s, strict=True)
            ),
        }
    finally:
        for cl in clients:
            cl.close()
        app.close()
        server.stop()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=int, nargs="+", default=[20000, 200000])
    ap.add_argument("--trials", type=int, default=7)
    ap.add_argument("--clients", type=int, nargs="+", default=[1, 4])
    ap.add_argument(
        "--client-points",
        type=int,
        nargs="+",
        default=[ViewerConfig().n_points],
        help="points of the clients table's rows (default: the viewer's default object)",
    )
    ap.add_argument("--client-trials", type=int, default=5)
    ap.add_argument("--skip-single", action="store_true", help="only the clients table")
    ap.add_argument(
        "--planner-process",
        nargs="+",
        choices=("off", "on"),
        default=["on"],
        help="the viewer's planner process in the clients table; several: alternated per row",
    )
    ap.add_argument("--rounds", type=int, default=1, help="times each clients row is run")
    args = ap.parse_args()
    print(
        f"# {platform.machine()}, Python {platform.python_version()}, numpy {np.__version__}, "
        f"viser {viser.__version__}, {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}"
    )
    print(
        f"# {args.trials} changes per row after one warm-up; medians in ms (min, max of received)"
    )
    if not args.skip_single:
        single_table(args)
    print()
    print(
        f"# after planning: a browser's volume-ratio edit until every client has it; "
        f"{args.client_trials} changes per row after one warm-up, medians (max)"
    )
    print()
    print("| points | clients | planner process | pool | new scene (ms) | max "
          "| new best grasp (ms) | max | min | stages (ms) | planner (ms) | other (ms) "
          "| CPU viewer / worker (ms) | load |")  # fmt: skip
    print("|---:|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|---|")
    for _ in range(args.rounds):
        for points in args.client_points:
            for n in args.clients:
                for mode in args.planner_process:
                    load0 = os.getloadavg()[0]
                    r = bench_clients(points, n, args.client_trials, mode == "on")
                    print(
                        f"| {r['points']:,} | {r['clients']} | {r['process']} | {r['pool']} | "
                        f"{r['scene'] * 1e3:.0f} | {r['scene_max'] * 1e3:.0f} | "
                        f"{r['best'] * 1e3:.0f} | {r['best_max'] * 1e3:.0f} | "
                        f"{r['best_min'] * 1e3:.0f} | "
                        f"{r['stages'] * 1e3:.0f} | {r['planner'] * 1e3:.0f} | "
                        f"{r['other'] * 1e3:.0f} | {r['cpu_here'] * 1e3:.0f} / "
                        f"{r['cpu_worker'] * 1e3:.0f} | {load0:.1f}-{os.getloadavg()[0]:.1f} |",
                        flush=True,
                    )


def single_table(args) -> None:
    print()
    print(
        "| points | change | pool | pipeline (ms) | callback (ms) | received (ms) | min | max "
        "| stages re-run (ms) |"
    )
    print("|---:|---|---:|---:|---:|---:|---:|---:|---|")
    for n in args.points:
        for r in bench(n, args.trials):
            print(
                f"| {r['points']:,} | {r['change']} | {r['pool']} | {r['pipeline'] * 1e3:.0f} | "
                f"{r['callback'] * 1e3:.0f} | {r['received'] * 1e3:.0f} | {r['min'] * 1e3:.0f} | "
                f"{r['max'] * 1e3:.0f} | {r['stages']} |",
                flush=True,
            )


if __name__ == "__main__":
    main()
