"""The GUI panels of the inspection app (viser's control panel).

Every callback is one line: it hands the new value to a :class:`~app.controller.Controller`
action through :meth:`Gui._do`, which runs it with error notifications. :meth:`Gui.sync` mirrors
the state into the display elements after every change; values it sets from Python fire their
callbacks synchronously, so a thread-local flag makes those callbacks do nothing (no feedback
loops).
"""

from __future__ import annotations

import dataclasses
import enum
import logging
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from pregrasp_core.io import SCENE_OBSTACLES
from pregrasp_core.limits import MAX_SCALE, MIN_SCALE
from pregrasp_core.paths import demo_depth_images, demo_objects
from pregrasp_core.pipeline import occluded_note
from pregrasp_core.planner.rank import score_text
from pregrasp_core.shape import GRASP_TYPES

from .compare_layer import compare_markdown
from .controller import (
    N_POINTS_RANGE,
    SEED_RANGE,
    SPEED_RANGE,
    UP_AXES,
    Controller,
    intrinsics_text,
    up_label,
)
from .safe_text import md_text
from .scene import SceneRenderer
from .scene_data import (
    UNITS,
    assumed_contacts,
    contact_arrays,
    ghost_selection,
    mask_matrix,
    neighbour_hidden_points,
    ranked_grasps,
    unit_fix,
    unit_label,
)
from .simulate_view import current_lift, lift_markdown, lift_outcomes, outcome_cell
from .state import ALL, AppState, n_splits
from .viser_hooks import add_slider_key_guard, push_value

logger = logging.getLogger(__name__)

DECOMPOSITION_CONTROLS: tuple[tuple[str, str, str, float, float, float], ...] = (
    ("decomposition", "volume_ratio", "volume ratio", 0.01, 0.05, 1.0),
    ("decomposition", "min_points", "min points", 10, 1, 1_000_000),
    ("decomposition", "max_depth", "max depth", 1, 0, 20),
    ("shape", "max_ratio_1d", "1D ratio (s2/s1 <)", 0.01, 0.01, 1.0),
    ("shape", "max_ratio_2d", "2D ratio (s3/s2 <)", 0.01, 0.01, 1.0),
    ("shape", "small_size", "small size (m)", 0.005, 0.0, 1.0),
    ("sampling", "aperture_scale", "aperture scale", 0.05, 0.1, 3.0),
)
"""Threshold controls of the decomposition panel: (``PipelineParams`` section, field, label,
step, min, max). The widget's range is the part of [min, max] that the parameter dataclass
accepts (:func:`accepted_range`): the dataclass's ``__post_init__`` is the one source of bounds."""

POOL_CONTROLS: tuple[tuple[str, str, str, float, float, float], ...] = (
    ("sampling", "interval", "sampling interval (m)", 0.005, 0.005, 0.2),
    ("sampling", "policy", "traversal", 0, 0, 0),
    ("facemask", "clearance", "face clearance (m)", 0.005, 0.0, 0.2),
    ("facemask", "support", "support plane", 0, 0, 0),
)
"""Controls of the pre-grasp panel (booleans become checkboxes, enums dropdowns)."""


def accepted_range(params: Any, name: str, lo: float, hi: float) -> tuple[float, float]:
    """The part of [``lo``, ``hi``] that ``params``' dataclass accepts for field ``name``.

    The bounds live in each parameter dataclass's ``__post_init__`` (a ``ValueError`` past
    them); this finds where they cut [lo, hi] by bisection between the field's current value
    (accepted) and the end that is refused, to a relative 1e-9 (integers: exactly), so that a
    widget never offers a value the server then refuses.
    """
    current = getattr(params, name)
    integer = isinstance(current, (int, np.integer)) and not isinstance(current, bool)

    def ok(v: float) -> bool:
        try:
            dataclasses.replace(params, **{name: int(v) if integer else float(v)})
        except ValueError:
            return False
        return True

    def edge(good: float, bad: float) -> float:
        for _ in range(200):
            if abs(bad - good) <= (1 if integer else 1e-9 * max(abs(good), abs(bad), 1e-12)):
                break
            mid = (good + bad) // 2 if integer else (good + bad) / 2
            good, bad = (mid, bad) if ok(mid) else (good, mid)
        return good

    c = float(current)
    new_lo = lo if ok(lo) else edge(c, lo)
    new_hi = hi if ok(hi) else edge(c, hi)
    return new_lo, new_hi


def _fmt_mask(mask: np.ndarray, blocked_by: list[str] | None = None) -> str:
    """A 6 x 5 face mask as a markdown table (rows: face f with its l, d, r, u neighbours),
    with what blocks each face (node ids, "table" for the support plane) when given."""
    from pregrasp_core.facemask import FACE_NAMES

    rows = ["| face | f | l | d | r | u | blocked by |", "|---|---|---|---|---|---|---|"]
    for f in range(mask.shape[0]):
        cells = " | ".join(str(int(x)) for x in mask[f])
        by = blocked_by[f] if blocked_by is not None else ""
        rows.append(f"| {f} ({FACE_NAMES[f]}) | {cells} | {by} |")
    return "\n".join(rows)


def _blocked_by(masks: Any, node: int) -> list[str]:
    """Per face of ``node``: the ids of the boxes blocking it, and "table" for the support."""
    out = []
    for f in range(6):
        who = [f"node {b}" for b in masks.blockers[node][f]]
        if bool(masks.by_support[node][f]):
            who.append("table")
        out.append(", ".join(who))
    return out


def demo_choices() -> list[Any]:
    """The demo chooser's files: the meshes, then the depth images (``mug_depth``)."""
    return [*demo_objects(), *demo_depth_images()]


def camera_markdown(s: AppState) -> str:
    """The Object panel's line on depth cameras: the intrinsics of the depth image shown, the
    image waiting for its intrinsics, or the camera kept for the next upload."""
    if s.waiting is not None:
        return f"**{md_text(s.waiting.name)} waits for its intrinsics** (type them above)"
    depth = (getattr(s.cloud, "info", None) or {}).get("depth") if s.loaded is None else None
    if depth is not None:
        where = str(depth["intrinsics_from"]).replace("--intrinsics", "the given fx fy cx cy")
        pose = "camera pose applied" if depth["pose"] else "camera frame"
        unit = float(depth["depth_scale"]) * 1000.0
        return md_text(
            f"depth image: {intrinsics_text(depth['intrinsics'])} from {Path(where).name}; "
            f"{pose}; depth unit {unit:g} mm"
        )
    if s.camera is not None:
        return md_text(f"intrinsics for the next depth upload: {intrinsics_text(s.camera)}")
    return ""


class Gui:
    """Builds the panels on ``server.gui`` and keeps them in line with the controller's state."""

    def __init__(self, server: Any, controller: Controller, scene: SceneRenderer) -> None:
        self.server = server
        self.controller = controller
        self.scene = scene
        self._local = threading.local()
        self._synced: AppState | None = None  # the state the panels show (sync runs locked)
        self._fix: tuple[Any, Any, Any] = (None, None, None)  # cloud, scale -> unit_fix
        self._demo_opts: tuple[Any, tuple[str, ...]] = (None, ())  # source -> chooser options
        self._runs: dict[Any, _EditRun] = {}  # control key -> its browser edits in progress
        self._runs_lock = threading.Lock()
        # id(control) -> the browser edit waiting for that control's run in progress (or None)
        self._merged: dict[int, tuple[Any, Callable[..., Any], tuple[Any, ...]] | None] = {}
        self._values_lock = threading.RLock()  # a re-send and a sync of the values never mix
        self._edits: dict[int, list[float]] = {}  # id(handle) -> arrival of edits not yet read
        self._edits_lock = threading.Lock()
        self._edit_seq: dict[int, int] = {}  # id(handle) -> browser edits arrived (both locks)
        self._refusals: dict[int, _Refusal] = {}  # id(handle) -> the refusal to answer (both locks)
        c, gui = controller, server.gui
        gui.configure_theme(control_width="large", dark_mode=False, show_logo=False)
        # docked, not floating: the panel no longer covers the scene, and the canvas beside it
        # is the part a frame must draw (software WebGL's cost is per pixel: docs/app.md)
        gui.main_panel.dock_right()

        with gui.add_folder("Object"):
            names = [p.stem for p in demo_choices()]
            self.demo = gui.add_dropdown("demo object", names or ["(none)"])
            self._supersede = {id(self.demo)}  # merged edits cancel the stale load (_do)
            self.demo.on_update(lambda e: self._do(e, c.load_demo, e.target.value))
            self.upload = gui.add_upload_button(
                "upload cloud / mesh / depth PNG / JSON",
                icon=None,
                hint="a point cloud, a mesh, a depth image (16-bit PNG in millimetres), its "
                "camera file (NAME.json: fx, fy, cx, cy, ...) or a pregrasp/1 result file",
            )
            self.upload.on_upload(lambda e: self._apply(e, self._upload, e.target))
            self.intrinsics = gui.add_text(
                "intrinsics (fx fy cx cy)",
                "",
                hint="a depth image's pinhole intrinsics in pixels, e.g. 525 525 319.5 239.5; "
                "press 'use intrinsics' (the shown depth image is read again with them)",
            )
            self.use_intrinsics = gui.add_button("use intrinsics")
            self.use_intrinsics.on_click(
                lambda e: self._do(e, c.set_intrinsics, self.intrinsics.value)
            )
            self.camera_info = gui.add_markdown("")
            self.compare = gui.add_upload_button("compare with result (JSON)", icon=None)
            self.compare.on_upload(lambda e: self._apply(e, self._compare, e.target))
            self.stop_compare = gui.add_button("stop comparing", visible=False)
            self.stop_compare.on_click(lambda e: self._do(e, c.clear_compare))
            self.n_points = gui.add_number(
                "points", c.state.n_points, min=N_POINTS_RANGE[0], max=N_POINTS_RANGE[1], step=1000
            )
            self.n_points.on_update(
                lambda e: self._coalesced(e, "n_points", c.set_n_points, e.target.value)
            )
            self.seed = gui.add_number(
                "seed", c.state.seed, min=SEED_RANGE[0], max=SEED_RANGE[1], step=1
            )
            self.seed.on_update(lambda e: self._coalesced(e, "seed", c.set_seed, e.target.value))
            self.units = gui.add_dropdown("units", (*UNITS, "custom"), initial_value="auto")
            self.units.on_update(lambda e: self._do(e, self._units, e.target.value))
            self.scale = gui.add_number(
                "scale (x coords)", 1.0, min=MIN_SCALE, max=MAX_SCALE, step=0.001
            )
            self.scale.on_update(lambda e: self._coalesced(e, "scale", c.set_scale, e.target.value))
            self.units_fix = gui.add_button("read as metres", visible=False)
            self.units_fix.on_click(lambda e: self._do(e, c.fix_units))
            self.pick_mode = gui.add_checkbox("click picks the object", False, disabled=True)
            self.flying = gui.add_checkbox("drop flying pixels", False, disabled=True)
            self.flying.on_update(lambda e: self._do(e, c.set_flying_pixels, e.target.value))
            self.obstacles = gui.add_dropdown(
                "scene obstacles", SCENE_OBSTACLES, initial_value=SCENE_OBSTACLES[0], disabled=True
            )
            self.obstacles.on_update(lambda e: self._do(e, c.set_scene_obstacles, e.target.value))
            self.status = gui.add_markdown("")
        server.scene.on_click()(self._scene_click)

        self.params: dict[tuple[str, str], Any] = {}
        """GUI handle of each pipeline parameter, keyed by (section, field)."""
        with gui.add_folder("Decomposition"):
            for spec in DECOMPOSITION_CONTROLS:
                self._add_param(*spec)
            self.level = gui.add_slider("level (splits)", min=0, max=1, step=1, initial_value=1)
            self.level.on_update(lambda e: self._do(e, c.set_level, e.target.value))
            self.boxes = gui.add_markdown("boxes: 0")
            self.node_info = gui.add_markdown("Click a box to see its node.")

        with gui.add_folder("Face masks and pre-grasps"):
            for spec in POOL_CONTROLS:
                self._add_param(*spec)
            self.up = gui.add_dropdown(
                "up (table normal)",
                (*UP_AXES, "custom"),
                initial_value=up_label(c.state.params.facemask.up),
            )
            self.up.on_update(lambda e: self._coalesced(e, "up", self._up_choice, e.target.value))
            self.show_masks = gui.add_checkbox("face masks", c.state.view.show_face_masks)
            self.show_masks.on_update(
                lambda e: self._do(e, c.set_face_masks_visible, e.target.value)
            )
            self.show_ghosts = gui.add_checkbox("hand ghosts", c.state.view.show_ghosts)
            self.show_ghosts.on_update(lambda e: self._do(e, c.set_ghosts_visible, e.target.value))
            self.show_hidden = gui.add_checkbox(
                "hidden space", c.state.view.show_hidden_space, disabled=True
            )
            self.show_hidden.on_update(
                lambda e: self._do(e, c.set_hidden_space_visible, e.target.value)
            )
            self.ghost_type = gui.add_dropdown("grasp type", (ALL, *GRASP_TYPES))
            self.ghost_type.on_update(lambda e: self._do(e, self._ghost_type, e.target.value))
            self.ghost_node = gui.add_dropdown("node", (ALL,))
            self.ghost_node.on_update(lambda e: self._do(e, self._ghost_node, e.target.value))
            self.pool_info = gui.add_markdown("")

        with gui.add_folder("Planner"):
            self.plan = gui.add_button("plan grasps")
            self.plan.on_click(lambda e: self._do(e, c.plan))
            self.progress = gui.add_progress_bar(0.0, visible=False, animated=True)
            self.grasp = gui.add_dropdown("grasp", ("(plan first)",), disabled=True)
            self.grasp.on_update(lambda e: self._do(e, self._grasp, e.target.value))
            self.play = gui.add_button("play")
            self.play.on_click(lambda e: self._do(e, c.play))
            self.pause = gui.add_button("pause")
            self.pause.on_click(lambda e: self._do(e, c.pause))
            self.speed = gui.add_slider(
                "speed", min=SPEED_RANGE[0], max=SPEED_RANGE[1], step=0.1, initial_value=1.0
            )
            self.speed.on_update(lambda e: self._do(e, c.set_speed, e.target.value))
            self.phase = gui.add_slider("phase", min=0.0, max=1.0, step=0.01, initial_value=1.0)
            self.phase.on_update(lambda e: self._do(e, c.set_anim_t, e.target.value))
            self.simulate = gui.add_button("simulate lift", disabled=True)
            self.simulate.on_click(lambda e: self._do(e, c.simulate, e.client))
            self.lift_info = gui.add_markdown("")
            self.table = gui.add_markdown("")
            self.compare_table = gui.add_markdown("")

        with gui.add_folder("Legend", expand_by_default=False):
            self.legend = gui.add_markdown(legend_markdown())

        with gui.add_folder("Export"):
            self.export = gui.add_button("download result (JSON)")
            self.export.on_click(lambda e: self._do(e, c.export_result, e.client))
            self.shot = gui.add_button("screenshot (PNG)")
            self.shot.on_click(lambda e: self._do(e, c.screenshot, e.client))
        add_slider_key_guard(gui)  # arrow keys on the sliders do not also move the camera

        controller.subscribe(self.sync)

    # ------------------------------------------------------------------ callbacks
    def begin_edit(self, handle: Any) -> None:
        """A browser's edit of ``handle`` has arrived and its callback has not run yet (called by
        the update guard of :mod:`app.viser_hooks`): :meth:`sync` leaves that control's value
        alone until the callback has read it (else a state committed meanwhile by another thread
        would put the old value back first and the edit would be lost)."""
        with self._edits_lock:
            self._edits.setdefault(id(handle), []).append(time.monotonic())
            self._edit_seq[id(handle)] = self._edit_seq.get(id(handle), 0) + 1

    def _end_edit(self, event: Any) -> None:
        if getattr(event, "client", None) is None:
            return  # an edit from Python: no browser edit was waiting
        with self._edits_lock:
            marks = self._edits.get(id(getattr(event, "target", None)))
            if marks:
                marks.pop(0)

    def _editing(self) -> set[int]:
        """ids of the controls with a browser edit whose callback has not run (marks older than
        :data:`EDIT_READ_S` are dropped: viser skips the callbacks of a browser gone meanwhile)."""
        with self._edits_lock:
            return self._editing_held()

    def _editing_held(self) -> set[int]:
        """:meth:`_editing`, the caller holding ``_edits_lock``."""
        now = time.monotonic()
        for key in list(self._edits):
            self._edits[key] = [t for t in self._edits[key] if now - t < EDIT_READ_S]
            if not self._edits[key]:
                del self._edits[key]
        return set(self._edits)

    def _set_value(self, key: str, handle: Any, value: Any) -> None:
        """Set ``handle``'s value unless a browser's edit of it waits for its callback, the look
        and the set under ``_edits_lock``: :meth:`begin_edit` runs before viser stores the
        browser's value, so an edit arriving meanwhile is either seen here or stores its value
        after this one. (Looked at first and set later, a commit storm put the old value back
        between the two and lost one toggle in 40 in 2 of 5 runs, 2026-12-07.)"""
        with self._edits_lock:
            if id(handle) not in self._editing_held():
                self._set(key, handle, "value", value)

    def _apply(self, event: Any, fn: Callable[..., Any], *args: Any) -> Any:
        """Run a controller action for a GUI event, unless :meth:`sync` is setting the value;
        then send the control's value in use to every browser (see :meth:`repush`)."""
        if getattr(self._local, "syncing", False):
            return None
        try:
            return self.controller.act(getattr(event, "client", None), fn, *args)
        finally:
            self._end_edit(event)
            if getattr(event, "client", None) is not None:
                self.repush(getattr(event, "target", None))

    def _do(self, event: Any, fn: Callable[..., Any], *args: Any) -> Any:
        """:meth:`_apply` for a browser's edit of a control, where edits of that control arriving
        while one of them runs are merged: the latest wins and runs after it (a value set, a
        button pressed again: the result equals running each in turn). A page flooding one
        control no longer queues its callbacks in front of every other browser's on viser's
        thread pool (2,000 toggles of a checkbox held another browser's edit back 1.9 s; 200
        demo choices or plan presses 5.4-5.7 s; ``tests/app/test_security.py``). Uploads are
        not merged (:meth:`_apply`: each file is its own); pipeline controls coalesce with
        cancelling (:meth:`_coalesced`); a newer choice of the demo object cancels the load
        of the one it replaces (the load it runs next would supersede it anyway)."""
        if getattr(self._local, "syncing", False):
            return None
        if getattr(event, "client", None) is None:
            return self._apply(event, fn, *args)
        key = id(getattr(event, "target", None))
        job: tuple[Any, Callable[..., Any], tuple[Any, ...]] | None = (event, fn, args)
        with self._runs_lock:
            running = key in self._merged
            replaced = self._merged.get(key) if running else None
            self._merged[key] = job if running else None
            if running and key in self._supersede:
                self.controller.cancel()  # the object being loaded is stale: stop it now
        if running:  # the run in progress takes this edit up after its own
            if replaced is not None:
                self._end_edit(replaced[0])  # merged into this newer one: never runs
            return None
        out = None
        try:
            while job is not None:
                ev, f, a = job
                out = self._apply(ev, f, *a)
                with self._runs_lock:
                    job = self._merged[key]
                    if job is None:
                        del self._merged[key]
                    else:
                        self._merged[key] = None
        except BaseException:
            with self._runs_lock:
                self._merged.pop(key, None)
            raise
        return out

    def _upload(self, handle: Any) -> Any:
        value = handle.value
        return self.controller.load_upload(str(value.name), bytes(value.content))

    def _up_choice(self, value: Any) -> Any:
        """An 'up' chosen: an axis re-plans along it; "custom" (a direction given with ``--up``
        that is no axis) keeps the one in use, and the dropdown shows it again."""
        if value != "custom":
            return self.controller.set_up(value)
        label = up_label(self.controller.state.params.facemask.up)
        if label != "custom":
            self._local.syncing = True
            try:
                self.up.value = label
            finally:
                self._local.syncing = False
        return self.controller.state

    def _units(self, value: Any) -> Any:
        if value == "custom":  # keep the factor in use, as typed in the scale field
            return self.controller.set_scale(self.scale.value)
        return self.controller.set_scale(value)

    def _scene_click(self, event: Any) -> None:
        """A click in the 3D scene: with "click picks the object" on, keep the cluster under it."""
        if self.pick_mode.value and not getattr(self._local, "syncing", False):
            self._do(event, self.controller.pick_ray, event.ray_origin, event.ray_direction)

    def _compare(self, handle: Any) -> Any:
        value = handle.value
        return self.controller.compare_result(bytes(value.content), str(value.name))

    def _ghost_type(self, value: Any) -> Any:
        if value not in (ALL, *GRASP_TYPES):
            raise ValueError(f"grasp type must be one of {(ALL, *GRASP_TYPES)}, got {value!r}")
        return self.controller.set_ghost_filter(str(value))

    def _ghost_node(self, value: Any) -> Any:
        return self.controller.set_ghost_filter(None, _node(value))

    def _grasp(self, value: Any) -> Any:
        return self.controller.select_grasp(_rank(value))

    def _add_param(
        self, section: str, name: str, label: str, step: float, lo: float, hi: float
    ) -> None:
        """A control for ``params.<section>.<name>`` whose kind follows the value's type; a
        number's range is what the parameter dataclass accepts within [lo, hi]."""
        sub = getattr(self.controller.state.params, section)
        value = getattr(sub, name)
        gui = self.server.gui
        if isinstance(value, bool):
            h = gui.add_checkbox(label, value)
        elif isinstance(value, enum.Enum):
            h = gui.add_dropdown(
                label, [str(m.value) for m in type(value)], initial_value=str(value.value)
            )
        else:
            lo, hi = accepted_range(sub, name, lo, hi)
            h = gui.add_number(label, value, min=lo, max=hi, step=step)
        h.on_update(self._param_cb(section, name))
        self.params[(section, name)] = h

    def _param_cb(self, section: str, name: str) -> Callable[[Any], Any]:
        c = self.controller
        return lambda e: self._coalesced(
            e, (section, name), c.set_param, section, name, e.target.value
        )

    def _coalesced(self, event: Any, key: Any, fn: Callable[..., Any], *args: Any) -> None:
        """Like :meth:`_do` for a control whose action runs the pipeline (thresholds, points,
        seed, scale): apply at once, coalesce the rest.

        A browser's first edit of the control runs at once. Edits of it arriving while that
        runs (a number input sends every keystroke: typing 500 sends 5, 50 and 500; or another
        browser's edit) are coalesced: the latest replaces any edit still waiting, and the work
        in progress, now stale, is cancelled at its next check (``Controller.cancel``: between
        stages and between planner chunks). When the running edit ends, the waiting one runs,
        so a burst of edits runs the pipeline at most twice and ends with the last value. Once
        no edit of the control has come for :data:`REPUSH_REST_S`, every browser is sent the
        value in use (at once, it would put an older value into the box still being typed
        in). Edits from Python (tests, scripts) have no client and apply at once."""
        if getattr(self._local, "syncing", False):
            return
        client = getattr(event, "client", None)
        if client is None:
            self.controller.act(None, fn, *args)
            return
        target = getattr(event, "target", None)
        job = (client, fn, args)
        with self._runs_lock:
            run = self._runs.get(key)
            start = run is None or not run.active
            if run is not None and not start:  # an edit of it runs: this one waits its end
                run.waiting = job
                self.controller.cancel()  # under the lock: never cancels the job run next
            else:
                run = self._runs.setdefault(key, _EditRun(target))
                run.active = True
                run.rest += 1  # a value to be sent after a rest is sent after this edit
            run.clients.add(getattr(event, "client_id", id(client)))
        self._end_edit(event)  # the edit is now held by its run (sync skips those controls)
        if start:
            self._run_edits(key, job)

    def _run_edits(self, key: Any, job: tuple[Any, Callable[..., Any], tuple[Any, ...]]) -> None:
        """Run ``job`` (client, action, args), then the edit of control ``key`` that arrived
        meanwhile, if any, until none is left; then, after a rest, send the value in use to
        every browser (:meth:`_rested`)."""
        client = job[0]
        next_job: tuple[Any, Callable[..., Any], tuple[Any, ...]] | None = job
        try:
            while True:
                while next_job is not None:
                    client, fn, args = next_job
                    self.controller.act(client, fn, *args)
                    with self._runs_lock:
                        run = self._runs[key]
                        next_job, run.waiting = run.waiting, None
                # what a cancel stopped and no edit took up (e.g. the last edit was refused)
                self.controller.act(client, self.controller.run_pending)
                with self._runs_lock:
                    run = self._runs[key]
                    next_job, run.waiting = run.waiting, None
                    if next_job is None:
                        run.active = False
                        run.timer = threading.Timer(REPUSH_REST_S, self._rested, (key, run.rest))
                        run.timer.daemon = True
                        run.timer.start()
                        break
        except BaseException:
            with self._runs_lock:
                self._runs.pop(key, None)
            raise

    def _shows_value_in_use(self, handle: Any) -> bool:
        """Whether ``handle`` holds its value in use. viser holds the last browser edit and has
        sent it on to the other browsers in order, so when one browser made the edits and the
        last one is in use, every browser shows it already: nothing is sent (a send would reach
        the box being typed in, however long the page lags behind its keystrokes)."""
        with self._values_lock:
            found, v = self._value_in_use(handle)
        return not found or bool(handle.value == v)

    def _rested(self, key: Any, token: int) -> None:
        """No edit of control ``key`` has come for :data:`REPUSH_REST_S` since its last run
        ended: send the value in use to every browser, the editing ones included
        (:meth:`repush`), when several browsers edited it or the value in use is not the last
        edit."""
        with self._runs_lock:
            run = self._runs.get(key)
            if run is None or run.active or run.rest != token:
                return  # a newer edit runs or came: it sends the value when it ends
            del self._runs[key]
            if len(run.clients) == 1 and self._shows_value_in_use(run.target):
                return  # one browser edited it and its last edit is in use: all show it
        self.repush(run.target)

    def settled(self) -> bool:
        """Whether no browser edit of a pipeline or view control runs or waits (tests and
        benchmarks wait for this and ``Controller.idle``)."""
        with self._runs_lock:
            return not self._runs and not self._merged

    def close(self) -> None:
        """Drop the browser edits still waiting (the ones running end by themselves) and the
        values still to be sent after a rest."""
        with self._runs_lock:
            for run in self._runs.values():
                run.waiting = None
                if run.timer is not None:
                    run.timer.cancel()

    def on_bad_value(self, client_id: Any, handle: Any, reason: str) -> None:
        """A browser sent a value the update guard of :mod:`app.viser_hooks` refuses (not of
        the control's type, outside its range): once no newer edit of that control has come
        for :data:`REFUSAL_REST_S`, tell that browser and send the value in use.

        One timer per control at most, re-armed while refusals keep coming: a page that floods
        a control with refused values costs a dictionary entry, not a thread per message
        (20,000 refused values started 3,848 timer threads before)."""
        due = time.monotonic() + REFUSAL_REST_S
        with self._edits_lock:
            seq = self._edit_seq[id(handle)] = self._edit_seq.get(id(handle), 0) + 1
            pending = id(handle) in self._refusals
            self._refusals[id(handle)] = _Refusal(client_id, handle, reason, seq, due)
        if not pending:
            self._arm_refusal(handle, REFUSAL_REST_S)

    def _arm_refusal(self, handle: Any, wait: float) -> None:
        timer = threading.Timer(wait, self._refusal_due, (handle,))
        timer.daemon = True
        timer.start()

    def _refusal_due(self, handle: Any) -> None:
        """The timer of a control's refusals: wait on while newer refusals came, else answer
        the latest one unless an accepted edit of the control came after it."""
        with self._edits_lock:
            r = self._refusals.get(id(handle))
            if r is None:
                return
            wait = r.due - time.monotonic()
            if wait <= 0:
                del self._refusals[id(handle)]
        if r is None:
            return
        if wait > 0:
            self._arm_refusal(handle, wait)
            return
        with self._edits_lock:
            if self._edit_seq.get(id(handle)) != r.seq:
                return  # a newer edit of the control came: a keystroke on the way
        label = getattr(handle, "label", "a control")
        client = self.server.get_clients().get(r.client_id)
        self.controller.notify(
            client, "Cannot do that", f"bad value for {label!r}: {r.reason}", "red"
        )
        self.repush(handle)

    # ------------------------------------------------------------------ mirror the state
    def _set(self, key: str, handle: Any, attr: str, value: Any) -> None:
        """Set ``handle.<attr>`` unless it already holds ``value`` (nothing is resent then)."""
        del key  # names the element in tracebacks only
        if getattr(handle, attr) == value:
            return
        setattr(handle, attr, value)

    def _input_values(self, s: AppState) -> list[tuple[str, Any, Any]]:
        """(name, handle, value) of every input control: the value each one shows for ``s``
        (the values its result was computed with, and its selections)."""
        out: list[tuple[str, Any, Any]] = [
            ("n_points", self.n_points, s.n_points),
            ("seed", self.seed, s.seed),
        ]
        if s.source is not None and s.cloud is not None:
            applied = float((s.cloud.info or {}).get("scale", 1.0) or 1.0)
            out += [
                ("units", self.units, unit_label(s.source.scale)),
                ("scale", self.scale, applied if s.source.scale is None else s.source.scale),
            ]
        for (sec, name), h in self.params.items():
            v = getattr(getattr(s.params, sec), name)
            out.append((f"param.{sec}.{name}", h, v.value if isinstance(v, enum.Enum) else v))
        out.append(("up", self.up, up_label(s.params.facemask.up)))
        out += [
            ("show_masks", self.show_masks, s.view.show_face_masks),
            ("show_ghosts", self.show_ghosts, s.view.show_ghosts),
            ("show_hidden", self.show_hidden, s.view.show_hidden_space),
            ("ghost_type", self.ghost_type, s.view.ghost_type),
            ("phase", self.phase, round(float(min(s.view.anim_t, 1.0)), 2)),
            ("speed", self.speed, float(s.view.speed)),
        ]
        if s.source is not None:
            out.append(("demo", self.demo, s.source.name))
            sensor = s.source.sensor
            out.append(("flying", self.flying, bool(sensor is not None and sensor.flying_pixels)))
            which = SCENE_OBSTACLES[0] if sensor is None else sensor.obstacles
            out.append(("obstacles", self.obstacles, which))
        if s.tree is not None:
            out.append(("level", self.level, s.shown_level))
        gn = ALL if s.view.ghost_node is None else f"node {s.view.ghost_node}"
        out.append(("ghost_node", self.ghost_node, gn))
        k = s.view.selected_grasp
        opts = self.grasp.options
        if s.planned and k is not None and k < len(opts) and opts[k].startswith("#"):
            out.append(("grasp", self.grasp, opts[k]))
        return out

    def repush(self, handle: Any) -> None:
        """Send ``handle``'s value in use to every browser, the one that edited it included.

        viser sends a browser's edit on to the other browsers at once; when two browsers edit
        one control at the same time each may end up showing the other's edit while the result
        was computed with a third value. The value in use is the state's, or the pending one
        while a newer request is being computed.
        """
        if handle is None:
            return
        with self._values_lock:
            found, v = self._value_in_use(handle)
            if not found:
                return
            with self._edits_lock:  # looked at and sent at once (see _set_value)
                if id(handle) in self._editing_held():
                    # a newer edit of it has arrived and its callback has not read it yet:
                    # sending the value in use now would overwrite that edit's value before it
                    # is read (a flood of 2,000 toggles then ended with the masks shown; 1 run
                    # in 5); that edit's own run sends the value in use when it ends
                    return
                push_value(handle, v)

    def _value_in_use(self, handle: Any) -> tuple[bool, Any]:
        """(whether ``handle`` is an input control, the value it shows in use): the state's, or
        the pending one while a newer request is being computed."""
        for key, h, v in self._input_values(self.controller.state):
            if h is handle:
                if key.startswith("param."):
                    sec, name = key.split(".")[1:]
                    v = getattr(getattr(self.controller.pending("params"), sec), name)
                    v = v.value if isinstance(v, enum.Enum) else v
                elif key in ("n_points", "seed"):
                    v = self.controller.pending(key)
                return True, v
        return False, None

    def sync(self, state: AppState) -> None:
        """Mirror ``state`` into the GUI (values set here do not trigger actions).

        A state that differs from the one shown only by its progress (a plan's progress
        reports, 10 to 20 per plan, each on the planner's way) moves the progress bar and
        nothing else, and one that differs only by the animation clock (30 ticks a second
        while the hand plays, often while the next edit computes) moves the phase slider and
        nothing else: the whole mirror took 5 to 8 ms each time on the default object."""
        self._local.syncing = True
        try:
            last = self._synced
            changed = None if last is None else changed_fields(last, state)
            clock = changed == {"view"}
            if changed is not None and changed <= {"progress"}:
                self._set(
                    "progress.value", self.progress, "value", round(100.0 * state.progress, 1)
                )
            elif last is not None and clock and changed_fields(last.view, state.view) <= CLOCK:
                phase = round(float(min(state.view.anim_t, 1.0)), 2)
                self._set_value("phase", self.phase, phase)  # a browser's edit is not lost
            else:
                self._sync(state)
            self._synced = state
        finally:
            self._local.syncing = False

    def _sync(self, s: AppState) -> None:
        busy = bool(s.busy)
        for key, h in (("plan", self.plan), ("export", self.export), ("upload", self.upload)):
            self._set(f"{key}.disabled", h, "disabled", busy or s.result is None)
        fix = None if s.loaded is not None else self._unit_fix(s)
        self._set("units_fix.visible", self.units_fix, "visible", fix is not None)
        if fix is not None:
            self._set("units_fix.label", self.units_fix, "label", fix[1])
        scene = getattr(s.cloud, "sensor", None) is not None
        self._set("pick_mode.disabled", self.pick_mode, "disabled", not scene)
        self._set("flying.disabled", self.flying, "disabled", not scene or s.loaded is not None)
        any_scene = (getattr(s.cloud, "info", None) or {}).get("scene") is not None  # complete too
        self._set(
            "obstacles.disabled", self.obstacles, "disabled", not any_scene or s.loaded is not None
        )
        hidden = getattr(s.result, "occupied", None) is not None  # --occluded occupied views
        hidden = hidden or len(neighbour_hidden_points(s.cloud)) > 0  # behind other objects
        self._set("show_hidden.disabled", self.show_hidden, "disabled", not hidden)
        if s.loaded is not None:  # a result file: nothing to plan or export again
            self._set("plan.disabled", self.plan, "disabled", True)
            self._set("export.disabled", self.export, "disabled", True)
        self._set("compare.disabled", self.compare, "disabled", busy or s.result is None)
        self._set("stop_compare.visible", self.stop_compare, "visible", s.compare is not None)
        self._set("compare_table", self.compare_table, "content", compare_markdown(s))
        self._set("progress.visible", self.progress, "visible", busy)
        self._set("progress.value", self.progress, "value", round(100.0 * s.progress, 1))
        self._set("plan.label", self.plan, "label", "planning..." if busy else "plan grasps")
        text = f"**{md_text(s.error)}**" if s.error else md_text(s.message)
        self._set("status", self.status, "content", text)
        self._set("camera_info", self.camera_info, "content", camera_markdown(s))
        if s.source is not None:
            if self._demo_opts[0] is not s.source:  # the files are listed once per object
                opts = tuple(p.stem for p in demo_choices())
                if s.source.name not in opts:
                    opts = (*opts, s.source.name)
                self._demo_opts = (s.source, opts)
            self._set("demo.options", self.demo, "options", self._demo_opts[1])
        tree = s.tree
        if tree is not None:
            n = n_splits(tree)
            self._set("level.max", self.level, "max", max(n, 1))
            self._set("level.disabled", self.level, "disabled", n == 0)
        pool = getattr(s.result, "pool", None)
        nodes = sorted({int(i) for i in np.asarray(pool.node)}) if pool is not None else []
        self._set(
            "ghost_node.options", self.ghost_node, "options", (ALL, *(f"node {i}" for i in nodes))
        )
        self._sync_grasp_options(s)
        with self._runs_lock:  # a control whose browser edits run or wait keeps the edit shown
            in_run = {id(run.target) for run in self._runs.values()}
        with self._values_lock:
            for key, h, v in self._input_values(s):
                if id(h) not in in_run:
                    self._set_value(key, h, v)
        self._set("boxes", self.boxes, "content", f"boxes: {self.scene.n_boxes}")
        self._set("node_info", self.node_info, "content", node_info(s))
        self._sync_pool(s)
        self._set("table", self.table, "content", grasp_table(s))
        lift = current_lift(s)
        running = lift is not None and lift.running is not None
        no_grasp = not s.planned or s.view.selected_grasp is None
        self._set("simulate.disabled", self.simulate, "disabled", busy or running or no_grasp)
        label = "simulating..." if running else "simulate lift"
        self._set("simulate.label", self.simulate, "label", label)
        self._set("lift_info", self.lift_info, "content", lift_markdown(s))

    def _unit_fix(self, s: AppState) -> Any:
        """``unit_fix`` of the state's cloud and scale, computed once per cloud and scale (it
        measures the cloud's extent: 2.7 ms on 20,000 points)."""
        cloud, scale = s.cloud, getattr(s.source, "scale", None)
        if self._fix[0] is not cloud or self._fix[1] != scale or cloud is None:
            self._fix = (cloud, scale, unit_fix(cloud, scale))
        return self._fix[2]

    def _sync_pool(self, s: AppState) -> None:
        pool = getattr(s.result, "pool", None)
        if pool is None:
            return
        kept = int(ghost_selection(pool, s.view.ghost_type, s.view.ghost_node).sum())
        dropped = getattr(pool, "dropped", {}) or {}
        drops = ", ".join(f"{md_text(k)}: {md_text(v)}" for k, v in dropped.items()) or "none"
        text = (
            f"pool: {len(pool)} pre-grasps, {kept} pass the filters, "
            f"{self.scene.n_ghosts_shown} ghosts drawn; dropped: {drops}"
        )
        occ = getattr(s.result, "occupied", None)
        if occ is not None:  # the hidden space the pool and the planner kept the hand out of
            text += (
                f"\n\nhidden space (occupied): {occ.volume * 1e6:.0f} cm^3, "
                f"{len(occ.points)} obstacle points, {self.scene.n_hidden_points_shown} drawn"
            )
        obstacles = getattr(s.cloud, "obstacles", None)
        if obstacles is not None and len(obstacles):  # the rest of the scene near the object
            behind = len(neighbour_hidden_points(s.cloud))
            text += (
                f"\n\nscene obstacles: {len(obstacles)} points (other objects and walls near the "
                f"object; {behind} of them the space hidden behind the other objects)"
            )
        which = ((getattr(s.cloud, "info", None) or {}).get("scene") or {}).get("obstacles")
        if which == "off":
            text += "\n\nscene obstacles: off (the hand may enter the other objects and walls)"
        view = getattr(s.cloud, "sensor", None) is not None
        if view and s.planned and (note := occluded_note(s.result)):  # which setting planned it
            text += f"\n\n{md_text(note)}"
        self._set("pool_info", self.pool_info, "content", text)

    def _sync_grasp_options(self, s: AppState) -> None:
        ranked = ranked_grasps(s.result) if s.planned else []
        if ranked:
            opts = tuple(grasp_label(k, g) for k, g in enumerate(ranked[:TABLE_ROWS]))
            self._set("grasp.options", self.grasp, "options", opts)
            self._set("grasp.disabled", self.grasp, "disabled", False)
        else:
            self._set("grasp.options", self.grasp, "options", ("(plan first)",))
            self._set("grasp.disabled", self.grasp, "disabled", True)


EDIT_READ_S = 5.0
"""A browser edit whose callback has not run after this long (seconds) no longer holds its
control's value back from :meth:`Gui.sync` (viser drops the callbacks of a closed tab)."""


@dataclasses.dataclass
class _EditRun:
    """The browser edits of one pipeline control in progress (:meth:`Gui._coalesced`)."""

    target: Any
    """The control's handle (its value in use is sent to every browser at the end)."""
    waiting: tuple[Any, Callable[..., Any], tuple[Any, ...]] | None = None
    """The latest edit that arrived while one ran: (client, action, args), run next."""
    active: bool = False
    """Whether an edit of the control runs (else the run waits to send the value in use)."""
    rest: int = 0
    """Counts the chains of edits started: a send after a rest is for the latest one only."""
    timer: threading.Timer | None = None
    """The timer of the send after the last chain's rest."""
    clients: set[Any] = dataclasses.field(default_factory=set)
    """The browsers whose edits of the control ran or waited since the last send."""


@dataclasses.dataclass(frozen=True)
class _Refusal:
    """The latest refused browser value of one control, still to be answered
    (:meth:`Gui.on_bad_value`)."""

    client_id: Any
    handle: Any
    reason: str
    seq: int
    """The control's edit count when it arrived: a later edit (accepted or not) supersedes it."""
    due: float
    """``time.monotonic()`` at which it is answered if nothing newer came."""


REPUSH_REST_S = 0.5
"""Once no edit of a pipeline control has come for this long (seconds) after its last run, the
value in use is sent to every browser when several browsers edited it since the last send or
the value in use is not the last edit (refused, or changed meanwhile) (:meth:`Gui._rested`);
when one browser edited it and its last edit is in use, nothing is sent. Applying an edit
never waits for this. Sending at each run's end put an older value into the box still being typed in
(typing 3000 into ``points`` ended as 300 in Chromium: 30 came back while 300 was typed)."""

REFUSAL_REST_S = 1.0
"""A value the update guard refuses is answered (a notice, the value in use sent back) once no
newer edit of that control has come for this long (seconds): a number typed key by key passes
through refused values (typing 3000 into ``points``, whose minimum is 10, sends 3 first; 0.55
into the volume ratio sends 0), and answering those at once put the old value back into the
box being typed in (typing 3000 ended as "0005000"). Accepted edits never wait."""

TABLE_ROWS = 20
"""Rows of the ranked grasp table and options of the grasp chooser."""


CLOCK = frozenset({"anim_t", "playing"})
"""The fields of ``ViewState`` that the animation clock's ticks change."""


def changed_fields(old: Any, new: Any) -> set[str]:
    """Names of the fields of two states (``AppState`` or ``ViewState``) that are not the same
    object, the version excepted (``dataclasses.replace`` keeps the unchanged ones; a float
    field set to an equal value counts as changed unless it is the same object)."""
    return {
        f.name
        for f in dataclasses.fields(old)
        if f.name != "version" and getattr(old, f.name) is not getattr(new, f.name)
    }


def _node(value: Any) -> int | None:
    """Node id of a node-filter option (``"node 3"``), ``None`` for :data:`ALL`."""
    if value == ALL:
        return None
    parts = str(value).split()
    if len(parts) != 2 or parts[0] != "node" or not parts[1].isdigit():
        raise ValueError(f"node filter must be {ALL!r} or 'node N', got {value!r}")
    return int(parts[1])


def _rank(value: Any) -> int | None:
    """Rank (0 = best) of a grasp-chooser option (``"#2 ..."``), ``None`` for no grasp."""
    text = str(value)
    if not text.startswith("#"):
        return None
    head = text.split()[0][1:]
    if not head.isdigit() or int(head) < 1:
        raise ValueError(f"grasp choice must start with '#N', got {value!r}")
    return int(head) - 1


def is_force_closure(g: Any) -> bool:
    """Whether a grasp is force closure (its Ferrari-Canny epsilon is > 0)."""
    return float(g.epsilon) > 0.0


def grasp_label(k: int, g: Any) -> str:
    """Option text of the grasp chooser: ``#rank type eps``, and ``NOT force closure`` when the
    grasp would not hold the object against every disturbance (epsilon 0)."""
    fc = "" if is_force_closure(g) else " NOT force closure"
    eps = score_text(g.epsilon, getattr(g, "epsilon_exact", True), ".3f")
    return f"#{k + 1} {_type_of(g)} eps {eps}{fc}"


def _type_of(g: Any) -> str:
    t = getattr(g, "grasp_type", "")
    return str(getattr(t, "value", t))


def force_closure_summary(s: AppState) -> str:
    """``N force-closure of M kept`` and the planner's one-line reason for its best grasp
    (``GraspSet.best_reason``: why there is none when no grasp is force closure), markdown."""
    grasps = getattr(s.result, "grasps", None)
    if not s.planned or grasps is None:
        return ""
    ranked = ranked_grasps(s.result)
    n_fc = getattr(grasps, "n_force_closure", None)
    n_fc = sum(is_force_closure(g) for g in ranked) if n_fc is None else int(n_fc)
    line = f"**{n_fc} force-closure of {len(ranked)} kept**"
    reason = getattr(grasps, "best_reason", "")
    if getattr(grasps, "best", 0) is None:
        line += " (no grasp holds the object: the hand shown does NOT hold it)"
    return line + (f"; {md_text(reason)}" if reason else "")


def grasp_table(s: AppState) -> str:
    """The ranked table of the best grasps (markdown): force-closure grasps with their rank,
    then the kept grasps that are not force closure, listed apart."""
    if not s.planned:
        if s.busy == "plan":
            return "Planning the grasps... (the progress bar shows how far)"
        return "Press **plan grasps** to rank the pre-grasps."
    ranked = ranked_grasps(s.result)
    if not ranked:
        return "No grasp survived planning: loosen the thresholds or the pool interval."
    pool = getattr(s.result, "pool", None)
    lifts = lift_outcomes(s)  # a "lift" column once a grasp of this plan was simulated
    header = [
        "| # | type | node | contacts | epsilon | volume | force closure |"
        + (" lift |" if lifts else ""),
        "|---|---|---|---|---|---|---|" + ("---|" if lifts else ""),
    ]

    def row(k: int, g: Any) -> str:
        node = "" if pool is None else int(np.asarray(pool.node)[int(g.pregrasp)])
        fc = "yes" if is_force_closure(g) else "**NO**"
        lift = f" {md_text(outcome_cell(lifts.get(int(g.pregrasp))))} |" if lifts else ""
        n_assumed = int(np.count_nonzero(assumed_contacts(g, s.cloud)))
        n_crest = sum(bool(getattr(c, "crest", False)) for c in g.contacts)
        notes = [f"{n_assumed} assumed"] if n_assumed else []
        notes += [f"{n_crest} at edges"] if n_crest else []  # the crest mean (docs/planner.md)
        contacts = f"{len(contact_arrays(g)[0])}" + (f" ({', '.join(notes)})" if notes else "")
        return (
            f"| {k + 1} | {md_text(_type_of(g))} | {node} | {contacts} | "
            f"{score_text(g.epsilon, getattr(g, 'epsilon_exact', True), '.4f')} | "
            f"{score_text(getattr(g, 'volume', 0.0), getattr(g, 'volume_exact', True), '.2e')} "
            f"| {fc} |{lift}"
        )

    fc_rows = [(k, g) for k, g in enumerate(ranked) if is_force_closure(g)]
    other = [(k, g) for k, g in enumerate(ranked) if not is_force_closure(g)]
    rows = [force_closure_summary(s), ""]
    if fc_rows:
        rows += ["force-closure grasps, best first:", "", *header]
        rows += [row(k, g) for k, g in fc_rows[:TABLE_ROWS]]
    if other:
        shown = other[: max(TABLE_ROWS - min(len(fc_rows), TABLE_ROWS), 5)]
        rows += ["", f"not force closure (epsilon 0, {len(other)} kept):", "", *header]
        rows += [row(k, g) for k, g in shown]
    return "\n".join(rows)


LEGEND = (
    ("part colours", "each box of the decomposition and its points share one colour"),
    ("green faces", "free faces: a hand may approach them"),
    ("red faces", "blocked faces: another part or the table is in front"),
    ("white outlines", "usable sub-faces where pre-grasps are sampled (the rule in use)"),
    ("blue ghosts", "cylindrical pre-grasps"),
    ("orange ghosts", "spherical pre-grasps"),
    ("purple ghosts", "three-finger-tip pre-grasps"),
    ("teal ghosts", "two-finger-tip pre-grasps"),
    ("ghost outline", "palm box (inner face towards the object) and finger chains, thumb apart"),
    ("ghost shade", "brighter or darker by the box face the pre-grasp was sampled from"),
    ("yellow dots", "contacts of the chosen grasp"),
    ("yellow cones", "their friction cones, as scored (half-angle atan mu)"),
    (
        "dark slate points",
        "the unseen back of a single depth view, assumed by symmetry (seen from above, also a "
        "short wall below its outline)",
    ),
    (
        "pale blue points",
        "the space hidden behind a single depth view, kept free of the hand (--occluded "
        "occupied; the boundary of its 3 mm voxels), and behind the scene's other objects "
        "(always: their unseen backs); tick 'hidden space' to show or hide it",
    ),
    ("orange dots and cones", "contacts on assumed (dark) points: the grasp rests on a guess"),
    ("light grey points", "the table of a depth-camera scene (removed from the object)"),
    ("brown points", "other objects of the scene: tick 'click picks the object', click one"),
    ("magenta points", "flying pixels of a depth-camera scene, dropped ('drop flying pixels')"),
)
"""(what, meaning) of each row of the legend panel."""


def legend_markdown() -> str:
    """The legend panel: what every colour of the scene means (markdown, text escaped)."""
    rows = ["| colour | meaning |", "|---|---|"]
    rows += [f"| {md_text(a)} | {md_text(b)} |" for a, b in LEGEND]
    rows += [
        "",
        md_text(
            "epsilon: the Ferrari-Canny quality, the smallest disturbance wrench the grasp "
            "resists per unit of contact force; 0 = not force closure (it does not hold)."
        ),
    ]
    return "\n".join(rows)


def node_info(s: AppState) -> str:
    """Markdown description of the selected node: class, grasp type, volume, points, mask."""
    i = s.view.selected_node
    if i is None or s.tree is None:
        return "Click a box to see its node."
    node = s.tree.node(i)
    shapes = getattr(s.result, "shapes", None)
    sh = shapes[i] if shapes is not None else None
    lines = [
        f"**node {i}** (depth {node.depth}, parent {node.parent}, "
        f"children {list(node.children) or 'none'})",
        "",
        f"- class: {md_text(sh.shape_class.value) if sh is not None else '?'}",
        f"- grasp type: {md_text(sh.grasp_type.value) if sh is not None else '?'}",
        f"- volume: {node.box.volume * 1e6:.1f} cm^3",
        f"- extents: {', '.join(f'{e * 1000:.1f}' for e in node.box.extents)} mm",
        f"- points: {len(node.indices)}",
    ]
    masks = getattr(s.result, "masks", None)
    if masks is not None:
        table = _fmt_mask(mask_matrix(masks, i), _blocked_by(masks, i))
        lines += ["", "face mask (0 free, 1 blocked):", "", table]
    return "\n".join(lines)


__all__ = [
    "Gui",
    "accepted_range",
    "force_closure_summary",
    "grasp_label",
    "grasp_table",
    "is_force_closure",
    "legend_markdown",
    "node_info",
]
