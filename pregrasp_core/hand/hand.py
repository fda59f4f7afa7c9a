"""``Hand``: the three-finger underactuated hand, one object over the hand modules (URDF model,
kinematics, preshapes, closing models, point-in-link queries, self-collision, meshes). Each
method's work is done by the module of its job; see ``docs/hand.md``."""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import fcl
import numpy as np
import trimesh

from ..box import OrientedBox
from . import closing, closing_batch, collision, kinematics, links, meshes, preshapes, urdf
from .model import (
    DEFAULT_CLOSING_STEPS,
    DEFAULT_COUPLING,
    Finger,
    FingerClosing,
    FlexionPlane,
    HandModel,
    grasp_type_name,
)

_PLANE_CACHE: int = 4096
"""Flexion planes :meth:`Hand.flexion_plane` keeps (then it starts again)."""


@dataclass(frozen=True, eq=False)
class Hand(HandModel):
    """The kinematic and geometric model of the hand, loaded once from its URDF, with its
    queries (the fields are those of :class:`HandModel`).

    Build it with :meth:`Hand.load` (or the cached :func:`load_hand`)."""

    @classmethod
    def load(cls, urdf_path: Path | str | None = None) -> Hand:
        """Read and check the hand URDF (default ``pregrasp_core.paths.HAND_URDF``)."""
        return urdf.load_model(urdf_path, cls)

    # ---------------------------------------------------------------- joints (kinematics.py)
    def clamp(self, q: np.ndarray) -> np.ndarray:
        """``q`` ((J,) or (B, J)) clipped to the joint limits."""
        return kinematics.clamp(self, q)

    def within_limits(self, q: np.ndarray, tol: float = 1e-9) -> np.ndarray:
        """Whether each configuration respects the limits: bool () for (J,), (B,) for (B, J)."""
        return kinematics.within_limits(self, q, tol)

    def full_cfg(self, q: np.ndarray) -> dict[str, float]:
        """Joint name -> value for every moving joint (actuated and mimic), e.g. for yourdfpy's
        and viser's ``update_cfg`` or the result file."""
        return kinematics.full_cfg(self, q)

    def with_flexion(self, q: np.ndarray, finger: str | Finger, q_flex: np.ndarray) -> np.ndarray:
        """A copy of ``q`` (J,) with the finger's two flexion joints set to ``q_flex`` (2,)."""
        return kinematics.with_flexion(self, q, finger, q_flex)

    # ---------------------------------------------------------------- kinematics.py
    def fk_array(self, q: np.ndarray) -> np.ndarray:
        """Link poses ``T_hand_link`` as one array: (B, L, 4, 4) for ``q`` (B, J), in
        ``link_names`` order; (L, 4, 4) for ``q`` (J,). Vectorised over configurations."""
        return kinematics.fk_array(self, q)

    def fk(self, q: np.ndarray) -> dict[str, np.ndarray]:
        """Link name -> ``T_hand_link``: (B, 4, 4) for ``q`` (B, J), (4, 4) for ``q`` (J,)."""
        return kinematics.fk(self, q)

    def box_poses(self, q: np.ndarray) -> np.ndarray:
        """Collision box poses ``T_hand_box``: (B, L, 4, 4) for (B, J), (L, 4, 4) for (J,)."""
        return kinematics.box_poses(self, q)

    def fingertips(self, q: np.ndarray) -> dict[str, np.ndarray]:
        """Finger name -> fingertip centre (end of the distal link on its axis), hand frame:
        (B, 3) for ``q`` (B, J), (3,) for (J,)."""
        return kinematics.fingertips(self, q)

    def tip_pads(self, q: np.ndarray) -> dict[str, np.ndarray]:
        """Finger name -> the fingertip's inner edge (end of the distal link, on the closing
        side, in the flexion plane): the point apertures are measured between. (3,) or (B, 3)."""
        return kinematics.tip_pads(self, q)

    def flexion_plane(self, finger: str | Finger, spread: float = 0.0) -> FlexionPlane:
        """The finger's flexion plane in the hand frame for a spread angle (ignored for the
        thumb). Independent of the flexion angles. Computed once per (finger, spread) value
        (a pure function of the hand; the pool builds it for hundreds of pinches), each call
        given its own copy."""
        f = self.finger(finger)
        if not any(f is g for g in self.fingers):  # a finger of another model
            return kinematics.flexion_plane(self, f, spread)
        key = (f.name, float(spread).hex())  # the bits: -0.0 is not 0.0 here
        hit = self._flexion_planes.get(key)
        if hit is None:
            hit = kinematics.flexion_plane(self, f, spread)
            if len(self._flexion_planes) >= _PLANE_CACHE:
                self._flexion_planes.clear()
            self._flexion_planes[key] = hit
        return FlexionPlane(
            origin=hit.origin.copy(), u=hit.u.copy(), v=hit.v.copy(), normal=hit.normal.copy()
        )

    @functools.cached_property
    def _flexion_planes(self) -> dict[tuple[str, str], FlexionPlane]:
        return {}

    @property
    def palm_box(self) -> OrientedBox:
        """The palm's collision box in the hand frame (its top face is the plane z = 0)."""
        return kinematics.palm_box(self)

    # ---------------------------------------------------------------- preshapes.py
    def spread_for(self, grasp_type: object) -> float:
        """Spread angle (radians) of a grasp type: 0, pi/3, 0, pi/2."""
        return preshapes.spread_for(grasp_type)

    def fingers_for(self, grasp_type: object) -> tuple[Finger, ...]:
        """The fingers a grasp type closes (two-finger tip: f1 and f2; the thumb stays open)."""
        return preshapes.fingers_for(self, grasp_type)

    def preshape(self, grasp_type: object) -> np.ndarray:
        """(J,) the open configuration a grasp of this type starts from (see ``docs/hand.md``)."""
        return preshapes.preshape(self, grasp_type)

    def aperture(self, grasp_type: object) -> float:
        """Largest object size (metres) the preshape can enclose, measured between the
        fingertips' inner edges (:meth:`tip_pads`); see :func:`preshapes.apertures`."""
        return self._apertures[grasp_type_name(grasp_type)][0]

    def grasp_center(self, grasp_type: object) -> np.ndarray:
        """(3,) the point on the palm plane (z = 0), hand frame, under the centre of the space
        the preshape's fingertips enclose: align the object's centre with the line through this
        point along +z (the approach). Not the hand origin for every type (the fingers are not
        placed symmetrically about it, e.g. two-finger tip pinches at y = 0.03)."""
        c = self._apertures[grasp_type_name(grasp_type)][1]
        return np.array([c[0], c[1], 0.0])

    @functools.cached_property
    def _apertures(self) -> dict[str, tuple[float, np.ndarray]]:
        return preshapes.apertures(self)

    # ---------------------------------------------------------------- closing models
    def close_finger(
        self,
        finger: str | Finger,
        points_2d: np.ndarray,
        q_start: np.ndarray,
        n_steps: int = DEFAULT_CLOSING_STEPS,
        margin: float = 0.0,
        coupling: float = DEFAULT_COUPLING,
        palm: bool = True,
    ) -> FingerClosing:
        """Close one finger in its flexion plane against points (the slice of the object):
        :func:`pregrasp_core.hand.closing.close_finger`."""
        return closing.close_finger(
            self, finger, points_2d, q_start, n_steps, margin, coupling, palm
        )

    def close_fingers(
        self,
        slices: Sequence[tuple[str | Finger, np.ndarray, np.ndarray]],
        n_steps: int = DEFAULT_CLOSING_STEPS,
        margin: float = 0.0,
        coupling: float = DEFAULT_COUPLING,
        palm: bool = True,
    ) -> list[FingerClosing]:
        """:meth:`close_finger` for many slices ``(finger, points_2d, q_start)`` at once, result
        ``i`` equal to ``close_finger(*slices[i], ...)``:
        :func:`pregrasp_core.hand.closing_batch.close_fingers`."""
        return closing_batch.close_fingers(self, slices, n_steps, margin, coupling, palm)

    # ---------------------------------------------------------------- links.py
    def points_in_links(self, p_hand: np.ndarray, q: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """(N, L) bool: point n lies inside link l's collision box grown by ``margin`` on every
        side, for one configuration ``q`` (J,). Columns in ``link_names`` order."""
        return links.points_in_links(self, p_hand, q, margin)

    def points_in_hand(self, p_hand: np.ndarray, q: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """(N,) bool: point inside any link (grown by ``margin``) at configuration ``q`` (J,)."""
        return links.points_in_hand(self, p_hand, q, margin)

    def link_point_counts(
        self, points: np.ndarray, T_world_hand: np.ndarray, q: np.ndarray, margin: float = 0.0
    ) -> np.ndarray:
        """(G, L) int64: how many of ``points`` (N, 3, world) lie in each link's box (grown by
        ``margin``) for G hands at poses ``T_world_hand`` (G, 4, 4) and configurations ``q``
        ((J,) shared by all hands, or (G, J)); see :func:`.links.link_point_counts`."""
        return links.link_point_counts(self, points, T_world_hand, q, margin)

    def hands_hit_points(
        self, points: np.ndarray, T_world_hand: np.ndarray, q: np.ndarray, margin: float = 0.0
    ) -> np.ndarray:
        """(G,) bool: any of ``points`` (N, 3, world) inside any link of hand g (see
        :meth:`link_point_counts`)."""
        return links.hands_hit_points(self, points, T_world_hand, q, margin)

    # ---------------------------------------------------------------- collision.py
    def collision_objects(self, q: np.ndarray) -> dict[str, fcl.CollisionObject]:
        """Link name -> python-fcl box object placed at configuration ``q`` (J,), hand frame."""
        return collision.collision_objects(self, q)

    @functools.cached_property
    def self_collision_checker(self) -> collision.SelfCollisionChecker:
        """The self-collision queries and the link pairs they check (built once)."""
        return collision.SelfCollisionChecker.of(self)

    @property
    def self_collision_pairs_checked(self) -> tuple[tuple[str, str], ...]:
        """Link pairs the self-collision check tests: all pairs except parent and child links
        (which touch at their joint by construction)."""
        return self.self_collision_checker.pairs

    def self_collisions(
        self, q: np.ndarray, box_poses: np.ndarray | None = None
    ) -> list[tuple[str, str]]:
        """The link pairs (of :attr:`self_collision_pairs_checked`) whose boxes intersect at
        configuration ``q`` (J,), by python-fcl. ``box_poses``: :meth:`box_poses` of ``q``
        (L, 4, 4) when the caller already has them (saves the forward kinematics)."""
        return self.self_collision_checker.collisions(q, box_poses)

    def self_collisions_many(
        self, Q: np.ndarray, box_poses: np.ndarray | None = None
    ) -> list[list[tuple[str, str]]]:
        """:meth:`self_collisions` for B configurations ``Q`` (B, J) at once: result ``b`` equals
        ``self_collisions(Q[b])`` exactly (same pairs, same order). ``box_poses``:
        :meth:`box_poses` of ``Q`` (B, L, 4, 4) when the caller already has them. B = 0 gives
        ``[]``."""
        return self.self_collision_checker.collisions_many(Q, box_poses)

    def self_collision(self, q: np.ndarray) -> bool:
        """True when two non-adjacent links' collision boxes intersect at ``q`` (J,)."""
        return len(self.self_collisions(q)) > 0

    # ---------------------------------------------------------------- meshes.py
    def hand_mesh(self, q: np.ndarray) -> trimesh.Trimesh:
        """The visual mesh of the whole hand at configuration ``q`` (J,), in the hand frame,
        with per-face colours from the URDF materials."""
        return meshes.hand_mesh(self, q)

    def collision_mesh(self, q: np.ndarray) -> trimesh.Trimesh:
        """The collision boxes at ``q`` (J,) as one mesh in the hand frame (for drawing)."""
        return meshes.collision_mesh(self, q)


@functools.lru_cache(maxsize=4)
def load_hand(urdf_path: Path | str | None = None) -> Hand:
    """:meth:`Hand.load`, cached per path (the model is immutable)."""
    return Hand.load(urdf_path)
