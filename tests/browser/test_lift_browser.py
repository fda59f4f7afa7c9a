"""The "simulate lift" button in headless Chromium: it is there, a click runs the MuJoCo lift
of the chosen grasp and the page shows its outcome (the one the server computed) and the grasp
table's lift column."""

from __future__ import annotations

import re
import time

LOAD_TIMEOUT_MS = 120_000
"""Generous: software WebGL, and the first press builds the object's collision model."""


def test_simulate_button_shows_the_outcome(browser_context, live_app, shots_dir):
    page = browser_context.new_page()
    page.set_default_timeout(LOAD_TIMEOUT_MS)
    try:
        page.goto(f"http://127.0.0.1:{live_app.server.get_port()}")
        page.get_by_text(re.compile(r"^\d+ force-closure of \d+ kept$")).wait_for()
        c = live_app.controller
        deadline = time.monotonic() + 120
        while not (c.state.planned and c.idle()):  # the start-up plan has been committed
            assert time.monotonic() < deadline, "the start-up plan does not finish"
            time.sleep(0.1)
        button = page.get_by_role("button", name="simulate lift")
        button.wait_for()
        assert button.is_enabled()
        button.click()
        outcome = re.compile(r"^lift of grasp #1: (lifted|slipped|dropped|unstable)$")
        page.get_by_text(outcome).wait_for()
        s = c.state
        pb = s.lift.playback
        assert pb is not None and pb.rank == 0
        shown = page.get_by_text(outcome).inner_text()
        assert shown == f"lift of grasp #1: {pb.outcome.outcome}"  # the server's outcome
        assert page.get_by_role("columnheader", name="lift").count() >= 1
        page.screenshot(path=str(shots_dir / "browser_lift.png"))
    finally:
        page.close()
