"""The lift protocol: approach, close, lift, hold; and the public entry points.

Protocol of one grasp (times from :class:`SimulationParams`):

1. **start**: the hand at the pre-grasp pose with the pre-grasp's own preshape (``pool.q``,
   :func:`grasp_specs`); the object at rest on the support (settled once per object for
   ``object_settle_time``); the deepest hand-object contact is recorded
   (``initial_penetration``);
2. **approach**: the base moves (smooth start and stop) along the approach axis to the planned
   grasp pose;
3. **close**: one command per closing finger advances both flexion targets along the closing
   model's coupled path at ``closing_speed`` up to the planned closed angles plus ``squeeze``;
   then ``settle_time`` for the grip to build; the object's displacement over the closing is the
   ``push``;
4. **lift**: the base rises ``lift_height`` along up (smooth);
5. **hold** for ``hold_time``.

Success: the object's centre of mass rose at least ``lift_height - max_slip`` and moved less
than ``max_slip`` in the hand frame from the start of the lift to the end of the hold.

Determinism: a run starts from ``mj_resetData`` and the cached settled object state, and MuJoCo
is deterministic on one thread, so the same grasp gives the same result bit for bit.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import mujoco
import numpy as np

from ..errors import InputError
from .object_model import ObjectModel, object_from_cloud, object_from_mesh
from .params import PlaybackFrame, SimulationParams, SimulationResult
from .scene import compile_scene, up_direction

if TYPE_CHECKING:
    import trimesh

    from ..facemask import SupportPlane
    from ..hand import Hand
    from ..io import PointCloud
    from ..pipeline import PipelineResult
    from ..planner import Grasp, GraspSet
    from ..pregrasps import PreGraspPool

logger = logging.getLogger(__name__)

DEFAULT_FRICTION: float = 0.5
"""Friction when neither the parameters nor a plan give one (the planner's default ``mu``)."""

_MESH_BOUNDS_TOL: float = 0.002
"""Metres: a reloaded mesh is used only when its bounds match the cloud's within this (else the
cloud model is used: the file is not the one the cloud was sampled from)."""


def _smooth(u: np.ndarray) -> np.ndarray:
    """Smoothstep 3u^2 - 2u^3 on [0, 1] (zero velocity at both ends)."""
    u = np.clip(u, 0.0, 1.0)
    return u * u * (3.0 - 2.0 * u)


def _pose(pos: np.ndarray, xmat: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = np.asarray(xmat).reshape(3, 3)
    T[:3, 3] = pos
    return T


def _as_T(T: np.ndarray, name: str) -> np.ndarray:
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4):
        raise ValueError(f"{name} must have shape (4, 4), got {T.shape}")
    return T


@dataclass(frozen=True)
class GraspSpec:
    """What the simulator needs of one grasp (all in the world frame)."""

    T_world_pregrasp: np.ndarray
    """(4, 4) the hand's start pose."""
    T_world_hand: np.ndarray
    """(4, 4) the grasp pose (end of the approach); same orientation as the start."""
    q_start: np.ndarray
    """(J,) the preshape."""
    q_closed: np.ndarray
    """(J,) the planned closed joints (the closing fingers' targets before the squeeze)."""
    closing: tuple[str, ...]
    """Names of the fingers that close; the others hold ``q_start``."""


class LiftSimulator:
    """A compiled scene (hand, object, support) that runs the lift test for many grasps.

    Build once per object; :meth:`run` resets the state for every grasp."""

    def __init__(
        self,
        hand: Hand,
        obj: ObjectModel,
        support: SupportPlane | None = None,
        params: SimulationParams | None = None,
        friction: float | None = None,
    ) -> None:
        self.hand = hand
        self.obj = obj
        self.support = support
        self.params = SimulationParams() if params is None else params
        if self.params.friction is not None:
            friction = self.params.friction
        self.friction = DEFAULT_FRICTION if friction is None else float(friction)
        self.up = up_direction(support)
        self.model, self.index = compile_scene(hand, obj, support, self.params, self.friction)
        self.data = mujoco.MjData(self.model)
        self._gravity = np.array(self.model.opt.gravity)
        self.held = False
        """Whether the object is held in its input pose until the lift (it does not rest)."""
        self._object_rest = self._settle()

    # ------------------------------------------------------------------ state
    def _park_qpos(self) -> np.ndarray:
        """qpos with the hand far away (above the object by 10 m) and the object at rest."""
        m, ix = self.model, self.index
        qpos = m.qpos0.copy()
        qpos[ix.base_qpos : ix.base_qpos + 3] = self.obj.com + 10.0 * self.up
        qpos[ix.base_qpos + 3 : ix.base_qpos + 7] = (1.0, 0.0, 0.0, 0.0)
        return qpos

    def _settle(self) -> np.ndarray:
        """The object's free-joint state (7,) after resting on the support (once per object)."""
        m, d, ix = self.model, self.data, self.index
        mujoco.mj_resetData(m, d)
        d.qpos[:] = self._park_qpos()
        d.mocap_pos[0] = d.qpos[ix.base_qpos : ix.base_qpos + 3]
        d.mocap_quat[0] = (1.0, 0.0, 0.0, 0.0)
        if self.support is not None:
            m.opt.gravity[:] = self._gravity
            for _ in range(int(round(self.params.object_settle_time / m.opt.timestep))):
                mujoco.mj_step(m, d)
        rest = d.qpos[ix.object_qpos : ix.object_qpos + 7].copy()
        shift = float(np.linalg.norm(rest[:3] - self.obj.com))
        self.held = shift > self.params.max_settle_shift
        if self.held:
            logger.warning(
                "the object moved %.1f mm while settling on the support: it does not rest in "
                "its input pose and is held there until the lift",
                1e3 * shift,
            )
            rest = m.qpos0[ix.object_qpos : ix.object_qpos + 7].copy()
        return rest

    def _reset(self, T_hand: np.ndarray, q: np.ndarray) -> None:
        m, d, ix = self.model, self.data, self.index
        mujoco.mj_resetData(m, d)
        qpos = m.qpos0.copy()
        quat = np.zeros(4)
        mujoco.mju_mat2Quat(quat, np.ascontiguousarray(T_hand[:3, :3]).reshape(9))
        qpos[ix.base_qpos : ix.base_qpos + 3] = T_hand[:3, 3]
        qpos[ix.base_qpos + 3 : ix.base_qpos + 7] = quat
        qpos[ix.hand_qpos] = q
        for adr, src in ix.mimic_qpos:
            qpos[adr] = q[src]
        qpos[ix.object_qpos : ix.object_qpos + 7] = self._object_rest
        d.qpos[:] = qpos
        d.mocap_pos[0] = T_hand[:3, 3]
        d.mocap_quat[0] = quat
        d.ctrl[ix.actuator_of_joint] = q
        m.opt.gravity[:] = self._gravity if self.support is not None else 0.0
        d.eq_active[ix.hold_eq] = 1 if self.held else 0
        mujoco.mj_forward(m, d)

    def _hand_object_contacts(self) -> tuple[float, set[str]]:
        """Deepest hand-object penetration (m, >= 0) and the touching links, now."""
        d, ix = self.data, self.index
        deepest = 0.0
        links: set[str] = set()
        for c in d.contact[: d.ncon]:
            g1, g2 = int(c.geom1), int(c.geom2)
            if g1 in ix.object_geoms and g2 in ix.geom_link:
                link = ix.geom_link[g2]
            elif g2 in ix.object_geoms and g1 in ix.geom_link:
                link = ix.geom_link[g1]
            else:
                continue
            if c.dist <= 0.0:
                links.add(link)
            deepest = max(deepest, -float(c.dist))
        return deepest, links

    def _object_T(self) -> np.ndarray:
        d, b = self.data, self.index.object_body
        return _pose(d.xpos[b], d.xmat[b])

    def _hand_T(self) -> np.ndarray:
        d, b = self.data, self.index.palm_body
        return _pose(d.xpos[b], d.xmat[b])

    # ------------------------------------------------------------------ the run
    def _commands(self, spec: GraspSpec) -> tuple[np.ndarray, np.ndarray, dict[str, int]]:
        """Per step: mocap position (n, 3) and joint targets (n, J); phase end steps."""
        p, hand = self.params, self.hand
        dt = self.model.opt.timestep
        # approach
        p0, p1 = spec.T_world_pregrasp[:3, 3], spec.T_world_hand[:3, 3]
        dist = float(np.linalg.norm(p1 - p0))
        n_app = max(1, math.ceil(dist / p.approach_speed / dt))
        # closing: targets along the coupled path (both flexion joints at the same rate)
        q0 = np.asarray(spec.q_start, dtype=np.float64)
        goal = q0.copy()
        for name in spec.closing:
            f = hand.finger(name)
            ji = list(f.flex_index)
            goal[ji] = np.minimum(np.maximum(spec.q_closed[ji], q0[ji]) + p.squeeze, f.upper)
        delta = goal - q0  # >= 0
        reach = float(delta.max(initial=0.0))  # path length (rad) until every target is reached
        plan = np.zeros_like(q0)  # synchronous: the way to the planned closed angles
        if p.synchronous:
            for name in spec.closing:
                ji = list(hand.finger(name).flex_index)
                plan[ji] = np.maximum(spec.q_closed[ji], q0[ji]) - q0[ji]
            reach = max(reach, float(plan.max(initial=0.0)) + p.squeeze)
        n_close = max(1, math.ceil(reach / p.closing_speed / dt))
        n_settle = math.ceil(p.settle_time / dt)
        n_lift = max(1, math.ceil(p.lift_height / p.lift_speed / dt))
        n_hold = math.ceil(p.hold_time / dt)
        n = n_app + n_close + n_settle + n_lift + n_hold
        k = np.arange(1, n + 1)  # the command applied during step k (state after k steps)
        s_app = _smooth(k / n_app)
        s_lift = _smooth((k - n_app - n_close - n_settle) / n_lift)
        pos = p0 + s_app[:, None] * (p1 - p0) + (p.lift_height * s_lift)[:, None] * self.up
        tau = np.clip((k - n_app) * dt * p.closing_speed, 0.0, None)  # path parameter (rad)
        if p.synchronous and plan.max(initial=0.0) > 0.0:
            d_max = float(plan.max())
            share = np.minimum(tau / d_max, 1.0)[:, None]  # 1: every finger at its contact
            beyond = np.clip(tau - d_max, 0.0, None)[:, None]  # then the squeeze, all at once
            ctrl = np.minimum(q0 + share * plan + beyond, goal)
        else:
            ctrl = q0 + np.minimum(tau[:, None], delta[None, :])
        ends = {
            "approach": n_app,
            "close": n_app + n_close + n_settle,
            "lift": n_app + n_close + n_settle + n_lift,
            "hold": n,
        }
        return pos, ctrl, ends

    def planned_penetration(self, spec: GraspSpec) -> float:
        """Deepest contact of the planned closed hand at the grasp pose with the object model."""
        self._reset(spec.T_world_hand, spec.q_closed)
        return self._hand_object_contacts()[0]

    def run(
        self, spec: GraspSpec, record_fps: float | None = None
    ) -> tuple[SimulationResult, list[PlaybackFrame]]:
        """Simulate one grasp; with ``record_fps`` also the frames for playback."""
        m, d, ix, p = self.model, self.data, self.index, self.params
        t_cpu = time.process_time()
        planned = self.planned_penetration(spec)
        pos, ctrl, ends = self._commands(spec)
        self._reset(spec.T_world_pregrasp, spec.q_start)
        initial = self._hand_object_contacts()[0]
        act = ix.actuator_of_joint
        dt = m.opt.timestep
        frames: list[PlaybackFrame] = []
        every = 0 if record_fps is None else max(1, round(1.0 / (record_fps * dt)))
        T_file = np.eye(4)
        T_file[:3, 3] = -self.obj.com  # file frame -> object body frame at rest (no rotation)

        def frame(t: float) -> PlaybackFrame:
            q = d.qpos[ix.hand_qpos].copy()
            return PlaybackFrame(t, self._hand_T(), q, self._object_T() @ T_file)

        if every:
            frames.append(frame(0.0))
        marks: dict[str, np.ndarray] = {"start": self._object_T()}
        hand_marks: dict[str, np.ndarray] = {"start": self._hand_T()}
        q_closed = spec.q_start.copy()
        unstable = False
        lift_start = ends["close"]
        gravity_on_at_lift = self.support is None
        n = len(pos)
        for i in range(n):
            if i == lift_start:
                if gravity_on_at_lift:
                    m.opt.gravity[:] = self._gravity
                d.eq_active[ix.hold_eq] = 0
            d.mocap_pos[0] = pos[i]
            d.ctrl[act] = ctrl[i]
            mujoco.mj_step(m, d)
            step = i + 1
            if every and step % every == 0:
                frames.append(frame(step * dt))
            for name, end in ends.items():
                if step == end:
                    if (
                        not np.isfinite(d.qpos).all()
                        or d.warning[mujoco.mjtWarning.mjWARN_BADQACC].number
                    ):
                        unstable = True
                    marks[name] = self._object_T()
                    hand_marks[name] = self._hand_T()
                    if name == "close":
                        q_closed = d.qpos[ix.hand_qpos].copy()
            if unstable:
                break
        _, links = self._hand_object_contacts()
        cpu = time.process_time() - t_cpu
        if unstable:
            nan = float("nan")
            result = SimulationResult(
                success=False,
                outcome="unstable",
                rise=nan,
                slip=nan,
                slip_angle=nan,
                push=nan,
                approach_push=nan,
                initial_penetration=initial,
                planned_penetration=planned,
                contact_links=(),
                object_held=self.held,
                q_closed=q_closed,
                sim_time=d.time,
                n_steps=step,
                cpu_time=cpu,
            )
            return result, frames

        def com(name: str) -> np.ndarray:
            return marks[name][:3, 3]

        def in_hand(name: str) -> np.ndarray:
            return np.linalg.inv(hand_marks[name]) @ marks[name]

        rise = float((com("hold") - com("close")) @ self.up)
        rel0, rel1 = in_hand("close"), in_hand("hold")
        slip = float(np.linalg.norm(rel1[:3, 3] - rel0[:3, 3]))
        dR = rel0[:3, :3].T @ rel1[:3, :3]
        slip_angle = float(np.arccos(np.clip(0.5 * (np.trace(dR) - 1.0), -1.0, 1.0)))
        rose = rise >= p.lift_height - p.max_slip
        if rose and slip < p.max_slip:
            outcome = "lifted"
        elif rose:
            outcome = "slipped"
        else:
            outcome = "dropped"
        phase = {
            "approach": ends["approach"] * dt,
            "close": (ends["close"] - ends["approach"]) * dt,
            "lift": (ends["lift"] - ends["close"]) * dt,
            "hold": (ends["hold"] - ends["lift"]) * dt,
        }
        result = SimulationResult(
            success=outcome == "lifted",
            outcome=outcome,
            rise=rise,
            slip=slip,
            slip_angle=slip_angle,
            push=float(np.linalg.norm(com("close") - com("approach"))),
            approach_push=float(np.linalg.norm(com("approach") - com("start"))),
            initial_penetration=initial,
            planned_penetration=planned,
            contact_links=tuple(sorted(links, key=self.hand.link_names.index)),
            object_held=self.held,
            q_closed=q_closed,
            sim_time=float(d.time),
            n_steps=n,
            cpu_time=cpu,
            phase_times=phase,
        )
        return result, frames


# ----------------------------------------------------------------------------------------------
# Public entry points


def grasp_spec(
    hand: Hand,
    T_world_hand: np.ndarray,
    q_closed: np.ndarray,
    q_start: np.ndarray,
    T_world_pregrasp: np.ndarray | None = None,
    closing: Sequence[str] | None = None,
) -> GraspSpec:
    """A :class:`GraspSpec` from arrays, checked. ``closing``: the fingers that close (default:
    those whose flexion differs between ``q_start`` and ``q_closed``)."""
    T = _as_T(T_world_hand, "T_world_hand")
    T0 = T if T_world_pregrasp is None else _as_T(T_world_pregrasp, "T_world_pregrasp")
    J = hand.n_joints
    qc = np.asarray(q_closed, dtype=np.float64)
    qs = np.asarray(q_start, dtype=np.float64)
    for name, q in (("q_closed", qc), ("q_start", qs)):
        if q.shape != (J,):
            raise ValueError(f"{name} must have shape ({J},), got {q.shape}")
    if closing is None:
        closing = tuple(
            f.name
            for f in hand.fingers
            if not np.array_equal(qc[list(f.flex_index)], qs[list(f.flex_index)])
        )
    names = tuple(hand.finger(n).name for n in closing)
    return GraspSpec(T0, T, hand.clamp(qs), hand.clamp(qc), names)


def simulate_grasp(
    obj: ObjectModel,
    hand: Hand,
    T_world_hand: np.ndarray,
    q_closed: np.ndarray,
    q_start: np.ndarray,
    T_world_pregrasp: np.ndarray | None = None,
    closing: Sequence[str] | None = None,
    support: SupportPlane | None = None,
    params: SimulationParams | None = None,
) -> SimulationResult:
    """Simulate one grasp of ``obj`` (see the module docstring for the protocol).

    T_world_hand: (4, 4) the grasp pose; q_closed: (J,) the planned closed joints; q_start: (J,)
    the preshape; T_world_pregrasp: (4, 4) the start pose (default: the grasp pose, no
    approach); closing: the fingers that close (default: those that moved in the plan);
    support: the table (None: no table, the object is weightless until the lift starts).
    Builds the MuJoCo scene for this one call; use :class:`LiftSimulator` for many grasps.
    """
    spec = grasp_spec(hand, T_world_hand, q_closed, q_start, T_world_pregrasp, closing)
    return LiftSimulator(hand, obj, support, params).run(spec)[0]


def _pipeline_parts(
    result_or_cloud: PipelineResult | PointCloud,
) -> tuple[PointCloud, np.ndarray | None, SupportPlane | None, float | None, GraspSet | None]:
    """(cloud, normals, support, mu, grasp set) of a pipeline result or a bare cloud."""
    from ..io import PointCloud

    if isinstance(result_or_cloud, PointCloud):
        return result_or_cloud, result_or_cloud.normals, None, None, None
    r = result_or_cloud
    support = None if r.masks is None else r.masks.support
    mu = float(r.params.planner.quality.mu)
    return r.cloud, r.normals, support, mu, r.grasps


def load_object_mesh(cloud: PointCloud) -> trimesh.Trimesh | None:
    """The mesh a cloud was sampled from, read again from ``cloud.source`` (scaled as the
    cloud), when the cloud came from a mesh file that is still there and matches its bounds;
    else None."""
    import trimesh

    if cloud.info.get("kind") != "mesh":
        return None
    path = Path(str(cloud.source))
    if not path.is_file():
        return None
    try:
        mesh = trimesh.load_scene(str(path)).to_mesh()
    except Exception:  # noqa: BLE001 - any parser failure: fall back to the cloud model
        logger.warning("%s: cannot read the mesh again; using the cloud's collision model", path)
        return None
    scale = float(cloud.info.get("scale", 1.0) or 1.0)
    if scale != 1.0:
        mesh.apply_scale(scale)
    if not np.allclose(mesh.bounds, cloud.bounds, atol=_MESH_BOUNDS_TOL):
        logger.warning("%s: the mesh does not match the cloud's bounds; using the cloud", path)
        return None
    return mesh


def object_model(
    result_or_cloud: PipelineResult | PointCloud,
    params: SimulationParams | None = None,
    mesh: trimesh.Trimesh | None = None,
) -> ObjectModel:
    """The object's collision model: from ``mesh``, else from the mesh the cloud was sampled
    from (:func:`load_object_mesh`), else from the cloud and its normals (the result's
    estimated normals, or the cloud's own)."""
    params = SimulationParams() if params is None else params
    cloud, normals, _, _, _ = _pipeline_parts(result_or_cloud)
    if mesh is None:
        mesh = load_object_mesh(cloud)
    if mesh is not None:
        return object_from_mesh(mesh, params.object)
    if normals is None:
        from ..planner import cloud_normals

        normals = cloud_normals(cloud)
    return object_from_cloud(cloud.points, normals, params.object)


def grasp_specs(
    hand: Hand,
    grasps: Sequence[Grasp | int],
    grasp_set: GraspSet | None,
    pool: PreGraspPool | None = None,
) -> list[GraspSpec]:
    """The simulator's description of each grasp (pose at the pre-grasp and after the approach,
    preshape and closed joints); ints index ``grasp_set``; rejected grasps are an error.

    The preshape is the pre-grasp's own (``pool.q[g.pregrasp]``, what the planner closed the
    fingers from: a pinch's is adapted to the part) when ``pool`` is given, else the grasp
    type's fixed preshape (``Hand.preshape``), which is the pre-grasp's for every grasp but the
    pinches."""
    specs = []
    for g in grasps:
        if isinstance(g, int | np.integer):
            if grasp_set is None:
                raise InputError(
                    f"grasp {int(g)} is an index, but a bare cloud has no planned grasps; pass "
                    "Grasp objects or a pipeline result run until 'grasps'"
                )
            g = grasp_set.grasps[int(g)]
        if g.rejection is not None:
            raise InputError(
                f"grasp {g.pregrasp} was rejected by the planner ({g.rejection}); simulate "
                "kept grasps only"
            )
        T = np.asarray(g.T_world_hand, dtype=np.float64)
        T0 = T.copy()
        T0[:3, 3] = T[:3, 3] - float(g.approach_distance) * T[:3, 2]
        q0 = hand.preshape(g.grasp_type)
        if pool is not None and 0 <= g.pregrasp < len(pool) and np.shape(pool.q)[1] == len(q0):
            q0 = np.asarray(pool.q[g.pregrasp], dtype=np.float64).copy()
        specs.append(
            GraspSpec(
                T0,
                T,
                q0,
                np.asarray(g.q, dtype=np.float64),
                tuple(f.name for f in hand.fingers_for(g.grasp_type)),
            )
        )
    return specs


def simulate_grasps(
    result_or_cloud: PipelineResult | PointCloud,
    grasps: Sequence[Grasp | int],
    hand: Hand,
    params: SimulationParams | None = None,
    mesh: trimesh.Trimesh | None = None,
    support: SupportPlane | None = None,
) -> list[SimulationResult]:
    """Simulate planned grasps of one object, one :class:`SimulationResult` per grasp.

    result_or_cloud: a :class:`~pregrasp_core.pipeline.PipelineResult` (its cloud, normals,
    support plane, friction and grasps) or a bare cloud; grasps: :class:`Grasp` objects or
    indices into the result's grasps (kept ones). Each grasp starts at its pre-grasp pose (the
    grasp pose moved back by its ``approach_distance`` along the approach) with its pre-grasp's
    preshape (the result's pool; a bare cloud's grasps: their type's preshape). The scene is
    compiled once for all of them. ``support`` overrides the result's.
    """
    sim = simulator(result_or_cloud, hand, params, mesh, support)
    _, _, _, _, gs = _pipeline_parts(result_or_cloud)
    specs = grasp_specs(hand, grasps, gs, getattr(result_or_cloud, "pool", None))
    return [sim.run(spec)[0] for spec in specs]


def simulator(
    result_or_cloud: PipelineResult | PointCloud,
    hand: Hand,
    params: SimulationParams | None = None,
    mesh: trimesh.Trimesh | None = None,
    support: SupportPlane | None = None,
) -> LiftSimulator:
    """The :class:`LiftSimulator` of a pipeline result or cloud (object model, support, mu)."""
    params = SimulationParams() if params is None else params
    _, _, sup, mu, _ = _pipeline_parts(result_or_cloud)
    obj = object_model(result_or_cloud, params, mesh)
    return LiftSimulator(hand, obj, sup if support is None else support, params, mu)


def simulate_playback(
    result_or_cloud: PipelineResult | PointCloud,
    grasp: Grasp | int,
    hand: Hand,
    params: SimulationParams | None = None,
    mesh: trimesh.Trimesh | None = None,
    fps: float | None = None,
) -> tuple[SimulationResult, list[PlaybackFrame]]:
    """The simulated lift of one grasp as frames ``(t, T_world_hand, q, T_world_object)`` at
    ``fps`` (default ``params.record_fps``) for a viewer, with its result (the same run
    :func:`simulate_grasps` makes, so the same outcome)."""
    params = SimulationParams() if params is None else params
    sim = simulator(result_or_cloud, hand, params, mesh)
    _, _, _, _, gs = _pipeline_parts(result_or_cloud)
    spec = grasp_specs(hand, [grasp], gs, getattr(result_or_cloud, "pool", None))[0]
    return sim.run(spec, record_fps=params.record_fps if fps is None else fps)
