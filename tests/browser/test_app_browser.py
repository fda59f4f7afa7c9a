"""The real app in headless Chromium: load the page, change a threshold and see the number of
boxes change (and a second tab see the same), hide the face masks and show the ghosts, plan and
see the ranked table, pick a grasp, open a result file, save screenshots, upload a broken file
and see the error notification. Each action is timed: the server must draw its change within
:data:`ACTION_S` of the edit's arrival, and the change must be on screen within
:data:`ACTION_S` of the action (the page's text, or the first frame Chromium composites with
the changed canvas), in the best of up to :data:`TRIES` tries (:func:`_shown_within`).

What the page shows is checked against what the server's scene holds (the box handles under
their fixed names), so the "boxes: N" label cannot drift from the scene.
"""

from __future__ import annotations

import dataclasses
import json
import re
import time

import numpy as np
import pytest

from app.scene import NAMES
from app.scene_data import ranked_grasps
from pregrasp_core.decomposition import decompose

LOAD_TIMEOUT_MS = 90_000
"""Generous: headless Chromium renders WebGL in software."""


def _scene_box_count(app) -> int:
    s = app.controller.state
    return sum(
        app.server.scene.get_handle_by_name(f"{NAMES['boxes']}/node_{i}") is not None
        for i in range(len(s.tree.nodes))
    )


def _boxes_in_page(page) -> int:
    text = page.get_by_text(re.compile(r"^boxes: \d+$")).inner_text()
    return int(text.split()[1])


@pytest.fixture(scope="module")
def page(browser_context, live_app):
    page = browser_context.new_page()
    page.set_default_timeout(LOAD_TIMEOUT_MS)
    t0 = time.perf_counter()
    page.goto(f"http://127.0.0.1:{live_app.server.get_port()}")
    page.get_by_text(re.compile(r"^boxes: \d+$")).wait_for(timeout=LOAD_TIMEOUT_MS)
    t1 = time.perf_counter()
    page.get_by_text(FC_TEXT).wait_for(timeout=LOAD_TIMEOUT_MS)
    print(  # noqa: T201 - figures for the log
        f"first screen: boxes {t1 - t0:.2f} s, best grasp {time.perf_counter() - t0:.2f} s"
    )
    yield page
    page.close()


ACTION_S = 2.0
"""Longest time from an action to its change on screen (issue 14)."""

TRIES = 3
"""Tries of an action whose change was not on screen within :data:`ACTION_S`. The shared
2-core VM's other jobs add their time to a try (software WebGL draws a frame of this scene in
about 0.2 s on a quiet machine, seconds while other browsers run), so an action is held to
its best of three tries, as a benchmark takes its minimum; an app that is slow fails every try
(a first screen of 214 hand ghosts took 11 to 28 s per action)."""


def _shown_within(what: str, attempt) -> float:
    """Call ``attempt(i)`` (the i-th try of an action, from the state the try before it left;
    it returns the seconds until the change was on screen) until one is within
    :data:`ACTION_S`, at most :data:`TRIES` times; assert that one was. Returns the number of
    tries."""
    times: list[float] = []
    for i in range(TRIES):
        times.append(attempt(i))
        if times[-1] < ACTION_S:
            break
    listed = ", ".join(f"{t:.2f}" for t in times)
    print(f"{what}: on screen after {listed} s")  # noqa: T201 - figures for the log
    assert min(times) < ACTION_S, f"{what}: on screen only after {listed} s in {len(times)} tries"
    return len(times)


def _wait_until(page, cond, what: str, timeout_s: float = 90.0) -> None:
    """Poll ``cond()`` every 50 ms (letting the page run) until it holds."""
    end = time.monotonic() + timeout_s
    while not cond():
        assert time.monotonic() < end, f"never: {what}"
        page.wait_for_timeout(50)


class _Watch:
    """Records when ``cond()`` first holds (polled every 5 ms on a thread)."""

    def __init__(self, cond) -> None:
        import threading

        self.t: float | None = None
        self._cond = cond
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            if self._cond():
                self.t = time.perf_counter()
                return
            time.sleep(0.005)

    def done(self, timeout: float = 120.0) -> float:
        self._thread.join(timeout)
        self._stop.set()
        assert self.t is not None, "the server never showed the change"
        return self.t


ARRIVALS: list[float] = []
"""When the server received each browser edit (``Gui.begin_edit``, called by the update guard)
or upload (``Controller.load_upload``), for the server's part of an action's time."""


class _RecordingEdits(dict):
    """``Gui._edits`` that records when each browser edit arrives (the update guard calls
    ``Gui.begin_edit``, which marks it here)."""

    def setdefault(self, key, default=None):
        ARRIVALS.append(time.perf_counter())
        return super().setdefault(key, default)


@pytest.fixture(scope="module", autouse=True)
def _record_arrivals(live_app):
    gui, c = live_app.gui, live_app.controller
    upload = c.load_upload

    def load_upload(*args):
        ARRIVALS.append(time.perf_counter())
        return upload(*args)

    with gui._edits_lock:
        gui._edits = _RecordingEdits(gui._edits)
    c.load_upload = load_upload
    yield
    c.load_upload = upload


class _Screencast:
    """The frames the page composites, as Chromium sends them (the DevTools protocol's
    ``Page.startScreencast``), each with the time the compositor gives it (``metadata.timestamp``,
    on the wall clock; else its arrival, an upper bound). ``page.screenshot`` instead asks for
    a frame of its own and waits for it (0.9-1.4 s while the hand animates, measured in session
    9): the screenshot's time is the test's, the first frame's time is the user's.

    Frames are read only while the test talks to the page (the sync API dispatches events
    then: :meth:`first_change` waits a moment first); each is acknowledged at once, else
    Chromium stops sending."""

    def __init__(self, page) -> None:
        self._page = page
        self._cdp = page.context.new_cdp_session(page)
        self._wall = time.time() - time.perf_counter()  # wall clock -> perf_counter
        self.frames: list[tuple[float, str]] = []  # (time on the perf_counter, base64 PNG)
        self._cdp.on("Page.screencastFrame", self._frame)
        self._cdp.send("Page.startScreencast", {"format": "png", "everyNthFrame": 1})

    def _frame(self, params: dict) -> None:
        t = time.perf_counter()
        stamp = params.get("metadata", {}).get("timestamp")
        if stamp is not None:
            t = min(t, float(stamp) - self._wall)
        self.frames.append((t, params["data"]))
        self._cdp.send("Page.screencastFrameAck", {"sessionId": params["sessionId"]})

    @staticmethod
    def _canvas(frame: tuple[float, str], clip: dict) -> np.ndarray:
        import base64

        import imageio.v3 as iio

        img = iio.imread(base64.b64decode(frame[1]), extension=".png")[..., :3].astype(np.int16)
        x0, y0 = int(clip["x"]), int(clip["y"])
        return img[y0 : y0 + int(clip["height"]), x0 : x0 + int(clip["width"])]

    def first_change(self, t0: float, clip: dict) -> float | None:
        """Seconds from ``t0`` to the first frame after it whose canvas differs from the last
        frame before it (as :func:`_differs`), or None (no frame before ``t0``, or none
        differs)."""
        self._page.wait_for_timeout(300)  # frames already drawn are read
        before = [f for f in self.frames if f[0] <= t0]
        if not before:
            return None
        base = self._canvas(before[-1], clip)
        for f in (f for f in self.frames if f[0] > t0):
            if _differs(self._canvas(f, clip), base):
                return f[0] - t0
        return None

    def stop(self) -> None:
        self._cdp.send("Page.stopScreencast")
        self._cdp.detach()


_TEXT_JS = """([want, key]) => {
  const re = new RegExp(want);
  window[key] = null;
  const hit = (n) => n && re.test((n.textContent || '').trim());
  const seen = new MutationObserver((records) => {
    if (records.some((r) => hit(r.target) || [...r.addedNodes].some(hit))) {
      seen.disconnect();
      requestAnimationFrame(() => requestAnimationFrame(() => { window[key] = Date.now(); }));
    }
  });
  seen.observe(document.body, {subtree: true, childList: true, characterData: true});
}"""


class _TextWatch:
    """When the page first painted a text matching ``pattern`` (a JavaScript regular
    expression): a ``MutationObserver`` in the page sees the node change, and the time is
    taken at the start of the second animation frame after it, when the frame that painted
    the text has been drawn (an upper bound). Playwright's own wait for a text polls at
    growing intervals (up to 0.5 s, each poll queued behind the page's frames), which put
    0.5 to 2.5 s on top of the page's time at a load of 3 (session 11)."""

    _n = 0

    def __init__(self, page, pattern: str) -> None:
        _TextWatch._n += 1
        self._page, self._key = page, f"__pregraspText{_TextWatch._n}"
        self._wall = time.time() - time.perf_counter()  # wall clock -> perf_counter
        page.evaluate(_TEXT_JS, [pattern, self._key])

    def painted(self) -> float | None:
        """The time (on the perf_counter) the text was painted, or None if it was not seen
        changing (it was there before, or the observer missed it)."""
        for _ in range(20):
            at = self._page.evaluate(f"() => window['{self._key}']")
            if at is not None:
                return float(at) / 1000.0 - self._wall
            self._page.wait_for_timeout(50)
        return None


def _differs(now: np.ndarray, before: np.ndarray) -> bool:
    """Whether more than 0.2 % of the canvas's pixels changed (by more than 12 of 255)."""
    return now.shape != before.shape or (np.abs(now - before).max(axis=2) > 12).mean() > 0.002


def _check_shown(
    page, what: str, t0: float, t_screen: float, watch: _Watch, frame: float | None = None
) -> float:
    """Assert that the server drew the action's change within :data:`ACTION_S` of the last
    arrival of its edit, print that with the time until the change was on screen, and return
    the time the user waited: ``frame`` (the first composited frame with the change,
    :class:`_Screencast`) when given, else ``t_screen - t0`` (the test saw the text, or a
    screenshot showed the canvas changed; a screenshot waits for a frame of its own, 0.9 to
    1.4 s while the hand animates, so for the canvas it is an upper bound)."""
    del page
    t_server = watch.done()
    came = [t for t in ARRIVALS if t0 <= t <= t_server]
    on_screen = t_screen - t0
    server = t_server - (came[-1] if came else t0)
    first = "" if frame is None else f", first frame with it {frame:.2f} s"
    print(  # noqa: T201 - figures for the log
        f"{what}: on screen {on_screen:.2f} s{first}, server {server:.2f} s from the edit's arrival"
    )
    assert server < ACTION_S, f"{what}: the server took {server:.2f} s to draw the change"
    return on_screen if frame is None else frame


def _canvas_changed(page, before: np.ndarray, clip: dict, timeout: float = 90.0) -> float:
    """Seconds until the canvas on screen differs from ``before`` (more than 0.2 % of its
    pixels). Each poll is a screenshot of the page as displayed, clipped to the canvas found
    before the action (``clip``); it waits for no frame of its own (a screenshot takes the
    newest composited frame), so that the polling does not hold up the page it watches."""
    t0 = time.perf_counter()
    while True:
        if _differs(_canvas_png(page, frames=0, clip=clip), before):
            return time.perf_counter() - t0
        assert time.perf_counter() - t0 < timeout, "the canvas never changed"


FC_TEXT = re.compile(r"^\d+ force-closure of \d+ kept$")
"""The planner's summary line in the Planner panel."""

OBJECT_LAYERS = ("cloud", "box_edges", "faces_free", "faces_blocked", "subfaces")
"""Scene layers of the object itself (with the boxes), hidden to see the background."""


def _canvas_clip(page) -> dict:
    """The page rectangle of the scene's canvas (the widest canvas on the page)."""
    canvas = max(
        page.locator("canvas").all(), key=lambda c: (c.bounding_box() or {}).get("width", 0)
    )
    box = canvas.bounding_box()
    return {k: box[k] for k in ("x", "y", "width", "height")}


def _canvas_png(page, frames: int = 3, clip: dict | None = None) -> np.ndarray:
    """The canvas as displayed (RGB), after ``frames`` pairs of animation frames."""
    import imageio.v3 as iio

    for _ in range(frames):  # frames drawn after the last change
        page.evaluate(
            "() => new Promise(r => requestAnimationFrame(() => requestAnimationFrame(r)))"
        )
    png = page.screenshot(clip=clip if clip is not None else _canvas_clip(page))
    return np.asarray(iio.imread(png, extension=".png"))[..., :3].astype(np.int16)


def _set_visible(app, handles, visible: bool) -> None:
    with app.server.atomic():
        for h in handles:
            h.visible = visible


def _object_fraction(page, app, footprint: bool = False) -> float:
    """Fraction of the canvas whose pixels change when the object and its boxes are hidden
    (the grasp's hand and the ghosts, which are not the object and may hide part of it, hidden
    in both); with ``footprint``, the fraction of the canvas the rectangle around those pixels
    spans (for a result file: no points, only translucent boxes whose inside barely changes)."""
    hand = [h for h in (app.scene.handle(k) for k in ("hand_frame", "contacts", "cones")) if h]
    hand += app.scene.ghost_handles()  # the pre-grasp ghosts are not the object either
    handles = [app.scene.handle(k) for k in OBJECT_LAYERS] + list(app.scene._boxes.values())
    handles = [h for h in handles if h is not None]
    try:
        _set_visible(app, hand, False)
        page.wait_for_timeout(1500)
        with_object = _canvas_png(page)
        _set_visible(app, handles, False)
        page.wait_for_timeout(1500)
        background = _canvas_png(page)
    finally:
        _set_visible(app, handles + hand, True)
    changed = np.abs(with_object - background).max(axis=2) > 12  # (H, W)
    if footprint:  # the rectangle the object's changed pixels span
        rows, cols = np.flatnonzero(changed.any(axis=1)), np.flatnonzero(changed.any(axis=0))
        if not len(rows):
            return 0.0
        area = (rows[-1] - rows[0] + 1) * (cols[-1] - cols[0] + 1)
        return float(area / changed.size)
    return float(changed.mean())


def test_first_screen_shows_object_boxes_and_best_grasp(page, live_app, shots_dir):
    """What a new user sees: the boxes, the best grasp planned in the background, force closure
    stated, ghosts off, the camera framed on the object (at least a fifth of the canvas)."""
    page.get_by_text(FC_TEXT).wait_for(timeout=LOAD_TIMEOUT_MS)
    s = live_app.controller.state
    assert s.planned and s.view.selected_grasp == 0 and not s.view.show_ghosts
    ranked = ranked_grasps(s.result)
    n_fc = sum(float(g.epsilon) > 0 for g in ranked)
    assert page.get_by_text(FC_TEXT).inner_text() == f"{n_fc} force-closure of {len(ranked)} kept"
    assert page.get_by_role("cell", name=f"{float(ranked[0].epsilon):.4f}").count() >= 1
    assert not page.get_by_label("hand ghosts", exact=True).is_checked()
    assert live_app.scene.n_ghosts_shown == 0
    assert live_app.scene.handle("hand_frame").visible  # the best grasp's hand is drawn
    assert _boxes_in_page(page) == _scene_box_count(live_app)
    page.screenshot(path=str(shots_dir / "browser_first_screen.png"))
    fraction = _object_fraction(page, live_app)
    print(f"object covers {fraction:.1%} of the canvas")  # noqa: T201 - a figure for the log
    assert fraction >= 0.2, f"the object covers {fraction:.1%} of the canvas"


def test_threshold_change_changes_the_boxes(page, live_app, shots_dir):
    s0 = live_app.controller.state
    n0 = _boxes_in_page(page)
    assert n0 == _scene_box_count(live_app) == len(s0.tree.leaves())
    page.screenshot(path=str(shots_dir / "browser_decomposition.png"))
    # a threshold for which the core's own decomposition of this cloud has another part count
    for ratio in ("0.5", "0.98", "0.99"):
        p = dataclasses.replace(s0.params.decomposition, volume_ratio=float(ratio))
        expected = len(decompose(s0.cloud.points, p).leaves())
        if expected != n0:
            break
    else:
        pytest.fail("no volume ratio changes the number of parts of the default object")
    box = page.get_by_label("volume ratio", exact=True)
    app = live_app
    # the tries go to the new ratio, back to the first one, and to the new one again
    steps = ((ratio, expected), (str(s0.params.decomposition.volume_ratio), n0))

    def change(i: int) -> float:
        want, n = steps[i % 2]

        def drawn() -> bool:
            r = app.scene.rendered
            return r is not None and r.params.decomposition.volume_ratio == float(want)

        watch = _Watch(drawn)
        text = _TextWatch(page, f"^boxes: {n}$")
        t0 = time.perf_counter()
        box.fill(want)  # sent as typed: the first edit runs at once, later ones coalesce
        box.press("Enter")
        page.get_by_text(f"boxes: {n}", exact=True).wait_for(timeout=LOAD_TIMEOUT_MS)
        t1 = text.painted() or time.perf_counter()
        return _check_shown(page, "threshold change", t0, t1, watch)

    ratio, expected = steps[(_shown_within("threshold change", change) - 1) % 2]
    assert _boxes_in_page(page) == expected == _scene_box_count(live_app)
    assert live_app.controller.state.params.decomposition.volume_ratio == float(ratio)
    # a second browser sees the same shared state (docs/app.md: one state per server)
    other = page.context.new_page()
    other.set_default_timeout(LOAD_TIMEOUT_MS)
    try:
        other.goto(page.url)
        other.get_by_text(f"boxes: {expected}", exact=True).wait_for(timeout=LOAD_TIMEOUT_MS)
        assert other.get_by_label("volume ratio", exact=True).input_value() == ratio
    finally:
        other.close()


def test_face_masks_and_ghosts_show_and_hide(page, live_app, shots_dir):
    """Untick the face masks, tick the hand ghosts: each shows on the canvas (the server draws
    it within 2 s), the panel says how many ghosts are drawn, and the scene holds what the panel
    says."""
    masks = page.get_by_label("face masks", exact=True)
    assert masks.is_checked() and live_app.scene.n_faces_shown != (0, 0)
    scene = live_app.scene
    clip = _canvas_clip(page)
    cast = _Screencast(page)

    def hide_masks(i: int) -> float:
        if i:  # the masks back on screen for another try
            masks.check()
            _wait_until(page, lambda: scene.n_faces_shown != (0, 0), "the masks drawn again")
            page.wait_for_timeout(1000)
        before = _canvas_png(page, clip=clip)
        page.wait_for_timeout(300)  # the frame on screen before the action
        watch = _Watch(lambda: scene.n_faces_shown == (0, 0))
        t0 = time.perf_counter()
        masks.uncheck()
        _canvas_changed(page, before, clip)
        t1 = time.perf_counter()
        return _check_shown(page, "face masks hidden", t0, t1, watch, cast.first_change(t0, clip))

    _shown_within("face masks hidden", hide_masks)
    assert live_app.scene.n_faces_shown == (0, 0) and not masks.is_checked()
    ghosts = page.get_by_label("hand ghosts", exact=True)
    drawn = re.compile(r"pool: \d+ pre-grasps, \d+ pass the filters, [1-9]\d* ghosts drawn")

    def show_ghosts(i: int) -> float:
        if i:  # the ghosts off the screen for another try
            ghosts.uncheck()
            page.get_by_text(re.compile(r", 0 ghosts drawn")).wait_for(timeout=LOAD_TIMEOUT_MS)
            page.wait_for_timeout(1000)
        before = _canvas_png(page, clip=clip)
        page.wait_for_timeout(300)  # the frame on screen before the action
        watch = _Watch(lambda: scene.n_ghosts_shown > 0)
        t0 = time.perf_counter()
        ghosts.check()
        page.get_by_text(drawn).wait_for(timeout=LOAD_TIMEOUT_MS)
        _canvas_changed(page, before, clip)
        t1 = time.perf_counter()
        return _check_shown(page, "ghosts shown", t0, t1, watch, cast.first_change(t0, clip))

    _shown_within("ghosts shown", show_ghosts)
    cast.stop()
    n = live_app.scene.n_ghosts_shown
    assert 0 < n <= live_app.scene.max_ghosts
    assert f", {n} ghosts drawn" in page.get_by_text(drawn).inner_text()
    page.screenshot(path=str(shots_dir / "browser_ghosts.png"))
    try:
        fraction = _object_fraction(page, live_app)
        print(f"with ghosts, the object covers {fraction:.1%} of the canvas")  # noqa: T201
        assert fraction >= 0.2, f"the object covers {fraction:.1%} of the canvas"
    finally:  # back to the first screen's layers, for the tests that follow
        live_app.controller.set_ghosts_visible(False)
        live_app.controller.set_face_masks_visible(True)
    page.get_by_text(re.compile(r", 0 ghosts drawn")).wait_for(timeout=LOAD_TIMEOUT_MS)


def test_plan_shows_ranked_table_and_pick_a_grasp(page, live_app, shots_dir):
    c = live_app.controller
    v0 = c.state.version

    def start_plan(i: int) -> float:
        nonlocal v0, t0
        # the plan before (the start-up plan, or the try before) has finished: a new plan
        # starts from a quiet app
        _wait_until(page, lambda: c.idle() and c.state.planned, "the plan before ended")
        # a fresh cloud (one point more), so that the plan runs the planner (the start-up
        # plan's grasps would be reused as they are)
        c.set_n_points(c.state.n_points + 1)
        assert not c.state.planned
        v0 = c.state.version
        # the page drops the old summary line first (the new cloud is not planned)
        page.get_by_text(FC_TEXT).first.wait_for(state="hidden", timeout=LOAD_TIMEOUT_MS)
        watch = _Watch(lambda: c.state.busy == "plan" or c.state.planned)
        text = _TextWatch(page, r"^(planning\.\.\.|\d+ force-closure of \d+ kept)")
        t0 = time.perf_counter()
        page.get_by_role("button", name="plan grasps").click()
        # the page shows the plan running, or already its result: a plan of 5,000 points can
        # end before the page has drawn its progress (both updates then arrive in one frame)
        page.wait_for_function(
            "() => [...document.querySelectorAll('button')].some(b => b.innerText.includes("
            "'planning...')) || document.querySelector('[role=progressbar]') !== null || "
            "[...document.querySelectorAll('strong')].some(e => "
            "/^\\d+ force-closure of \\d+ kept$/.test(e.innerText))",
            timeout=LOAD_TIMEOUT_MS,
        )
        t1 = text.painted() or time.perf_counter()
        return _check_shown(page, "plan started", t0, t1, watch)

    t0 = time.perf_counter()
    _shown_within("plan started", start_plan)
    for _ in range(900):  # the plan is committed (the button is enabled again)
        s = live_app.controller.state
        if s.version > v0 and s.planned and live_app.controller.idle():
            break
        page.wait_for_timeout(100)
    page.get_by_text(FC_TEXT).wait_for(timeout=LOAD_TIMEOUT_MS)
    print(f"plan to ranked table: {time.perf_counter() - t0:.2f} s")  # noqa: T201
    s = live_app.controller.state
    ranked = ranked_grasps(s.result)
    assert ranked and s.planned
    assert page.get_by_role("cell", name=f"{float(ranked[0].epsilon):.4f}").count() >= 1
    page.screenshot(path=str(shots_dir / "browser_planned.png"))
    if len(ranked) < 2:
        pytest.fail("the default object should give at least two ranked grasps")
    clip = _canvas_clip(page)
    app = live_app
    cast = _Screencast(page)
    order = (1, 2, 1) if len(ranked) >= 3 else (1, 0, 1)  # grasps chosen by the tries

    def closed() -> bool:  # the choice plays the approach and closing (2 s at speed 1)
        s = app.controller.state  # the scene has drawn the closed hand, not just been told
        return not s.view.playing and s.view.anim_t == 1.0 and app.scene.rendered is s

    def choose(i: int) -> float:
        k = order[i]
        if i:  # the hand of the try before at rest, for another try
            _wait_until(page, closed, "the hand closed")
        page.get_by_label("grasp", exact=True).click()
        option = page.get_by_role("option", name=re.compile(rf"^#{k + 1} "))
        option.wait_for()
        before = _canvas_png(page, clip=clip)
        page.wait_for_timeout(300)  # the frame on screen before the action

        def posed() -> bool:
            r = app.scene.rendered
            return r is not None and r.view.selected_grasp == k

        watch = _Watch(posed)
        t0 = time.perf_counter()
        option.click()
        page.wait_for_function(
            f"() => [...document.querySelectorAll('input')].some(i => i.value.startsWith("
            f"'#{k + 1} '))",
            timeout=LOAD_TIMEOUT_MS,
        )
        _canvas_changed(page, before, clip)  # the hand moves
        t1 = time.perf_counter()
        return _check_shown(page, "grasp choice", t0, t1, watch, cast.first_change(t0, clip))

    chosen = order[_shown_within("grasp choice", choose) - 1]
    cast.stop()
    # the server saw the choice and posed the URDF hand at that grasp
    _wait_until(page, lambda: app.controller.state.view.selected_grasp == chosen, "the choice")
    _wait_until(page, closed, "the hand closed")
    frame = live_app.scene.handle("hand_frame")
    assert frame.visible
    # against the result the scene drew: a plan committed after the table was read (the
    # start-up plan finishing late) may rank slightly different poses
    shown = ranked_grasps(live_app.scene.rendered.result)
    assert abs(frame.position - shown[chosen].T_world_hand[:3, 3]).max() < 1e-6
    page.screenshot(path=str(shots_dir / "browser_grasp.png"))


def test_bad_upload_shows_a_notification(page, live_app):
    s0 = live_app.controller.state
    page.locator("input[type=file]").first.set_input_files(
        files=[
            {
                "name": "broken.ply",
                "mimeType": "application/octet-stream",
                "buffer": b"ply\nformat junk\n",
            }
        ]
    )
    # viser first shows its own "Uploading broken.ply" notice; the app's error follows
    note = page.locator(".mantine-Notification-root", has_text="Cannot do that")
    note.first.wait_for(timeout=LOAD_TIMEOUT_MS)
    assert "broken.ply" in note.first.inner_text()
    s = live_app.controller.state
    assert s.result is s0.result and "broken.ply" in s.error  # the object stays loaded


def test_export_downloads_result_and_screenshot(page, live_app, shots_dir):
    with page.expect_download(timeout=LOAD_TIMEOUT_MS) as dl:
        page.get_by_role("button", name="download result (JSON)").click()
    path = shots_dir / "export.pregrasp.json"
    dl.value.save_as(path)
    doc = json.loads(path.read_text())
    assert doc["schema"] == "pregrasp/1"
    assert dl.value.suggested_filename == "mug_handle.pregrasp.json"
    with page.expect_download(timeout=LOAD_TIMEOUT_MS) as dl:
        page.get_by_role("button", name="screenshot (PNG)").click()
    png = shots_dir / "export_screenshot.png"
    dl.value.save_as(png)
    data = png.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n"  # a PNG rendered by the browser's own canvas
    width, height = int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")
    assert width >= 64 and height >= 64


def test_html_in_an_uploaded_file_name_is_shown_as_text(page, live_app):
    """A file whose name holds HTML is loaded; its name shows in the status as text and no
    script of it runs (viser renders markdown as raw HTML, so the app escapes it)."""
    page.evaluate("() => { window.__pwned = 0; }")
    pts = np.random.default_rng(0).random((400, 3)) * [0.06, 0.05, 0.04]
    data = "\n".join(" ".join(f"{v:.6f}" for v in p) for p in pts).encode()
    names = (
        '<img src=x onerror="window.__pwned=1">.xyz',
        '<iframe srcdoc="<script>parent.__pwned=2</script>">.xyz',
    )
    for name in names:
        page.locator("input[type=file]").first.set_input_files(
            files=[{"name": name, "mimeType": "text/plain", "buffer": data}]
        )
        status = page.get_by_text(f"{name}: 400 points", exact=False)
        status.first.wait_for(timeout=LOAD_TIMEOUT_MS)
        assert live_app.controller.state.source.name == name
    page.wait_for_timeout(500)
    assert page.evaluate("() => window.__pwned") == 0
    assert page.locator("img[src=x], iframe[srcdoc]").count() == 0


TYPED = (
    "([el, v, at]) => { window.__fired = null; setTimeout(() => {"
    " Object.getOwnPropertyDescriptor(HTMLInputElement.prototype, 'value').set.call(el, v);"
    " el.dispatchEvent(new Event('input', {bubbles: true})); window.__fired = Date.now(); },"
    " at - Date.now()); }"
)
"""Types ``v`` into the input ``el`` at the epoch time ``at`` (ms), as a user would."""


def _round_trip_ms(page) -> float:
    t0 = time.perf_counter()
    page.evaluate("() => 0")
    return (time.perf_counter() - t0) * 1000.0


def test_two_browsers_editing_one_threshold_end_with_the_same_value(page, live_app):
    """Two tabs type into the volume ratio at one agreed instant: both end showing the value
    the result was computed with (before, each kept the other's echo: 5 of 5 trials differed).

    The two edits are scheduled in the tabs ahead of time (each tab's timer fires at the agreed
    instant) and the test waits until both tabs have typed and the server has applied every
    edit: a loaded machine can delay a tab's script by seconds (the earlier version of this test
    checked before the second tab had typed, and failed about 1 run in 3)."""
    other = page.context.new_page()
    other.set_default_timeout(LOAD_TIMEOUT_MS)
    try:
        other.goto(page.url)
        other.get_by_text(re.compile(r"^boxes: \d+$")).wait_for(timeout=LOAD_TIMEOUT_MS)
        a = page.get_by_label("volume ratio", exact=True)
        b = other.get_by_label("volume ratio", exact=True)
        c = live_app.controller

        def quiet() -> bool:
            return c.idle() and live_app.gui.settled() and not live_app.gui._editing()

        for _ in range(600):  # start from a quiet app (no plan or edit still running)
            if quiet():
                break
            page.wait_for_timeout(100)
        skews = []
        for va, vb in (("0.6", "0.95"), ("0.7", "0.85"), ("0.5", "0.9")):
            version = c.state.version
            lead = max(1000.0, 3 * max(_round_trip_ms(page), _round_trip_ms(other)))
            at = page.evaluate("() => Date.now()") + lead
            a.evaluate(f"el => ({TYPED})([el, '{va}', {at}])")
            b.evaluate(f"el => ({TYPED})([el, '{vb}', {at}])")
            fired = [
                p.wait_for_function("() => window.__fired").json_value() for p in (page, other)
            ]
            skews.append(abs(fired[0] - fired[1]))
            page.wait_for_timeout(600)  # both edits reach the server (a tab sends at once)
            for _ in range(600):  # (the version also moves with the animation's clock)
                ratio = c.state.params.decomposition.volume_ratio
                if c.state.version > version and ratio in (float(va), float(vb)) and quiet():
                    break
                page.wait_for_timeout(100)
            used = c.state.params.decomposition.volume_ratio
            assert used in (float(va), float(vb))
            for p, box in ((page, a), (other, b)):
                for _ in range(100):
                    if box.input_value() and float(box.input_value()) == used:
                        break
                    p.wait_for_timeout(100)
                assert float(box.input_value()) == used, (va, vb, used, box.input_value())
            assert c.state.params.decomposition.volume_ratio == used  # no late edit came after
            want = len(c.state.tree.leaves())
            for p in (page, other):
                p.get_by_text(f"boxes: {want}", exact=True).wait_for(timeout=LOAD_TIMEOUT_MS)
        print(f"the two tabs typed {', '.join(f'{x:.0f}' for x in skews)} ms apart")  # noqa: T201
    finally:
        other.close()


def test_open_a_result_file(page, live_app, shots_dir):
    """Upload a pregrasp/1 result file (as `pregrasp plan -o` writes it): the page says what it
    holds and that it has no points, shows its boxes, force-closure line and best epsilon, and
    draws the boxes and the file's best grasp covering at least a fifth of the canvas; the
    status shows (drawn by the server within 2 s of the upload)."""
    from pregrasp_core import pipeline as ppl

    c = live_app.controller
    for _ in range(900):
        if c.idle():
            break
        page.wait_for_timeout(100)
    c.load_demo("mug_handle")  # the object the result is computed from (by the core here)
    res = ppl.run_pipeline(c.state.cloud, c.state.params, c.hand, until="grasps")
    doc = ppl.result_document(res)
    data = json.dumps(doc).encode()

    def name(i: int) -> str:  # each try uploads the file under a name of its own
        return "mug.result.json" if i == 0 else f"mug-{i + 1}.result.json"

    def status(i: int):
        return page.get_by_text(f"{name(i)}: result file of", exact=False)

    what = f"result file ({len(data) / 1e6:.1f} MB) opened"

    def upload(i: int) -> float:
        def shown() -> bool:
            r = live_app.scene.rendered
            return r is not None and r.loaded is not None and r.loaded.name == name(i)

        if i:
            _wait_until(page, c.idle, "the file before loaded")
        watch = _Watch(shown)
        text = _TextWatch(page, "^" + re.escape(f"{name(i)}: result file of"))
        t0 = time.perf_counter()
        page.locator("input[type=file]").first.set_input_files(
            files=[{"name": name(i), "mimeType": "application/json", "buffer": data}]
        )
        status(i).first.wait_for(timeout=LOAD_TIMEOUT_MS)
        t1 = text.painted() or time.perf_counter()
        return _check_shown(page, what, t0, t1, watch)

    last = _shown_within(what, upload) - 1
    assert "holds no points" in status(last).first.inner_text()
    leaves = doc["tree"]["leaves"]
    page.get_by_text(f"boxes: {len(leaves)}", exact=True).wait_for(timeout=LOAD_TIMEOUT_MS)
    assert live_app.scene.box_ids == leaves
    kept, n_fc = doc["grasps"]["n_kept"], doc["grasps"]["n_force_closure"]
    line = page.get_by_text(FC_TEXT)
    line.wait_for(timeout=LOAD_TIMEOUT_MS)
    assert line.inner_text() == f"{n_fc} force-closure of {kept} kept"
    best = doc["grasps"]["items"][doc["best"]]
    assert page.get_by_role("cell", name=f"{best['epsilon']:.4f}").count() >= 1
    for _ in range(300):  # the file's best grasp plays and stops on the closed hand
        s = c.state
        if not s.view.playing and s.view.anim_t == 1.0 and live_app.scene.rendered is s:
            break
        page.wait_for_timeout(100)
    frame = live_app.scene.handle("hand_frame")
    assert frame.visible
    assert abs(frame.position - np.asarray(best["T_world_hand"])[:3, 3]).max() < 1e-9
    page.screenshot(path=str(shots_dir / "browser_result_file.png"))
    fraction = _object_fraction(page, live_app, footprint=True)
    print(f"the result file's boxes span {fraction:.1%} of the canvas")  # noqa: T201
    assert fraction >= 0.2, f"the object covers {fraction:.1%} of the canvas"
    # a threshold edit is answered by a notice, the file stays shown (the edit must differ
    # from the file's value, which an earlier test may have left at 0.5: no change, no notice)
    want = doc["parameters"]["decomposition"]["volume_ratio"]
    box = page.get_by_label("volume ratio", exact=True)
    box.fill("0.6" if want == 0.5 else "0.5")
    box.press("Enter")
    note = page.locator(".mantine-Notification-root", has_text="is a loaded result file")
    note.first.wait_for(timeout=LOAD_TIMEOUT_MS)
    assert c.state.loaded is not None and c.state.result.tree is not None
    for _ in range(100):  # the widget shows the file's value again
        if box.input_value() and float(box.input_value()) == want:
            break
        page.wait_for_timeout(100)
    assert float(box.input_value()) == want
