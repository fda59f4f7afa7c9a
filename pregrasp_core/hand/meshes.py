"""The hand's meshes: the visual mesh of each link read from the URDF (face colours from its
materials) and the whole hand's visual and collision meshes at a configuration, hand frame."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh
import yourdfpy

from ..errors import HandModelError
from .kinematics import box_poses, fk_array
from .model import HandModel


def load_visual_mesh(
    urdf_path: Path, link: yourdfpy.Link, materials: dict[str, yourdfpy.Material]
) -> trimesh.Trimesh:
    """The link's visual mesh in its link frame, coloured by its URDF material (``materials``:
    the robot-level materials by name, which a link's material may refer to)."""
    if len(link.visuals) != 1 or link.visuals[0].geometry.mesh is None:
        raise HandModelError(f"hand URDF {urdf_path}: link {link.name} needs one visual <mesh>")
    vis = link.visuals[0]
    mesh_path = urdf_path.parent / vis.geometry.mesh.filename
    if not mesh_path.is_file():
        raise HandModelError(
            f"hand mesh {mesh_path} (link {link.name}) is missing; run scripts/make_hand_meshes.py"
        )
    mesh = trimesh.load(str(mesh_path), force="mesh")
    if not isinstance(mesh, trimesh.Trimesh):
        raise HandModelError(
            f"hand mesh {mesh_path} (link {link.name}) is not one triangle mesh; "
            "run scripts/make_hand_meshes.py"
        )
    if vis.origin is not None:
        mesh.apply_transform(vis.origin)
    rgba = (0.7, 0.7, 0.7, 1.0)
    mat = vis.material
    if mat is not None and mat.color is None and mat.name in materials:
        mat = materials[mat.name]  # a reference to a robot-level material
    if mat is not None and mat.color is not None:
        rgba = tuple(mat.color.rgba)
    visual = mesh.visual
    if not isinstance(visual, trimesh.visual.ColorVisuals):
        raise HandModelError(f"hand mesh {mesh_path} (link {link.name}) must not be textured")
    visual.face_colors = np.round(np.asarray(rgba) * 255).astype(np.uint8)
    return mesh


def _concatenate(parts: list[trimesh.Trimesh]) -> trimesh.Trimesh:
    mesh = trimesh.util.concatenate(parts)
    assert isinstance(mesh, trimesh.Trimesh)  # (typed Geometry; a list of meshes gives a mesh)
    return mesh


def hand_mesh(model: HandModel, q: np.ndarray) -> trimesh.Trimesh:
    """The visual mesh of the whole hand at configuration ``q`` (J,), in the hand frame,
    with per-face colours from the URDF materials."""
    T = fk_array(model, model.one_q(q))
    parts = []
    for i, n in enumerate(model.link_names):
        m = model.visual_meshes[n].copy()
        m.apply_transform(T[i])
        parts.append(m)
    return _concatenate(parts)


def collision_mesh(model: HandModel, q: np.ndarray) -> trimesh.Trimesh:
    """The collision boxes at ``q`` (J,) as one mesh in the hand frame (for drawing)."""
    Tb = box_poses(model, model.one_q(q))
    parts = [
        trimesh.creation.box(extents=2.0 * model.link_box_half[i], transform=Tb[i])
        for i in range(len(model.link_names))
    ]
    return _concatenate(parts)
