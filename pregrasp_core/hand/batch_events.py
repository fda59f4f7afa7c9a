"""The batched closing model's first events: for one closing phase of many slices, the first
touching coarse sample of each (a sweep by conservative advancement), the bracket around it
refined level by level for all slices together, and the touching points at its end (see
``docs/hand.md``, "Many slices at once")."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..tolerances import HAND_CLOSING_ANGLE_TOL
from .batch_hits import (
    Configs,
    SliceBatch,
    batch_distance,
    pair_hits,
    paths,
    points_of,
)
from .closing import REFINE_BUDGET, REFINE_SAMPLES, FingerGeometry
from .sweep_kernel import candidate_kernels, refine_kernels, sweep_kernel


def _coarse_sweep(
    B: SliceBatch,
    sl: np.ndarray,
    qb: np.ndarray,
    A: np.ndarray,
    upper: np.ndarray,
    t: np.ndarray,
    n_t: np.ndarray,
    step: np.ndarray,
    pts: np.ndarray,
    rows: np.ndarray,
    links: tuple[bool, bool],
) -> tuple[np.ndarray, np.ndarray]:
    """The first touching coarse sample of every slice (``k`` (R,), -1 if none) without testing
    every (sample, point) pair: the samples go in order, and each point is tested at a sample
    only when its last test leaves it possibly touching there (conservative advancement: a point
    at Euclidean distance d from a link's rectangle stays off it while the rectangle moves less
    than d), and not after its slice's first touch. Also ``free`` per point (as ``pts``): the
    point is off both links for every path parameter in ``[0, free)``."""
    R, C1 = t.shape
    Q = paths(qb, A, upper, t)  # (R, C1, 2) every coarse sample
    cfg = Configs.of(B, sl, Q, links)
    am = abs(B.margin)
    Lm, h = B.Lm[sl], B.h[sl]
    speed_mid = A[0] * np.hypot(Lm + am, h + am)  # (R,) joint 1 turns at most A[0] per unit t
    speed_dis = (A[0] + A[1]) * np.hypot(B.Ld[sl] + am, h + am) + A[0] * Lm
    flat = {f: getattr(cfg, f).reshape(-1) for f in ("d1x", "d1y", "d2x", "d2y", "cs", "cr")}
    flat["hm"] = np.repeat(h + B.margin, C1)  # (R * C1,) per configuration
    flat["top0"] = np.repeat(Lm + B.margin, C1)
    flat["top1"] = np.repeat(B.Ld[sl] + B.margin, C1)
    flat["sp0"] = np.repeat(speed_mid, C1)
    flat["sp1"] = np.repeat(speed_dis, C1)
    valid = np.arange(C1)[None, :] < n_t[:, None]
    palm = (cfg.palm_mid | cfg.palm_dis) & valid
    best = np.where(palm.any(axis=1), np.argmax(palm, axis=1), C1)  # (R,) first touch so far
    t_flat = t.reshape(-1)
    inv_step = np.divide(1.0, step, out=np.full(R, np.inf), where=step > 0)
    names = ("d1x", "d1y", "d2x", "d2y", "cs", "cr", "hm", "top0", "top1", "sp0", "sp1")
    every = len(pts) == len(B.x)  # every point of the batch, in order (points_of)
    best, free = sweep_kernel()(
        np.stack([flat[f] for f in names]), np.ascontiguousarray(t_flat), inv_step,
        n_t.astype(np.int64), best.astype(np.int64), B.x if every else B.x[pts],
        B.y if every else B.y[pts], rows.astype(np.int64, copy=False), C1, float(B.margin),
        bool(links[0]), bool(links[1]),
    )  # fmt: skip
    k_first = np.where(best < n_t, best, -1)
    return k_first, free


@dataclass
class BatchEvents:
    """First events of one phase for R slices (arrays (R,) unless noted)."""

    t: np.ndarray
    """(R, n_steps + 1) coarse samples of the path parameter (only the first ``n_t`` used)."""
    n_t: np.ndarray
    """Number of coarse samples (n_steps + 1, or 1 when t_end <= 0)."""
    k: np.ndarray
    """First touching coarse sample, -1 if none."""
    t_free: np.ndarray
    """The last contact-free path parameter."""
    distal_hit: np.ndarray
    """bool: the distal link touched (a point or the palm)."""
    palm: np.ndarray
    """bool: a link touched the palm."""
    middle_idx: np.ndarray
    """The point the middle link touched (index into ``B.P``), -1 if none."""
    distal_idx: np.ndarray
    """The point the distal link touched, -1 if none."""


def batch_first_events(
    B: SliceBatch,
    sl: np.ndarray,
    qb: np.ndarray,
    A: np.ndarray,
    t_end: np.ndarray,
    n_steps: int,
    links: tuple[bool, bool],
    candidates: tuple[np.ndarray, np.ndarray] | None = None,
) -> BatchEvents:
    """The first event of a closing phase (as ``closing``'s single-slice version) for the
    slices ``sl`` (R,) (distinct, increasing) with paths ``min(qb + A t, upper)`` (qb (R, 2))
    and parameter ranges ``t_end`` (R,), level by level for all slices together.
    ``candidates``: ``(pts, rows)`` as :func:`~pregrasp_core.hand.batch_hits.points_of` gives
    them for ``sl``, less the points that cannot touch a link along the paths (an exact
    superset of those that can); None: every point of the slices."""
    R = len(sl)
    upper = B.upper[sl]
    m = B.margin
    # coarse samples: np.linspace(0, t_end, n_steps + 1) (arange * step + 0, last = t_end)
    n_t = np.where(t_end > 0, n_steps + 1, 1)
    step = np.where(t_end > 0, t_end, 0.0) / n_steps
    t = np.arange(n_steps + 1, dtype=np.float64)[None, :] * step[:, None]
    t += 0.0
    t[:, -1] = np.where(t_end > 0, t_end, 0.0)
    pts_all, rows_all = points_of(B, sl) if candidates is None else candidates
    k, free = _coarse_sweep(B, sl, qb, A, upper, t, n_t, step, pts_all, rows_all, links)
    has = k >= 0
    lo = np.zeros(R)
    hi = np.zeros(R)
    pos = has & (k > 0)
    lo[pos] = t[pos, k[pos] - 1]
    hi[pos] = t[pos, k[pos]]
    # the points that may touch a link in [lo, hi]: those that the sweep did not certify off the
    # links over [0, hi] (an exact superset)
    # of those, the ones that may touch a link between the bracket's ends along the path
    # (closing.may_touch: the same exact superset, from the distances at hi); one compiled
    # pass, with numpy's cos and sin of the brackets' ends
    Qb = paths(qb, A, upper, np.stack([lo, hi], axis=1))  # (R, 2, 2)
    qa0, qa1 = np.ascontiguousarray(Qb[:, 0, 0]), np.ascontiguousarray(Qb[:, 0, 1])
    qz0, qz1 = np.ascontiguousarray(Qb[:, 1, 0]), np.ascontiguousarray(Qb[:, 1, 1])
    a2 = qz0 + qz1
    p_near, r_near = candidate_kernels()[0](
        has, hi, free, pts_all.astype(np.int64, copy=False),
        rows_all.astype(np.int64, copy=False), qa0, qa1, qz0, qz1, np.cos(qz0), np.sin(qz0),
        np.cos(a2), np.sin(a2), B.x, B.y, B.seg, B.Lm, B.Ld, B.h, float(m), bool(links[0]),
        bool(links[1]),
    )  # fmt: skip
    # refinement of [last free, first touching], all slices level by level, each with its own
    # number of samples per level (as for one slice: REFINE_BUDGET // points within reach)
    ref = np.flatnonzero(pos)
    if len(ref):
        cnt = B.count[sl[ref]]
        n_ref = np.maximum(1, np.minimum(REFINE_SAMPLES, REFINE_BUDGET // np.maximum(cnt, 1)))
        row_of = np.full(R, -1, dtype=np.int64)
        row_of[ref] = np.arange(len(ref))
        sel = row_of[r_near] >= 0
        p_ref, r_ref = p_near[sel], row_of[r_near[sel]]
        f_lo, f_hi = lo[ref], hi[ref]
        n_max = int(n_ref.max())
        samples, level = refine_kernels()
        qb_r, up_r, sl_r = qb[ref], upper[ref], sl[ref]
        p_ref, r_ref = p_ref.astype(np.int64, copy=False), r_ref.astype(np.int64, copy=False)
        A0, A1 = float(A[0]), float(A[1])
        while True:  # one level: two compiled passes around numpy's cosines and sines
            live = np.flatnonzero(f_hi - f_lo > HAND_CLOSING_ANGLE_TOL)
            if len(live) == 0:
                break
            ts, a1, a2 = samples(f_lo, f_hi, n_ref, live, n_max, qb_r, A0, A1, up_r)
            level(
                ts, np.cos(a1), np.sin(a1), np.cos(a2), np.sin(a2), live, n_ref, f_lo, f_hi,
                sl_r, B.Lk, B.Lm, B.Ld, B.h, float(m), bool(B.palm), B.x, B.y, B.seg, p_ref,
                r_ref, bool(links[0]), bool(links[1]),
            )  # fmt: skip
        lo[ref], hi[ref] = f_lo, f_hi
    # the event at hi (tested on the points that may touch there, a superset of those that do):
    # the touching point of least distance per link
    ev = np.flatnonzero(has)
    mid_idx = np.full(R, -1, dtype=np.int64)
    dis_idx = np.full(R, -1, dtype=np.int64)
    distal_hit = np.zeros(R, dtype=bool)
    palm = np.zeros(R, dtype=bool)
    if len(ev):
        Qh = paths(qb[ev], A, upper[ev], hi[ev][:, None])  # (E, 1, 2)
        cfg = Configs.of(B, sl[ev], Qh, links)
        row_of = np.full(R, -1, dtype=np.int64)
        row_of[ev] = np.arange(len(ev))
        p_ev, r_ev = p_near, row_of[r_near]
        a, b = pair_hits(B, cfg, r_ev, p_ev, links)
        q_free = paths(qb[ev], A, upper[ev], lo[ev][:, None])[:, 0]  # (E, 2)
        for link, hits, out in ((0, a[:, 0], mid_idx), (1, b[:, 0], dis_idx)):
            if not hits.any():
                continue
            cand, crow = p_ev[hits], r_ev[hits]
            dist = batch_distance(B, q_free[crow], cand, link)
            order = np.lexsort((cand, dist, crow))  # per row: least distance, then lowest index
            cand, crow, dist = cand[order], crow[order], dist[order]
            first = np.flatnonzero(np.concatenate([[True], crow[1:] != crow[:-1]]))
            best = cand[first]
            # a near-tie of two distances (the single version's matrix product may round the
            # last bit otherwise): decide it with FingerGeometry.distance itself
            nxt = first + 1
            ok = nxt < len(crow)
            tie = np.zeros(len(first), dtype=bool)
            tie[ok] = (crow[nxt[ok]] == crow[first[ok]]) & (
                dist[nxt[ok]] - dist[first[ok]] <= 1e-15
            )
            for i in np.flatnonzero(tie):  # rare
                e = crow[first[i]]
                c = p_ev[hits][r_ev[hits] == e]
                s = sl[ev[e]]
                geo = FingerGeometry(B.fingers[s], m, B.palm)
                best[i] = c[np.argmin(geo.distance(q_free[e], B.P[c], link))]
            out[ev[crow[first]]] = best
        bm = np.zeros(len(ev), dtype=bool)
        bm[r_ev[b[:, 0]]] = True
        distal_hit[ev] = bm | cfg.palm_dis[:, 0]
        palm[ev] = cfg.palm_mid[:, 0] | cfg.palm_dis[:, 0]
    t_free = np.where(has, lo, t[np.arange(R), n_t - 1])
    return BatchEvents(
        t=t,
        n_t=n_t,
        k=k,
        t_free=t_free,
        distal_hit=distal_hit,
        palm=palm,
        middle_idx=mid_idx,
        distal_idx=dis_idx,
    )
