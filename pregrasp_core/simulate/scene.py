"""The MuJoCo scene of the lift test: the hand (from its URDF), the object, the support plane.

* **Hand.** One body per URDF link, nested as in the URDF (body pose = joint origin, hinge
  joints with the URDF axes and limits, the URDF inertials); each link's collision geometry is
  the planner's box (``Hand.link_box_T``, ``Hand.link_box_half``). ``f2_spread`` follows
  ``f1_spread`` through an equality constraint (the URDF mimic). The palm has a free joint
  welded to a mocap body: moving the mocap body drives the 6-DoF base with true velocities
  (contacts see the hand move). Gravity is compensated on every hand body (a robot arm would
  carry the hand).
* **Fingers.** Every joint has a position servo with a torque limit. The underactuated coupling
  of the closing model is in the commands (:mod:`.run`): one closing command per finger drives
  both flexion targets along the closing model's coupled path (both joints at the coupling
  rate); a link the object stops cannot follow (the servo saturates at its torque limit) while
  the other joint goes on, as in the closing model's phases (middle stops -> distal closes
  alone; distal stops -> the finger stops). Each joint's target ends ``squeeze`` beyond the
  planned closed angle, so the stopped links press with up to the torque limit.
* **Contacts.** Every hand link collides with the object, the support and the other fingers,
  except a link with its parent link (they touch at their joint); the palm collides with the
  finger links, so the palm stops a curling finger. Friction: the planner's ``mu``; elliptic
  friction cones with ``impratio``; one contact point per convex pair unless
  ``SimulationParams.multiccd``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import mujoco
import numpy as np

from .object_model import ObjectModel
from .params import SimulationParams

if TYPE_CHECKING:
    from ..facemask import SupportPlane
    from ..hand import Hand


def _f(x: float) -> str:
    return repr(float(x))


def _v(a: object) -> str:
    return " ".join(_f(x) for x in np.asarray(a, dtype=np.float64).reshape(-1))


def _quat(R: np.ndarray) -> np.ndarray:
    """wxyz quaternion of a rotation matrix (MuJoCo's convention)."""
    q = np.zeros(4)
    mujoco.mju_mat2Quat(q, np.ascontiguousarray(R, dtype=np.float64).reshape(9))
    return q


def _z_to(n: np.ndarray) -> np.ndarray:
    """A rotation matrix whose third column is the unit vector ``n``."""
    n = n / np.linalg.norm(n)
    a = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = a - (a @ n) * n
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(n, x), n], axis=1)


def up_direction(support: SupportPlane | None) -> np.ndarray:
    """(3,) the lift direction: the support's normal, or world +z without a support."""
    if support is None:
        return np.array([0.0, 0.0, 1.0])
    n = np.asarray(support.normal, dtype=np.float64)
    return n / np.linalg.norm(n)


def scene_xml(
    hand: Hand,
    obj: ObjectModel,
    support: SupportPlane | None,
    params: SimulationParams,
    friction: float,
) -> str:
    """The MJCF document of the scene (deterministic: the same inputs give the same text)."""
    urdf = hand.urdf
    links = {link.name: link for link in urdf.robot.links}
    joints_by_parent: dict[str, list] = {}
    for j in urdf.robot.joints:
        joints_by_parent.setdefault(j.parent, []).append(j)
    index = {n: i for i, n in enumerate(hand.link_names)}
    condim = 4 if params.torsional_friction > 0.0 else 3
    fr = f"{_f(friction)} {_f(params.torsional_friction)} 0.0001"
    tau1, tau2 = params.finger_torque
    flex_torque: dict[str, float] = {}
    for f in hand.fingers:
        flex_torque[f.flexion_joints[0]] = tau1
        flex_torque[f.flexion_joints[1]] = tau2

    def inertial(link) -> str:
        ine = link.inertial
        if ine is None or ine.mass is None:
            return ""
        T = np.eye(4) if ine.origin is None else np.asarray(ine.origin)
        R = T[:3, :3]
        I = R @ np.asarray(ine.inertia) @ R.T  # in the link frame
        full = [I[0, 0], I[1, 1], I[2, 2], I[0, 1], I[0, 2], I[1, 2]]
        return f'<inertial pos="{_v(T[:3, 3])}" mass="{_f(ine.mass)}" fullinertia="{_v(full)}"/>'

    def geom(name: str) -> str:
        i = index[name]
        T = hand.link_box_T[i]
        return (
            f'<geom name="{name}" type="box" size="{_v(hand.link_box_half[i])}" '
            f'pos="{_v(T[:3, 3])}" quat="{_v(_quat(T[:3, :3]))}" group="1"/>'
        )

    def body(name: str, joint=None, depth: int = 2) -> str:
        pad = "  " * depth
        out = []
        if joint is None:  # the palm: free joint at the pre-grasp pose (set at reset)
            out.append(f'{pad}<body name="{name}" gravcomp="1">')
            out.append(f'{pad}  <freejoint name="hand_base"/>')
        else:
            T = np.asarray(joint.origin)
            out.append(
                f'{pad}<body name="{name}" pos="{_v(T[:3, 3])}" '
                f'quat="{_v(_quat(T[:3, :3]))}" gravcomp="1">'
            )
            if joint.type in ("revolute", "continuous"):
                lim = joint.limit
                rng = f' range="{_f(lim.lower)} {_f(lim.upper)}"' if lim is not None else ""
                out.append(
                    f'{pad}  <joint name="{joint.name}" type="hinge" axis="{_v(joint.axis)}"'
                    f'{rng} damping="{_f(params.finger_damping)}" '
                    f'armature="{_f(params.finger_armature)}"/>'
                )
            elif joint.type != "fixed":
                raise ValueError(f"hand joint {joint.name}: type {joint.type} is not simulated")
        out.append(f"{pad}  {inertial(links[name])}")
        out.append(f"{pad}  {geom(name)}")
        for child in joints_by_parent.get(name, []):
            out.append(body(child.child, child, depth + 1))
        out.append(f"{pad}</body>")
        return "\n".join(out)

    root = hand.link_names[0]
    com = obj.com
    meshes = "\n".join(
        f'    <mesh name="piece{k}" vertex="{_v(p - com)}"/>' for k, p in enumerate(obj.pieces)
    )
    I = obj.inertia
    obj_geoms = "\n".join(
        f'      <geom name="object{k}" type="mesh" mesh="piece{k}" group="2"/>'
        for k in range(obj.n_pieces)
    )
    up = up_direction(support)
    g = -params.gravity * up
    table = ""
    if support is not None:
        R = _z_to(up)
        p = float(support.height) * up
        table = (
            f'    <geom name="support" type="plane" size="0 0 1" pos="{_v(p)}" '
            f'quat="{_v(_quat(R))}" group="0"/>'
        )
    excludes = "\n".join(
        f'    <exclude body1="{hand.link_names[par]}" body2="{name}"/>'
        for name, par in zip(hand.link_names, hand.link_parent, strict=True)
        if par >= 0
    )
    equalities = [
        f'    <weld name="base" body1="hand_target" body2="{root}" relpose="0 0 0 1 0 0 0" '
        f'solref="{_f(params.base_timeconst)} 1"/>',
        # holds an object that does not rest on its own in its input pose (off by default)
        f'    <weld name="hold" body1="object" active="false" '
        f'solref="{_f(params.base_timeconst)} 1"/>',
    ]
    actuators = []
    for j in urdf.robot.joints:
        if j.type not in ("revolute", "continuous"):
            continue
        if j.mimic is not None:
            equalities.append(
                f'    <joint name="mimic_{j.name}" joint1="{j.name}" joint2="{j.mimic.joint}" '
                f'polycoef="{_f(j.mimic.offset or 0.0)} {_f(j.mimic.multiplier or 1.0)} 0 0 0"/>'
            )
            continue
        if j.name in flex_torque:
            kp, tau = params.finger_kp, flex_torque[j.name]
        else:
            kp, tau = params.spread_kp, float(j.limit.effort) if j.limit is not None else 2.0
        actuators.append(
            f'    <position name="{j.name}" joint="{j.name}" kp="{_f(kp)}" '
            f'forcerange="{_f(-tau)} {_f(tau)}" ctrlrange="{_f(j.limit.lower)} '
            f'{_f(j.limit.upper)}"/>'
        )
    return f"""<mujoco model="pregrasp_lift">
  <compiler angle="radian" inertiafromgeom="false" autolimits="true"/>
  <option timestep="{_f(params.timestep)}" gravity="{_v(g)}" integrator="implicitfast"
          cone="elliptic" impratio="{_f(params.impratio)}"
          noslip_iterations="{int(params.noslip_iterations)}">
    <flag multiccd="{"enable" if params.multiccd else "disable"}" filterparent="disable"/>
  </option>
  <default>
    <geom friction="{fr}" condim="{condim}" solref="{_f(params.contact_timeconst)} 1"/>
  </default>
  <asset>
{meshes}
  </asset>
  <worldbody>
{table}
    <body name="hand_target" mocap="true"/>
{body(root)}
    <body name="object" pos="{_v(com)}">
      <freejoint name="object"/>
      <inertial pos="0 0 0" mass="{_f(obj.mass)}"
                fullinertia="{_v([I[0, 0], I[1, 1], I[2, 2], I[0, 1], I[0, 2], I[1, 2]])}"/>
{obj_geoms}
    </body>
  </worldbody>
  <contact>
{excludes}
  </contact>
  <equality>
{chr(10).join(equalities)}
  </equality>
  <actuator>
{chr(10).join(actuators)}
  </actuator>
</mujoco>
"""


@dataclass(frozen=True)
class SceneIndex:
    """Addresses in the compiled model (MuJoCo ids)."""

    palm_body: int
    object_body: int
    hand_qpos: np.ndarray
    """(J,) qpos address of each of ``Hand.joint_names``."""
    mimic_qpos: tuple[tuple[int, int], ...]
    """(qpos of a mimic joint, index into ``Hand.joint_names`` of its source)."""
    actuator_of_joint: np.ndarray
    """(J,) actuator id of each of ``Hand.joint_names``."""
    base_qpos: int
    """qpos address of the palm's free joint (position then wxyz quaternion)."""
    object_qpos: int
    """qpos address of the object's free joint."""
    geom_link: dict[int, str]
    """Hand geom id -> link name."""
    object_geoms: frozenset[int]
    """Geom ids of the object's pieces."""
    hold_eq: int
    """Id of the equality that holds the object in its input pose."""


def compile_scene(
    hand: Hand,
    obj: ObjectModel,
    support: SupportPlane | None,
    params: SimulationParams,
    friction: float,
) -> tuple[mujoco.MjModel, SceneIndex]:
    """Compile :func:`scene_xml` and look up the addresses the run needs."""
    xml = scene_xml(hand, obj, support, params, friction)
    model = mujoco.MjModel.from_xml_string(xml)

    def jid(name: str) -> int:
        return mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, name)

    hand_qpos = np.array([model.jnt_qposadr[jid(n)] for n in hand.joint_names], dtype=np.int64)
    act = np.array(
        [mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_ACTUATOR, n) for n in hand.joint_names],
        dtype=np.int64,
    )
    mimic = []
    for j in hand.urdf.robot.joints:
        if j.mimic is not None:
            mimic.append(
                (int(model.jnt_qposadr[jid(j.name)]), hand.joint_names.index(j.mimic.joint))
            )
    geom_link = {}
    for name in hand.link_names:
        geom_link[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, name)] = name
    object_geoms = frozenset(
        mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, f"object{k}")
        for k in range(obj.n_pieces)
    )
    idx = SceneIndex(
        palm_body=mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, hand.link_names[0]),
        object_body=mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, "object"),
        hand_qpos=hand_qpos,
        mimic_qpos=tuple(mimic),
        actuator_of_joint=act,
        base_qpos=int(model.jnt_qposadr[jid("hand_base")]),
        object_qpos=int(model.jnt_qposadr[jid("object")]),
        geom_link=geom_link,
        object_geoms=object_geoms,
        hold_eq=mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_EQUALITY, "hold"),
    )
    return model, idx
