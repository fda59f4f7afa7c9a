"""Steps 3 and 4 for one pre-grasp, after the closing: 3D verification of the closed hand
(fingers closed into each other or into the cloud are opened back along their closing paths;
penetration, self-collision and support checks) and its contacts (:func:`finish`)."""

from __future__ import annotations

import itertools
from typing import TYPE_CHECKING

import fcl
import numpy as np

from ..tolerances import GEOM_EPS
from .boxes import box_push_direction, box_signed_distance
from .context import Context, View
from .kernels import kernels
from .types import Contact, FingerTrace, Grasp

if TYPE_CHECKING:
    from ..hand import Finger
    from .approach import Prepared
    from .slicing import ClosedFinger

SUPPORT_PRETEST_MARGIN: float = 1e-6
"""Metres: a link box whose lowest point is this far above the support's collision plane is
not handed to fcl (fcl would report no contact; the margin is far above the rounding)."""

CONTACT_TIE: float = 1e-12
"""Metres: cloud points this close to a link's least distance tie for its contact."""


def finish(
    ctx: Context, pre: Prepared, q: np.ndarray, closings: list[ClosedFinger], lift: float
) -> Grasp:
    """Pre-grasp ``pre`` after the closing (``q`` and ``closings`` from
    :func:`~pregrasp_core.planner.slicing.closing_records`, closed ``lift`` metres back along
    the approach): 3D verification and contacts; the grasp is scored by the caller."""
    prm = ctx.params
    i, gt, T0 = pre.i, pre.gt, pre.T0
    T, s, stop, view = pre.T.copy(), pre.s, pre.stop, pre.view

    if lift > 0.0:  # the hand closed from higher up (the retreat from the support)
        T[:3, 3] -= lift * T0[:3, 2]
        view = view.moved(lift)
        s -= lift
        stop = "support_lifted"

    # 3. verification in 3D. Fingers that closed into each other (python-fcl) stop where they
    # meet: the finger that needs the least opening goes back along its closing path.
    corrected = {c.finger.name: False for c in closings}
    q, clean = open_self_collisions(ctx, q, closings, corrected)
    q_checked = q.copy()
    # depth of the nearby cloud points in every link
    reach = max(prm.contact_distance, prm.penetration_tol)
    near = _link_distances_flat(ctx, view, q, reach)
    least = _least(near)  # (L,) per link, inf without points
    bad = {ctx.link_names[j] for j in np.flatnonzero(least < -prm.penetration_tol).tolist()}
    if bad:
        q = _open_penetrating(ctx, view, q, closings, bad, pre.spread, corrected)
        near = _link_distances_flat(ctx, view, q, reach)
        least = _least(near)
    fingers = tuple(
        FingerTrace(
            f.name,
            n,
            q[list(f.flex_index)].copy(),
            touched,
            bool(cl.palm_stop),
            on_table,
            bool(cl.at_limits),
            corrected[f.name],
        )
        for f, cl, n, touched, on_table in closings
    )

    def rejected(reason: str, detail: str) -> Grasp:
        return Grasp.from_rejection(i, gt, T, q, reason, detail, s, stop, fingers)

    depth = -least
    if depth.max() > prm.penetration_tol:
        j = int(np.argmax(depth))
        detail = f"{ctx.link_names[j]} holds a point {depth[j] * 1e3:.1f} mm deep"
        return rejected("penetration", detail)
    pairs = [] if clean and np.array_equal(q, q_checked) else ctx.self_pairs(q)
    if pairs:
        return rejected("self_collision", f"{pairs[0][0]} and {pairs[0][1]}")
    below = support_collision(ctx, T, q)
    if below is not None:
        return rejected("support_collision", f"{below} below the support plane")
    contacts = _contacts(ctx, T, q, near)
    if not contacts:
        return rejected("no_contact", "")
    # 5. quality: by the caller
    return Grasp(i, gt, T, s, stop, q, fingers, contacts, 0.0, 0.0, None, None, "")


def _open_penetrating(
    ctx: Context,
    view: View,
    q: np.ndarray,
    closings: list[ClosedFinger],
    bad: set[str],
    spread: float,
    corrected: dict[str, bool],
) -> np.ndarray:
    """``q`` with every finger whose middle or distal link is in ``bad`` (links holding a point
    deeper than ``penetration_tol``) opened back along its closing path (bisection over the path
    samples) to the last sample where its links hold no such point; the fingers opened are
    marked in ``corrected``. ``view``: the cloud in the hand frame; ``spread``: the pre-grasp's
    finger spread."""
    prm = ctx.params
    reach = max(prm.contact_distance, prm.penetration_tol)
    q = q.copy()
    for f, cl, *_ in closings:  # loop over <= 3 fingers
        cols = [ctx.link_index[n] for n in (f.links[1], f.links[2])]
        if not bad & {f.links[1], f.links[2]}:
            continue
        origin = ctx.plane(f, spread).origin
        near = view.near(ctx, origin, ctx.reach + reach)

        def clear(k: int, f=f, cl=cl, cols=cols, near=near) -> bool:
            qq = q.copy()
            qq[list(f.flex_index)] = cl.path[k]
            d = box_signed_distance(near, ctx.hand.box_poses(qq)[cols], ctx.half[cols])
            return not np.any(d < -prm.penetration_tol)

        if len(cl.path) and clear(0):
            lo, hi = 0, len(cl.path) - 1
            while hi - lo > 1:  # bisection over the closing steps
                mid = (lo + hi) // 2
                lo, hi = (mid, hi) if clear(mid) else (lo, mid)
            q[list(f.flex_index)] = cl.path[hi if clear(hi) else lo]
            corrected[f.name] = True
    return q


def _contacts(
    ctx: Context, T: np.ndarray, q: np.ndarray, near: tuple[np.ndarray, np.ndarray, np.ndarray]
) -> tuple[Contact, ...]:
    """4. The contacts of the hand at pose ``T`` and joints ``q`` (``near``: per link, the
    nearby cloud points and their distances, from :func:`_link_distances_flat`): one per link,
    the nearest cloud point within ``contact_distance``. Points as near as it (within
    :data:`CONTACT_TIE`: a face of the object parallel to the link's face) form a patch; the
    contact is its point nearest the link box's centre (then the lowest cloud index), so the
    choice never depends on rounding or on the candidates' order (the choice is the compiled
    loop ``kernels.link_contacts``)."""
    prm = ctx.params
    ids, d, first = near
    centres = np.ascontiguousarray((T @ ctx.boxes(q)[0])[:, :3, 3])  # (L, 3) box centres, world
    _, pick = kernels().link_contacts(
        ids, d, first, ctx.xyz, centres, float(prm.contact_distance), CONTACT_TIE
    )
    links = np.flatnonzero(pick >= 0)
    if len(links) == 0:
        return ()
    pid = ids[pick[links]]
    dist = d[pick[links]].tolist()
    Tb = ctx.boxes(q)[0]
    tangents = Tb[links, :3, 1] @ T[:3, :3].T  # link box y axes in the world
    normals_in = -ctx.normals[pid]
    on_crest = np.zeros(len(pid), dtype=bool) if ctx.crest is None else ctx.crest[pid]
    if on_crest.any():  # no trustworthy normal there: the mean with the link's push
        at = np.flatnonzero(on_crest)
        normals_in[at] = crest_contact_normals(
            normals_in[at], ctx.surface[pid[at]], T @ Tb[links[at]], ctx.half[links[at]]
        )
    return tuple(
        Contact(
            ctx.surface[p].copy(), normals_in[k].copy(), ctx.link_names[j], int(p), dist[k],
            tangents[k].copy(), bool(ctx.assumed[p]), bool(on_crest[k]),
        )
        for k, (j, p) in enumerate(zip(links.tolist(), pid.tolist(), strict=True))
    )  # fmt: skip


def crest_contact_normals(
    n_in: np.ndarray, points: np.ndarray, T_links: np.ndarray, half: np.ndarray
) -> np.ndarray:
    """(K, 3) the contact normals at crest points (flat at no scale: an edge, a rolled rim,
    a notch), where a cloud without normals has no trustworthy one: the unit mean of the
    cloud's normal ``n_in`` (K, 3, into the object: the direction away from the neighbours'
    centroid, negated) and the direction in which the touching link's box (poses ``T_links``
    (K, 4, 4), half extents ``half`` (K, 3)) pushes the point ``points`` (K, 3), its outward
    normal nearest the point (:func:`~pregrasp_core.planner.boxes.box_push_direction`). Each
    alone is wrong where the other is right (an edge of the link's box against the object's
    edge; a PCA line across a notch); their mean lies nearer the true normal on every demo
    object (``docs/limits.md``, "Normals in creases")."""
    mid = n_in + box_push_direction(points, T_links, half)
    norm = np.linalg.norm(mid, axis=1, keepdims=True)
    # (the two exactly opposite: the cloud's normal stays)
    return np.where(norm > GEOM_EPS, mid / np.maximum(norm, GEOM_EPS), n_in)


def _least(near: tuple[np.ndarray, np.ndarray, np.ndarray]) -> np.ndarray:
    """(L,) the least signed distance per link of :func:`_link_distances_flat`'s ``near``
    (inf for a link without points)."""
    ids, d, first = near
    empty = np.zeros((3, 0))  # no contacts asked for: only the least distances
    return kernels().link_contacts(ids, d, first, empty, np.zeros((0, 3)), 0.0, 0.0)[0]


def open_self_collisions(
    ctx: Context, q: np.ndarray, closings: list[ClosedFinger], corrected: dict[str, bool]
) -> tuple[np.ndarray, bool]:
    """Undo finger-finger collisions of the closed hand (python-fcl): for a colliding pair, each
    finger owning one of the two links is opened back along its closing path (bisection over
    the path samples) to the last sample where the pair is apart; the finger that keeps the
    most of its closing is used. At most ``len(closings)`` pairs are resolved; what remains is
    rejected later as ``self_collision``. Returns ``(q, clean)``; ``clean`` says that python-fcl
    found no pair at the returned ``q``; the fingers opened are marked in ``corrected``."""
    hand = ctx.hand
    checker = hand.self_collision_checker
    q = q.copy()
    for _ in range(len(closings)):  # loop over <= 3 fingers
        pairs = ctx.self_pairs(q)
        if not pairs:
            return q, True
        a, b = pairs[0]
        only = np.array([checker.pairs.index((a, b))])
        best: tuple[int, Finger, np.ndarray] | None = None  # (kept path index, finger, q_flex)
        for f, cl, *_ in closings:  # loop over <= 3 fingers
            if not {a, b} & {f.links[1], f.links[2]} or len(cl.path) == 0:
                continue

            # the pair's state at every sample of the path, in one batched check (the
            # bisection below reads the samples it needs from it)
            Q = np.repeat(q[None], len(cl.path), axis=0)
            Q[:, list(f.flex_index)] = cl.path
            hits = checker.collisions_of(hand.box_poses(Q), only)  # this pair only
            free = [not h for h in hits]

            def apart(i: int, free=free) -> bool:
                return free[i]

            if not apart(0):
                continue
            lo, hi = 0, len(cl.path) - 1  # apart(lo) holds; find the last apart sample
            while hi - lo > 1:  # bisection over the path samples
                mid = (lo + hi) // 2
                if apart(mid):
                    lo = mid
                else:
                    hi = mid
            i = hi if apart(hi) else lo
            if best is None or i > best[0]:
                best = (i, f, cl.path[i])
        if best is None:
            break
        _, f, q_flex = best
        q[list(f.flex_index)] = q_flex
        corrected[f.name] = True
    return q, not ctx.self_pairs(q)


def _link_distances(
    ctx: Context, view: View, q: np.ndarray, reach: float
) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Per link of the hand at configuration ``q``: cloud indices of the points within
    ``reach`` of its box and their exact signed distances to it (< 0 inside), in ascending
    cloud order (``view``: the cloud in the hand's frame). Candidates: the points in the AABB
    of a box grown by ``reach`` (found through the cells); all pairs' distances at once."""
    ids, d, first = _link_distances_flat(ctx, view, q, reach)
    cut = first.tolist()
    return (
        [ids[a:b] for a, b in itertools.pairwise(cut)],
        [d[a:b] for a, b in itertools.pairwise(cut)],
    )


def _link_distances_flat(
    ctx: Context, view: View, q: np.ndarray, reach: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`_link_distances` as ``(ids (K,), d (K,), first (L + 1,))``: link l's points
    ``ids[first[l]:first[l + 1]]`` (``kernels.link_distances``)."""
    Tb, lo, hi = ctx.boxes(q)  # hand frame
    blo, bhi = lo - reach, hi + reach  # (L, 3)
    cells = ctx.cells
    ids, d, first = kernels().link_distances(
        ctx.xyz, cells.order, cells.start, cells.count, view.centres, cells.radius,
        float(sum(view.dz)), view.T0, view.r, view.z_lo, view.z_hi,
        np.array(view.dz, dtype=np.float64), blo, bhi, Tb, ctx.half, reach,
    )  # fmt: skip
    return ids, d, first


def support_collision(ctx: Context, T: np.ndarray, q: np.ndarray) -> str | None:
    """The first link whose box reaches below the support plane by > penetration_tol (fcl)."""
    if ctx.support is None:
        return None
    n = np.asarray(ctx.support.normal, dtype=np.float64)
    level = float(ctx.support.height) - ctx.params.penetration_tol
    Tb = T @ ctx.boxes(q)[0]  # (L, 4, 4) world
    # the lowest point of each box along n; fcl reports a box whose lowest point is at or below
    # the plane, so a box clearly above it (by far more than any rounding) needs no fcl call
    low = Tb[:, :3, 3] @ n - np.sum(np.abs(np.einsum("lji,j->li", Tb[:, :3, :3], n)) * ctx.half, 1)
    near = np.flatnonzero(low - level <= SUPPORT_PRETEST_MARGIN)
    if len(near) == 0:
        return None
    table = fcl.CollisionObject(fcl.Halfspace(n, level), fcl.Transform())
    req = fcl.CollisionRequest()
    for i in near.tolist():  # the links near the table, in link order
        name = ctx.link_names[i]
        obj = fcl.CollisionObject(
            fcl.Box(*(2.0 * ctx.half[i])), fcl.Transform(Tb[i, :3, :3], Tb[i, :3, 3])
        )
        if fcl.collide(obj, table, req, fcl.CollisionResult()) > 0:
            return name
    return None
