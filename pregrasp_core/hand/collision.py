"""Collision queries of the hand's link boxes with python-fcl: placed collision objects, and
self-collision of one or many configurations (a ball test and, for batches, an exact
separating-axis pre-filter in front of python-fcl, whose verdict every answer is)."""

from __future__ import annotations

from dataclasses import dataclass, field

import fcl
import numpy as np

from ..tolerances import SAT_ABS_ROTATION_EPS, SELF_COLLISION_SAT_MARGIN
from . import kinematics
from .model import HandModel

SAT_MIN_PAIRS: int = 40
"""Self-collision: the separating-axis pre-filter runs only when at least this many (hand, link
pair) candidates pass the ball test, so never for one hand (36 checked pairs). Its fixed numpy
cost (about 80 us) exceeds python-fcl on each candidate (about 1 us a test plus 3-4 us per placed
link box) for one hand at every candidate count (measured: 98 vs 60 us at 0-5 candidates, 275 vs
162 us at 24-36), and pays off for a batch (``benchmarks/bench_hand.py``). Either way the answer
is python-fcl's."""

_I1 = np.array([1, 2, 0])
"""The first of the two other axes of axis i (i + 1 mod 3)."""
_I2 = np.array([2, 0, 1])
"""The second of the two other axes of axis i (i + 2 mod 3)."""


def obb_apart(
    Ra: np.ndarray,
    ca: np.ndarray,
    ha: np.ndarray,
    Rb: np.ndarray,
    cb: np.ndarray,
    hb: np.ndarray,
    margin: float = SELF_COLLISION_SAT_MARGIN,
) -> np.ndarray:
    """(N,) bool: oriented boxes a and b of each of N pairs are proven apart, i.e. one of the 15
    separating axes (the 3 + 3 face normals, the 9 cross products of an edge direction of a with
    one of b) parts them by more than ``margin`` (metres). False means "not proven": on every
    axis the boxes overlap, touch or are closer than the margin.

    Pair index last (every operation runs over contiguous length-N rows): ``Ra``, ``Rb``
    (3, 3, N) rotations, ``Ra[:, i, n]`` = axis i of box a of pair n; ``ca``, ``cb`` (3, N)
    centres; ``ha``, ``hb`` (3, N) half sides; all in one frame. Everything is expressed in a's
    frame: ``C = Ra^T Rb`` (b's axes as columns), ``t = Ra^T (cb - ca)``. ``|C|`` is padded by
    ``SAT_ABS_ROTATION_EPS`` (near-parallel edges), which only grows the projected radii. An
    axis u_i x v_j is not a unit vector: its length ``|(C[i1, j], C[i2, j])|`` scales the
    margin, so that the margin is metres along the unit axis. The 9 cross-product axes are
    tested only on the pairs the 6 face normals leave."""
    d = cb - ca  # (3, N)
    # (3, 3, N): C[i, j] = u_i . v_j
    C = Ra[0, :, None] * Rb[0, None] + Ra[1, :, None] * Rb[1, None] + Ra[2, :, None] * Rb[2, None]
    t = Ra[0] * d[0] + Ra[1] * d[1] + Ra[2] * d[2]  # (3, N): b's centre in a's frame
    A = np.abs(C) + SAT_ABS_ROTATION_EPS  # (3, 3, N)
    # a's face normals u_i: |t_i| - (ha_i + sum_j |C_ij| hb_j)
    s_a = np.abs(t) - ha - (A[:, 0] * hb[0] + A[:, 1] * hb[1] + A[:, 2] * hb[2])  # (3, N)
    # b's face normals v_j: |sum_i C_ij t_i| - (sum_i |C_ij| ha_i + hb_j)
    s_b = np.abs(C[0] * t[0] + C[1] * t[1] + C[2] * t[2])
    s_b -= A[0] * ha[0] + A[1] * ha[1] + A[2] * ha[2] + hb  # (3, N)
    apart = (np.maximum(s_a, s_b) > margin).any(axis=0)  # (N,)
    left = np.flatnonzero(~apart)  # pairs no face normal parts
    if len(left) == 0:
        return apart
    C, A, t = C[:, :, left], A[:, :, left], t[:, left]
    ha, hb = ha[:, left], hb[:, left]
    # u_i x v_j, (3, 3, M) indexed [i, j]; i1, i2 (j1, j2) are the two other axes of i (j):
    # |t_i2 C_i1j - t_i1 C_i2j| - (ha_i1 |C_i2j| + ha_i2 |C_i1j| + hb_j1 |C_ij2| + hb_j2 |C_ij1|)
    C1, C2 = C[_I1], C[_I2]
    s_x = np.abs(t[_I2, None] * C1 - t[_I1, None] * C2)
    s_x -= ha[_I1, None] * A[_I2] + ha[_I2, None] * A[_I1]
    s_x -= hb[None, _I1] * A[:, _I2] + hb[None, _I2] * A[:, _I1]
    length = np.sqrt(C1 * C1 + C2 * C2)  # |u_i x v_j|
    apart[left] = (s_x > margin * length).any(axis=(0, 1))
    return apart


def collision_objects(model: HandModel, q: np.ndarray) -> dict[str, fcl.CollisionObject]:
    """Link name -> python-fcl box object placed at configuration ``q`` (J,), hand frame."""
    Tb = kinematics.box_poses(model, model.one_q(q))
    out = {}
    for i, n in enumerate(model.link_names):
        geom = fcl.Box(*(2.0 * model.link_box_half[i]))
        out[n] = fcl.CollisionObject(geom, fcl.Transform(Tb[i, :3, :3], Tb[i, :3, 3]))
    return out


@dataclass(frozen=True, eq=False)
class SelfCollisionChecker:
    """Self-collision queries of one hand: the link pairs it checks (all pairs except parent and
    child links, which touch at their joint by construction) and what the tests need, built
    once per hand (:meth:`of`)."""

    model: HandModel = field(repr=False)
    """The hand (limits, forward kinematics, box sizes)."""
    pairs: tuple[tuple[str, str], ...]
    """(P,) the checked link pairs, by link names (``Hand.self_collision_pairs_checked``)."""
    a: np.ndarray
    """(P,) int64 index of each pair's first link in ``link_names``."""
    b: np.ndarray
    """(P,) int64 index of each pair's second link."""
    reach: np.ndarray
    """(P,) sum of the two boxes' circumscribed radii (metres): farther apart, no contact."""
    boxes: tuple[fcl.Box, ...]
    """(L,) python-fcl box geometry of every link (immutable; shared by the placed objects)."""

    @classmethod
    def of(cls, model: HandModel) -> SelfCollisionChecker:
        """The checker of ``model``'s hand."""
        pairs: list[tuple[str, str]] = []
        L = len(model.link_names)
        for a in range(L):
            for b in range(a + 1, L):
                if model.link_parent[a] == b or model.link_parent[b] == a:
                    continue
                pairs.append((model.link_names[a], model.link_names[b]))
        index = {n: i for i, n in enumerate(model.link_names)}
        ia = np.array([index[a] for a, _ in pairs], dtype=np.int64)
        ib = np.array([index[b] for _, b in pairs], dtype=np.int64)
        r = np.linalg.norm(np.asarray(model.link_box_half, dtype=np.float64), axis=1)
        boxes = tuple(
            fcl.Box(*(2.0 * h)) for h in np.asarray(model.link_box_half, dtype=np.float64)
        )
        return cls(model=model, pairs=tuple(pairs), a=ia, b=ib, reach=r[ia] + r[ib], boxes=boxes)

    def collisions(
        self, q: np.ndarray, box_poses: np.ndarray | None = None
    ) -> list[tuple[str, str]]:
        """The link pairs (of ``pairs``) whose boxes intersect at configuration ``q`` (J,), by
        python-fcl. ``box_poses``: ``Hand.box_poses`` of ``q``
        (L, 4, 4) when the caller already has them (saves the forward kinematics).

        The ball test of :meth:`collisions_many` skips pairs proven apart and python-fcl
        decides the rest, so the answer is python-fcl's on every checked pair (the batch's
        separating-axis filter does not pay for one hand; see ``SAT_MIN_PAIRS``)."""
        q1 = self.model.one_q(q)
        if box_poses is None:
            Tb = kinematics.box_poses(self.model, q1)  # (L, 4, 4)
        else:
            Tb = np.asarray(box_poses, dtype=np.float64)
            L = len(self.model.link_names)
            if Tb.shape != (L, 4, 4):
                raise ValueError(f"box_poses must have shape ({L}, 4, 4), got {Tb.shape}")
        return self.collisions_of(Tb[None])[0]

    def collisions_many(
        self, Q: np.ndarray, box_poses: np.ndarray | None = None
    ) -> list[list[tuple[str, str]]]:
        """:meth:`collisions` for B configurations ``Q`` (B, J) at once: result ``b`` equals
        ``collisions(Q[b])`` exactly (same pairs, same order). ``box_poses``: ``Hand.box_poses``
        of ``Q`` (B, L, 4, 4) when the caller already has them. B = 0 gives ``[]``.

        Per (configuration, checked pair), all at once: the circumscribed-ball test, then (when
        at least ``SAT_MIN_PAIRS`` candidates are left, i.e. for batches) an exact oriented-box
        separating-axis test (3 + 3 face normals, 9 edge cross products) that calls a pair apart
        only when an axis parts the boxes by more than ``SELF_COLLISION_SAT_MARGIN``; python-fcl
        decides the rest (touching or intersecting boxes, a few per closed hand), so every
        verdict is python-fcl's."""
        Qa = np.asarray(Q, dtype=np.float64)
        J, L = self.model.n_joints, len(self.model.link_names)
        if Qa.ndim != 2 or Qa.shape[1] != J:
            raise ValueError(f"Q must have shape (B, {J}), got {Qa.shape}")
        B = Qa.shape[0]
        if box_poses is None:
            if B == 0:
                return []
            Tb = kinematics.box_poses(self.model, Qa)  # (B, L, 4, 4)
        else:
            Tb = np.asarray(box_poses, dtype=np.float64)
            if Tb.shape != (B, L, 4, 4):
                raise ValueError(f"box_poses must have shape ({B}, {L}, 4, 4), got {Tb.shape}")
            if B == 0:
                return []
        return self.collisions_of(Tb)

    def collisions_of(
        self, Tb: np.ndarray, only: np.ndarray | None = None
    ) -> list[list[tuple[str, str]]]:
        """The intersecting checked pairs of each of B hands given their box poses Tb
        (B, L, 4, 4): ball test, separating-axis test, python-fcl on what is left. ``only``:
        the positions in ``pairs`` of the pairs to check (None: every pair); each verdict is
        the one the check of every pair gives (the pairs are tested independently)."""
        sel = np.arange(len(self.pairs)) if only is None else np.asarray(only, dtype=np.int64)
        ia, ib, reach = self.a[sel], self.b[sel], self.reach[sel]  # (P,), (P,), (P,)
        B = Tb.shape[0]
        out: list[list[tuple[str, str]]] = [[] for _ in range(B)]
        c = Tb[:, :, :3, 3]  # (B, L, 3) box centres
        # exact pre-test: boxes whose circumscribed balls are apart cannot intersect
        gap = np.linalg.norm(c[:, ia] - c[:, ib], axis=2) - reach  # (B, P)
        bb, kk = np.nonzero(gap <= 1e-6)  # (N,) candidates, by configuration then pair order
        if len(bb) == 0:
            return out
        la, lb = ia[kk], ib[kk]  # (N,) link indices of each candidate
        if len(bb) >= SAT_MIN_PAIRS:
            Tt = Tb.transpose(2, 3, 0, 1)  # (4, 4, B, L) view: gathers come out pair-last
            half = np.asarray(self.model.link_box_half, dtype=np.float64).T  # (3, L)
            apart = obb_apart(
                Tt[:3, :3, bb, la], Tt[:3, 3, bb, la], half[:, la],
                Tt[:3, :3, bb, lb], Tt[:3, 3, bb, lb], half[:, lb],
            )  # fmt: skip
            todo = np.flatnonzero(~apart)  # candidates python-fcl decides (few)
        else:  # one hand's candidates: python-fcl on each is cheaper (measured)
            todo = np.arange(len(bb))
        if len(todo) == 0:
            return out
        geoms = self.boxes
        objs: dict[tuple[int, int], fcl.CollisionObject] = {}  # (hand, link) -> placed box
        req = fcl.CollisionRequest()
        pairs = [self.pairs[k] for k in sel.tolist()]
        # loop over the pairs no separating axis parts (a few per hand); plain ints (fast keys)
        for b, k, *links in zip(*(x[todo].tolist() for x in (bb, kk, la, lb)), strict=True):
            for li in links:  # place each link box of this hand once
                if (b, li) not in objs:
                    objs[(b, li)] = fcl.CollisionObject(
                        geoms[li], fcl.Transform(Tb[b, li, :3, :3], Tb[b, li, :3, 3])
                    )
            res = fcl.CollisionResult()
            if fcl.collide(objs[(b, links[0])], objs[(b, links[1])], req, res) > 0:
                out[b].append(pairs[k])
        return out
