"""The controller: the only code that changes the app's state.

It receives the server (it never creates one), owns one lock (viser runs callbacks on a thread
pool), calls the pure core (``pregrasp_core.io`` and ``pregrasp_core.pipeline``), replaces the
:class:`~app.state.AppState` as a whole and asks the scene to render it. Every public action is a
method; the GUI calls them through :meth:`Controller.act`, which turns any exception into a
notification to the browser that caused it, so the server keeps running.
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

from pregrasp_core import io as pio
from pregrasp_core import pipeline as ppl
from pregrasp_core.errors import InputError, PregraspError
from pregrasp_core.paths import demo_objects

from .scene import SceneRenderer, ranked_grasps
from .state import ALL, AppState, ObjectSource, ViewState, n_splits

logger = logging.getLogger(__name__)

DEFAULT_MAX_UPLOAD_BYTES = 50 * 1024 * 1024
"""Largest upload accepted (bytes): 50 MiB, about 2 million points of binary PLY."""


class Controller:
    """Owns the app state; every change goes through one of its methods under its lock.

    server: the ``viser.ViserServer`` (only used for notifications and downloads);
    scene: the :class:`~app.scene.SceneRenderer` that draws each new state;
    hand: the ``pregrasp_core.hand.Hand`` the pipeline uses;
    params: initial ``PipelineParams`` (defaults when ``None``); view: initial display options.
    """

    def __init__(
        self,
        server: Any,
        scene: SceneRenderer,
        hand: Any,
        params: Any = None,
        n_points: int = 20000,
        seed: int = 0,
        max_upload_bytes: int = DEFAULT_MAX_UPLOAD_BYTES,
        view: ViewState | None = None,
    ) -> None:
        self.server = server
        self.scene = scene
        self.hand = hand
        self.max_upload_bytes = int(max_upload_bytes)
        self._lock = threading.RLock()
        self._state = AppState(
            n_points=int(n_points),
            seed=int(seed),
            params=params if params is not None else ppl.PipelineParams(),
            view=view if view is not None else ViewState(),
        )
        self._listeners: list[Callable[[AppState], None]] = []

    # ------------------------------------------------------------------ state
    @property
    def state(self) -> AppState:
        """The current state (immutable; read it freely from any thread)."""
        return self._state

    def subscribe(self, fn: Callable[[AppState], None]) -> None:
        """Call ``fn(state)`` after every state change (the GUI mirrors the state this way)."""
        self._listeners.append(fn)

    def _commit(self, state: AppState, render: bool = True) -> AppState:
        """Replace the state, render it and tell the listeners. Call with the lock held."""
        state = dataclasses.replace(state, version=self._state.version + 1)
        self._state = state
        if render:
            self.scene.render(state)
        for fn in self._listeners:
            fn(state)
        return state

    def act(self, client: Any, fn: Callable[..., Any], *args: Any) -> Any:
        """Run ``fn(*args)``; on failure notify ``client`` (or every browser) and keep serving.

        A ``PregraspError`` is the user's problem (bad file, impossible threshold) and is shown
        as it is; anything else is logged with its traceback and shown as an internal error.
        """
        try:
            return fn(*args)
        except Exception as exc:  # noqa: BLE001 - a callback must never kill the server
            if isinstance(exc, (PregraspError, ValueError)):
                title, body = "Cannot do that", str(exc)
                logger.warning("%s", exc)
            else:
                title, body = "Internal error", f"{type(exc).__name__}: {exc}"
                logger.exception("callback failed")
            with self._lock:
                self._commit(
                    dataclasses.replace(self._state, error=body, busy="", progress=0.0),
                    render=False,
                )
            self.notify(client, title, body, color="red")
            return None

    def notify(self, client: Any, title: str, body: str, color: str = "blue") -> None:
        """Show a notification in ``client``'s browser (all browsers when ``client`` is None)."""
        clients = [client] if client is not None else list(self.server.get_clients().values())
        for c in clients:
            try:
                c.add_notification(title, body, auto_close_seconds=8.0, color=color)
            except Exception:  # noqa: BLE001 - a closed tab must not break the action
                logger.debug("could not notify client", exc_info=True)

    # ------------------------------------------------------------------ loading
    def load_path(self, path: str | Path) -> AppState:
        """Load a point cloud or mesh file and run the pipeline up to the pool."""
        p = Path(path)
        demo = p.resolve() in {d.resolve() for d in demo_objects()}
        return self._load(ObjectSource(name=p.stem if demo else p.name, path=str(p)))

    def load_demo(self, name: str) -> AppState:
        """Load the demo object ``name`` (file stem or file name in ``assets/objects/``).

        Choosing the object already shown (e.g. an uploaded file listed in the chooser) keeps it.
        """
        src = self._state.source
        if src is not None and name == src.name:
            return self._state
        for p in demo_objects():
            if name in (p.stem, p.name):
                return self._load(ObjectSource(name=p.stem, path=str(p)))
        names = ", ".join(p.stem for p in demo_objects())
        raise InputError(f"no demo object named {name!r}; choose one of: {names}")

    def load_upload(self, filename: str, data: bytes) -> AppState:
        """Load an uploaded file (size-limited; parsed by ``pregrasp_core.io`` only)."""
        if len(data) > self.max_upload_bytes:
            raise InputError(
                f"upload {filename!r} is {len(data) / 2**20:.1f} MiB; the limit is "
                f"{self.max_upload_bytes / 2**20:.0f} MiB: subsample the cloud or decimate the "
                "mesh, or run `pregrasp view FILE` on the machine that has the file"
            )
        if not data:
            raise InputError(f"upload {filename!r} is empty: choose a point cloud or mesh file")
        return self._load(ObjectSource(name=filename, data=bytes(data)))

    def set_n_points(self, n: int) -> AppState:
        """Resample the current object with ``n`` points and re-run everything."""
        n = int(n)
        if n < 10:
            raise ValueError(f"number of points must be at least 10, got {n}")
        with self._lock:
            self._state = dataclasses.replace(self._state, n_points=n)
            return self._reload()

    def set_seed(self, seed: int) -> AppState:
        """Resample the current object with another seed and re-run everything."""
        seed = int(seed)
        if seed < 0:
            raise ValueError(f"seed must be >= 0, got {seed}")
        with self._lock:
            self._state = dataclasses.replace(self._state, seed=seed)
            return self._reload()

    def _reload(self) -> AppState:
        if self._state.source is None:
            return self._state
        return self._load(self._state.source)

    def _read(self, source: ObjectSource, n_points: int, seed: int) -> Any:
        if source.data is not None:
            return pio.load_point_cloud_bytes(
                source.data,
                source.name,
                n_points=n_points,
                seed=seed,
                max_bytes=self.max_upload_bytes,
            )
        return pio.load_point_cloud(source.path, n_points=n_points, seed=seed)

    def _load(self, source: ObjectSource) -> AppState:
        with self._lock:
            s = self._state
            t0 = time.perf_counter()
            cloud = self._read(source, s.n_points, s.seed)
            result = self._run(cloud, s.params, previous=None, plan=False)
            dt = time.perf_counter() - t0
            tree = result.tree
            msg = (
                f"{source.name}: {len(cloud.points)} points, {len(tree.leaves())} parts, "
                f"pool {len(result.pool) if getattr(result, 'pool', None) is not None else 0} "
                f"({dt * 1000:.0f} ms)"
            )
            warn = list(getattr(cloud, "info", {}).get("warnings", []) or [])
            state = dataclasses.replace(
                s,
                source=source,
                result=result,
                planned=False,
                view=ViewState(
                    show_face_masks=s.view.show_face_masks,
                    show_ghosts=s.view.show_ghosts,
                    speed=s.view.speed,
                ),
                message=msg + ("; " + "; ".join(warn) if warn else ""),
                error="",
            )
            return self._commit(state)

    # ------------------------------------------------------------------ thresholds
    def set_param(self, section: str, name: str, value: Any) -> AppState:
        """Set ``params.<section>.<name>`` (e.g. ``decomposition.volume_ratio``) and re-run the
        decomposition and everything downstream (re-planning when grasps were planned)."""
        with self._lock:
            s = self._state
            sub = getattr(s.params, section)
            current = getattr(sub, name)
            if isinstance(current, bool):
                value = bool(value)
            elif isinstance(current, enum.Enum):
                value = type(current)(value)
            elif isinstance(current, int):
                value = int(round(float(value)))
            elif isinstance(current, float):
                value = float(value)
            if current == value:
                return s
            new_sub = dataclasses.replace(sub, **{name: value})  # validates (ValueError)
            params = dataclasses.replace(s.params, **{section: new_sub})
            return self._rerun(params)

    def _rerun(self, params: Any) -> AppState:
        s = self._state
        if s.result is None:
            return self._commit(dataclasses.replace(s, params=params))
        t0 = time.perf_counter()
        result = self._run(s.result.cloud, params, previous=s.result, plan=s.planned)
        dt = time.perf_counter() - t0
        view = s.view
        new_tree = result.tree is not s.result.tree
        if new_tree:
            view = dataclasses.replace(view, level=None, selected_node=None, ghost_node=None)
        if result is not s.result:
            view = dataclasses.replace(view, selected_grasp=0 if s.planned else None)
        msg = f"{len(result.tree.leaves())} parts, pool {len(result.pool)} ({dt * 1000:.0f} ms)"
        return self._commit(
            dataclasses.replace(s, params=params, result=result, view=view, message=msg, error="")
        )

    # ------------------------------------------------------------------ view
    def _set_view(self, **changes: Any) -> AppState:
        with self._lock:
            s = self._state
            view = dataclasses.replace(s.view, **changes)
            if view == s.view:
                return s
            return self._commit(dataclasses.replace(s, view=view))

    def set_level(self, level: int | None) -> AppState:
        """Show the boxes after ``level`` accepted splits (``None`` = the leaves)."""
        with self._lock:  # the check and the change see the same tree
            tree = self._state.tree
            if level is not None and tree is not None:
                n = n_splits(tree)
                if not 0 <= int(level) <= n:
                    raise ValueError(f"level must be in [0, {n}], got {level}")
                level = None if int(level) == n else int(level)
            return self._set_view(level=level)

    def select_node(self, node: int | None) -> AppState:
        """Select node ``node`` (as a click on its box does) or clear the selection."""
        with self._lock:
            tree = self._state.tree
            if node is not None:
                if tree is None or not 0 <= int(node) < len(tree.nodes):
                    raise ValueError(f"no node {node} in the current tree")
                node = int(node)
            return self._set_view(selected_node=node)

    def set_face_masks_visible(self, visible: bool) -> AppState:
        """Show or hide the face masks."""
        return self._set_view(show_face_masks=bool(visible))

    def set_ghosts_visible(self, visible: bool) -> AppState:
        """Show or hide the pre-grasp ghosts."""
        return self._set_view(show_ghosts=bool(visible))

    def set_ghost_filter(self, grasp_type: str | None = None, node: Any = "keep") -> AppState:
        """Filter the ghosts by grasp type (:data:`ALL` for all) and/or node (``None`` = all)."""
        changes: dict[str, Any] = {}
        if grasp_type is not None:
            changes["ghost_type"] = str(grasp_type)
        if node != "keep":
            changes["ghost_node"] = None if node is None else int(node)
        return self._set_view(**changes)

    # ------------------------------------------------------------------ planner
    def plan(self) -> AppState:
        """Run the slicing planner on the pool; ranks the grasps and selects the best."""
        with self._lock:
            s = self._state
            if s.result is None:
                raise InputError("load an object before planning")
            self._commit(dataclasses.replace(s, busy="plan", progress=0.0), render=False)
            t0 = time.perf_counter()
            try:
                result = self._run(
                    s.result.cloud,
                    s.params,
                    previous=s.result,
                    plan=True,
                    progress=self._progress,
                )
            finally:
                self._state = dataclasses.replace(self._state, busy="", progress=0.0)
            dt = time.perf_counter() - t0
            n = len(ranked_grasps(result))
            view = dataclasses.replace(
                self._state.view, selected_grasp=0 if n else None, anim_t=0.0, playing=bool(n)
            )
            msg = f"planned {len(result.pool)} pre-grasps: {n} grasps ({dt:.1f} s)"
            return self._commit(
                dataclasses.replace(
                    self._state, result=result, planned=True, view=view, message=msg, error=""
                )
            )

    def _progress(self, fraction: float) -> None:
        self._commit(
            dataclasses.replace(self._state, progress=float(np.clip(fraction, 0, 1))),
            render=False,
        )

    def select_grasp(self, rank: int | None) -> AppState:
        """Show the grasp of rank ``rank`` (0 = best): the URDF hand plays its approach and
        closing once, from the pre-grasp pose in its preshape to the closed configuration."""
        with self._lock:
            if rank is not None:
                n = len(ranked_grasps(self._state.result))
                if not 0 <= int(rank) < n:
                    raise ValueError(f"grasp rank must be in [0, {n - 1}], got {rank}")
                rank = int(rank)
            return self._set_view(selected_grasp=rank, anim_t=0.0, playing=rank is not None)

    def set_anim_t(self, t: float) -> AppState:
        """Set the animation phase (0 pre-grasp, 0.5 approached, 1 closed); pauses it."""
        return self._set_view(anim_t=float(np.clip(t, 0.0, 1.0)), playing=False)

    def play(self) -> AppState:
        """Start the animation (from the pre-grasp if it was at the end)."""
        with self._lock:
            t = self._state.view.anim_t
            return self._set_view(playing=True, anim_t=0.0 if t >= 1.0 else t)

    def pause(self) -> AppState:
        """Stop the animation where it is."""
        return self._set_view(playing=False)

    def set_speed(self, speed: float) -> AppState:
        """Animation speed (1 = one cycle per 2 s)."""
        speed = float(speed)
        if not 0 < speed <= 10:
            raise ValueError(f"speed must be in (0, 10], got {speed}")
        return self._set_view(speed=speed)

    def tick(self, dt: float) -> AppState:
        """Advance the animation clock by ``dt`` seconds when playing (called by the animator);
        it stops on the closed hand (phase 1)."""
        with self._lock:
            v = self._state.view
            if not v.playing or v.selected_grasp is None:
                return self._state
            t = v.anim_t + dt * v.speed / 2.0
            return self._set_view(anim_t=min(t, 1.0), playing=t < 1.0)

    # ------------------------------------------------------------------ export
    def result_json(self) -> bytes:
        """The ``pregrasp/1`` result document of the current state, as UTF-8 JSON."""
        s = self._state
        if s.result is None:
            raise InputError("nothing to export: load an object first")
        doc = ppl.result_document(s.result, s.params)
        import json

        return json.dumps(doc, indent=1).encode("utf-8")

    def export_result(self, client: Any) -> None:
        """Send the result file to ``client`` as a download."""
        data = self.result_json()
        name = Path(self._state.source.name).stem + ".pregrasp.json"
        target = client if client is not None else self.server
        target.send_file_download(name, data, save_immediately=True)

    def screenshot(self, client: Any) -> None:
        """Render ``client``'s current view at its canvas size; send it back as a PNG download."""
        if client is None:
            raise InputError("a screenshot needs a browser: open the app and press the button")
        import imageio.v3 as iio

        cam = client.camera
        height, width = max(int(cam.image_height), 64), max(int(cam.image_width), 64)
        img = client.get_render(height=height, width=width, transport_format="png", timeout=30)
        name = Path(self._state.source.name).stem + ".png"
        client.send_file_download(
            name, iio.imwrite("<bytes>", img, extension=".png"), save_immediately=True
        )

    # ------------------------------------------------------------------ the core
    def _run(
        self,
        cloud: Any,
        params: Any,
        previous: Any,
        plan: bool,
        progress: Callable[[float], None] | None = None,
    ) -> Any:
        """One call into ``pregrasp_core.pipeline`` (the app has no pipeline of its own)."""
        return ppl.run_pipeline(
            cloud,
            params,
            self.hand,
            until="grasps" if plan else "pool",
            previous=previous,
            progress=progress,
        )


__all__ = ["ALL", "Controller", "DEFAULT_MAX_UPLOAD_BYTES"]
