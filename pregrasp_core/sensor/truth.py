"""Grasps checked against the true mesh behind a generated view (the reference of issue 13).

A grasp planned on a single view rests on what the camera saw and on what the completion
assumed. :func:`check_grasp` measures it against the object itself, the mesh the view was ray
cast from (``scripts/make_views.py`` keeps it beside every view):

- **penetration**: the deepest point of the closed hand inside the mesh, over a regular grid of
  ``grid`` x ``grid`` x ``grid`` points in every link's collision box (corners, edges, faces and
  the inside; 7 gives a 2.5 mm spacing on a 15 mm link);
- **contact distance**: per contact, the distance of the contact point to the mesh surface.

:class:`MeshDistance` is the signed distance to a triangle mesh, exact where it matters and fast
enough for thousands of grasps: the surface is sampled densely once (a KD-tree of the samples
and the face of each); a query point's candidate faces are those of its ``k`` nearest samples;
the exact closest point on each candidate triangle (trimesh's vectorised point-triangle
projection) gives the distance, and the side is the sign of ``(p - c) . n`` for the closest
triangle's normal ``n`` (ties at an edge: the triangle whose normal is most aligned with
``p - c``). Positive inside, as trimesh's ``signed_distance``; checked against it in
``tests/core/test_partial_grasps.py``. The error is bounded by the sample spacing when the
nearest triangle has none of the ``k`` nearest samples (tiny faces next to large ones), which
never happened on the demo meshes.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import trimesh
from scipy.spatial import cKDTree

if TYPE_CHECKING:
    from ..hand import Hand
    from ..planner import Grasp

TIE: float = 1e-9
"""Metres: candidate triangles whose distances differ by less than this tie (an edge)."""


class BodyDistance:
    """Signed distance to one body of a mesh (positive inside; see the module)."""

    def __init__(self, mesh: trimesh.Trimesh, samples: int, k: int, seed: int) -> None:
        self.mesh = mesh
        self.k = int(k)
        pts, face = trimesh.sample.sample_surface(mesh, max(int(samples), 1), seed=seed)
        # every face gets at least its centroid, so that no face is without a sample
        pts = np.concatenate([np.asarray(pts), mesh.triangles_center])
        face = np.concatenate([np.asarray(face), np.arange(len(mesh.faces))])
        self.tree = cKDTree(pts)
        self.face = face.astype(np.int64)
        self.triangles = np.asarray(mesh.triangles, dtype=np.float64)
        self.normals = np.asarray(mesh.face_normals, dtype=np.float64)

    def signed(self, p: np.ndarray, refine: float) -> np.ndarray:
        """(N,) signed distances of ``p`` (N, 3), positive inside: exact for the points within
        ``refine`` of a surface sample, the distance to the nearest sample (at most a sample
        spacing too long) for the others."""
        d0, _ = self.tree.query(p)
        dist = d0.copy()
        todo = np.flatnonzero(d0 <= refine)
        cand = np.zeros((0, self.k), dtype=np.int64)
        v = np.zeros((0, self.k, 3))
        if len(todo):
            pt = p[todo]
            _, idx = self.tree.query(pt, k=self.k)  # (T, k)
            cand = self.face[idx]  # (T, k) candidate faces (repeats are harmless)
            q = np.repeat(pt, self.k, axis=0)
            c = trimesh.triangles.closest_point(self.triangles[cand.reshape(-1)], q)
            v = (q - c).reshape(len(pt), self.k, 3)
            dist[todo] = np.linalg.norm(v, axis=2).min(axis=1)
        if self.mesh.is_watertight:  # the side by ray parity (embree when installed)
            inside = np.asarray(self.mesh.contains(p), dtype=bool)
        else:  # the side of the closest triangle (ties at an edge: the most aligned normal)
            _, i0 = self.tree.query(p)
            n0 = self.normals[self.face[i0]]
            inside = np.einsum("ij,ij->i", p - self.tree.data[i0], n0) < 0.0
            if len(todo):
                d = np.linalg.norm(v, axis=2)
                dot = np.einsum("nkj,nkj->nk", v, self.normals[cand])
                cos = np.abs(dot) / np.maximum(d, 1e-15)
                near = d <= d.min(axis=1, keepdims=True) + TIE
                pick = np.argmax(np.where(near, cos, -1.0), axis=1)
                inside[todo] = dot[np.arange(len(todo)), pick] < 0.0
        return np.where(inside, dist, -dist)


class MeshDistance:
    """Signed distance to a triangle mesh, positive inside (see the module).

    A mesh of several bodies (a hammer's head over its handle) is their union: the signed
    distance is the largest over the bodies, exact outside and near the surface, a lower bound
    of the depth deep inside where bodies overlap.
    """

    def __init__(self, mesh: trimesh.Trimesh, samples: int = 200_000, k: int = 8,
                 seed: int = 0, refine: float = 0.01) -> None:  # fmt: skip
        self.mesh = mesh
        self.refine = float(refine)
        bodies = mesh.split(only_watertight=False) if mesh.body_count > 1 else [mesh]
        area = sum(float(b.area) for b in bodies)
        self.bodies = [
            BodyDistance(b, int(samples * float(b.area) / area), k, seed + i)
            for i, b in enumerate(bodies)
        ]

    def signed(self, points: np.ndarray) -> np.ndarray:
        """(N,) signed distances of ``points`` (N, 3) to the surface, metres, positive inside:
        exact within ``refine`` of the surface, at most a sample spacing (0.2-0.7 mm on the
        demo objects) too far beyond."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        if len(p) == 0:
            return np.zeros(0)
        return np.max([b.signed(p, self.refine) for b in self.bodies], axis=0)

    def unsigned(self, points: np.ndarray) -> np.ndarray:
        """(N,) distances of ``points`` (N, 3) to the surface, metres."""
        return np.abs(self.signed(points))


@dataclass(frozen=True)
class GraspCheck:
    """One grasp measured against the true mesh."""

    penetration: float
    """Metres: the deepest grid point of the hand's link boxes inside the mesh (<= 0: none)."""
    link: str
    """The link holding that point."""
    contact_distance: np.ndarray
    """(C,) metres: each contact point's distance to the mesh surface."""

    @property
    def worst_contact(self) -> float:
        """The largest contact distance (0 without contacts)."""
        return float(self.contact_distance.max()) if len(self.contact_distance) else 0.0


def link_grid(hand: Hand, T_world_hand: np.ndarray, q: np.ndarray, grid: int = 7) -> np.ndarray:
    """(L, grid**3, 3) world points filling every collision box of the hand at ``q``."""
    g = np.linspace(-1.0, 1.0, int(grid))
    unit = np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1).reshape(-1, 3)
    half = np.asarray(hand.link_box_half, dtype=np.float64)  # (L, 3)
    Tb = np.asarray(T_world_hand) @ hand.box_poses(np.asarray(q))  # (L, 4, 4)
    local = unit[None] * half[:, None, :]
    return np.einsum("lij,lpj->lpi", Tb[:, :3, :3], local) + Tb[:, None, :3, 3]


def check_grasp(grasp: Grasp, hand: Hand, truth: MeshDistance, grid: int = 7) -> GraspCheck:
    """``grasp`` (a kept :class:`~pregrasp_core.planner.Grasp`) against the true mesh."""
    pts = link_grid(hand, grasp.T_world_hand, grasp.q, grid)
    sd = truth.signed(pts.reshape(-1, 3)).reshape(pts.shape[:2])
    per_link = sd.max(axis=1)
    j = int(np.argmax(per_link))
    cp = np.array([c.point for c in grasp.contacts]).reshape(-1, 3)
    return GraspCheck(float(per_link[j]), hand.link_names[j], truth.unsigned(cp))
