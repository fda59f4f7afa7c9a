"""The planar closing model of one finger (``Hand.close_finger``): coupled closing of its two
flexion joints in its flexion plane against the points of the object's slice, the middle link's
stop, the distal link's stop and the palm (see ``docs/hand.md``, "The closing model")."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ..tolerances import HAND_CLOSING_ANGLE_TOL
from .model import (
    DEFAULT_CLOSING_STEPS,
    DEFAULT_COUPLING,
    Finger,
    FingerClosing,
    FingerContact,
    HandModel,
)

REFINE_SAMPLES: int = 32
"""Closing model: most samples per refinement level of the bracket around the first touch."""

SWEEP_CHUNK: int = 8
"""Closing model: samples in the first chunk of a phase's sweep (the chunks double; the sweep
stops at the first chunk that touches)."""

REFINE_BUDGET: int = 2000
"""Closing model: a refinement level evaluates about this many (sample, point) pairs: many
samples per level for small slices (few numpy calls), plain bisection for large ones."""


def close_finger(
    model: HandModel,
    finger: str | Finger,
    points_2d: np.ndarray,
    q_start: np.ndarray,
    n_steps: int = DEFAULT_CLOSING_STEPS,
    margin: float = 0.0,
    coupling: float = DEFAULT_COUPLING,
    palm: bool = True,
) -> FingerClosing:
    """Close one finger in its flexion plane against points (the slice of the object).

    ``points_2d`` (M, 2) are in the finger's flexion-plane frame (x along the straight
    finger from the first flexion joint, y the closing direction); ``q_start`` (2,) the
    flexion angles to start from (clamped to the limits). The model (``docs/hand.md``):

    1. Both joints close together, the distal at ``coupling`` times the proximal rate; a
       joint that reaches its upper limit stays there while the other goes on.
    2. When the middle link touches a point (comes within ``margin`` of it), the proximal
       joint stops and the distal joint closes alone.
    3. When the distal link touches a point, the finger stops.
    4. With ``palm``, the palm's inner face (2D line x = -Lk) stops a link like a point does
       (``palm_stop``), so the model never drives the finger into the palm.

    Every phase is sampled in ``n_steps`` steps, all steps x all points at once, and the
    first touching step is refined (up to 32 samples per level, all at once) until the
    bracket is narrower than ``HAND_CLOSING_ANGLE_TOL``. The returned configuration is the
    last one at which no point is within ``margin`` of a moving link.
    """
    f = model.finger(finger)
    P = np.asarray(points_2d, dtype=np.float64)
    if P.ndim != 2 or P.shape[1] != 2:
        raise ValueError(f"points_2d must have shape (M, 2), got {P.shape}")
    q0 = np.asarray(q_start, dtype=np.float64)
    if q0.shape != (2,):
        raise ValueError(f"q_start must have shape (2,), got {q0.shape}")
    if n_steps < 1:
        raise ValueError(f"n_steps must be >= 1, got {n_steps}")
    if coupling <= 0:
        raise ValueError(f"coupling must be > 0, got {coupling}")
    q0 = np.clip(q0, f.lower, f.upper)
    geo = FingerGeometry(f, margin, palm)
    # only points within the finger's reach from its first joint can ever be touched
    reach = f.middle_length + np.hypot(f.distal_length, 0.5 * f.thickness) + 2.0 * abs(margin)
    keep = np.flatnonzero(np.einsum("ij,ij->i", P, P) <= reach * reach)  # (M',) into P
    Pr = P[keep]

    def contact(link: str, i: int) -> FingerContact:  # i indexes Pr
        return FingerContact(link, P[keep[i]].copy(), int(keep[i]))

    # ---- phase 1: both joints close together (clipped at their limits)
    def path1(t: np.ndarray) -> np.ndarray:  # (K,) -> (K, 2)
        out = np.empty((t.shape[0], 2))
        np.minimum(q0[0] + t, f.upper[0], out=out[:, 0])
        np.minimum(q0[1] + coupling * t, f.upper[1], out=out[:, 1])
        return out

    t_end = max(f.upper[0] - q0[0], (f.upper[1] - q0[1]) / coupling, 0.0)
    ev1 = _first_event(geo, Pr, path1, t_end, n_steps, links=(True, True))
    contacts: list[FingerContact] = []
    stopped_middle = stopped_distal = palm_stop = False
    start_in_contact = ev1.k_hit == 0
    if ev1.t_hit is None:  # no stop: both joints end at their limits
        path = path1(ev1.t_samples)
        return FingerClosing(
            finger=f.name,
            q=path[-1].copy(),
            contact_link=None,
            contact_point=None,
            contact_index=None,
            contacts=(),
            stopped_middle=False,
            stopped_distal=False,
            palm_stop=False,
            at_limits=True,
            start_in_contact=False,
            path=path,
        )
    q_free = path1(np.array([ev1.t_free]))[0]
    path = np.concatenate([path1(ev1.t_samples[ev1.t_samples < ev1.t_free]), q_free[None]])
    if ev1.distal_hit:  # the distal touched (maybe together with the middle): stop
        if ev1.middle_idx is not None:
            contacts.append(contact(f.links[1], ev1.middle_idx))
            stopped_middle = True
        if ev1.distal_idx is not None:
            contacts.append(contact(f.links[2], ev1.distal_idx))
            stopped_distal = True
        palm_stop = ev1.palm
        return _closing(
            f,
            q_free,
            contacts,
            stopped_middle,
            stopped_distal,
            palm_stop,
            start_in_contact,
            path,
        )

    # ---- phase 2: the middle link stopped; the distal joint closes alone
    if ev1.middle_idx is not None:
        contacts.append(contact(f.links[1], ev1.middle_idx))
        stopped_middle = True
    palm_stop = ev1.palm
    q1 = q_free[0]

    def path2(t: np.ndarray) -> np.ndarray:
        out = np.empty((t.shape[0], 2))
        out[:, 0] = q1
        np.minimum(q_free[1] + t, f.upper[1], out=out[:, 1])
        return out

    t_end2 = max(f.upper[1] - q_free[1], 0.0)
    ev2 = _first_event(geo, Pr, path2, t_end2, n_steps, links=(False, True))
    if ev2.t_hit is None:
        path = np.concatenate([path, path2(ev2.t_samples[1:])])
        return _closing(
            f,
            path[-1].copy(),
            contacts,
            stopped_middle,
            False,
            palm_stop,
            start_in_contact,
            path,
        )
    q_stop = path2(np.array([ev2.t_free]))[0]
    path = np.concatenate(
        [
            path,
            path2(ev2.t_samples[(ev2.t_samples > 0) & (ev2.t_samples < ev2.t_free)]),
            q_stop[None],
        ]
    )
    if ev2.distal_idx is not None:
        contacts.append(contact(f.links[2], ev2.distal_idx))
        stopped_distal = True
    palm_stop = palm_stop or ev2.palm
    return _closing(
        f, q_stop, contacts, stopped_middle, stopped_distal, palm_stop, start_in_contact, path
    )


class FingerGeometry:
    """Planar link rectangles of one finger: hit tests for many configurations x points."""

    def __init__(self, f: Finger, margin: float, palm: bool) -> None:
        self.f = f
        self.m = float(margin)
        self.h = 0.5 * f.thickness
        self.palm = palm

    def hits(
        self, Q: np.ndarray, P: np.ndarray, links: tuple[bool, bool]
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """For configurations Q (K, 2) and points P (M, 2): (middle (K, M), distal (K, M),
        middle at the palm (K,), distal at the palm (K,)) bool; a link touches a point within
        ``margin`` (``links``: which of middle, distal are tested; the others are False)."""
        f, m, h = self.f, self.m, self.h
        K, M = Q.shape[0], P.shape[0]
        # d (K, 2) along a link, n (K, 2) across it; filled in place (no np.stack: this runs
        # ~40 times per closing on small arrays, where numpy's call overhead dominates)
        a1 = Q[:, 0]
        a2 = Q[:, 0] + Q[:, 1]
        d1 = np.empty((K, 2))
        d2 = np.empty((K, 2))
        np.cos(a1, out=d1[:, 0])
        np.sin(a1, out=d1[:, 1])
        np.cos(a2, out=d2[:, 0])
        np.sin(a2, out=d2[:, 1])
        n1 = d1[:, ::-1].copy()
        n1[:, 0] *= -1.0
        n2 = d2[:, ::-1].copy()
        n2[:, 0] *= -1.0
        o2 = f.middle_length * d1  # (K, 2) second joint
        mid = dis = None
        if M:
            if links[0]:
                s = d1 @ P.T  # (K, M) along the link
                r = n1 @ P.T  # (K, M) across
                mid = s >= -m  # the same three tests, combined in place
                mid &= s <= f.middle_length + m
                mid &= np.abs(r, out=r) <= h + m
            if links[1]:
                # sum over 2 terms written out (bit-identical to np.sum(., axis=1))
                s = d2 @ P.T
                s -= (d2[:, 0] * o2[:, 0] + d2[:, 1] * o2[:, 1])[:, None]
                r = n2 @ P.T
                r -= (n2[:, 0] * o2[:, 0] + n2[:, 1] * o2[:, 1])[:, None]
                dis = s >= -m
                dis &= s <= f.distal_length + m
                dis &= np.abs(r, out=r) <= h + m
        if mid is None:
            mid = np.zeros((K, M), dtype=bool)
        if dis is None:
            dis = np.zeros((K, M), dtype=bool)
        palm = np.zeros(K, dtype=bool)
        palm_mid = np.zeros(K, dtype=bool)
        if self.palm:
            floor = -f.knuckle_length + m
            # lowest corner of each moving rectangle along the 2D x axis
            low_mid = np.minimum(0.0, f.middle_length * d1[:, 0]) - h * np.abs(n1[:, 0])
            low_dis = o2[:, 0] + np.minimum(0.0, f.distal_length * d2[:, 0]) - h * np.abs(n2[:, 0])
            if links[0]:
                palm_mid = low_mid < floor
            if links[1]:
                palm = low_dis < floor
        return mid, dis, palm_mid, palm

    def distance(self, q: np.ndarray, P: np.ndarray, link: int) -> np.ndarray:
        """(M,) box-distance (Chebyshev-style; < 0 inside) of points to link 0 (middle) or 1
        (distal) at flexion ``q`` (2,)."""
        f, h = self.f, self.h
        a = q[0] if link == 0 else q[0] + q[1]
        d = np.array([np.cos(a), np.sin(a)])
        n = np.array([-d[1], d[0]])
        o = np.zeros(2) if link == 0 else f.middle_length * np.array([np.cos(q[0]), np.sin(q[0])])
        length = f.middle_length if link == 0 else f.distal_length
        s = (P - o) @ d
        r = (P - o) @ n
        return np.maximum(np.abs(s - 0.5 * length) - 0.5 * length, np.abs(r) - h)


@dataclass
class _Event:
    """The first event along one closing phase (:func:`_first_event`)."""

    t_samples: np.ndarray
    """(K,) the coarse path parameters, before refinement."""
    t_free: float
    """The last contact-free path parameter."""
    t_hit: float | None
    """The first touching path parameter (None: no event up to the end)."""
    k_hit: int | None
    """Index of the first touching coarse sample."""
    distal_hit: bool = False
    """The distal link touched (a point or the palm)."""
    palm: bool = False
    """A link touched the palm."""
    middle_idx: int | None = None
    """The point (index into the phase's points) the middle link touched."""
    distal_idx: int | None = None
    """The point the distal link touched."""


def may_touch(
    geo: FingerGeometry, P: np.ndarray, Q_bracket: np.ndarray, links: tuple[bool, bool]
) -> np.ndarray:
    """(M,) bool: which points ``P`` (M, 2) may touch a link (``links``: middle, distal) at some
    configuration between ``Q_bracket[0]`` and ``Q_bracket[1]`` (2, 2) along a monotone path.

    Exact superset: a link touches a point when its box-distance (:meth:`FingerGeometry.distance`,
    1-Lipschitz in the point's link-frame coordinates) is <= margin. Turning the first joint by
    d1 and the sum of the joints by d2 moves a point's middle-link coordinates by at most
    ``|p| d1`` and its distal-link coordinates by at most ``(|p| + Lm) d2 + Lm d1``."""
    qa, qb = Q_bracket
    d1 = abs(float(qb[0] - qa[0]))
    d2 = abs(float((qb[0] + qb[1]) - (qa[0] + qa[1])))
    rho = np.sqrt(np.einsum("ij,ij->i", P, P))  # (M,) distance to the first joint
    lm = geo.f.middle_length
    slack = 1e-9  # metres, far above the rounding of the two ways of computing the distance
    keep = np.zeros(len(P), dtype=bool)
    if links[0]:
        keep |= geo.distance(qb, P, 0) <= geo.m + rho * d1 + slack
    if links[1]:
        keep |= geo.distance(qb, P, 1) <= geo.m + (rho + lm) * d2 + lm * d1 + slack
    return keep


def _first_event(
    geo: FingerGeometry,
    P: np.ndarray,
    path: Callable[[np.ndarray], np.ndarray],
    t_end: float,
    n_steps: int,
    links: tuple[bool, bool],
) -> _Event:
    """The first touch of the links (``links``: middle, distal) with the points ``P`` (M, 2) or
    the palm along ``path`` (path parameters (K,) -> flexion (K, 2)) for parameters in
    ``[0, t_end]``: coarse samples in growing chunks, then the bracket of the first touching
    sample refined below ``HAND_CLOSING_ANGLE_TOL``."""
    t = np.linspace(0.0, t_end, n_steps + 1) if t_end > 0 else np.zeros(1)
    Q = path(t)  # (K, 2)
    # the samples in growing chunks, in order, up to the first chunk that touches: the samples
    # after the first touch are never needed (same first touching sample as testing all at once)
    k = -1
    lo_k, size = 0, SWEEP_CHUNK
    while lo_k < len(t):
        hi_k = min(lo_k + size, len(t))
        mid, dis, pmid, pdis = geo.hits(Q[lo_k:hi_k], P, links)
        any_hit = mid.any(axis=1) | dis.any(axis=1) | pmid | pdis  # (chunk,)
        if any_hit.any():
            k = lo_k + int(np.argmax(any_hit))
            break
        lo_k, size = hi_k, 2 * size
    if k < 0:
        return _Event(t_samples=t, t_free=float(t[-1]), t_hit=None, k_hit=None)
    if k == 0:
        lo = hi = 0.0
    else:
        lo, hi = float(t[k - 1]), float(t[k])
        # refine [last free, first touching] by sampling it densely, all samples at once, until
        # it is narrower than the tolerance (each level shrinks it n_ref + 1 times)
        n_ref = max(1, min(REFINE_SAMPLES, REFINE_BUDGET // max(P.shape[0], 1)))
        # only the points that can touch a link inside the bracket take part in refining it
        P_ref = P[may_touch(geo, P, path(np.array([lo, hi])), links)] if len(P) > 16 else P
        while hi - lo > HAND_CLOSING_ANGLE_TOL:
            ts = np.linspace(lo, hi, n_ref + 2)[1:-1]
            a, b, c, d = geo.hits(path(ts), P_ref, links)
            hit = a.any(axis=1) | b.any(axis=1) | c | d
            if hit.any():
                j = int(np.argmax(hit))
                lo, hi = (float(ts[j - 1]) if j > 0 else lo), float(ts[j])
            else:
                lo = float(ts[-1])
    a, b, c, d = geo.hits(path(np.array([hi])), P, links)
    ev = _Event(t_samples=t, t_free=lo, t_hit=hi, k_hit=k)
    q_free = path(np.array([lo]))[0]
    if a[0].any():
        idx = np.flatnonzero(a[0])
        ev.middle_idx = int(idx[np.argmin(geo.distance(q_free, P[idx], 0))])
    if b[0].any():
        idx = np.flatnonzero(b[0])
        ev.distal_idx = int(idx[np.argmin(geo.distance(q_free, P[idx], 1))])
    ev.distal_hit = bool(b[0].any() or d[0])
    ev.palm = bool(c[0] or d[0])
    return ev


def _closing(
    f: Finger,
    q: np.ndarray,
    contacts: list[FingerContact],
    stopped_middle: bool,
    stopped_distal: bool,
    palm_stop: bool,
    start_in_contact: bool,
    path: np.ndarray,
) -> FingerClosing:
    last = contacts[-1] if contacts else None
    at_limits = bool(np.all(np.abs(q - f.upper) <= HAND_CLOSING_ANGLE_TOL)) and not stopped_distal
    return FingerClosing(
        finger=f.name,
        q=np.clip(q, f.lower, f.upper),
        contact_link=None if last is None else last.link,
        contact_point=None if last is None else last.point,
        contact_index=None if last is None else last.index,
        contacts=tuple(contacts),
        stopped_middle=stopped_middle,
        stopped_distal=stopped_distal,
        palm_stop=palm_stop,
        at_limits=at_limits,
        start_in_contact=start_in_contact,
        path=path,
    )
