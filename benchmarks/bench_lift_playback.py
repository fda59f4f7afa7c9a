"""The viewer's "simulate lift" button in the real app (issue 11; ``docs/benchmarks.md``).

Builds the app on a real ``ViserServer`` (no browser) as ``pregrasp view`` does (default object,
20,000 points), plans, then presses simulate (``Controller.simulate``, what the button calls) on
each of the best ``--top`` grasps in turn. Per press: the seconds from the press until the
scene has drawn the lift's first frame (``SceneRenderer.rendered`` shows it: the poses are then
on their way to the browsers), the CPU seconds of the worker thread building the object's
scene (the first press only: it is kept for the next) and of the simulated run, the frames
recorded and the outcome. With ``--browser`` the presses are clicks on the page's button in
headless Chromium (software WebGL) and the first column is the wall time from the click until
the page shows the outcome (sent with the first frame), split into: click until the server gets
the press (the page's input latency), the press until the scene drew the first frame (the
simulation), and from there until the page shows it (delivery and the page's rendering). One
core: BLAS on one thread, the process pinned to one CPU (not with ``--browser``: Chromium
would inherit it).

Usage::

    .venv/bin/python benchmarks/bench_lift_playback.py [INPUT] [--top 5] [--points 20000]
        [--browser]
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import contextlib  # noqa: E402
import datetime  # noqa: E402
import platform  # noqa: E402
import re  # noqa: E402
import statistics  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from collections.abc import Iterator  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

from _timing import pin_one_core  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from app.scene_data import ranked_grasps  # noqa: E402
from app.server import ViewerConfig, run  # noqa: E402
from app.simulate_view import lift_frame  # noqa: E402


@contextlib.contextmanager
def _page(port: int) -> Iterator[Any]:
    """The app's page in headless Chromium, loaded."""
    from playwright.sync_api import sync_playwright

    from app.headless import launch

    with sync_playwright() as p:
        ctx = launch(p, tempfile.mkdtemp(prefix="pregrasp-bench-"), viewport=VIEWPORT)
        try:
            page = ctx.new_page()
            page.set_default_timeout(180_000)
            page.goto(f"http://127.0.0.1:{port}")
            page.get_by_text(re.compile(r"^\d+ force-closure of \d+ kept$")).wait_for()
            yield page
        finally:
            ctx.close()


def _drain(page: Any) -> None:
    """Return once the page has drawn everything it was sent (it is idle)."""
    for _ in range(3):
        page.evaluate(
            "() => new Promise(r => requestAnimationFrame(() => requestAnimationFrame(r)))"
        )


def _press(page: Any, c: Any, k: int) -> tuple[float, float]:
    """Click the page's button for grasp ``k`` once the page is idle: (perf_counter at the
    click, seconds until the page shows its outcome)."""
    button = page.get_by_role("button", name="simulate lift")
    deadline = time.monotonic() + 60
    while not button.is_enabled():  # the selection has reached the page
        if time.monotonic() > deadline:
            raise SystemExit("the simulate button stays disabled")
        time.sleep(0.01)
    while c.state.view.playing:  # the chosen grasp's closing animation has played
        time.sleep(0.05)
    _drain(page)
    outcome = page.get_by_text(re.compile(rf"^lift of grasp #{k + 1}: [a-z]+$"))
    t0 = time.perf_counter()
    button.click()
    outcome.wait_for()
    return t0, time.perf_counter() - t0


def _press_server(app: Any, k: int) -> float:
    """Press for grasp ``k`` through the controller; seconds until the scene drew frame 0."""
    c = app.controller
    t0 = time.perf_counter()
    c.simulate()
    while True:
        f = lift_frame(app.scene.rendered) if app.scene.rendered is not None else None
        if f is not None and f.playback.rank == k:
            return time.perf_counter() - t0
        if not c.lift.running and c.state.error:
            raise SystemExit(f"grasp #{k + 1}: {c.state.error}")
        time.sleep(0.002)


VIEWPORT = {"width": 1400, "height": 900}
"""The browser window of ``--browser``."""


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("input", nargs="?", type=Path)
    ap.add_argument("--top", type=int, default=5)
    ap.add_argument("--points", type=int, default=20000)
    ap.add_argument("--browser", action="store_true", help="click the button in Chromium")
    args = ap.parse_args()
    if not args.browser:  # Chromium would inherit the pinning
        pin_one_core()
    import viser

    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    app = run(ViewerConfig(input=args.input, n_points=args.points), server)
    c = app.controller
    rows = []
    split: list[tuple[float, float]] = []  # --browser: (click to press, press to result)
    page = None
    try:
        c.plan()
        name = c.state.source.name
        n = min(args.top, len(ranked_grasps(c.state.result)))
        with contextlib.ExitStack() as stack:
            if args.browser:
                page = stack.enter_context(_page(server.get_port()))
            for k in range(n):
                c.select_grasp(k)
                if page is not None:
                    t_click, first = _press(page, c, k)
                else:
                    t_click, first = 0.0, _press_server(app, k)
                c.lift.wait()
                pb = c.state.lift.playback
                rows.append((k, first, pb, pb.outcome))
                if page is not None:
                    split.append((pb.pressed - t_click, pb.wall))
    finally:
        app.close()
        server.stop()
    now = datetime.datetime.now(datetime.UTC)
    cpu = platform.processor() or platform.machine()
    pinned = "not pinned" if args.browser else "one core"
    print(
        f"# {now:%Y-%m-%d %H:%M} UTC, {cpu}, Python {platform.python_version()}, object "
        f"{name}, {args.points} points, {pinned}, load average {os.getloadavg()[0]:.1f}"
    )
    what = "click to outcome in the page (s)" if args.browser else "press to first frame (s)"
    print(f"| grasp | outcome | {what} | build CPU (s) | run CPU (s) | frames | simulated (s) |")
    print("|---|---|---|---|---|---|---|")
    for k, first, pb, res in rows:
        print(
            f"| #{k + 1} | {res.outcome} | {first:.2f} | {pb.build_cpu:.2f} | {pb.run_cpu:.3f} | "
            f"{len(pb.times)} | {pb.duration:.2f} |"
        )
    if split:
        print(
            "\n| grasp | click to server press (s) | press to result (s) | then to the page (s) |"
        )
        print("|---|---|---|---|")
        for (k, first, _, _), (to_press, to_result) in zip(rows, split, strict=True):
            rest = first - to_press - to_result
            print(f"| #{k + 1} | {to_press:.2f} | {to_result:.2f} | {rest:.2f} |")
    warm = [first for _, first, pb, _ in rows if pb.build_cpu == 0.0]
    runs = [pb.run_cpu for _, _, pb, _ in rows]
    if warm:
        med, top = statistics.median(warm), max(warm)
        print(f"\nwarm press to first frame: median {med:.2f} s, max {top:.2f} s")
    print(f"run CPU per grasp: median {statistics.median(runs):.3f} s, max {max(runs):.3f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
