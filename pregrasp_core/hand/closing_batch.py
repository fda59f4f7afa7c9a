"""The closing model for many slices at once (``Hand.close_fingers``): result ``i`` equals
``close_finger`` of slice ``i``, bit for bit, with each stage run for all slices together (see
``docs/hand.md``, "Many slices at once")."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from ..tolerances import HAND_CLOSING_ANGLE_TOL
from .batch_events import BatchEvents, batch_first_events
from .batch_hits import SliceBatch, paths
from .model import (
    DEFAULT_CLOSING_STEPS,
    DEFAULT_COUPLING,
    Finger,
    FingerClosing,
    FingerContact,
    HandModel,
)
from .sweep_kernel import candidate_kernels, reach_kernel


def close_fingers(
    model: HandModel,
    slices: Sequence[tuple[str | Finger, np.ndarray, np.ndarray]],
    n_steps: int = DEFAULT_CLOSING_STEPS,
    margin: float = 0.0,
    coupling: float = DEFAULT_COUPLING,
    palm: bool = True,
) -> list[FingerClosing]:
    """:func:`~pregrasp_core.hand.closing.close_finger` for many slices at once: result ``i``
    equals ``close_finger(model, *slices[i], n_steps, margin, coupling, palm)``.

    ``slices``: ``(finger, points_2d (M_i, 2), q_start (2,))`` per slice, any fingers and
    sizes (``M_i`` may be 0); the results come in the same order, and contact indices refer
    to each slice's own ``points_2d``. The same model and the same sampling as
    ``close_finger`` (coarse steps, refinement of the bracket of the first touch with
    the same samples per level, the event at its end), each stage run for all slices
    together, every point with its own slice's path. The coarse sweep goes through the steps
    in order and tests a point only at the steps where it may touch (conservative
    advancement from its distance to the links), so most (step, point) pairs are never
    evaluated; see ``docs/hand.md``. Memory: O(points) per step of the sweep and per
    refinement level (the refinement's tests are one compiled loop). The hit tests write each
    2-term dot product out where ``close_finger`` uses a matrix product (equal up to the
    last bit, which can only matter for a point within ~1e-18 m of a link's boundary)."""
    if n_steps < 1:
        raise ValueError(f"n_steps must be >= 1, got {n_steps}")
    if coupling <= 0:
        raise ValueError(f"coupling must be > 0, got {coupling}")
    if len(slices) == 0:
        return []
    fingers: list[Finger] = []
    pts: list[np.ndarray] = []
    q0 = np.empty((len(slices), 2))
    for i, item in enumerate(slices):  # loop over slices: checks and per-slice inputs
        try:
            finger, points_2d, q_start = item
        except (TypeError, ValueError):
            raise ValueError(
                f"slices[{i}] must be (finger, points_2d, q_start), got {type(item).__name__}"
            ) from None
        fingers.append(model.finger(finger))
        P = np.asarray(points_2d, dtype=np.float64)
        if P.ndim != 2 or P.shape[1] != 2:
            raise ValueError(f"slices[{i}]: points_2d must have shape (M, 2), got {P.shape}")
        qs = np.asarray(q_start, dtype=np.float64)
        if qs.shape != (2,):
            raise ValueError(f"slices[{i}]: q_start must have shape (2,), got {qs.shape}")
        pts.append(P)
        q0[i] = qs
    S = len(fingers)
    geom = np.array(
        [(f.knuckle_length, f.middle_length, f.distal_length, 0.5 * f.thickness) for f in fingers]
    )  # (S, 4)
    lower = np.array([f.lower for f in fingers])  # (S, 2)
    upper = np.array([f.upper for f in fingers])
    q0 = np.clip(q0, lower, upper)
    # only points within a finger's reach from its first joint can ever be touched
    sizes = np.array([len(P) for P in pts], dtype=np.int64)
    P_all = np.concatenate(pts) if sizes.sum() else np.zeros((0, 2))
    seg_all = np.repeat(np.arange(S), sizes)
    reach = geom[:, 1] + np.hypot(geom[:, 2], geom[:, 3]) + 2.0 * abs(margin)
    # the columns and the reach test in one compiled pass (x * x + y * y <= reach^2, the bits
    # of einsum("ij,ij->i")'s 2-term sums)
    x_all, y_all, keep, n_keep = reach_kernel()(np.ascontiguousarray(P_all), sizes, reach * reach)
    kept = None  # the rows of P_all kept (None: all)
    if n_keep < len(P_all):  # (integer indices: much faster than a boolean mask on (N, 2))
        kept = np.flatnonzero(keep)
        P_all, seg_all = P_all[kept], seg_all[kept]
        x_all, y_all = x_all[kept], y_all[kept]
    seg = seg_all
    B = SliceBatch(
        fingers=tuple(fingers),
        Lk=geom[:, 0],
        Lm=geom[:, 1],
        Ld=geom[:, 2],
        h=geom[:, 3],
        upper=upper,
        P=P_all,
        x=x_all,
        y=y_all,
        seg=seg,
        start=np.concatenate([[0], np.cumsum(np.bincount(seg, minlength=S))]),
        margin=float(margin),
        palm=bool(palm),
    )

    # ---- phase 1: both joints close together (clipped at their limits)
    every = np.arange(S)
    A1 = np.array([1.0, float(coupling)])
    t_end = np.maximum(np.maximum(upper[:, 0] - q0[:, 0], (upper[:, 1] - q0[:, 1]) / coupling), 0.0)
    ev1 = batch_first_events(B, every, q0, A1, t_end, n_steps, (True, True))
    Q1 = paths(q0, A1, upper, ev1.t)  # (S, n_steps + 1, 2) the coarse samples
    q_free = paths(q0, A1, upper, ev1.t_free[:, None])[:, 0]  # (S, 2)
    # ---- phase 2: the middle link stopped; the distal joint closes alone
    two = np.flatnonzero((ev1.k >= 0) & ~ev1.distal_hit)
    ev2: BatchEvents | None = None
    Q2 = np.zeros((0, n_steps + 1, 2))  # (the phase-2 results of the slices in ``two``)
    q_stop = n_t2 = np.zeros((0, 2))
    if len(two):
        A2 = np.array([0.0, 1.0])
        t_end2 = np.maximum(upper[two, 1] - q_free[two, 1], 0.0)
        # the distal joint stays where it is: only the points within the distal link's
        # circumradius (grown by the margin) of it can be touched
        o2x, o2y = B.Lm * np.cos(q_free[:, 0]), B.Lm * np.sin(q_free[:, 0])  # (S,)
        r2 = np.hypot(B.Ld + abs(margin), B.h + abs(margin)) + 1e-9  # (S,)
        # (the points of these slices only, in one compiled pass)
        cand2 = candidate_kernels()[1](B.start, two, B.x, B.y, o2x, o2y, r2 * r2)
        ev2 = batch_first_events(B, two, q_free[two], A2, t_end2, n_steps, (False, True), cand2)
        Q2 = paths(q_free[two], A2, upper[two], ev2.t)
        q_stop = paths(q_free[two], A2, upper[two], ev2.t_free[:, None])[:, 0]
        n_t2 = ev2.n_t
    # ---- the results, per slice: which case, the end configuration, flags, path lengths
    found1 = ev1.k >= 0
    stop1 = found1 & ev1.distal_hit  # phase 1 ended by the distal (or its palm test)
    in2 = np.zeros(S, dtype=bool)
    in2[two] = True
    found2 = np.zeros(S, dtype=bool)
    q_end = Q1[every, ev1.n_t - 1].copy()  # (S, 2) no stop: the last coarse sample
    q_end[stop1] = q_free[stop1]
    valid1 = np.arange(n_steps + 1)[None, :] < ev1.n_t[:, None]
    j1 = np.count_nonzero((ev1.t < ev1.t_free[:, None]) & valid1, axis=1)  # a prefix
    dis2 = np.full(S, -1, dtype=np.int64)
    palm2 = np.zeros(S, dtype=bool)
    row2 = np.full(S, -1, dtype=np.int64)
    j2 = np.zeros(S, dtype=np.int64)
    if ev2 is not None:
        row2[two] = np.arange(len(two))
        f2 = ev2.k >= 0
        found2[two] = f2
        q_end[two] = np.where(f2[:, None], q_stop, Q2[np.arange(len(two)), ev2.n_t - 1])
        valid2 = np.arange(n_steps + 1)[None, :] < ev2.n_t[:, None]
        j2[two] = np.count_nonzero((ev2.t < ev2.t_free[:, None]) & valid2, axis=1)
        dis2[two] = np.where(f2, ev2.distal_idx, -1)
        palm2[two] = f2 & ev2.palm
    mid1 = np.where(found1, ev1.middle_idx, -1)
    dis1 = np.where(stop1, ev1.distal_idx, -1)
    stopped_middle = mid1 >= 0
    stopped_distal = (dis1 >= 0) | (dis2 >= 0)
    palm_stop = found1 & (ev1.palm | palm2)
    at_limits = ~found1 | (
        np.all(np.abs(q_end - upper) <= HAND_CLOSING_ANGLE_TOL, axis=1) & ~stopped_distal
    )
    q_out = np.where(found1[:, None], np.clip(q_end, lower, upper), q_end)
    c_idx = np.stack([mid1, dis1, dis2])  # (3, S) the contacts' points in B.P, -1 for none
    P_c = B.P[np.maximum(c_idx, 0)] if len(B.P) else np.zeros((3, S, 2))  # (3, S, 2)
    # the contacts' indices in their slices' own points_2d
    src = np.zeros((3, S), dtype=np.int64)
    if len(B.P):
        ci = np.maximum(c_idx, 0)
        src = (ci if kept is None else kept[ci]) - (np.cumsum(sizes) - sizes)[B.seg[ci]]

    out: list[FingerClosing] = []
    # (per-slice values as Python lists: one conversion each, not S numpy scalar reads)
    found1_l, in2_l, found2_l = found1.tolist(), in2.tolist(), found2.tolist()
    n_t1_l, j1_l, j2_l, row2_l, n_t2_l = (
        ev1.n_t.tolist(),
        j1.tolist(),
        j2.tolist(),
        row2.tolist(),
        np.asarray(n_t2).tolist(),
    )
    idx_l, src_l = c_idx.T.tolist(), src.T.tolist()  # (S, 3)
    flags = np.stack([stopped_middle, stopped_distal, palm_stop, at_limits, ev1.k == 0]).T
    flags_l = flags.tolist()
    for s in range(S):  # loop over slices: the small result objects
        f = fingers[s]
        if not found1_l[s]:  # no stop: both joints end at their limits
            path = Q1[s, : n_t1_l[s]].copy()
        elif not in2_l[s]:
            path = np.concatenate([Q1[s, : j1_l[s]], q_free[s : s + 1]])
        else:
            r = row2_l[s]
            tail = (
                [Q2[r, 1 : j2_l[s]], q_stop[r : r + 1]] if found2_l[s] else [Q2[r, 1 : n_t2_l[r]]]
            )
            path = np.concatenate([Q1[s, : j1_l[s]], q_free[s : s + 1], *tail])
        ids, srcs = idx_l[s], src_l[s]
        contacts = tuple(
            FingerContact(f.links[1 if c == 0 else 2], P_c[c, s].copy(), srcs[c])
            for c in range(3)
            if ids[c] >= 0
        )
        last = contacts[-1] if contacts else None
        sm, sd, ps, al, sc = flags_l[s]
        out.append(
            FingerClosing(
                finger=f.name,
                q=q_out[s].copy(),  # (own arrays, as close_finger's)
                contact_link=None if last is None else last.link,
                contact_point=None if last is None else last.point,
                contact_index=None if last is None else last.index,
                contacts=contacts,
                stopped_middle=sm,
                stopped_distal=sd,
                palm_stop=ps,
                at_limits=al,
                start_in_contact=sc,
                path=path,
            )
        )
    return out
