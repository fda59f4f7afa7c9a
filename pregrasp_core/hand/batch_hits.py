"""The batched closing model's slices and hit tests: every (slice, sample, point) pair is tested
with the point's own slice's configuration, each 2-term dot product written out (see
``docs/hand.md``, "Many slices at once")."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .model import Finger
from .sweep_kernel import hits_kernel


@dataclass(frozen=True)
class SliceBatch:
    """The slices of one :meth:`Hand.close_fingers` call: per-slice finger geometry and the
    points within reach of every slice, concatenated in slice order."""

    fingers: tuple[Finger, ...]
    """(S,) the finger of each slice."""
    Lk: np.ndarray
    """(S,) knuckle lengths."""
    Lm: np.ndarray
    """(S,) middle link lengths."""
    Ld: np.ndarray
    """(S,) distal link lengths."""
    h: np.ndarray
    """(S,) half thicknesses of the links."""
    upper: np.ndarray
    """(S, 2) upper flexion limits."""
    P: np.ndarray
    """(N, 2) the points within reach of all slices (``Pr`` of ``closing.close_finger``), slice
    by slice."""
    x: np.ndarray
    """(N,) ``P[:, 0]``, contiguous."""
    y: np.ndarray
    """(N,) ``P[:, 1]``, contiguous."""
    seg: np.ndarray
    """(N,) int64 slice of each point (non-decreasing)."""
    start: np.ndarray
    """(S + 1,) int64: the points of slice ``s`` are ``P[start[s]:start[s + 1]]``."""
    margin: float
    """Contact margin (metres)."""
    palm: bool
    """Whether the palm's inner face stops a link."""

    @property
    def count(self) -> np.ndarray:
        """(S,) number of points within reach per slice."""
        return np.diff(self.start)


@dataclass(frozen=True)
class Configs:
    """Link directions of configurations ``Q (R, C, 2)`` (one row of C samples per slice), as
    ``FingerGeometry.hits`` computes them."""

    d1x: np.ndarray
    """(R, C) cos q1: the middle link's direction d1, x."""
    d1y: np.ndarray
    """(R, C) sin q1: d1, y."""
    d2x: np.ndarray
    """(R, C) cos(q1 + q2): the distal link's direction d2, x."""
    d2y: np.ndarray
    """(R, C) sin(q1 + q2): d2, y."""
    cs: np.ndarray
    """(R, C) ``d2 . o2`` (o2 = the distal joint)."""
    cr: np.ndarray
    """(R, C) ``n2 . o2`` (n2 = d2 turned by +90 degrees)."""
    palm_mid: np.ndarray
    """(R, C) bool: the middle link reaches the palm."""
    palm_dis: np.ndarray
    """(R, C) bool: the distal link reaches the palm."""

    @classmethod
    def of(cls, B: SliceBatch, sl: np.ndarray, Q: np.ndarray, links: tuple[bool, bool]) -> Configs:
        """The configurations ``Q`` (R, C, 2) of the slices ``sl`` (R,) of ``B`` (the palm
        tests only for the links in ``links``: middle, distal)."""
        a1 = Q[..., 0]
        a2 = Q[..., 0] + Q[..., 1]
        d1x, d1y, d2x, d2y = np.cos(a1), np.sin(a1), np.cos(a2), np.sin(a2)
        Lm = B.Lm[sl][:, None]
        o2x, o2y = Lm * d1x, Lm * d1y
        cs = d2x * o2x + d2y * o2y
        cr = -d2y * o2x + d2x * o2y
        palm_mid = np.zeros(Q.shape[:2], dtype=bool)
        palm_dis = np.zeros(Q.shape[:2], dtype=bool)
        if B.palm:
            h = B.h[sl][:, None]
            floor = -B.Lk[sl][:, None] + B.margin
            if links[0]:
                low_mid = np.minimum(0.0, Lm * d1x) - h * np.abs(d1y)
                palm_mid = low_mid < floor
            if links[1]:
                low_dis = o2x + np.minimum(0.0, B.Ld[sl][:, None] * d2x) - h * np.abs(d2y)
                palm_dis = low_dis < floor
        return cls(d1x, d1y, d2x, d2y, cs, cr, palm_mid, palm_dis)


def pair_hits(
    B: SliceBatch, cfg: Configs, rows: np.ndarray, pts: np.ndarray, links: tuple[bool, bool]
) -> tuple[np.ndarray, np.ndarray]:
    """(middle, distal) (Np, C) bool: does point ``pts[i]`` touch the link at the C
    configurations of row ``rows[i]`` of ``cfg``. The same tests as ``FingerGeometry.hits``,
    with each 2-term dot product written out (the single-slice version uses a matrix product,
    which may round the last bit differently)."""
    m = B.margin
    px = B.x[pts][:, None]
    py = B.y[pts][:, None]
    sl = B.seg[pts]
    C = cfg.d1x.shape[1]
    mid = dis = None
    hm = (B.h[sl] + m)[:, None]
    if links[0]:
        dx, dy = cfg.d1x[rows], cfg.d1y[rows]  # (Np, C)
        s = dx * px + dy * py
        r = -dy * px + dx * py
        mid = s >= -m
        mid &= s <= (B.Lm[sl] + m)[:, None]
        mid &= np.abs(r, out=r) <= hm
    if links[1]:
        dx, dy = cfg.d2x[rows], cfg.d2y[rows]
        s = dx * px + dy * py
        s -= cfg.cs[rows]
        r = -dy * px + dx * py
        r -= cfg.cr[rows]
        dis = s >= -m
        dis &= s <= (B.Ld[sl] + m)[:, None]
        dis &= np.abs(r, out=r) <= hm
    if mid is None:
        mid = np.zeros((len(pts), C), dtype=bool)
    if dis is None:
        dis = np.zeros((len(pts), C), dtype=bool)
    return mid, dis


def any_hit_ragged(
    B: SliceBatch,
    cfg: Configs,
    pts: np.ndarray,
    rows: np.ndarray,
    n_row: np.ndarray,
    links: tuple[bool, bool],
) -> np.ndarray:
    """(R, C) bool: some point (``pts``, with their rows ``rows``) or the palm touches a link
    at the configurations of ``cfg``; row ``i`` uses only its first ``n_row[i]``
    configurations (the others are False): each point is paired with its row's samples only.
    The (point, sample) tests of :func:`pair_hits` as one compiled loop
    (:func:`~pregrasp_core.hand.sweep_kernel.ragged_hits_loop`, the same arithmetic)."""
    R, C = cfg.d1x.shape
    out = cfg.palm_mid | cfg.palm_dis
    out &= np.arange(C)[None, :] < n_row[:, None]
    c = np.ascontiguousarray
    return hits_kernel()(
        c(cfg.d1x), c(cfg.d1y), c(cfg.d2x), c(cfg.d2y), c(cfg.cs), c(cfg.cr), out, B.x, B.y,
        B.seg, B.h, B.Lm, B.Ld, float(B.margin), pts.astype(np.int64), rows.astype(np.int64),
        n_row.astype(np.int64), bool(links[0]), bool(links[1]),
    )  # fmt: skip


def points_of(B: SliceBatch, sl: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The points of the slices ``sl`` (R,) (distinct, increasing) and the row of each in
    ``sl``: ``(pts (Np,), rows (Np,))``."""
    if len(sl) == len(B.start) - 1:  # every slice (sl = 0, 1, ...): every point, in order
        return np.arange(len(B.seg)), B.seg
    row_of = np.full(len(B.start) - 1, -1, dtype=np.int64)
    row_of[sl] = np.arange(len(sl))
    pts = np.flatnonzero(row_of[B.seg] >= 0)
    return pts, row_of[B.seg[pts]]


def paths(qb: np.ndarray, A: np.ndarray, upper: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(R, C, 2) ``min(qb + A t, upper)`` for parameters t (R, C): phase 1 is A = (1, coupling),
    phase 2 is A = (0, 1) (the proximal joint stays at ``qb[:, 0]``, which is within limits)."""
    out = np.empty(t.shape + (2,))
    np.minimum(qb[:, None, 0] + A[0] * t, upper[:, None, 0], out=out[..., 0])
    np.minimum(qb[:, None, 1] + A[1] * t, upper[:, None, 1], out=out[..., 1])
    return out


def batch_distance(B: SliceBatch, q: np.ndarray, pts: np.ndarray, link: int) -> np.ndarray:
    """(Np,) ``FingerGeometry.distance`` of points ``pts`` to link 0 (middle) or 1 (distal) at
    their own configuration ``q`` (Np, 2), 2-term dot products written out."""
    sl = B.seg[pts]
    a = q[:, 0] if link == 0 else q[:, 0] + q[:, 1]
    dx, dy = np.cos(a), np.sin(a)
    px, py = B.x[pts], B.y[pts]
    if link == 1:
        px = px - B.Lm[sl] * np.cos(q[:, 0])
        py = py - B.Lm[sl] * np.sin(q[:, 0])
    length = B.Lm[sl] if link == 0 else B.Ld[sl]
    s = px * dx + py * dy
    r = px * -dy + py * dx
    return np.maximum(np.abs(s - 0.5 * length) - 0.5 * length, np.abs(r) - B.h[sl])
