"""The viewer's "simulate lift" button: the MuJoCo lift of the chosen grasp, played in the scene.

:class:`LiftRunner` runs the lift test (``pregrasp_core.simulate``, ``docs/simulation.md``) of
the grasp chosen in the Planner panel on a worker thread, outside the controller's lock, so
other browsers and actions go on meanwhile; the compiled scene of the object (its collision
model, the slow part) is kept for the next press on the same object. The outcome and the
recorded frames go into the state as a :class:`LiftView` (``AppState.lift``); the animation
clock (``ViewState.lift_t``, advanced by the app's animator at real time times the speed
slider) picks the frame the scene shows: the cloud posed by the object's simulated motion and
the URDF hand at the simulated base pose and joints. The pure functions here are what the
controller, the scene and the GUI read (:func:`lift_frame`, :func:`lift_markdown`, ...).
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any

import numpy as np

from pregrasp_core.errors import InputError

from .safe_text import md_text
from .scene_data import attr_or_none, ranked_grasps, selected_grasp
from .state import AppState

logger = logging.getLogger(__name__)

LIFT_FPS = 15.0
"""Frames recorded per simulated second: the browser gets at most this many pose updates per
second of playback (light for software WebGL), smooth enough for a 10 cm lift."""


@dataclass(frozen=True, eq=False)
class LiftPlayback:
    """One simulated lift, recorded for playback (compared by identity)."""

    pregrasp: int
    """Pool index of the simulated grasp (``Grasp.pregrasp``)."""
    rank: int
    """Its rank in the table when it was simulated (0 = best)."""
    outcome: Any
    """The ``pregrasp_core.simulate.SimulationResult``."""
    times: np.ndarray
    """(F,) seconds of simulated time of each frame, from 0."""
    T_world_hand: np.ndarray
    """(F, 4, 4) the palm's pose per frame."""
    q: np.ndarray
    """(F, J) the hand's joints per frame (``Hand.joint_names``)."""
    T_world_object: np.ndarray
    """(F, 4, 4) per frame: maps a cloud point (as loaded) to where the object has it now."""
    model: str
    """Where the collision model came from: ``"mesh"`` or ``"cloud"``."""
    n_pieces: int
    """Convex pieces of the collision model."""
    mass: float
    """kg, the object's simulated mass."""
    build_cpu: float
    """CPU seconds (this thread) of building the object's scene; 0 when it was reused."""
    run_cpu: float
    """CPU seconds (this thread) of the simulated run."""
    wall: float
    """Seconds from the button press to the result (the first frame is drawn at once)."""
    pressed: float = 0.0
    """``time.perf_counter()`` when the server got the press (benchmarks split the latency)."""

    @property
    def duration(self) -> float:
        """Simulated seconds of the last frame."""
        return float(self.times[-1]) if len(self.times) else 0.0

    def frame_index(self, t: float) -> int:
        """Index of the frame shown at playback time ``t`` (the last one at or before it)."""
        i = int(np.searchsorted(self.times, t, side="right")) - 1
        return int(np.clip(i, 0, len(self.times) - 1))


@dataclass(frozen=True, eq=False)
class LiftView:
    """The lift tests of one grasp set: every outcome so far and the last recorded lift."""

    grasps: Any
    """The ``GraspSet`` they belong to (by identity: a new plan or object makes them stale)."""
    outcomes: Mapping[int, Any]
    """Pool index -> ``SimulationResult`` of every grasp simulated on this set."""
    playback: LiftPlayback | None = None
    """The lift last simulated, or None."""
    running: int | None = None
    """Rank of the grasp being simulated now, or None."""


# ---------------------------------------------------------------------------------------------
# pure readers of the state


def current_lift(state: AppState) -> LiftView | None:
    """The state's :class:`LiftView` when it belongs to the grasps shown, else None."""
    lift = getattr(state, "lift", None)
    grasps = attr_or_none(state.result, "grasps")
    if lift is None or grasps is None or lift.grasps is not grasps or not state.planned:
        return None
    return lift


def lift_outcomes(state: AppState) -> Mapping[int, Any]:
    """Pool index -> ``SimulationResult`` of the grasps simulated on the grasps shown."""
    lift = current_lift(state)
    return MappingProxyType({}) if lift is None else lift.outcomes


def shown_playback(state: AppState) -> LiftPlayback | None:
    """The recorded lift the scene shows now: the chosen grasp's, while ``show_lift`` is on."""
    lift = current_lift(state)
    if lift is None or lift.playback is None or not state.view.show_lift:
        return None
    g = selected_grasp(state)
    if g is None or int(g.pregrasp) != lift.playback.pregrasp:
        return None
    return lift.playback


@dataclass(frozen=True)
class LiftFrame:
    """What the scene draws at one instant of a lift."""

    playback: LiftPlayback
    index: int
    T_world_hand: np.ndarray
    q: np.ndarray
    T_world_object: np.ndarray


def lift_frame(state: AppState) -> LiftFrame | None:
    """The frame of the shown lift at the clock ``state.view.lift_t``, or None."""
    pb = shown_playback(state)
    if pb is None:
        return None
    i = pb.frame_index(float(state.view.lift_t))
    return LiftFrame(pb, i, pb.T_world_hand[i], pb.q[i], pb.T_world_object[i])


def lift_tick(state: AppState, dt: float) -> dict[str, Any] | None:
    """View changes that advance the shown lift's clock by ``dt`` seconds times the speed
    (real time at speed 1; it stops on the last frame); None when no lift is shown."""
    pb = shown_playback(state)
    if pb is None:
        return None
    t = float(state.view.lift_t) + float(dt) * float(state.view.speed)
    return {"lift_t": min(t, pb.duration), "playing": t < pb.duration}


def lift_restart(state: AppState) -> dict[str, Any] | None:
    """View changes of "play" on a shown lift (from the start when it is at the end)."""
    pb = shown_playback(state)
    if pb is None:
        return None
    t = float(state.view.lift_t)
    return {"playing": True, "lift_t": 0.0 if t >= pb.duration else t}


def outcome_cell(result: Any) -> str:
    """The grasp table's ``lift`` cell: the outcome and the slip in cm."""
    if result is None:
        return ""
    slip = float(result.slip)
    return f"{result.outcome}" + (f" ({slip * 100:.1f} cm)" if np.isfinite(slip) else "")


def lift_markdown(state: AppState) -> str:
    """The panel's text under the button: the chosen grasp's lift outcome or what to do."""
    lift = current_lift(state)
    if not state.planned:
        return "Plan the grasps, then **simulate lift** tests the chosen one in MuJoCo."
    if lift is not None and lift.running is not None:
        return (
            f"Simulating the lift of grasp #{lift.running + 1}... (the first press on an "
            "object also builds its collision model: a few seconds)"
        )
    g = selected_grasp(state)
    if g is None:
        return "Choose a grasp, then **simulate lift**."
    res = lift_outcomes(state).get(int(g.pregrasp))
    k = state.view.selected_grasp
    if res is None:
        return (
            f"Press **simulate lift** to test grasp #{(k or 0) + 1} in MuJoCo: approach, "
            "close, lift 10 cm, hold 1 s."
        )
    pb = lift.playback if lift is not None else None
    lines = [
        f"**lift of grasp #{(k or 0) + 1}: {md_text(res.outcome)}**",
        "",
        f"- rose {res.rise * 100:.1f} cm (the hand 10 cm), slip {res.slip * 100:.1f} cm "
        "(2 cm allowed)",
        f"- push while closing {res.push * 100:.1f} cm, initial penetration "
        f"{res.initial_penetration * 1000:.1f} mm",
    ]
    if res.object_held:
        lines.append("- the object does not rest in its pose on its own: held until the lift")
    if pb is not None and pb.pregrasp == int(g.pregrasp):
        lines.append(
            f"- model from the {pb.model} ({pb.n_pieces} pieces, {pb.mass:.3f} kg); "
            f"{pb.duration:.1f} s simulated in {pb.run_cpu:.2f} s CPU"
        )
    return "\n".join(lines)


# ---------------------------------------------------------------------------------------------
# the worker


@dataclass
class _Cached:
    cloud: Any
    support: Any
    mu: float
    simulator: Any
    model: str


class LiftRunner:
    """Runs the lift of the chosen grasp on a worker thread and commits it to the controller.

    One lift at a time (a second press while one runs is refused with a notice); the compiled
    scene of the last object is reused while the cloud, its support plane and ``mu`` stay."""

    def __init__(self, controller: Any, params: Any = None) -> None:
        self.controller = controller
        self.params = params
        """``SimulationParams`` of the test (None: the defaults, as ``pregrasp plan
        --simulate``)."""
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self._cached: _Cached | None = None

    @property
    def running(self) -> bool:
        """True while a lift is being simulated."""
        t = self._thread
        return t is not None and t.is_alive()

    def wait(self, timeout: float | None = None) -> bool:
        """Wait for the lift in progress (if any); True when none runs any more."""
        t = self._thread
        if t is not None:
            t.join(timeout)
        return not self.running

    def start(self, client: Any = None) -> AppState:
        """Simulate the chosen grasp on a worker thread; returns at once. The result (or a
        notice saying why there is none) reaches ``client``'s browser and the state."""
        t_press = time.perf_counter()
        s = self.controller.state
        if s.result is None:
            raise InputError("load an object, plan its grasps, then simulate one")
        if not s.planned or attr_or_none(s.result, "grasps") is None:
            raise InputError("plan the grasps first (plan grasps), then simulate the chosen one")
        g = selected_grasp(s)
        if g is None:
            raise InputError("no grasp chosen: pick one in the grasp list, then simulate it")
        rank = int(s.view.selected_grasp)
        with self._lock:
            if self.running:
                raise InputError("a lift is being simulated already; wait for its outcome")
            self._thread = threading.Thread(
                target=self._work, args=(client, s, g, rank, t_press), name="pregrasp-lift"
            )
            self._thread.daemon = True
        self.controller.update(lambda st: _with_lift(st, s.result.grasps, running=rank))
        self._thread.start()
        return self.controller.state

    def _work(self, client: Any, s: AppState, g: Any, rank: int, t_press: float) -> None:
        try:
            self.controller.act(client, self._simulate, client, s, g, rank, t_press)
        finally:
            try:
                self.controller.update(lambda st: _with_lift(st, s.result.grasps, running=None))
            except Exception:  # noqa: BLE001 - e.g. the server stopped meanwhile
                logger.warning("could not clear the running lift", exc_info=True)

    def _simulator(self, s: AppState) -> tuple[Any, str, float]:
        """The compiled scene of the state's object (reused when unchanged), its model's
        source and the CPU seconds spent building it (0 when reused)."""
        from pregrasp_core.simulate import (
            LiftSimulator,
            SimulationParams,
            object_from_cloud,
            object_model,
        )

        result = s.result
        masks = attr_or_none(result, "masks")
        support = None if masks is None else masks.support
        mu = float(s.params.planner.quality.mu)
        c = self._cached
        if c is not None and c.cloud is result.cloud and c.support is support and c.mu == mu:
            return c.simulator, c.model, 0.0
        params = self.params if self.params is not None else SimulationParams()
        t0 = time.thread_time()
        src = s.source
        if src is not None and src.data is not None:
            # an upload: its name is not a path on this machine, never read a file by it
            normals = result.normals if result.normals is not None else result.cloud.normals
            if normals is None:
                from pregrasp_core.planner import cloud_normals

                normals = cloud_normals(result.cloud)
            obj = object_from_cloud(result.cloud.points, normals, params.object)
        else:
            obj = object_model(result, params)
        sim = LiftSimulator(self.controller.hand, obj, support, params, mu)
        self._cached = _Cached(result.cloud, support, mu, sim, obj.source)
        return sim, obj.source, time.thread_time() - t0

    def _simulate(self, client: Any, s: AppState, g: Any, rank: int, t_press: float) -> None:
        from pregrasp_core.simulate import grasp_specs

        sim, model, build_cpu = self._simulator(s)
        spec = grasp_specs(self.controller.hand, [g], s.result.grasps, s.result.pool)[0]
        t0 = time.thread_time()
        res, frames = sim.run(spec, record_fps=LIFT_FPS)
        run_cpu = time.thread_time() - t0
        if not frames:
            raise InputError(f"the lift of grasp #{rank + 1} recorded no frame")
        pb = LiftPlayback(
            pregrasp=int(g.pregrasp),
            rank=rank,
            outcome=res,
            times=np.array([f.t for f in frames]),
            T_world_hand=np.stack([f.T_world_hand for f in frames]),
            q=np.stack([f.q for f in frames]),
            T_world_object=np.stack([f.T_world_object for f in frames]),
            model=model,
            n_pieces=int(sim.obj.n_pieces),
            mass=float(sim.obj.mass),
            build_cpu=build_cpu,
            run_cpu=run_cpu,
            wall=time.perf_counter() - t_press,
            pressed=t_press,
        )
        shown = self.controller.update(lambda st: _with_playback(st, s.result.grasps, pb))
        if current_lift(shown) is None:  # a new plan or object arrived meanwhile
            self.controller.notify(
                client,
                "Lift discarded",
                f"grasp #{rank + 1} was simulated ({res.outcome}), but the grasps changed "
                "meanwhile: press simulate lift again",
            )
        logger.info(
            "lift of grasp #%d: %s (build %.2f s CPU, run %.2f s CPU, %.2f s to the result)",
            rank + 1,
            res.outcome,
            build_cpu,
            run_cpu,
            pb.wall,
        )

    def seek(self, t: float) -> AppState:
        """Show the shown lift at playback time ``t`` (seconds) and pause (scripts)."""

        def change(st: AppState) -> AppState:
            pb = shown_playback(st)
            if pb is None:
                raise InputError("no lift is shown: press simulate lift first")
            tt = float(np.clip(float(t), 0.0, pb.duration))
            view = dataclasses.replace(st.view, lift_t=tt, playing=False)
            return dataclasses.replace(st, view=view)

        return self.controller.update(change)


def _with_lift(state: AppState, grasps: Any, running: int | None) -> AppState:
    """``state`` with its lift view for ``grasps`` marked running (or not); unchanged when the
    grasps are not the state's any more."""
    if attr_or_none(state.result, "grasps") is not grasps:
        return state
    lift = getattr(state, "lift", None)
    if lift is None or lift.grasps is not grasps:
        lift = LiftView(grasps, MappingProxyType({}))
    if lift.running == running:
        return state
    return dataclasses.replace(state, lift=dataclasses.replace(lift, running=running))


def _with_playback(state: AppState, grasps: Any, pb: LiftPlayback) -> AppState:
    """``state`` with the new lift recorded and, when its grasp is still the chosen one,
    shown from its start (playing)."""
    if attr_or_none(state.result, "grasps") is not grasps or not state.planned:
        return state
    lift = getattr(state, "lift", None)
    if lift is None or lift.grasps is not grasps:
        lift = LiftView(grasps, MappingProxyType({}))
    outcomes = MappingProxyType({**lift.outcomes, pb.pregrasp: pb.outcome})
    lift = dataclasses.replace(lift, outcomes=outcomes, playback=pb)
    view = state.view
    g = selected_grasp(state)
    if g is not None and int(g.pregrasp) == pb.pregrasp:
        view = dataclasses.replace(view, show_lift=True, lift_t=0.0, playing=True)
    return dataclasses.replace(state, lift=lift, view=view)


def rank_of(state: AppState, pregrasp: int) -> int | None:
    """Rank (0 = best) of the kept grasp planned from pool index ``pregrasp``, or None."""
    for k, g in enumerate(ranked_grasps(state.result)):
        if int(g.pregrasp) == int(pregrasp):
            return k
    return None


__all__ = [
    "LIFT_FPS",
    "LiftFrame",
    "LiftPlayback",
    "LiftRunner",
    "LiftView",
    "current_lift",
    "lift_frame",
    "lift_markdown",
    "lift_outcomes",
    "lift_restart",
    "lift_tick",
    "outcome_cell",
    "rank_of",
    "shown_playback",
]
