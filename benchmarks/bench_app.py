"""App latency: a threshold change until the updated scene has been sent to a browser.

The app runs on a real ``ViserServer``; one websocket client (speaking viser's wire format: zstd
msgpack frames) stays connected like a browser. Each trial sets the volume-ratio GUI input from
Python, which runs exactly the callback a browser's edit runs (re-run the decomposition and
everything downstream, redraw, update the GUI), and stops the clock when the client has received
the frame carrying the new "boxes: N" label, which the app sends after the scene update.

Rows: a volume-ratio change (re-runs the decomposition and everything downstream) and a level
slider change (no pipeline stage: boxes, colours and face masks redrawn). Columns: pipeline =
the pipeline stages the change re-ran (from the result's timings, reused stages excluded);
callback = the whole callback on the server (pipeline + scene + GUI); received = the change
until the client has received the new scene (median, min and max over the trials). Timings
are wall-clock on one machine; under load they are noisy, so compare rows of one run.

    .venv/bin/python benchmarks/bench_app.py [--points 20000 200000] [--trials 7]
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


class Listener:
    """A websocket client that records when each "boxes: N" label arrives."""

    def __init__(self, port: int) -> None:
        self.ws = connect(
            f"ws://127.0.0.1:{port}",
            subprotocols=[f"viser-v{viser.__version__}"],
            max_size=None,
            open_timeout=30,
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


def bench(n_points: int, trials: int) -> list[dict]:
    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    app = run(ViewerConfig(n_points=n_points), server)
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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=int, nargs="+", default=[20000, 200000])
    ap.add_argument("--trials", type=int, default=7)
    args = ap.parse_args()
    print(
        f"# {platform.machine()}, Python {platform.python_version()}, numpy {np.__version__}, "
        f"viser {viser.__version__}, {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}"
    )
    print(
        f"# {args.trials} changes per row after one warm-up; medians in ms (min, max of received)"
    )
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
