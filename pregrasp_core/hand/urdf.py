"""Reading the hand URDF (``assets/hand.urdf``) with yourdfpy into a :class:`HandModel`: the
kinematic chain, joint limits, collision boxes, visual meshes and the fingers, with the checks
the planar closing model relies on (every failure names the file and what to fix)."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import TypeVar

import numpy as np
import trimesh
import yourdfpy

from ..errors import HandModelError
from ..paths import HAND_URDF
from .meshes import load_visual_mesh
from .model import FINGER_NAMES, Finger, HandModel, Joint

logger = logging.getLogger(__name__)

ModelT = TypeVar("ModelT", bound=HandModel)
"""The model class to build (:class:`HandModel` or a subclass)."""


def load_model(urdf_path: Path | str | None, model_type: type[ModelT]) -> ModelT:
    """Read and check the hand URDF (default ``pregrasp_core.paths.HAND_URDF`` when None) into
    a ``model_type`` (:class:`HandModel` or a subclass such as ``Hand``)."""
    path = Path(HAND_URDF if urdf_path is None else urdf_path)
    if not path.is_file():
        raise HandModelError(
            f"hand URDF {path} does not exist; reinstall pregrasp or pass the path of "
            "assets/hand.urdf"
        )
    try:
        urdf = yourdfpy.URDF.load(str(path), build_scene_graph=True, load_meshes=False)
    except Exception as exc:  # yourdfpy raises many types on malformed XML
        raise HandModelError(f"cannot parse hand URDF {path}: {exc}") from exc
    if not urdf.validate():
        raise HandModelError(
            f"hand URDF {path} fails yourdfpy validation: {urdf.errors}; fix the file"
        )
    return _build(path, urdf, model_type)


def _build(path: Path, urdf: yourdfpy.URDF, model_type: type[ModelT]) -> ModelT:
    """The model of a parsed and validated URDF; raises ``HandModelError`` naming the file and
    what the hand modules need of it."""
    joint_names = tuple(urdf.actuated_joint_names)
    jmap = {j.name: j for j in urdf.robot.joints}
    link_names = tuple(lk.name for lk in urdf.robot.links)
    if urdf.base_link != "palm":
        raise HandModelError(f"hand URDF {path}: root link must be 'palm', got {urdf.base_link!r}")
    lower = np.array([jmap[n].limit.lower for n in joint_names], dtype=np.float64)
    upper = np.array([jmap[n].limit.upper for n in joint_names], dtype=np.float64)

    # kinematic chain in topological order (parents before children)
    child_of = {j.child: j for j in urdf.robot.joints}
    order: list[str] = []
    seen = {"palm"}
    pending = [j for j in urdf.robot.joints]
    while pending:
        ready = [j for j in pending if j.parent in seen]
        if not ready:
            raise HandModelError(f"hand URDF {path}: joints do not form a tree from 'palm'")
        for j in ready:
            order.append(j.name)
            seen.add(j.child)
            pending.remove(j)
    index = {n: i for i, n in enumerate(link_names)}
    chain = []
    for name in order:
        j = jmap[name]
        origin = np.eye(4) if j.origin is None else np.asarray(j.origin, dtype=np.float64)
        ip, ic = index[j.parent], index[j.child]
        if j.type == "fixed":
            chain.append(
                Joint(name, j.parent, j.child, origin, None, -1, 1.0, 0.0, ip, ic, None, None)
            )
            continue
        if j.type != "revolute":
            raise HandModelError(f"hand URDF {path}: joint {name} must be revolute or fixed")
        axis = np.asarray(j.axis, dtype=np.float64)
        axis = axis / np.linalg.norm(axis)
        if j.mimic is not None:
            src = joint_names.index(j.mimic.joint)
            mult, off = float(j.mimic.multiplier or 1.0), float(j.mimic.offset or 0.0)
        else:
            src, mult, off = joint_names.index(name), 1.0, 0.0
        x, y, z = axis
        K = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])  # cross-product matrix
        chain.append(Joint(name, j.parent, j.child, origin, axis, src, mult, off, ip, ic, K, K @ K))

    # collision boxes and visual meshes
    L = len(link_names)
    box_T = np.zeros((L, 4, 4))
    box_half = np.zeros((L, 3))
    visuals: dict[str, trimesh.Trimesh] = {}
    materials = {m.name: m for m in urdf.robot.materials}
    for i, lk in enumerate(urdf.robot.links):
        if len(lk.collisions) != 1 or lk.collisions[0].geometry.box is None:
            raise HandModelError(
                f"hand URDF {path}: link {lk.name} needs exactly one collision <box>"
            )
        col = lk.collisions[0]
        box_T[i] = np.eye(4) if col.origin is None else col.origin
        box_half[i] = np.asarray(col.geometry.box.size, dtype=np.float64) / 2.0
        visuals[lk.name] = load_visual_mesh(path, lk, materials)
    parent_idx = tuple(
        -1 if n == "palm" else link_names.index(child_of[n].parent) for n in link_names
    )

    fingers = []
    for fname in FINGER_NAMES:
        links = (f"{fname}_knuckle", f"{fname}_middle", f"{fname}_distal")
        flex = (f"{fname}_j1", f"{fname}_j2")
        for n in links:
            if n not in link_names:
                raise HandModelError(f"hand URDF {path}: missing link {n}")
        for n in flex:
            if n not in joint_names:
                raise HandModelError(f"hand URDF {path}: missing actuated joint {n}")
            if not np.allclose(jmap[n].axis, [0.0, 1.0, 0.0]):
                raise HandModelError(f"hand URDF {path}: flexion joint {n} must turn about y")
        j1, j2 = jmap[flex[0]], jmap[flex[1]]
        mid = link_names.index(links[1])
        dist = link_names.index(links[2])
        # the planar closing model assumes: links start at their joint on the finger axis,
        # equal cross-sections, and the distal joint on the middle link's axis
        for li, length in ((mid, j2.origin[2, 3]), (dist, 2.0 * box_half[dist, 2])):
            expected = np.eye(4)
            expected[2, 3] = length / 2.0
            if not (np.allclose(box_T[li], expected) and np.isclose(box_half[li, 2], length / 2)):
                raise HandModelError(
                    f"hand URDF {path}: link {link_names[li]}'s box must run from its joint "
                    "along z (origin 0 0 length/2) for the planar closing model"
                )
        if not (
            np.allclose(box_half[mid, :2], box_half[dist, :2])
            and np.allclose(j2.origin[:3, :3], np.eye(3))
            and np.allclose(j2.origin[:2, 3], 0.0)
        ):
            raise HandModelError(
                f"hand URDF {path}: finger {fname}: the middle and distal links must have "
                "equal cross-sections and the distal joint must sit on the middle link's axis"
            )
        spread = f"{fname}_spread" if f"{fname}_spread" in jmap else None
        fingers.append(
            Finger(
                name=fname,
                links=links,
                flexion_joints=flex,
                flex_index=(joint_names.index(flex[0]), joint_names.index(flex[1])),
                spread_joint=spread,
                knuckle_length=float(j1.origin[2, 3]),
                middle_length=float(j2.origin[2, 3]),
                distal_length=float(box_T[dist, 2, 3] + box_half[dist, 2]),
                thickness=float(2.0 * box_half[mid, 0]),
                width=float(2.0 * box_half[mid, 1]),
                lower=lower[[joint_names.index(flex[0]), joint_names.index(flex[1])]],
                upper=upper[[joint_names.index(flex[0]), joint_names.index(flex[1])]],
            )
        )
    if "f1_spread" not in joint_names:
        raise HandModelError(f"hand URDF {path}: f1_spread must be an actuated joint")
    for arr in (lower, upper, box_T, box_half):
        arr.flags.writeable = False  # the model is immutable
    for f in fingers:
        f.lower.flags.writeable = False
        f.upper.flags.writeable = False
    model = model_type(
        urdf_path=path,
        urdf=urdf,
        joint_names=joint_names,
        lower=lower,
        upper=upper,
        link_names=link_names,
        fingers=tuple(fingers),
        spread_index=joint_names.index("f1_spread"),
        link_box_T=box_T,
        link_box_half=box_half,
        link_parent=parent_idx,
        visual_meshes=visuals,
        chain=tuple(chain),
    )
    logger.debug("loaded hand %s: joints %s", path, joint_names)
    return model
