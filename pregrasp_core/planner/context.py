"""What every pre-grasp of one plan shares (:class:`Context`: the cloud, its cells, the hand's
geometry and caches) and the cloud as one hand pose sees it (:class:`View`)."""

from __future__ import annotations

import dataclasses
import threading
from dataclasses import dataclass
from typing import TYPE_CHECKING, TypeVar

import numpy as np

from ..geometry import box_corners, to_frame_t
from .cells import Cells
from .types import PlannerParams

if TYPE_CHECKING:
    from ..facemask import SupportPlane
    from ..hand import Finger, FlexionPlane, Hand

_V = TypeVar("_V")

PlaneArrays = tuple[tuple["Finger", ...], list["FlexionPlane"], np.ndarray, tuple[np.ndarray, ...]]
"""The fingers of a grasp type, their flexion planes at a spread, their reaches and the slice
kernel's per-plane arguments (``slicing._plane_arrays``)."""

CELL_SIZE: float = 0.01
"""Side (metres) of the cubic cells that group the cloud for the planner's candidate searches
(see :class:`Cells`). Only the speed depends on it, never a result."""


@dataclass(frozen=True)
class View:
    """The cloud as the hand sees it: in the frame of the pre-grasp pose ``T0``, then moved
    along the approach by the shifts ``dz`` (hand z), added one after the other as the planner
    moved the hand (so that every coordinate is rounded exactly as when the planner worked on
    one array of all the points). Only the points in the keep box (``T0`` frame: ``|x|, |y| <=
    r``, ``z_lo <= z <= z_hi``) are ever seen: every point a link can touch or hold."""

    T0: np.ndarray  # (4, 4) the pre-grasp pose
    centres: np.ndarray  # (C, 3) the cell centres in the frame of T0
    r: float
    z_lo: float
    z_hi: float
    dz: tuple[float, ...] = ()

    def moved(self, dz: float) -> View:
        """The view after the hand moved by ``dz`` along hand z (a retreat: positive)."""
        return dataclasses.replace(self, dz=(*self.dz, dz))

    def cells(self, ctx: Context) -> tuple[np.ndarray, np.ndarray]:
        """``(centres (C, 3), ok (C,))``: the cell centres in the hand frame (the shifts summed:
        the cell tests need no exact rounding, their radii cover it) and which cells' balls
        meet the keep box."""
        rad = ctx.cells.radius
        c = self.centres
        ok = (np.abs(c[:, 0]) <= self.r + rad) & (np.abs(c[:, 1]) <= self.r + rad)
        ok &= (c[:, 2] >= self.z_lo - rad) & (c[:, 2] <= self.z_hi + rad)
        c = c.copy()
        c[:, 2] += sum(self.dz)
        return c, ok

    def points(self, ctx: Context, pid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(ok (K,), p (3, K'))``: which of the cloud points ``pid`` are in the keep box, and
        their coordinates in the hand frame (by coordinate: x, y, z rows)."""
        p0 = to_frame_t(ctx.xyz[:, pid], self.T0)
        x, y, z = p0
        ok = (np.abs(x) <= self.r) & (np.abs(y) <= self.r) & (z >= self.z_lo) & (z <= self.z_hi)
        p = p0[:, ok]
        for d in self.dz:  # loop over <= 2 moves
            p[2] += d
        return ok, p

    def near(self, ctx: Context, centre: np.ndarray, radius: float) -> np.ndarray:
        """(M, 3) the seen points within ``radius`` of ``centre`` (hand frame), in ascending
        cloud order."""
        c, ok = self.cells(ctx)
        ok &= np.sum((c - centre) ** 2, axis=1) <= (radius + ctx.cells.radius) ** 2
        _, p = self.points(ctx, ctx.cells.points_of(np.flatnonzero(ok)))
        d2 = (p[0] - centre[0]) ** 2 + (p[1] - centre[1]) ** 2 + (p[2] - centre[2]) ** 2
        return np.ascontiguousarray(p[:, d2 <= radius**2].T)


class Context:
    """Per-call data shared by every pre-grasp (cloud, hand geometry caches)."""

    def __init__(
        self,
        points: np.ndarray,
        normals: np.ndarray,
        hand: Hand,
        params: PlannerParams,
        support: SupportPlane | None,
        surface: np.ndarray | None = None,
        assumed: np.ndarray | None = None,
        crest: np.ndarray | None = None,
    ) -> None:
        """points, normals: (N, 3) float64, world (outward unit normals); support: the table
        or None; surface: (N, 3) the contacts' positions when they differ from the points the
        hand clears (assumed points, ``planner/assumed.py``); assumed: (N,) bool or None; crest:
        (N,) bool or None, the points whose normal is the crest rule's (their contacts take the
        mean of it and the link's push, ``verify.crest_contact_normals``)."""
        self.surface = points if surface is None else surface
        self.assumed = np.zeros(len(points), dtype=bool) if assumed is None else assumed
        self.points = points
        self.normals = normals
        self.crest = crest
        self.hand = hand
        self.params = params
        self.support = support
        self.cells = Cells(points, CELL_SIZE)
        self.xyz = np.ascontiguousarray(points.T)  # (3, N) the cloud by coordinate
        self.link_names = tuple(hand.link_names)
        self.half = np.asarray(hand.link_box_half, dtype=np.float64)
        self.link_index = {n: i for i, n in enumerate(self.link_names)}
        self.clock = dict.fromkeys(("approach_slicing", "closing", "verification", "quality"), 0.0)
        self._planes: dict[tuple[str, float], FlexionPlane] = {}
        # per (grasp type, spread): the slice kernel's plane arguments (slicing._plane_arrays)
        self.slice_planes: dict[tuple[str, float], PlaneArrays] = {}
        self._boxes: dict[bytes, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
        self._pairs: dict[bytes, list[tuple[str, str]]] = {}
        self._corners: dict[bytes, np.ndarray] = {}
        self._lock = threading.Lock()
        # reach: half side of a cube about the palm origin that holds every link box at any
        # configuration (palm half diagonal, or first joint + middle + distal at any flexion)
        reach = np.linalg.norm(self.half[self.link_index["palm"]])
        for f in hand.fingers:
            base = np.linalg.norm(hand.flexion_plane(f, 0.0).origin)
            tip = f.middle_length + f.distal_length + np.hypot(0.5 * f.thickness, 0.5 * f.width)
            reach = max(reach, base + tip)
        self.reach = float(reach)

    def plane(self, finger: Finger, spread: float) -> FlexionPlane:
        """:meth:`Hand.flexion_plane` of ``finger`` at the spread ``spread`` (cached)."""
        key = (finger.name, round(float(spread), 12))
        hit = self._planes.get(key)
        if hit is None:  # (threads: a plane computed twice is the same plane)
            hit = self._planes.setdefault(key, self.hand.flexion_plane(finger, spread))
        return hit

    def prefetch_boxes(self, Q: np.ndarray) -> None:
        """Compute and cache the box poses and the self-collisions (:meth:`self_pairs`) of many
        configurations ``Q`` (B, J) at once."""
        Q = np.ascontiguousarray(Q, dtype=np.float64)
        new = [b for b in range(len(Q)) if Q[b].tobytes() not in self._pairs]
        if not new:
            return
        Tb_all = self.hand.box_poses(Q[new])  # (B', L, 4, 4)
        corners = box_corners(Tb_all.reshape(-1, 4, 4), np.tile(self.half, (len(new), 1)))
        corners = corners.reshape(len(new), -1, 8, 3)
        lo, hi = corners.min(axis=2), corners.max(axis=2)
        pairs = self.hand.self_collisions_many(Q[new], Tb_all)
        for k, b in enumerate(new):  # loop over the configurations: fill the caches
            key = Q[b].tobytes()
            self._store(self._boxes, key, (Tb_all[k], lo[k], hi[k]))
            self._store(self._pairs, key, pairs[k])

    def _store(self, cache: dict[bytes, _V], key: bytes, value: _V) -> None:
        with self._lock:  # the planner's threads share the caches; every change goes here
            cache[key] = value
            while len(cache) > 4096:  # a bound for pools of arbitrary preshapes
                cache.pop(next(iter(cache)))

    def self_pairs(self, q: np.ndarray) -> list[tuple[str, str]]:
        """:meth:`Hand.self_collisions` at ``q`` (cached)."""
        key = q.tobytes()
        hit = self._pairs.get(key)
        if hit is None:
            hit = self.hand.self_collisions(q, self.boxes(q)[0])
            self._store(self._pairs, key, hit)
        return hit

    def corners(self, q: np.ndarray) -> np.ndarray:
        """(8 L, 3) ``geometry.box_corners`` of the link boxes at ``q`` in the hand frame
        (cached: the approach asks for them at every pre-grasp, with a few preshapes)."""
        key = q.tobytes()
        hit = self._corners.get(key)
        if hit is None:
            hit = box_corners(self.boxes(q)[0], self.half)
            hit.flags.writeable = False  # (shared by the threads)
            self._store(self._corners, key, hit)
        return hit

    def boxes(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Box poses (L, 4, 4) and their hand-frame AABBs lo, hi (L, 3) at ``q`` (cached)."""
        key = q.tobytes()
        hit = self._boxes.get(key)
        if hit is None:
            Tb = self.hand.box_poses(q)
            corners = box_corners(Tb, self.half).reshape(-1, 8, 3)
            hit = (Tb, corners.min(axis=1), corners.max(axis=1))
            self._store(self._boxes, key, hit)
        return hit
