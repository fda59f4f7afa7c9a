"""Arrow keys in headless Chromium: on a focused slider handle they step the slider and never
reach the page's ``document``, where viser's camera controls listen for them (they skip only
``input``, ``textarea`` and ``select`` targets; a Mantine slider handle is a ``div``); the app's
key guard, ``app.viser_hooks.add_slider_key_guard``, keeps them for the slider. With nothing
focused the same key does reach the document (the control case: the camera still answers it)."""

from __future__ import annotations

import re
import time

import numpy as np

LOAD_TIMEOUT_MS = 120_000
"""Generous: software WebGL on a shared machine."""

RECORD_KEYS = (
    "() => { window.__docKeys = []; document.addEventListener('keydown', (e) => "
    "window.__docKeys.push([e.code, e.target.getAttribute ? e.target.getAttribute('role') "
    ": null])); }"
)
"""Records every keydown that reaches ``document`` (as viser's camera controls see them)."""


def _camera(client) -> np.ndarray:
    return np.concatenate([np.asarray(client.camera.position), np.asarray(client.camera.wxyz)])


def _settled_camera(page, client, quiet_s: float = 2.0, timeout_s: float = 60.0) -> np.ndarray:
    """The browser's camera once it has not changed for ``quiet_s``."""
    last, since, t0 = _camera(client), time.perf_counter(), time.perf_counter()
    while time.perf_counter() - since < quiet_s:
        assert time.perf_counter() - t0 < timeout_s, "the camera never came to rest"
        page.wait_for_timeout(200)
        now = _camera(client)
        if not np.array_equal(now, last):
            last, since = now, time.perf_counter()
    return last


def test_arrow_keys_on_a_slider_step_it_and_do_not_reach_the_camera(browser_context, live_app):
    page = browser_context.new_page()
    page.set_default_timeout(LOAD_TIMEOUT_MS)
    try:
        page.goto(f"http://127.0.0.1:{live_app.server.get_port()}")
        page.get_by_text(re.compile(r"^boxes: \d+$")).wait_for()
        c = live_app.controller
        deadline = time.monotonic() + 120
        while not (c.idle() and c.state.tree is not None and live_app.server.get_clients()):
            assert time.monotonic() < deadline, "the app does not settle"
            time.sleep(0.1)
        client = next(iter(live_app.server.get_clients().values()))
        level = c.state.shown_level
        assert level >= 1, "the default object must have at least one split"
        assert page.evaluate("() => window.__pregraspSliderKeys") == 1  # the guard is installed
        page.evaluate(RECORD_KEYS)
        handle = page.get_by_role("slider").first  # the first slider is "level (splits)"
        before = _settled_camera(page, client)
        handle.focus()
        page.keyboard.press("ArrowLeft")
        for _ in range(100):
            if c.state.shown_level == level - 1:
                break
            page.wait_for_timeout(100)
        assert c.state.shown_level == level - 1  # the slider stepped once
        assert page.evaluate("() => window.__docKeys") == []  # the camera never saw the key
        after = _settled_camera(page, client)
        assert np.array_equal(after, before), f"the camera moved: {before} -> {after}"
        # the control case: with nothing focused (the page's body) the key reaches the document
        handle.evaluate("el => el.blur()")
        assert page.evaluate("() => document.activeElement === document.body")
        page.keyboard.press("ArrowLeft")
        assert page.evaluate("() => window.__docKeys") == [["ArrowLeft", None]]
        assert c.state.shown_level == level - 1  # and the slider did not see it
    finally:
        page.close()
