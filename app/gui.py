"""The GUI panels of the inspection app (viser's control panel).

Every callback is one line: it hands the new value to a :class:`~app.controller.Controller`
action through :meth:`Gui._do`, which runs it with error notifications. :meth:`Gui.sync` mirrors
the state into the display elements after every change; values it sets from Python fire their
callbacks synchronously, so a thread-local flag makes those callbacks do nothing (no feedback
loops).
"""

from __future__ import annotations

import enum
import threading
from collections.abc import Callable
from typing import Any

import numpy as np

from pregrasp_core.paths import demo_objects
from pregrasp_core.shape import GRASP_TYPES

from .controller import Controller
from .scene import SceneRenderer, contact_arrays, ghost_selection, ranked_grasps
from .state import ALL, AppState, n_splits

"""Options of the grasp-type filter (besides ``all``)."""

DECOMPOSITION_CONTROLS: tuple[tuple[str, str, str, float, float, float], ...] = (
    ("decomposition", "volume_ratio", "volume ratio", 0.01, 0.05, 1.0),
    ("decomposition", "min_points", "min points", 10, 3, 1_000_000),
    ("decomposition", "max_depth", "max depth", 1, 0, 20),
    ("shape", "max_ratio_1d", "1D ratio (s2/s1 <)", 0.01, 0.01, 1.0),
    ("shape", "max_ratio_2d", "2D ratio (s3/s2 <)", 0.01, 0.01, 1.0),
    ("shape", "small_size", "small size (m)", 0.005, 0.0, 1.0),
    ("sampling", "aperture_scale", "aperture scale", 0.05, 0.1, 3.0),
)
"""Threshold controls of the decomposition panel: (``PipelineParams`` section, field, label,
step, min, max)."""

POOL_CONTROLS: tuple[tuple[str, str, str, float, float, float], ...] = (
    ("sampling", "interval", "sampling interval (m)", 0.005, 0.005, 0.2),
    ("sampling", "policy", "traversal", 0, 0, 0),
    ("facemask", "clearance", "face clearance (m)", 0.005, 0.0, 0.2),
    ("facemask", "support", "support plane", 0, 0, 0),
)
"""Controls of the pre-grasp panel (booleans become checkboxes, enums dropdowns)."""


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


class Gui:
    """Builds the panels on ``server.gui`` and keeps them in line with the controller's state."""

    def __init__(self, server: Any, controller: Controller, scene: SceneRenderer) -> None:
        self.server = server
        self.controller = controller
        self.scene = scene
        self._local = threading.local()
        self._timers: dict[Any, threading.Timer] = {}  # pending debounced edit per control
        self._timers_lock = threading.Lock()
        c, gui = controller, server.gui
        gui.configure_theme(control_width="large", dark_mode=False, show_logo=False)

        with gui.add_folder("Object"):
            names = [p.stem for p in demo_objects()]
            self.demo = gui.add_dropdown("demo object", names or ["(none)"])
            self.demo.on_update(lambda e: self._do(e, c.load_demo, e.target.value))
            self.upload = gui.add_upload_button("upload cloud / mesh", icon=None)
            self.upload.on_upload(lambda e: self._do(e, c.load_upload, *_upload(e.target)))
            self.n_points = gui.add_number(
                "points", c.state.n_points, min=10, max=2_000_000, step=1000
            )
            self.n_points.on_update(
                lambda e: self._debounced(e, "n_points", c.set_n_points, e.target.value)
            )
            self.seed = gui.add_number("seed", c.state.seed, min=0, max=2**31 - 1, step=1)
            self.seed.on_update(lambda e: self._debounced(e, "seed", c.set_seed, e.target.value))
            self.status = gui.add_markdown("")

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
            self.show_masks = gui.add_checkbox("face masks", c.state.view.show_face_masks)
            self.show_masks.on_update(
                lambda e: self._do(e, c.set_face_masks_visible, e.target.value)
            )
            self.show_ghosts = gui.add_checkbox("hand ghosts", c.state.view.show_ghosts)
            self.show_ghosts.on_update(lambda e: self._do(e, c.set_ghosts_visible, e.target.value))
            self.ghost_type = gui.add_dropdown("grasp type", (ALL, *GRASP_TYPES))
            self.ghost_type.on_update(lambda e: self._do(e, c.set_ghost_filter, e.target.value))
            self.ghost_node = gui.add_dropdown("node", (ALL,))
            self.ghost_node.on_update(
                lambda e: self._do(e, c.set_ghost_filter, None, _node(e.target.value))
            )
            self.pool_info = gui.add_markdown("")

        with gui.add_folder("Planner"):
            self.plan = gui.add_button("plan grasps")
            self.plan.on_click(lambda e: self._do(e, c.plan))
            self.progress = gui.add_progress_bar(0.0, visible=False, animated=True)
            self.grasp = gui.add_dropdown("grasp", ("(plan first)",), disabled=True)
            self.grasp.on_update(lambda e: self._do(e, c.select_grasp, _rank(e.target.value)))
            self.play = gui.add_button("play")
            self.play.on_click(lambda e: self._do(e, c.play))
            self.pause = gui.add_button("pause")
            self.pause.on_click(lambda e: self._do(e, c.pause))
            self.speed = gui.add_slider("speed", min=0.1, max=4.0, step=0.1, initial_value=1.0)
            self.speed.on_update(lambda e: self._do(e, c.set_speed, e.target.value))
            self.phase = gui.add_slider("phase", min=0.0, max=1.0, step=0.01, initial_value=1.0)
            self.phase.on_update(lambda e: self._do(e, c.set_anim_t, e.target.value))
            self.table = gui.add_markdown("")

        with gui.add_folder("Export"):
            self.export = gui.add_button("download result (JSON)")
            self.export.on_click(lambda e: self._do(e, c.export_result, e.client))
            self.shot = gui.add_button("screenshot (PNG)")
            self.shot.on_click(lambda e: self._do(e, c.screenshot, e.client))

        controller.subscribe(self.sync)

    # ------------------------------------------------------------------ callbacks
    def _do(self, event: Any, fn: Callable[..., Any], *args: Any) -> Any:
        """Run a controller action for a GUI event, unless :meth:`sync` is setting the value."""
        if getattr(self._local, "syncing", False):
            return None
        return self.controller.act(getattr(event, "client", None), fn, *args)

    def _add_param(
        self, section: str, name: str, label: str, step: float, lo: float, hi: float
    ) -> None:
        """A control for ``params.<section>.<name>`` whose kind follows the value's type."""
        value = getattr(getattr(self.controller.state.params, section), name)
        gui = self.server.gui
        if isinstance(value, bool):
            h = gui.add_checkbox(label, value)
        elif isinstance(value, enum.Enum):
            h = gui.add_dropdown(
                label, [str(m.value) for m in type(value)], initial_value=str(value.value)
            )
        else:
            h = gui.add_number(label, value, min=lo, max=hi, step=step)
        h.on_update(self._param_cb(section, name))
        self.params[(section, name)] = h

    def _param_cb(self, section: str, name: str) -> Callable[[Any], Any]:
        c = self.controller
        return lambda e: self._debounced(
            e, (section, name), c.set_param, section, name, e.target.value
        )

    def _debounced(self, event: Any, key: Any, fn: Callable[..., Any], *args: Any) -> None:
        """Like :meth:`_do`, but a browser's edits of one control are applied only once they
        have rested for :data:`PARAM_DEBOUNCE_S` (a number input sends every keystroke: typing
        500 would otherwise run the pipeline for 5, 50 and 500). Edits from Python (tests,
        scripts) have no client and apply at once."""
        if getattr(self._local, "syncing", False):
            return
        client = getattr(event, "client", None)
        if client is None:
            self.controller.act(None, fn, *args)
            return
        timer = threading.Timer(PARAM_DEBOUNCE_S, self.controller.act, args=(client, fn, *args))
        timer.daemon = True
        with self._timers_lock:
            old = self._timers.pop(key, None)
            if old is not None:
                old.cancel()
            self._timers[key] = timer
            timer.start()

    def close(self) -> None:
        """Cancel the pending debounced edits."""
        with self._timers_lock:
            for t in self._timers.values():
                t.cancel()
            self._timers.clear()

    # ------------------------------------------------------------------ mirror the state
    def _set(self, key: str, handle: Any, attr: str, value: Any) -> None:
        """Set ``handle.<attr>`` unless it already holds ``value`` (nothing is resent then)."""
        del key  # names the element in tracebacks only
        if getattr(handle, attr) == value:
            return
        setattr(handle, attr, value)

    def sync(self, state: AppState) -> None:
        """Mirror ``state`` into the GUI (values set here do not trigger actions)."""
        self._local.syncing = True
        try:
            self._sync(state)
        finally:
            self._local.syncing = False

    def _sync(self, s: AppState) -> None:
        busy = bool(s.busy)
        for key, h in (("plan", self.plan), ("export", self.export), ("upload", self.upload)):
            self._set(f"{key}.disabled", h, "disabled", busy or s.result is None)
        self._set("progress.visible", self.progress, "visible", busy)
        self._set("progress.value", self.progress, "value", round(100.0 * s.progress, 1))
        self._set("plan.label", self.plan, "label", "planning..." if busy else "plan grasps")
        text = f"**{s.error}**" if s.error else s.message
        self._set("status", self.status, "content", text)
        self._set("n_points", self.n_points, "value", s.n_points)
        self._set("seed", self.seed, "value", s.seed)
        if s.source is not None:
            opts = tuple(p.stem for p in demo_objects())
            if s.source.name not in opts:
                opts = (*opts, s.source.name)
            self._set("demo.options", self.demo, "options", opts)
            self._set("demo", self.demo, "value", s.source.name)
        for (sec, name), h in self.params.items():
            v = getattr(getattr(s.params, sec), name)
            self._set(f"param.{sec}.{name}", h, "value", v.value if isinstance(v, enum.Enum) else v)
        tree = s.tree
        if tree is not None:
            n = n_splits(tree)
            self._set("level.max", self.level, "max", max(n, 1))
            self._set("level.disabled", self.level, "disabled", n == 0)
            self._set("level", self.level, "value", s.shown_level)
        self._set("boxes", self.boxes, "content", f"boxes: {self.scene.n_boxes}")
        self._set("node_info", self.node_info, "content", node_info(s))
        self._sync_pool(s)
        self._sync_grasps(s)

    def _sync_pool(self, s: AppState) -> None:
        pool = getattr(s.result, "pool", None)
        self._set("show_masks", self.show_masks, "value", s.view.show_face_masks)
        self._set("show_ghosts", self.show_ghosts, "value", s.view.show_ghosts)
        self._set("ghost_type", self.ghost_type, "value", s.view.ghost_type)
        nodes = sorted({int(i) for i in np.asarray(pool.node)}) if pool is not None else []
        self._set(
            "ghost_node.options", self.ghost_node, "options", (ALL, *(f"node {i}" for i in nodes))
        )
        gn = ALL if s.view.ghost_node is None else f"node {s.view.ghost_node}"
        self._set("ghost_node", self.ghost_node, "value", gn)
        if pool is None:
            return
        kept = int(ghost_selection(pool, s.view.ghost_type, s.view.ghost_node).sum())
        dropped = getattr(pool, "dropped", {}) or {}
        drops = ", ".join(f"{k}: {v}" for k, v in dropped.items()) or "none"
        self._set(
            "pool_info",
            self.pool_info,
            "content",
            f"pool: {len(pool)} pre-grasps, {kept} pass the filters, "
            f"{self.scene.n_ghosts_shown} ghosts drawn; dropped: {drops}",
        )

    def _sync_grasps(self, s: AppState) -> None:
        ranked = ranked_grasps(s.result) if s.planned else []
        if ranked:
            opts = tuple(grasp_label(k, g) for k, g in enumerate(ranked[:TABLE_ROWS]))
            self._set("grasp.options", self.grasp, "options", opts)
            k = s.view.selected_grasp
            if k is not None and k < len(opts):
                self._set("grasp", self.grasp, "value", opts[k])
            self._set("grasp.disabled", self.grasp, "disabled", False)
        else:
            self._set("grasp.options", self.grasp, "options", ("(plan first)",))
            self._set("grasp.disabled", self.grasp, "disabled", True)
        self._set("table", self.table, "content", grasp_table(s))
        self._set("phase", self.phase, "value", round(float(min(s.view.anim_t, 1.0)), 2))
        self._set("speed", self.speed, "value", float(s.view.speed))


PARAM_DEBOUNCE_S = 0.3
"""A browser's edit of a number (thresholds, points, seed) is applied once the control has
rested this long (seconds)."""

TABLE_ROWS = 20
"""Rows of the ranked grasp table and options of the grasp chooser."""


def _upload(handle: Any) -> tuple[str, bytes]:
    return handle.value.name, handle.value.content


def _node(value: str) -> int | None:
    return None if value == ALL else int(value.split()[-1])


def _rank(value: str) -> int | None:
    return int(value.split()[0].lstrip("#")) - 1 if value.startswith("#") else None


def grasp_label(k: int, g: Any) -> str:
    """Option text of the grasp chooser: ``#rank type eps``."""
    return f"#{k + 1} {_type_of(g)} eps {float(g.epsilon):.3f}"


def _type_of(g: Any) -> str:
    t = getattr(g, "grasp_type", "")
    return str(getattr(t, "value", t))


def grasp_table(s: AppState) -> str:
    """The ranked table of the best grasps (markdown)."""
    if not s.planned:
        return "Press **plan grasps** to rank the pre-grasps."
    ranked = ranked_grasps(s.result)
    if not ranked:
        return "No grasp survived planning: loosen the thresholds or the pool interval."
    rows = [
        f"ranked grasps: {len(ranked)}",
        "",
        "| # | type | node | contacts | epsilon | volume |",
        "|---|---|---|---|---|---|",
    ]
    pool = getattr(s.result, "pool", None)
    for k, g in enumerate(ranked[:TABLE_ROWS]):
        node = "" if pool is None else int(np.asarray(pool.node)[int(g.pregrasp)])
        rows.append(
            f"| {k + 1} | {_type_of(g)} | {node} | {len(contact_arrays(g)[0])} | "
            f"{float(g.epsilon):.4f} | {float(getattr(g, 'volume', 0.0)):.2e} |"
        )
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
        f"- class: {sh.shape_class.value if sh is not None else '?'}",
        f"- grasp type: {sh.grasp_type.value if sh is not None else '?'}",
        f"- volume: {node.box.volume * 1e6:.1f} cm^3",
        f"- extents: {', '.join(f'{e * 1000:.1f}' for e in node.box.extents)} mm",
        f"- points: {len(node.indices)}",
    ]
    masks = getattr(s.result, "masks", None)
    if masks is not None:
        from .scene import _mask_matrix

        table = _fmt_mask(_mask_matrix(masks, i), _blocked_by(masks, i))
        lines += ["", "face mask (0 free, 1 blocked):", "", table]
    return "\n".join(lines)


__all__ = ["Gui", "grasp_table", "node_info"]
