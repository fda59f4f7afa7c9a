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
import functools
import logging
import re
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from pregrasp_core import io as pio
from pregrasp_core import pipeline as ppl
from pregrasp_core.errors import InputError, PregraspError
from pregrasp_core.limits import MAX_SCALE, MIN_SCALE, check_real
from pregrasp_core.paths import demo_depth_images, demo_objects
from pregrasp_core.pregrasps.traversal import no_fit_hint
from pregrasp_core.sensor import CameraFile, Intrinsics
from pregrasp_core.sensor.camera_layouts import LAYOUT_KEYS

from .result_file import ResultFile, looks_like_result, read_result_file
from .scene import SceneRenderer
from .scene_data import (
    kept_cluster,
    parse_scale,
    pickable,
    ranked_grasps,
    ray_pick,
    unit_fix,
)
from .simulate_view import LiftRunner, lift_restart, lift_tick
from .state import ALL, AppState, ObjectSource, ViewState, n_splits

logger = logging.getLogger(__name__)

DEFAULT_MAX_UPLOAD_BYTES = 50 * 1024 * 1024
"""Largest upload accepted (bytes): 50 MiB, about 2 million points of binary PLY."""

N_POINTS_RANGE = (10, 2_000_000)
"""Accepted numbers of points sampled on a mesh (the ``points`` control uses the same range)."""
SEED_RANGE = (0, 2**31 - 1)
"""Accepted sampling seeds (the ``seed`` control uses the same range)."""
SPEED_RANGE = (0.1, 4.0)
"""Accepted animation speeds, cycles per 2 s (the ``speed`` control uses the same range)."""


def loaded_result_notice(loaded: ResultFile, what: str = "change the thresholds") -> str:
    """Why a threshold, a resample or a plan is refused while a result file is shown."""
    return (
        f"{loaded.name} is a loaded result file: it is shown as it was computed, with its "
        f"parameters, and nothing is recomputed. To {what}, open the object it was computed "
        f"from ({loaded.source or 'its input'}) and plan again"
    )


class Superseded(Exception):
    """Raised inside a long action when a newer request has arrived: the newer one runs instead
    (it includes every change the superseded one asked for)."""


class _Replan:
    """The re-plan of a threshold change (:meth:`Controller._rerun`) on a thread of its own,
    started as soon as the stages have run, so that the planner (the planner process's worker,
    on the other core) plans while the controller commits and draws the new scene. Its
    progress reaches the state only after that commit (which resets the progress bar), its
    result or exception is taken by :meth:`result`, and :meth:`cancel` stops it (the pipeline's
    checks of ``gen``, the worker's cancel) and waits for it."""

    def __init__(self, controller: Controller, result: Any, params: Any, gen: int) -> None:
        self._value: Any = None
        self._error: BaseException | None = None
        self._stopped = threading.Event()
        self.shown = shown = threading.Event()
        """Set once the new scene is committed: the re-plan's progress may show from then."""

        def run() -> None:
            try:
                self._value = controller._run(
                    result.cloud, params, previous=result, plan=True, gen=gen, show=True,
                    shown=shown, stopped=self._stopped,
                )  # fmt: skip
            except BaseException as exc:  # noqa: BLE001 - raised again by result()
                self._error = exc

        self._thread = threading.Thread(target=run, name="replan", daemon=True)
        self._thread.start()

    def result(self) -> Any:
        self._thread.join()
        if self._error is not None:
            raise self._error
        return self._value

    def cancel(self) -> None:
        self._stopped.set()
        self._thread.join()


def _number(value: Any, what: str, integer: bool = False) -> float:
    """``value`` as a finite number (an integer when ``integer``), else ``ValueError`` naming
    ``what``; GUI values arrive as whatever a browser sent."""
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        try:
            value = float(str(value))
        except ValueError:
            raise ValueError(f"{what} must be a number, got {value!r}") from None
    v = float(value)
    if not np.isfinite(v):
        raise ValueError(f"{what} must be a finite number, got {value!r}")
    if integer:
        if v != round(v):
            raise ValueError(f"{what} must be a whole number, got {value!r}")
        return int(round(v))
    return v


def _in_range(v: float, lo: float, hi: float, what: str) -> None:
    if not lo <= v <= hi:
        raise ValueError(f"{what} must be in [{lo:g}, {hi:g}], got {v:g}")


UP_AXES: dict[str, tuple[float, float, float]] = {
    "+z": (0.0, 0.0, 1.0),
    "-z": (0.0, 0.0, -1.0),
    "+y": (0.0, 1.0, 0.0),
    "-y": (0.0, -1.0, 0.0),
    "+x": (1.0, 0.0, 0.0),
    "-x": (-1.0, 0.0, 0.0),
}
"""The 'up' directions the viewer offers (the support plane's normal, ``--up``): the file's
axes. Meshes from tools that are Y-up (glTF by its specification, Blender's default OBJ
export, ShapeNet) stand along +y."""


def up_label(up: Any) -> str:
    """The :data:`UP_AXES` key of the direction ``up`` (normalised), or ``"custom"``."""
    u = np.asarray(up, dtype=np.float64)
    u = u / np.linalg.norm(u)
    for key, axis in UP_AXES.items():
        if np.allclose(u, axis, atol=1e-9):
            return key
    return "custom"


def coerce_param(current: Any, value: Any, what: str) -> Any:
    """``value`` (from a GUI control) in the type of the parameter's ``current`` value; the
    parameter dataclass then checks its bounds. ``ValueError`` naming ``what`` when it is not
    of that kind at all."""
    if isinstance(current, bool):
        if not isinstance(value, (bool, np.bool_)):
            raise ValueError(f"{what} must be true or false, got {value!r}")
        return bool(value)
    if isinstance(current, enum.Enum):
        try:
            return type(current)(value)
        except ValueError:
            names = [m.value for m in type(current)]
            raise ValueError(f"{what} must be one of {names}, got {value!r}") from None
    if isinstance(current, (int, np.integer)):
        return _number(value, what, integer=True)
    if isinstance(current, (float, np.floating)):
        return _number(value, what)
    raise ValueError(f"{what} cannot be set from the GUI")


class Controller:
    """Owns the app state; every change goes through one of its methods under its lock.

    server: the ``viser.ViserServer`` (only used for notifications and downloads);
    scene: the :class:`~app.scene.SceneRenderer` that draws each new state;
    hand: the ``pregrasp_core.hand.Hand`` the pipeline uses;
    params: initial ``PipelineParams`` (defaults when ``None``); view: initial display options;
    planner: the :class:`~app.planner_proc.PlannerProcess` that plans (on both cores) in place
    of the in-process ``plan_grasps``, or ``None``.
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
        planner: Any = None,
    ) -> None:
        self.server = server
        self.planner = planner
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
        self._req_lock = threading.Lock()  # guards the two fields below (never held long)
        self._generation = 0  # bumped by every long request: older ones stop at their next stage
        self._pending: dict[str, Any] = {}  # params/n_points/seed asked for, not yet computed
        self._orphaned = False  # the pending changes' computation was cancelled (cancel())
        self._running = 0  # long actions in progress (a plan runs outside the lock)
        self.lift = LiftRunner(self)
        """Runs the "simulate lift" button's MuJoCo lift on a worker thread (app.simulate_view)."""

    # ------------------------------------------------------------------ state
    @property
    def state(self) -> AppState:
        """The current state (immutable; read it freely from any thread)."""
        return self._state

    def idle(self) -> bool:
        """True when no computation runs and none is pending (tests and benchmarks wait on it)."""
        with self._req_lock:  # not the lock: the animation's ticks hold it many times a second
            return not self._pending and self._running == 0 and not self.lift.running

    def subscribe(self, fn: Callable[[AppState], None]) -> None:
        """Call ``fn(state)`` after every state change (the GUI mirrors the state this way)."""
        self._listeners.append(fn)

    def _commit(self, state: AppState, render: bool = True, gen: int | None = None) -> AppState:
        """Replace the state, render it and tell the listeners. Call with the lock held.

        With ``gen`` (the long request that computed ``state``), the state is replaced only if
        no newer request has arrived, and the pending changes it included are dropped in the
        same step, so a request arriving meanwhile builds on the new state.
        """
        with self._req_lock:
            if gen is not None:
                self._check(gen)
                self._pending = {}
                self._orphaned = False
            state = dataclasses.replace(state, version=self._state.version + 1)
            self._state = state
        if render:
            self.scene.render(state)
        for fn in self._listeners:
            fn(state)
        return state

    def update(self, change: Callable[[AppState], AppState]) -> AppState:
        """Commit ``change(state)`` under the lock (nothing when it returns the state itself):
        for helpers that compute outside the lock (``app.simulate_view``)."""
        with self._lock:
            s = self._state
            new = change(s)
            return s if new is s else self._commit(new)

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
            elif isinstance(exc, MemoryError):
                title = "Out of memory"
                body = "the computation needs more memory than this machine has: " + (
                    "use larger thresholds (fewer parts, a coarser sampling interval)"
                )
                logger.warning("MemoryError in an action: %s", exc)
            else:
                title, body = "Internal error", f"{type(exc).__name__}: {exc}"
                logger.exception("callback failed")
            self.notify(client, title, body, color="red")  # at once, even while a run goes on
            with self._lock:
                self._commit(
                    dataclasses.replace(self._state, error=body, busy="", progress=0.0),
                    render=False,
                )
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
    def load_path(
        self, path: str | Path, scale: float | None = None, sensor: Any = None
    ) -> AppState:
        """Load a point cloud, mesh or depth image (coordinates times ``scale`` if given; the
        depth-camera options ``sensor``, a ``pregrasp_core.io.SensorOptions``) and run the
        pipeline up to the pool."""
        p = Path(path)
        demos = [*demo_objects(), *demo_depth_images()]
        demo = p.resolve() in {d.resolve() for d in demos}
        name = p.stem if demo else p.name
        return self._load(ObjectSource(name=name, path=str(p), scale=scale, sensor=sensor))

    def load_demo(self, name: str) -> AppState:
        """Load the demo object ``name`` (file stem or file name in ``assets/objects/``).

        A demo depth image (``mug_depth``: the PNG with its camera file beside it) is read as
        ``pregrasp view`` reads it (the table found and removed, the mug kept, its back
        completed) and planned, as ``pregrasp view`` plans on start. Choosing the object
        already shown (e.g. an uploaded file listed in the chooser) keeps it.
        """
        src = self._state.source
        if src is not None and name == src.name:
            return self._state
        for p in demo_objects():
            if name in (p.stem, p.name):
                return self._load(ObjectSource(name=p.stem, path=str(p)))
        for p in demo_depth_images():
            if name in (p.stem, p.name):
                source = ObjectSource(name=p.stem, path=str(p))
                state = self._load(source)
                if state.source is not source or state.result is None:
                    return state  # superseded by a newer request
                return self.plan()
        names = ", ".join(p.stem for p in [*demo_objects(), *demo_depth_images()])
        raise InputError(f"no demo object named {name!r}; choose one of: {names}")

    def load_upload(self, filename: str, data: bytes) -> AppState:
        """Load an uploaded file (size-limited; parsed by ``pregrasp_core.io`` only).

        A JSON file is a result file, or a depth camera's file (fx, fy, cx, cy, ...: see
        :meth:`set_camera_file`). A depth image (a PNG; an NPY 2-D float array that is not a
        cloud's N x 3 or N x 6 while a camera is given) is read with the camera given in the
        panel; without one it waits for it (:meth:`set_intrinsics`, :meth:`set_camera_file`)
        and a notice says what to enter.
        """
        if len(data) > self.max_upload_bytes:
            raise InputError(
                f"upload {filename!r} is {len(data) / 2**20:.1f} MiB; the limit is "
                f"{self.max_upload_bytes / 2**20:.0f} MiB: subsample the cloud or decimate the "
                "mesh, or run `pregrasp view FILE` on the machine that has the file"
            )
        if not data:
            raise InputError(f"upload {filename!r} is empty: choose a point cloud or mesh file")
        if Path(filename).suffix.lower() == ".json" or looks_like_result(bytes(data[:64])):
            if is_camera_file(bytes(data)):
                return self.set_camera_file(bytes(data), filename)
            return self.load_result(bytes(data), filename)
        source = ObjectSource(name=filename, data=bytes(data))
        camera = self._state.camera
        if is_depth_upload(filename, bytes(data), camera):
            if camera is None:
                return self._wait_for_camera(source)
            return self._load(
                dataclasses.replace(source, sensor=pio.SensorOptions(intrinsics=camera))
            )
        return self._load(source)

    # ------------------------------------------------------------------ depth cameras
    def _wait_for_camera(self, source: ObjectSource) -> AppState:
        """Keep the uploaded depth image ``source`` until its intrinsics are given."""
        msg = (
            f"{source.name} is a depth image and needs its camera's intrinsics: type fx fy cx "
            "cy (pixels) in 'intrinsics (fx fy cx cy)' and press 'use intrinsics', or upload "
            f"its camera file ({Path(source.name).stem}.json: fx, fy, cx, cy; optionally width, "
            "height, T_world_camera, depth_scale). The object shown stays until then"
        )
        with self._lock:
            state = self._commit(
                dataclasses.replace(self._state, waiting=source, message=msg, error=""),
                render=False,
            )
        self.notify(None, "Intrinsics needed", msg, color="yellow")
        return state

    def set_intrinsics(self, value: Any) -> AppState:
        """The intrinsics typed in the panel (``"fx fy cx cy"``, pixels; empty forgets them):
        they read the depth image waiting for them, else the depth image shown again (as
        ``--intrinsics FX FY CX CY``: its camera file's pose, size and depth unit kept), and
        are kept for the next depth image uploaded."""
        K = parse_intrinsics(value)
        with self._lock:
            s = self._state
            if K is None:
                msg = "intrinsics forgotten: a depth image uploaded next waits for its own"
                state = dataclasses.replace(s, camera=None, message=msg, error="")
                return self._commit(state, render=False)
            camera = s.camera.with_intrinsics(K) if isinstance(s.camera, CameraFile) else K
            self._commit(dataclasses.replace(s, camera=camera), render=False)
        return self._use_camera(camera, K)

    def set_camera_file(self, data: bytes, name: str) -> AppState:
        """An uploaded camera file (the sidecar JSON of a depth image: fx, fy, cx, cy, optionally
        width, height, T_world_camera, depth_scale; checked by ``CameraFile.parse``, an error
        names the file and the field): it reads the depth image waiting for it, else the depth
        image shown again (as ``--intrinsics FILE.json``), and is kept for the next upload."""
        camera = CameraFile.parse(bytes(data), name)
        with self._lock:
            self._commit(dataclasses.replace(self._state, camera=camera), render=False)
        return self._use_camera(camera, None)

    def _use_camera(self, camera: Any, typed: Intrinsics | None) -> AppState:
        s = self._state
        if s.waiting is not None:
            return self._load(
                dataclasses.replace(s.waiting, sensor=pio.SensorOptions(intrinsics=camera))
            )
        info = getattr(s.cloud, "info", None) or {}
        if s.source is not None and s.loaded is None and info.get("kind") == "depth":
            base = s.source.sensor if s.source.sensor is not None else pio.SensorOptions()
            if typed is None:
                intr: Any = camera
            elif isinstance(base.intrinsics, CameraFile):
                intr = base.intrinsics.with_intrinsics(typed)
            else:
                intr = typed  # a file on disk: the loader keeps its sidecar's other fields
            return self._load(
                dataclasses.replace(s.source, sensor=dataclasses.replace(base, intrinsics=intr))
            )
        msg = f"intrinsics {intrinsics_text(camera)} kept: the next depth image uploaded uses them"
        with self._lock:
            return self._commit(
                dataclasses.replace(self._state, message=msg, error=""), render=False
            )

    # ------------------------------------------------------------------ result files
    def _read_result(self, data: bytes, name: str) -> ResultFile:
        if len(data) > self.max_upload_bytes:
            raise InputError(
                f"{name} is {len(data) / 2**20:.1f} MiB; the limit for result files is "
                f"{self.max_upload_bytes / 2**20:.0f} MiB"
            )
        return read_result_file(data, name, self.hand)

    def load_result_path(self, path: str | Path) -> AppState:
        """Open a ``pregrasp/1`` result file (``pregrasp plan -o X.json``) from disk."""
        p = Path(path)
        try:
            with p.open("rb") as fh:
                data = fh.read(self.max_upload_bytes + 1)
        except OSError as exc:
            raise InputError(f"{p}: cannot read the result file ({exc.strerror or exc})") from None
        return self.load_result(data, p.name)

    def load_result(self, data: bytes, name: str) -> AppState:
        """Show the result file ``data`` exactly as it holds it (boxes, face masks, pool,
        grasps, best), without recomputing anything (:mod:`app.result_file`). Supersedes a
        computation in progress."""
        loaded = self._read_result(data, name)  # outside the lock: parsing only
        with self._req_lock:
            self._generation += 1
            gen = self._generation
            self._pending = {}
            self._orphaned = False
        res = loaded.result
        n = len(ranked_grasps(res))
        n_parts = 0 if res.tree is None else len(res.tree.leaves())
        best_rank = _best_rank(loaded)
        parts = [
            f"{name}: result file of {loaded.source or 'an unnamed input'} "
            f"({loaded.n_points} points), {n_parts} parts",
            f"pool {0 if res.pool is None else len(res.pool)}",
            f"{n} grasps kept" if loaded.planned else "not planned",
        ]
        note = (
            "the file holds no points: showing its boxes, face masks, pre-grasps, the hand "
            "and its contacts (nothing recomputed)"
        )
        with self._lock:
            s = self._state
            state = dataclasses.replace(
                s,
                source=ObjectSource(name=name),
                params=res.params,
                result=res,
                planned=loaded.planned,
                replanning=False,
                loaded=loaded,
                compare=None,
                view=s.view.for_new_object(
                    selected_grasp=best_rank,
                    anim_t=0.0 if best_rank is not None else 1.0,
                    playing=best_rank is not None,
                ),
                busy="",
                progress=0.0,
                message=", ".join(parts) + "; " + note,
                error="",
            )
            return self._settle(gen, state)

    def compare_result(self, data: bytes, name: str) -> AppState:
        """Draw the best grasps of a second result file of the same object beside the current
        ones (a view: the current result stays as it is)."""
        other = self._read_result(data, name)
        with self._lock:
            s = self._state
            if s.result is None:
                raise InputError("open an object or a result file before comparing")
            mine = s.loaded.source if s.loaded is not None else s.cloud.source
            if Path(str(mine)).name != Path(other.source).name:
                raise InputError(
                    f"{name} is a result of {Path(other.source).name or 'another input'}, not of "
                    f"{Path(str(mine)).name}: compare two results of the same object"
                )
            if not other.planned:
                raise InputError(f"{name} holds no planned grasps to compare with")
            return self._commit(dataclasses.replace(s, compare=other))

    def compare_result_path(self, path: str | Path) -> AppState:
        """:meth:`compare_result` with a file on disk."""
        p = Path(path)
        try:
            data = p.read_bytes()
        except OSError as exc:
            raise InputError(f"{p}: cannot read the result file ({exc.strerror or exc})") from None
        return self.compare_result(data, p.name)

    def clear_compare(self) -> AppState:
        """Stop comparing."""
        with self._lock:
            if self._state.compare is None:
                return self._state
            return self._commit(dataclasses.replace(self._state, compare=None))

    def set_n_points(self, n: Any) -> AppState:
        """Resample the current object with ``n`` points and re-run everything."""
        n = _number(n, "number of points", integer=True)
        _in_range(n, *N_POINTS_RANGE, "number of points")
        return self._request(n_points=int(n))

    def set_seed(self, seed: Any) -> AppState:
        """Resample the current object with another seed and re-run everything."""
        seed = _number(seed, "seed", integer=True)
        _in_range(seed, *SEED_RANGE, "seed")
        return self._request(seed=int(seed))

    def set_scale(self, value: Any) -> AppState:
        """Read the current object again with its coordinates times ``value``: a factor in
        [``MIN_SCALE``, ``MAX_SCALE``] (``pregrasp_core.limits``), a unit (``m``, ``cm``,
        ``mm``) or ``auto`` (the loader's millimetre rule), as ``--scale`` does."""
        scale = parse_scale(value)
        if scale is not None:
            scale = check_real("scale", scale, MIN_SCALE, MAX_SCALE, what="a positive factor")
        src = self._state.source
        if src is None:
            raise InputError("load an object before setting its scale")
        if self._state.loaded is not None:
            raise InputError(loaded_result_notice(self._state.loaded, "change the scale"))
        if scale == src.scale:
            return self._state
        return self._load(dataclasses.replace(src, scale=scale))

    def set_flying_pixels(self, on: Any) -> AppState:
        """Read the current scene again with its flying pixels dropped (``on``) or kept, as
        ``--flying-pixels`` does (``docs/input.md``, "Flying pixels")."""
        if not isinstance(on, (bool, np.bool_)):
            raise ValueError(f"flying pixels: expected true or false, got {on!r}")
        src = self._state.source
        if src is None or getattr(self._state.cloud, "sensor", None) is None:
            raise InputError(
                "flying pixels are dropped from a depth-camera scene (a depth image, a PCD with "
                "a VIEWPOINT, or pregrasp view FILE --scene --viewpoint X Y Z)"
            )
        return self._reload_sensor("drop flying pixels", flying_pixels=bool(on))

    def set_scene_obstacles(self, which: Any) -> AppState:
        """Read the current scene again with ``which`` of its rest as obstacles for the hand
        (``"all"``, ``"seen"`` or ``"off"``, as ``--scene-obstacles``; ``docs/input.md``,
        "The rest of the scene as obstacles")."""
        if which not in pio.SCENE_OBSTACLES:
            raise ValueError(
                f"scene obstacles: expected one of {', '.join(pio.SCENE_OBSTACLES)}, got {which!r}"
            )
        src = self._state.source
        scene = getattr(self._state.cloud, "info", {}).get("scene")
        if src is None or scene is None:
            raise InputError(
                "scene obstacles are the rest of a scene (a depth image, a PCD with a VIEWPOINT, "
                "or pregrasp view FILE --scene)"
            )
        return self._reload_sensor("change the scene obstacles", obstacles=str(which))

    def _reload_sensor(self, action: str, **change: Any) -> AppState:
        """Read the current scene again with the depth-camera options ``change``d (nothing
        when they are already so); ``action`` names it in the notice of a result file, which
        cannot be read again."""
        src = self._state.source
        assert src is not None  # (the callers checked)
        if self._state.loaded is not None:
            raise InputError(loaded_result_notice(self._state.loaded, action))
        base = src.sensor if src.sensor is not None else pio.SensorOptions()
        sensor = dataclasses.replace(base, **change)
        if sensor == base:
            return self._state
        return self._load(dataclasses.replace(src, sensor=sensor))

    def fix_units(self) -> AppState:
        """Apply the fix of the loader's unit hint (:func:`~app.scene_data.unit_fix`): metres
        for a cloud it read as millimetres, millimetres for one it only warned about."""
        fix = unit_fix(self._state.cloud, getattr(self._state.source, "scale", None))
        if fix is None:
            raise InputError("no unit hint to act on: set the scale field instead")
        return self.set_scale(fix[0])

    def pick_ray(self, origin: Any, direction: Any) -> AppState:
        """A click in the scene (a ray from the camera): keep the object cluster under it as the
        object (:meth:`pick_at` at the scene point the ray hits, :func:`~app.scene_data.ray_pick`
        over the clusters above the table)."""
        sensor = getattr(self._state.cloud, "sensor", None)
        if sensor is None:
            raise InputError(
                "picking needs a depth-camera scene (a depth image, a PCD with a VIEWPOINT, or "
                "pregrasp view FILE --scene --viewpoint X Y Z)"
            )
        seg = sensor.segmentation
        i = ray_pick(seg.points, origin, direction, candidates=pickable(sensor))
        if i is None:
            raise InputError("no object of the scene under the click: click one of its points")
        return self.pick_at(seg.points[i])

    def pick_at(self, point: Any) -> AppState:
        """Keep the scene's cluster nearest ``point`` (metres) as the object, as ``--pick X Y Z``
        does, and plan its grasps; the status line and a notification say which cluster."""
        p = np.asarray(point, dtype=np.float64).reshape(-1)
        if p.shape != (3,) or not np.all(np.isfinite(p)):
            raise ValueError(f"pick must be 3 finite numbers, got {point!r}")
        src = self._state.source
        if src is None or getattr(self._state.cloud, "sensor", None) is None:
            raise InputError("picking needs a depth-camera scene loaded")
        base = src.sensor if src.sensor is not None else pio.SensorOptions()
        sensor = dataclasses.replace(base, pick=(float(p[0]), float(p[1]), float(p[2])))
        self._load(dataclasses.replace(src, sensor=sensor))
        sv = getattr(self._state.cloud, "sensor", None)
        if self._state.source is None or self._state.source.sensor != sensor or sv is None:
            return self._state  # superseded by a newer request
        kept = kept_cluster(sv)
        where = ", ".join(f"{v:.3f}" for v in p)
        notice = f"kept the cluster nearest ({where}) m" + (
            ""
            if kept is None
            else f": cluster {kept[0] + 1} of {kept[2]} by size, {kept[1]} points seen"
        )
        self.notify(None, "Object picked", notice)
        self.plan()
        with self._lock:
            return self._commit(
                dataclasses.replace(self._state, message=f"{notice}; {self._state.message}")
            )

    # ------------------------------------------------------------------ long actions
    def pending(self, key: str) -> Any:
        """The value of ``key`` (``params``, ``n_points`` or ``seed``) that the next computation
        uses: the newest one asked for, else the state's."""
        with self._req_lock:
            return self._pending.get(key, getattr(self._state, key))

    def _request(self, **changes: Any) -> AppState:
        """Ask for a computation with ``changes`` on top of the pending ones; it supersedes the
        computation in progress (which stops at its next stage)."""
        loaded = self._state.loaded
        if loaded is not None:
            what = "change the thresholds" if "params" in changes else "resample the points"
            raise InputError(loaded_result_notice(loaded, what))
        with self._req_lock:
            asked = {k: self._pending.get(k, getattr(self._state, k)) for k in changes}
            if asked == changes and not self._orphaned:
                return self._state
            self._pending.update(changes)
            self._orphaned = False  # this request computes every pending change
            self._generation += 1
            gen = self._generation
            rerun = "params" in changes and not ({"n_points", "seed"} & set(self._pending))
        return self._long(gen, self._rerun if rerun else self._reload)

    def cancel(self) -> None:
        """Stop the long action in progress at its next check (between stages and between
        planner chunks) without starting another: a newer edit has made its result stale. The
        pending changes stay; the next request includes them, and :meth:`run_pending` computes
        them when no request follows."""
        with self._req_lock:
            if self._running:
                self._generation += 1
                self._orphaned = bool(self._pending) or self._state.replanning

    def run_pending(self) -> AppState:
        """Compute what :meth:`cancel` stopped and no newer request has taken up: the pending
        changes, and the re-plan of a threshold change (nothing to do otherwise)."""
        with self._req_lock:
            if not (self._orphaned and (self._pending or self._state.replanning)):
                self._orphaned = False
                return self._state
            self._orphaned = False
            self._generation += 1
            gen = self._generation
            rerun = not ({"n_points", "seed"} & set(self._pending))
        return self._long(gen, self._rerun if rerun else self._reload)

    def _long(self, gen: int, fn: Callable[[int], AppState]) -> AppState:
        """Run the long action ``fn(gen)``; a superseded one returns the state as it is, a failed
        one drops the pending changes (the GUI then shows the values in use again)."""
        with self._req_lock:
            self._running += 1
        try:
            return fn(gen)
        except Superseded:
            return self._state
        except BaseException:
            with self._req_lock:
                if self._generation == gen:
                    self._pending = {}
            raise
        finally:
            with self._req_lock:
                self._running -= 1

    def _check(self, gen: int, stopped: threading.Event | None = None) -> None:
        """Raise :class:`Superseded` when a newer long request has arrived (or ``stopped`` is
        set: the request's own thread has given up on it)."""
        if self._generation != gen or (stopped is not None and stopped.is_set()):
            raise Superseded

    def _settle(self, gen: int, state: AppState) -> AppState:
        """Commit the result of long request ``gen`` (lock held); see :meth:`_commit`."""
        return self._commit(state, gen=gen)

    def _reload(self, gen: int) -> AppState:
        if self._state.source is None:
            with self._lock:
                s = self._state
                changes = {k: self.pending(k) for k in ("params", "n_points", "seed")}
                return self._settle(gen, dataclasses.replace(s, **changes))
        return self._load(self._state.source, gen)

    def _read(self, source: ObjectSource, n_points: int, seed: int) -> Any:
        if source.data is not None:
            return pio.load_point_cloud_bytes(
                source.data,
                source.name,
                n_points=n_points,
                seed=seed,
                scale=source.scale,
                max_bytes=self.max_upload_bytes,
                sensor=source.sensor,
            )
        if source.path is None:
            raise InputError(f"{source.name}: nothing to load (no file and no data)")
        return pio.load_point_cloud(
            source.path, n_points=n_points, seed=seed, scale=source.scale, sensor=source.sensor
        )

    def _load(self, source: ObjectSource, gen: int | None = None) -> AppState:
        if gen is None:
            with self._req_lock:
                self._orphaned = False  # the load reads every pending change
                self._generation += 1
                gen = self._generation
        return self._long(gen, lambda g: self._load_now(source, g))

    def _load_now(self, source: ObjectSource, gen: int) -> AppState:
        """Read and run the pipeline outside the lock (other browsers and view actions go on);
        commit under it when no newer request has arrived."""
        with self._lock:
            self._check(gen)
            n_points, seed, params = (self.pending(k) for k in ("n_points", "seed", "params"))
        t0 = time.perf_counter()
        cloud = self._read(source, n_points, seed)
        self._check(gen)
        result = self._run(cloud, params, previous=None, plan=False, gen=gen)
        dt = time.perf_counter() - t0
        tree = result.tree
        msg = (
            f"{source.name}: {len(cloud.points)} points, {len(tree.leaves())} parts, "
            f"pool {len(result.pool) if getattr(result, 'pool', None) is not None else 0} "
            f"({dt * 1000:.0f} ms)"
        )
        warn = list(getattr(cloud, "info", {}).get("warnings", []) or [])
        trav = getattr(result, "traversal", None)
        if trav is not None and not trav.candidates and result.hand is not None:
            # (a mug in inches; or parts whose shape class gives a type that does not fit)
            warn.append(no_fit_hint(tree, result.shapes, result.hand, params.sampling))
        depth = (getattr(cloud, "info", {}) or {}).get("depth")
        if depth is not None:
            where = str(depth["intrinsics_from"]).replace("--intrinsics", "the given fx fy cx cy")
            msg += f"; depth image, intrinsics {intrinsics_text(depth['intrinsics'])} from {where}"
        with self._lock:
            s = self._state
            state = dataclasses.replace(
                s,
                source=source,
                n_points=n_points,
                seed=seed,
                params=params,
                result=result,
                planned=False,
                replanning=False,
                loaded=None,
                compare=None,
                waiting=None,
                view=s.view.for_new_object(),
                busy="",
                progress=0.0,
                message=msg + ("; " + "; ".join(warn) if warn else ""),
                error="",
            )
            return self._settle(gen, state)

    # ------------------------------------------------------------------ thresholds
    def set_param(self, section: str, name: str, value: Any) -> AppState:
        """Set ``params.<section>.<name>`` (e.g. ``decomposition.volume_ratio``) and re-run the
        decomposition and everything downstream (re-planning when grasps were planned).

        The value is checked by the parameter dataclass (its ``__post_init__`` holds the bounds,
        the one source of them); a request superseded by a newer one returns the state as is.
        """
        base = self.pending("params")
        sub = getattr(base, section)
        value = coerce_param(getattr(sub, name), value, f"{section}.{name}")
        new_sub = dataclasses.replace(sub, **{name: value})  # validates (ValueError)
        params = dataclasses.replace(base, **{section: new_sub})
        return self._request(params=params)

    def set_up(self, value: Any) -> AppState:
        """Set the 'up' direction (``params.facemask.up``, the support plane's normal, as
        ``--up``) to one of the file's axes (:data:`UP_AXES`: ``"+y"`` for a Y-up mesh) and
        re-run everything downstream; ``"custom"`` keeps the direction in use (one given with
        ``--up`` that is not an axis)."""
        if value == "custom":
            return self._state
        if value not in UP_AXES:
            raise ValueError(f"up must be one of {', '.join(UP_AXES)}, got {value!r}")
        base = self.pending("params")
        facemask = dataclasses.replace(base.facemask, up=UP_AXES[value])
        return self._request(params=dataclasses.replace(base, facemask=facemask))

    def _rerun(self, gen: int) -> AppState:
        """Re-run the stages downstream of a threshold change outside the lock and commit the
        new scene (boxes, masks, pool) under it; when grasps were planned, re-plan (the
        progress bar shows it) and commit the new grasps. The re-plan starts before the new
        scene is committed and drawn (:class:`_Replan`: with the planner process, the worker
        plans while this thread draws). Each commit builds on the state as it is then, unless a
        newer request has arrived (it then includes this change)."""
        with self._lock:
            self._check(gen)
            s = self._state
            params = self.pending("params")
            if s.result is None:
                return self._settle(gen, dataclasses.replace(s, params=params))
            if s.loaded is not None:
                raise InputError(loaded_result_notice(s.loaded))
        replan = s.planned or s.replanning  # a re-plan this edit cancelled: plan again
        t0 = time.perf_counter()
        result = self._run(s.result.cloud, params, previous=s.result, plan=False, gen=gen)
        dt = time.perf_counter() - t0
        msg = f"{len(result.tree.leaves())} parts, pool {len(result.pool)} ({dt * 1000:.0f} ms)"
        t1 = time.perf_counter()
        plan = _Replan(self, result, params, gen) if replan else None
        try:
            state = self._show_rerun(gen, s, result, params, plan, msg)
        except BaseException:
            if plan is not None:  # superseded or failed: the plan stops at its next check
                plan.cancel()
            raise
        if plan is None:
            return state
        planned = plan.result()
        n = len(ranked_grasps(planned))
        with self._lock:
            self._check(gen)
            now = self._state
            if now.result is not result:
                raise Superseded
            view = dataclasses.replace(
                now.view, selected_grasp=0 if n else None, anim_t=0.0, playing=bool(n)
            )
            return self._settle(
                gen,
                dataclasses.replace(
                    now,
                    result=planned,
                    planned=True,
                    replanning=False,
                    view=view,
                    busy="",
                    progress=0.0,
                    message=f"{msg}; planned again: {n} grasps kept "
                    f"({time.perf_counter() - t1:.1f} s)"
                    + (f"; {note}" if (note := ppl.occluded_note(planned)) else ""),
                    error="",
                ),
            )

    def _show_rerun(
        self, gen: int, s: AppState, result: Any, params: Any, plan: _Replan | None, msg: str
    ) -> AppState:
        """Commit (and draw) the new scene of :meth:`_rerun`'s stages (``result``, computed from
        the state ``s``); ``plan``: the re-plan that runs meanwhile, or None."""
        replan = plan is not None
        with self._lock:
            self._check(gen)
            now = self._state
            if now.result is not s.result:  # another object or result was opened meanwhile
                raise Superseded
            view = now.view
            if result.tree is not s.result.tree:
                view = dataclasses.replace(view, level=None, selected_node=None, ghost_node=None)
            if replan or result is not s.result:
                view = dataclasses.replace(view, selected_grasp=None, playing=False)
            state = self._settle(
                gen,
                dataclasses.replace(
                    now,
                    params=params,
                    result=result,
                    planned=False,
                    replanning=replan,
                    view=view,
                    busy="plan" if replan else "",
                    progress=0.0,
                    message=msg + ("; planning the grasps again" if replan else ""),
                    error="",
                ),
            )
        if plan is not None:
            plan.shown.set()  # the re-plan's progress bar may move from here on
        return state

    # ------------------------------------------------------------------ view
    def _set_view(self, **changes: Any) -> AppState:
        with self._lock:
            s = self._state
            view = dataclasses.replace(s.view, **changes)
            if view == s.view:
                return s
            return self._commit(dataclasses.replace(s, view=view))

    def set_level(self, level: Any) -> AppState:
        """Show the boxes after ``level`` accepted splits (``None`` = the leaves)."""
        with self._lock:  # the check and the change see the same tree
            tree = self._state.tree
            if level is not None and tree is not None:
                n = n_splits(tree)
                k = int(_number(level, "level", integer=True))
                if not 0 <= k <= n:
                    raise ValueError(f"level must be in [0, {n}], got {level}")
                level = None if k == n else k
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

    def set_hidden_space_visible(self, visible: bool) -> AppState:
        """Show or hide the hidden space of an ``--occluded occupied`` view (no re-plan)."""
        return self._set_view(show_hidden_space=bool(visible))

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
        """Run the slicing planner on the pool; ranks the grasps and selects the best. A newer
        request (a threshold change, a new object) cancels it after its current chunk."""
        with self._req_lock:
            self._generation += 1
            gen = self._generation
        return self._long(gen, self._plan_now)

    def _plan_now(self, gen: int) -> AppState:
        """Plan outside the lock (view actions and other browsers go on meanwhile; progress and
        the result are committed under it, on top of the state as it is then)."""
        with self._lock:
            self._check(gen)
            s = self._state
            if s.result is None:
                raise InputError("load an object before planning")
            if s.loaded is not None:
                raise InputError(loaded_result_notice(s.loaded, "plan"))
            params = self.pending("params")
            self._commit(dataclasses.replace(s, busy="plan", progress=0.0), render=False)
        t0 = time.perf_counter()
        try:
            result = self._run(
                s.result.cloud, params, previous=s.result, plan=True, gen=gen, show=True
            )
        except BaseException:
            with self._lock:
                if self._generation == gen:  # a newer run keeps its own progress bar
                    self._commit(
                        dataclasses.replace(self._state, busy="", progress=0.0), render=False
                    )
            raise
        dt = time.perf_counter() - t0
        n = len(ranked_grasps(result))
        with self._lock:
            if self._state.result is not s.result or self._generation != gen:
                # the object or the thresholds changed meanwhile: this plan is stale
                self._commit(dataclasses.replace(self._state, busy="", progress=0.0), render=False)
                raise Superseded
            view = dataclasses.replace(
                self._state.view, selected_grasp=0 if n else None, anim_t=0.0, playing=bool(n)
            )
            msg = f"planned {len(result.pool)} pre-grasps: {n} grasps kept ({dt:.1f} s)"
            if note := ppl.occluded_note(result):
                msg += f"; {note}"
            new = dataclasses.replace(
                self._state,
                params=params,
                result=result,
                planned=True,
                replanning=False,
                view=view,
                busy="",
                progress=0.0,
                message=msg,
                error="",
            )
            try:
                return self._settle(gen, new)
            except Superseded:
                self._commit(dataclasses.replace(self._state, busy="", progress=0.0), render=False)
                raise

    def _progress(
        self, check: Callable[[], None], show: bool, shown: threading.Event | None = None
    ) -> Callable[[float], None]:
        """The pipeline's progress callback of a request: ``check()`` (raises when it is
        superseded) and, when ``show``, publishes the fraction done (the GUI's progress bar;
        with ``shown``, only once it is set)."""

        def progress(fraction: float) -> None:
            check()
            if show and (shown is None or shown.is_set()):
                with self._lock:
                    self._commit(
                        dataclasses.replace(self._state, progress=float(np.clip(fraction, 0, 1))),
                        render=False,
                    )

        return progress

    def select_grasp(self, rank: int | None) -> AppState:
        """Show the grasp of rank ``rank`` (0 = best): the URDF hand plays its approach and
        closing once, from the pre-grasp pose in its preshape to the closed configuration."""
        with self._lock:
            if rank is not None:
                n = len(ranked_grasps(self._state.result))
                if not 0 <= int(rank) < n:
                    raise ValueError(f"grasp rank must be in [0, {n - 1}], got {rank}")
                rank = int(rank)
            return self._set_view(
                selected_grasp=rank, anim_t=0.0, playing=rank is not None, show_lift=False
            )

    def set_anim_t(self, t: Any) -> AppState:
        """Set the animation phase (0 pre-grasp, 0.5 approached, 1 closed); pauses it."""
        t = float(np.clip(_number(t, "phase"), 0.0, 1.0))
        return self._set_view(anim_t=t, playing=False, show_lift=False)

    def play(self) -> AppState:
        """Start the animation (from the pre-grasp if it was at the end)."""
        with self._lock:
            lift = lift_restart(self._state)  # a shown simulated lift plays instead
            if lift is not None:
                return self._set_view(**lift)
            t = self._state.view.anim_t
            return self._set_view(playing=True, anim_t=0.0 if t >= 1.0 else t)

    def pause(self) -> AppState:
        """Stop the animation where it is."""
        return self._set_view(playing=False)

    def set_speed(self, speed: Any) -> AppState:
        """Animation speed (1 = one cycle per 2 s)."""
        v = _number(speed, "speed")
        _in_range(v, *SPEED_RANGE, "speed")
        return self._set_view(speed=v)

    def tick(self, dt: float) -> AppState:
        """Advance the animation clock by ``dt`` seconds when playing (called by the animator);
        it stops on the closed hand (phase 1)."""
        with self._lock:
            v = self._state.view
            if not v.playing or v.selected_grasp is None:
                return self._state
            lift = lift_tick(self._state, dt)  # a shown simulated lift: real time x speed
            if lift is not None:
                return self._set_view(**lift)
            t = v.anim_t + dt * v.speed / 2.0
            return self._set_view(anim_t=min(t, 1.0), playing=t < 1.0)

    def simulate(self, client: Any = None) -> AppState:
        """Simulate the chosen grasp's lift in MuJoCo on a worker thread (outside the lock) and
        play it; the outcome goes to the panel and the grasp table (``app.simulate_view``)."""
        return self.lift.start(client)

    # ------------------------------------------------------------------ export
    def result_json(self) -> bytes:
        """The ``pregrasp/1`` result document of the current state, as UTF-8 JSON."""
        s = self._state
        if s.result is None:
            raise InputError("nothing to export: load an object first")
        if s.loaded is not None:
            raise InputError(
                f"{s.loaded.name} is a result file already: it is exported as it is (no points "
                "to write a new one from)"
            )
        doc = ppl.result_document(s.result, s.params)
        import json

        return json.dumps(doc, indent=1).encode("utf-8")

    def _download_stem(self) -> str:
        """File stem of downloads: the object's name with anything but letters, digits, ``.``,
        ``_`` and ``-`` replaced by ``_`` (an uploaded name may hold anything)."""
        src = self._state.source
        stem = Path(src.name).stem if src is not None else "pregrasp"
        return re.sub(r"[^A-Za-z0-9._-]", "_", stem)[:100] or "pregrasp"

    def export_result(self, client: Any) -> None:
        """Send the result file to ``client`` as a download."""
        data = self.result_json()
        name = self._download_stem() + ".pregrasp.json"
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
        name = self._download_stem() + ".png"
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
        gen: int,
        show: bool = False,
        shown: threading.Event | None = None,
        stopped: threading.Event | None = None,
    ) -> Any:
        """One call into ``pregrasp_core.pipeline`` (the app has no pipeline of its own); it
        stops between stages (and between planner chunks) when request ``gen`` is superseded.
        The core refuses work past its limits (``WorkLimitError``, ``docs/limits.md``). With a
        planner process, the grasps stage plans there (cancelled as soon as ``gen`` is stale).
        ``shown``: progress is published only once it is set; ``stopped``: once set, the run
        stops as if superseded."""
        planner = None
        check = functools.partial(self._check, gen, stopped)
        if plan and self.planner is not None:
            planner = functools.partial(self.planner.plan, check=check)
        result = ppl.run_pipeline(
            cloud,
            params,
            self.hand,
            until="grasps" if plan else "pool",
            previous=previous,
            progress=self._progress(check, show, shown),
            planner=planner,
        )
        check()
        return result


CAMERA_FILE_KEYS = (
    frozenset(("fx", "fy", "cx", "cy", "width", "height", "T_world_camera", "depth_scale"))
    | LAYOUT_KEYS
)
"""Keys that make an uploaded JSON object a depth camera's file rather than a result file
(pregrasp's, and those of the layouts other tools write: ``sensor/camera_layouts.py``)."""

MAX_INTRINSICS_CHARS = 200
"""Longest text accepted in the intrinsics field."""


def is_camera_file(data: bytes) -> bool:
    """Whether the uploaded JSON ``data`` is a depth camera's file: an object with a camera key
    (fx, fy, cx, cy, width, height, T_world_camera, depth_scale) and no ``schema`` (a result
    file's); its fields are checked when it is read (``CameraFile.parse``)."""
    import json

    if len(data) > 1 << 20:
        return False
    try:
        doc = json.loads(data.decode("utf-8"))
    except (UnicodeDecodeError, ValueError, RecursionError):
        return False
    return isinstance(doc, dict) and "schema" not in doc and bool(CAMERA_FILE_KEYS & set(doc))


def is_depth_upload(filename: str, data: bytes, camera: Any) -> bool:
    """Whether an upload is a depth image: a PNG always; an NPY when a camera is given and its
    header declares a 2-D float array that is not a cloud's (N x 3 or N x 6 columns)."""
    ext = Path(filename).suffix.lower()
    if ext in pio.DEPTH_IMAGE_EXTENSIONS:
        return True
    if ext != ".npy" or camera is None:
        return False
    import io

    fh = io.BytesIO(data)
    try:
        version = np.lib.format.read_magic(fh)
        if version == (1, 0):
            shape, _, dtype = np.lib.format.read_array_header_1_0(fh)
        else:
            shape, _, dtype = np.lib.format.read_array_header_2_0(fh)
    except Exception:  # noqa: BLE001 - not a readable NPY: the loader says why
        return False
    return len(shape) == 2 and shape[1] not in (3, 6) and np.dtype(dtype).kind == "f"


def parse_intrinsics(value: Any) -> Intrinsics | None:
    """``"fx fy cx cy"`` (pixels; spaces or commas) as ``Intrinsics``; None for an empty text;
    ``ValueError`` naming the value at fault otherwise."""
    text = str(value).strip()
    if len(text) > MAX_INTRINSICS_CHARS:
        raise ValueError(f"intrinsics: at most {MAX_INTRINSICS_CHARS} characters")
    if not text:
        return None
    parts = text.replace(",", " ").split()
    if len(parts) != 4:
        raise ValueError(
            f"intrinsics: give four numbers fx fy cx cy (pixels), got {len(parts)}: {text!r}"
        )
    vals = []
    for name, part in zip(("fx", "fy", "cx", "cy"), parts, strict=True):
        try:
            v = float(part)
        except ValueError:
            raise ValueError(f"intrinsics: {name} must be a number, got {part!r}") from None
        vals.append(v)
    return Intrinsics(*vals)  # finite, fx and fy positive (InputError naming them)


def intrinsics_text(camera: Any) -> str:
    """``fx 420 fy 420 cx 239.5 cy 179.5`` of an ``Intrinsics``, a ``CameraFile`` or a dict."""
    if isinstance(camera, CameraFile):
        camera = camera.intrinsics
    d = camera.to_dict() if isinstance(camera, Intrinsics) else dict(camera)
    return " ".join(f"{k} {float(d[k]):.10g}" for k in ("fx", "fy", "cx", "cy"))


def _best_rank(loaded: ResultFile) -> int | None:
    """Rank (0 = first of the ranking) of the file's ``best`` grasp, else of its first ranked
    grasp, or ``None`` when it has none."""
    gs = loaded.result.grasps
    if gs is None or len(gs.ranking) == 0:
        return None
    if loaded.best is None:
        return 0
    hits = np.flatnonzero(np.asarray(gs.ranking) == loaded.best)
    return int(hits[0]) if len(hits) else 0


__all__ = [
    "ALL",
    "Controller",
    "DEFAULT_MAX_UPLOAD_BYTES",
    "N_POINTS_RANGE",
    "SEED_RANGE",
    "SPEED_RANGE",
    "Superseded",
    "coerce_param",
    "intrinsics_text",
    "is_camera_file",
    "up_label",
    "is_depth_upload",
    "loaded_result_notice",
    "parse_intrinsics",
]
