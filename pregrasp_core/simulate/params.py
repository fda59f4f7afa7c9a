"""Parameters and results of the physics check (no MuJoCo import here)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from ..limits import moved_field, real_or_nan
from .object_model import ObjectModelParams

OUTCOMES: dict[str, str] = {
    "lifted": "the object rose with the hand and slipped less than max_slip relative to it",
    "slipped": "the object rose but moved max_slip or more relative to the hand",
    "dropped": "the object did not rise with the hand (it stayed, fell or was pushed away)",
    "unstable": "the simulation diverged (non-finite state); the grasp is not judged",
}
"""Outcome key -> meaning (``SimulationResult.outcome``)."""


SIMULATION_BOUNDS: dict[str, tuple[float, float]] = {
    "timestep": (1e-5, 0.01),
    "approach_speed": (1e-3, 10.0),
    "closing_speed": (1e-2, 100.0),
    "lift_speed": (1e-3, 10.0),
    "settle_time": (0.0, 60.0),
    "hold_time": (0.0, 60.0),
    "object_settle_time": (0.0, 60.0),
    "lift_height": (0.0, 1.0),
    "record_fps": (1e-3, 1000.0),
}
"""Bounds of the fields that set how long one lift is simulated (speeds in m/s and rad/s, times in
s, heights in m): at the bounds a lift is at most a few minutes of simulated time, where
``hold_time`` 1e300 or ``approach_speed`` 1e-300 would never end."""


@dataclass(frozen=True)
class SimulationParams:
    """Parameters of the lift test (SI units: metres, seconds, radians, newton metres)."""

    timestep: float = 0.002
    """Seconds per MuJoCo step."""
    approach_speed: float = 0.1
    """m/s: the hand's speed from the pre-grasp pose to the grasp pose (smooth start and stop)."""
    closing_speed: float = 2.0
    """rad/s: rate of the fingers' closing command (the URDF's joint velocity limit)."""
    squeeze: float = 0.3
    """Radians: each closing joint is commanded this far beyond its planned closed angle
    (clamped to its limit), so a finger stopped by the object presses on it."""
    synchronous: bool = False
    """Close the fingers so that every closing joint reaches its planned closed angle at the same
    moment (each at its own rate, the one with the farthest to go at ``closing_speed``), then
    squeeze all at ``closing_speed``. False (the protocol since issue 11): every joint at
    ``closing_speed`` until it reaches its target, so the finger with the shortest way touches
    first and can push a light round part away before the others arrive."""
    settle_time: float = 0.25
    """Seconds between the end of the closing command and the lift (the grip builds up)."""
    lift_height: float = 0.10
    """Metres the hand rises (along the support's up direction, or world +z)."""
    lift_speed: float = 0.2
    """m/s mean lifting speed (smooth start and stop)."""
    hold_time: float = 1.0
    """Seconds the hand holds still at the top."""
    max_slip: float = 0.02
    """Metres: success needs the object's centre of mass to move less than this in the hand
    frame from the start of the lift to the end of the hold, and to rise by at least
    ``lift_height - max_slip``."""
    finger_kp: float = 10.0
    """N m/rad: stiffness of the flexion joints' position servos."""
    finger_torque: tuple[float, float] = (1.2, 0.8)
    """N m: torque limits of the (proximal, distal) flexion servos (the grip strength)."""
    finger_damping: float = 0.05
    """N m s/rad: damping of every finger joint."""
    finger_armature: float = 2e-4
    """kg m^2: rotor inertia added to every finger joint (keeps the light links stable)."""
    spread_kp: float = 20.0
    """N m/rad: stiffness of the spread servos holding the preshape's spread."""
    base_timeconst: float = 0.005
    """Seconds: time constant of the weld that drives the hand's base (>= 2 timesteps)."""
    friction: float | None = None
    """Coulomb friction of every contact; None = the planner's ``mu`` (0.5 without a plan)."""
    torsional_friction: float = 0.002
    """Metres: torsional friction of the contacts (a soft finger pad)."""
    impratio: float = 10.0
    """MuJoCo's friction-to-normal impedance ratio (elliptic cones; > 1 resists slip better)."""
    multiccd: bool = False
    """Several contact points per pair of convex shapes (MuJoCo's multiccd); off: one point per
    pair (about twice as fast on wrap grasps, see ``docs/simulation.md``)."""
    noslip_iterations: int = 5
    """MuJoCo's no-slip solver iterations (0 = off): removes the slow creep of soft frictional
    contacts under a sustained load."""
    contact_timeconst: float = 0.005
    """Seconds: time constant of the contacts' soft constraint (MuJoCo's solref; >= 2
    timesteps): smaller is stiffer (less penetration, less creep)."""
    object_settle_time: float = 0.3
    """Seconds the object rests on the support before the test (once per object)."""
    max_settle_shift: float = 0.005
    """Metres: an object that moves more than this while settling is not at rest on the support
    in its input pose (it topples); it is then held in that pose (welded to the world) until
    the lift starts, so that the grasps are tested on the pose they were planned for
    (``SimulationResult.object_held``)."""
    gravity: float = 9.81
    """m/s^2."""
    record_fps: float = 30.0
    """Frames per second of :func:`simulate_playback`."""
    object: ObjectModelParams = field(default_factory=ObjectModelParams)
    """The object's collision model and mass."""

    def __post_init__(self) -> None:
        positive = (
            "timestep",
            "approach_speed",
            "closing_speed",
            "lift_speed",
            "max_slip",
            "finger_kp",
            "spread_kp",
            "base_timeconst",
            "impratio",
            "record_fps",
        )
        for name in positive:
            v = real_or_nan(getattr(self, name))
            if not (np.isfinite(v) and v > 0.0):
                raise ValueError(f"SimulationParams.{name} must be a finite number > 0, got {v}")
            object.__setattr__(self, name, v)
        nonneg = (
            "squeeze",
            "settle_time",
            "lift_height",
            "hold_time",
            "finger_damping",
            "finger_armature",
            "torsional_friction",
            "object_settle_time",
            "max_settle_shift",
            "gravity",
        )
        for name in nonneg:
            v = real_or_nan(getattr(self, name))
            if not (np.isfinite(v) and v >= 0.0):
                raise ValueError(f"SimulationParams.{name} must be a finite number >= 0, got {v}")
            object.__setattr__(self, name, v)
        for name, (lo, hi) in SIMULATION_BOUNDS.items():
            v = getattr(self, name)
            if not lo <= v <= hi:
                raise ValueError(
                    f"SimulationParams.{name} must be in [{lo:g}, {hi:g}], got {v} (the bounds "
                    "that keep one lift's simulated time finite: docs/limits.md)"
                )
        torque = self.finger_torque
        if (
            not isinstance(torque, (tuple, list))
            or len(torque) != 2
            or not all(real_or_nan(t) > 0.0 and math.isfinite(real_or_nan(t)) for t in torque)
        ):
            raise ValueError(
                f"SimulationParams.finger_torque must be two torques > 0, got {self.finger_torque}"
            )
        object.__setattr__(self, "finger_torque", tuple(float(t) for t in torque))
        friction = self.friction
        if friction is not None and not (math.isfinite(real_or_nan(friction)) and friction >= 0):
            raise ValueError(f"SimulationParams.friction must be >= 0 or None, got {self.friction}")
        if friction is not None:
            object.__setattr__(self, "friction", float(friction))
        if (
            isinstance(self.noslip_iterations, bool)
            or not isinstance(self.noslip_iterations, (int, np.integer))
            or not 0 <= self.noslip_iterations <= 10_000
        ):
            raise ValueError(
                "SimulationParams.noslip_iterations must be an integer in [0, 10,000], got "
                f"{self.noslip_iterations!r}"
            )
        object.__setattr__(self, "noslip_iterations", int(self.noslip_iterations))
        if not isinstance(self.synchronous, (bool, np.bool_)):
            raise ValueError(
                f"SimulationParams.synchronous must be True or False, got {self.synchronous!r}"
            )
        object.__setattr__(self, "synchronous", bool(self.synchronous))
        if not isinstance(self.multiccd, (bool, np.bool_)):
            raise ValueError(
                f"SimulationParams.multiccd must be True or False, got {self.multiccd!r}"
            )
        object.__setattr__(self, "multiccd", bool(self.multiccd))
        if not isinstance(self.object, ObjectModelParams):
            raise ValueError(
                "SimulationParams.object must be an ObjectModelParams, got "
                f"{type(self.object).__name__}"
            )
        ct = real_or_nan(self.contact_timeconst)
        if not (math.isfinite(ct) and ct >= 2.0 * self.timestep):
            name = moved_field(self, "timestep", "contact_timeconst")
            raise ValueError(
                f"SimulationParams.{name} (contact_timeconst {self.contact_timeconst}) must keep "
                "contact_timeconst at least "
                f"two timesteps ({2.0 * self.timestep})"
            )
        if self.base_timeconst < 2.0 * self.timestep:
            name = moved_field(self, "timestep", "base_timeconst")
            raise ValueError(
                f"SimulationParams.{name} (base_timeconst {self.base_timeconst}) must keep "
                "base_timeconst at least two "
                f"timesteps ({2.0 * self.timestep})"
            )
        object.__setattr__(self, "contact_timeconst", ct)


@dataclass(frozen=True)
class SimulationResult:
    """The outcome of one simulated lift (see ``docs/simulation.md``)."""

    success: bool
    """True when ``outcome == "lifted"``."""
    outcome: str
    """A key of :data:`OUTCOMES`."""
    rise: float
    """Metres the object's centre of mass rose (along up) from the start of the lift to the end
    of the hold (the hand rises ``lift_height``)."""
    slip: float
    """Metres the object's centre of mass moved in the hand frame from the start of the lift to
    the end of the hold."""
    slip_angle: float
    """Radians the object turned relative to the hand over the same interval."""
    push: float
    """Metres the object's centre of mass moved while the fingers closed (closing and settling,
    before the lift)."""
    approach_push: float
    """Metres the object's centre of mass moved during the approach."""
    initial_penetration: float
    """Metres: deepest hand-object contact at the start (hand at the pre-grasp pose with the
    preshape); 0 when they do not touch."""
    planned_penetration: float
    """Metres: deepest hand-object contact of the planned closed hand at the grasp pose against
    the collision model (a kinematic check before the run; the planner allows 2 mm against the
    cloud)."""
    contact_links: tuple[str, ...]
    """Hand links touching the object at the end of the hold."""
    object_held: bool
    """True when the object does not rest in its input pose on its own (it moved more than
    ``max_settle_shift`` while settling) and was held in place until the lift started."""
    q_closed: np.ndarray
    """(J,) float64, radians: the hand's joints at the start of the lift (``Hand.joint_names``)."""
    sim_time: float
    """Simulated seconds."""
    n_steps: int
    """MuJoCo steps."""
    cpu_time: float
    """CPU seconds of the run (process time; the model build is not included)."""
    phase_times: dict[str, float] = field(default_factory=dict)
    """Simulated seconds of each phase: ``approach``, ``close``, ``lift``, ``hold``."""

    def to_dict(self) -> dict[str, object]:
        """JSON-ready dict (arrays as lists, every field by name)."""
        return {
            "success": self.success,
            "outcome": self.outcome,
            "rise": self.rise,
            "slip": self.slip,
            "slip_angle": self.slip_angle,
            "push": self.push,
            "approach_push": self.approach_push,
            "initial_penetration": self.initial_penetration,
            "planned_penetration": self.planned_penetration,
            "contact_links": list(self.contact_links),
            "object_held": self.object_held,
            "q_closed": self.q_closed.tolist(),
            "sim_time": self.sim_time,
            "n_steps": self.n_steps,
            "cpu_time": self.cpu_time,
            "phase_times": dict(self.phase_times),
        }


class PlaybackFrame(NamedTuple):
    """One frame of a simulated lift, for a viewer."""

    t: float
    """Seconds since the start."""
    T_world_hand: np.ndarray
    """(4, 4) pose of the palm (hand frame) in the world."""
    q: np.ndarray
    """(J,) the hand's joints (``Hand.joint_names``; ``f2_spread`` follows ``f1_spread``)."""
    T_world_object: np.ndarray
    """(4, 4) motion of the object: maps a point of the input (file frame, as the object was at
    the start) to where it is now; the identity at t = 0 up to the settling on the table."""
