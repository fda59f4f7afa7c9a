"""The planner's speed paths (issue 5) give the same answers as the straightforward ones.

* ``Hand.close_finger`` sweeps a phase in growing chunks and stops at the first chunk that
  touches; with one chunk holding every sample (the straightforward sweep) every field of the
  result must be identical, on random slices and start configurations.
* ``Hand.self_collisions`` skips the link pairs whose circumscribed balls are apart; python-fcl
  on every checked pair (the straightforward test) must find the same pairs, in the same order.
"""

from __future__ import annotations

import fcl
import numpy as np
import pytest

import pregrasp_core.hand.closing as closing_module
from pregrasp_core.hand import load_hand


@pytest.fixture(scope="module")
def hand():
    return load_hand()


def _same_closing(a, b) -> None:
    assert a.finger == b.finger
    np.testing.assert_array_equal(a.q, b.q)
    np.testing.assert_array_equal(a.path, b.path)
    assert a.contact_link == b.contact_link
    assert a.contact_index == b.contact_index
    assert [(c.link, c.index) for c in a.contacts] == [(c.link, c.index) for c in b.contacts]
    for ca, cb in zip(a.contacts, b.contacts, strict=True):
        np.testing.assert_array_equal(ca.point, cb.point)
    flags = ("stopped_middle", "stopped_distal", "palm_stop", "at_limits", "start_in_contact")
    assert [getattr(a, k) for k in flags] == [getattr(b, k) for k in flags]


@pytest.mark.parametrize("seed", range(6))
def test_chunked_closing_sweep_equals_the_full_sweep(hand, monkeypatch, seed):
    rng = np.random.default_rng(seed)
    n_touch = 0
    for f in hand.fingers:  # loop over the 3 fingers
        reach = f.middle_length + f.distal_length
        for _ in range(8):  # random slices: a blob ahead of the finger, sometimes nothing
            m = int(rng.integers(0, 400))
            centre = rng.uniform([0.2, 0.1], [0.9, 0.9]) * reach
            pts = centre + rng.normal(scale=0.15 * reach, size=(m, 2))
            q0 = rng.uniform(f.lower, 0.5 * (f.lower + f.upper))
            margin = float(rng.choice([0.0, 0.001]))
            monkeypatch.setattr(closing_module, "SWEEP_CHUNK", 8)
            fast = hand.close_finger(f, pts, q0, margin=margin)
            monkeypatch.setattr(closing_module, "SWEEP_CHUNK", 10_000)  # one chunk: every sample
            full = hand.close_finger(f, pts, q0, margin=margin)
            _same_closing(fast, full)
            n_touch += fast.contact_link is not None
    assert n_touch > 0  # the comparison covered closings that touched the slice


def _self_collisions_all_pairs(hand, q) -> list[tuple[str, str]]:
    objs = hand.collision_objects(q)
    out = []
    for a, b in hand.self_collision_pairs_checked:
        if fcl.collide(objs[a], objs[b], fcl.CollisionRequest(), fcl.CollisionResult()) > 0:
            out.append((a, b))
    return out


def test_self_collision_ball_pretest_equals_fcl_on_every_pair(hand):
    rng = np.random.default_rng(7)
    lower = np.asarray(hand.lower, dtype=np.float64)
    upper = np.asarray(hand.upper, dtype=np.float64)
    Q = rng.uniform(lower, upper, size=(300, hand.n_joints))
    n_hit = 0
    for q in Q:  # loop over sampled configurations
        expected = _self_collisions_all_pairs(hand, q)
        assert hand.self_collisions(q) == expected
        n_hit += bool(expected)
    assert 0 < n_hit < len(Q)  # both colliding and free configurations were compared


@pytest.mark.parametrize("seed", range(4))
def test_refinement_point_filter_equals_refining_with_every_point(hand, monkeypatch, seed):
    rng = np.random.default_rng(100 + seed)
    everything = lambda geo, P, Q, links: np.ones(len(P), dtype=bool)  # noqa: E731
    real = closing_module.may_touch
    n_touch = 0
    for f in hand.fingers:  # loop over the 3 fingers
        reach = f.middle_length + f.distal_length
        for _ in range(6):
            pts = rng.uniform(-0.2, 1.0, size=(int(rng.integers(20, 600)), 2)) * reach
            q0 = rng.uniform(f.lower, 0.5 * (f.lower + f.upper))
            monkeypatch.setattr(closing_module, "may_touch", real)
            fast = hand.close_finger(f, pts, q0, margin=0.001)
            monkeypatch.setattr(closing_module, "may_touch", everything)
            full = hand.close_finger(f, pts, q0, margin=0.001)
            _same_closing(fast, full)
            n_touch += fast.contact_link is not None
    assert n_touch > 0


def test_may_touch_keeps_every_point_touched_inside_the_bracket(hand):
    """Dense sampling of random brackets: every point some sample touches is kept, and the
    filter does drop points (else it would be pointless)."""
    rng = np.random.default_rng(5)
    f = hand.fingers[0]
    geo = closing_module.FingerGeometry(f, 0.001, palm=True)
    reach = f.middle_length + f.distal_length
    n_dropped = n_touched = 0
    for _ in range(40):  # random brackets and point sets
        P = rng.uniform(-0.3, 1.0, size=(500, 2)) * reach
        qa = rng.uniform(f.lower, f.upper)
        qb = np.minimum(qa + rng.uniform(0.0, 0.1, size=2), f.upper)
        keep = closing_module.may_touch(geo, P, np.stack([qa, qb]), (True, True))
        Q = qa + np.linspace(0.0, 1.0, 201)[:, None] * (qb - qa)  # (201, 2) dense samples
        mid, dis, _, _ = geo.hits(Q, P, (True, True))
        touched = (mid | dis).any(axis=0)
        assert not np.any(touched & ~keep)
        n_dropped += int(np.count_nonzero(~keep))
        n_touched += int(np.count_nonzero(touched))
    assert n_touched > 0 and n_dropped > 0


# ---- the compiled kernels (pregrasp_core/planner/kernels.py) against the numpy code they
# replaced (copied here from the planner before issue 15): equal to the bit on every pre-grasp
# of the default object, at the pre-grasp pose and moved along the approach


@pytest.fixture(scope="module")
def mug_plan(hand):
    from pregrasp_core.io import load_point_cloud
    from pregrasp_core.paths import DEFAULT_OBJECT
    from pregrasp_core.pipeline import PipelineParams, run_pipeline
    from pregrasp_core.planner import PlannerParams
    from pregrasp_core.planner.context import Context

    cloud = load_point_cloud(DEFAULT_OBJECT, n_points=6000, seed=0)
    params = PipelineParams(planner=PlannerParams(threads=1))
    res = run_pipeline(cloud, params=params, hand=hand, until="pool")
    ctx = Context(
        cloud.points, np.zeros_like(cloud.points), hand, params.planner, res.masks.support
    )
    return ctx, res.pool


def _ref_points(ctx, view, pid):
    from pregrasp_core.geometry import to_frame_t

    p0 = to_frame_t(ctx.xyz[:, pid], view.T0)
    x, y, z = p0
    ok = (np.abs(x) <= view.r) & (np.abs(y) <= view.r) & (z >= view.z_lo) & (z <= view.z_hi)
    p = p0[:, ok]
    for d in view.dz:
        p[2] += d
    return ok, p


def _ref_slices(ctx, view, gt, spread):
    """finger_slices before issue 15 (without the support trace): per finger (points, n_slice)."""
    from pregrasp_core.geometry import to_frame_t
    from pregrasp_core.planner.slicing import thin_2d

    prm = ctx.params
    fingers = ctx.hand.fingers_for(gt)
    planes = [ctx.plane(f, spread) for f in fingers]
    nrm = np.array([pl.normal for pl in planes]).T
    shift = np.array([pl.origin @ pl.normal for pl in planes])
    half_w = np.array([0.5 * f.width for f in fingers])
    reach = [f.middle_length + np.hypot(f.distal_length, 0.5 * f.thickness) for f in fingers]
    r_all = np.array(reach) + prm.closing_margin
    c, ok = view.cells(ctx)
    rad = ctx.cells.radius[:, None]
    origins = np.array([pl.origin for pl in planes])
    d2 = np.sum((c[:, None, :] - origins[None]) ** 2, axis=2)
    cand = (
        ok[:, None]
        & (np.abs(c @ nrm - shift) <= half_w + 1e-9 + rad)
        & (d2 <= (np.hypot(r_all, half_w) + 1e-9 + rad) ** 2)
    )
    _, p = _ref_points(ctx, view, ctx.cells.points_of(np.flatnonzero(cand.any(axis=1))))
    along = p[0, :, None] * nrm[0] + p[1, :, None] * nrm[1] + p[2, :, None] * nrm[2]
    near_band = np.abs(along - shift) <= half_w + 1e-9
    out = []
    for j, (f, plane) in enumerate(zip(fingers, planes, strict=True)):
        uvn = to_frame_t(p[:, near_band[:, j]], plane.T_hand_plane)
        p2, off = uvn[:2].T, uvn[2]
        r_f = r_all[j]
        in_slice = (np.abs(off) <= 0.5 * f.width) & (
            p2[:, 0] ** 2 + p2[:, 1] ** 2 <= (r_f + 1e-9) ** 2
        )
        out.append((thin_2d(p2[in_slice], prm.slice_resolution), int(np.count_nonzero(in_slice))))
    return out


def _ref_approach_sweep(ctx, T0, q, c0, window):
    """The object part of the approach before issue 15 (one window): the first travel, inf if
    none."""
    from pregrasp_core.geometry import to_frame_t
    from pregrasp_core.planner.boxes import sweep_pairs

    c = ctx.params.approach_clearance
    Tb, lo, hi = ctx.boxes(q)
    wlo, whi = lo - c, hi + c
    rad = ctx.cells.radius[:, None]
    cm, cp = c0 - rad, c0 + rad
    top = whi[:, 2] + window
    ci, il = np.nonzero(
        (cp[:, 2:3] >= wlo[:, 2]) & (cm[:, 2:3] <= top) & (cp[:, 0:1] >= wlo[:, 0])
        & (cm[:, 0:1] <= whi[:, 0]) & (cp[:, 1:2] >= wlo[:, 1]) & (cm[:, 1:2] <= whi[:, 1])
    )  # fmt: skip
    pid, k = ctx.cells.expand(ci)
    il = il[k]
    px, py, pz = to_frame_t(ctx.xyz[:, pid], T0)
    hit = np.flatnonzero(
        (pz >= wlo[il, 2]) & (pz <= top[il]) & (px >= wlo[il, 0]) & (px <= whi[il, 0])
        & (py >= wlo[il, 1]) & (py <= whi[il, 1])
    )  # fmt: skip
    if not len(hit):
        return np.inf
    return sweep_pairs(px[hit], py[hit], pz[hit], il[hit], Tb, ctx.half + c)[0]


def _ref_link_distances(ctx, view, q, reach):
    """verify._link_distances before issue 15."""
    Tb, lo, hi = ctx.boxes(q)
    blo, bhi = lo - reach, hi + reach
    c, ok = view.cells(ctx)
    rad = ctx.cells.radius[:, None]
    cm, cp = c - rad, c + rad
    ci, il = np.nonzero(
        ok[:, None] & (cp[:, 0:1] >= blo[:, 0]) & (cm[:, 0:1] <= bhi[:, 0])
        & (cp[:, 1:2] >= blo[:, 1]) & (cm[:, 1:2] <= bhi[:, 1]) & (cp[:, 2:3] >= blo[:, 2])
        & (cm[:, 2:3] <= bhi[:, 2])
    )  # fmt: skip
    pid, k = ctx.cells.expand(ci)
    seen, p = _ref_points(ctx, view, pid)
    pid, il = pid[seen], il[k[seen]]
    x, y, z = p
    inside = np.flatnonzero(
        (x >= blo[il, 0]) & (x <= bhi[il, 0]) & (y >= blo[il, 1]) & (y <= bhi[il, 1])
        & (z >= blo[il, 2]) & (z <= bhi[il, 2])
    )  # fmt: skip
    il, pid = il[inside], pid[inside]
    Tl = Tb[il]
    v0, v1, v2 = x[inside] - Tl[:, 0, 3], y[inside] - Tl[:, 1, 3], z[inside] - Tl[:, 2, 3]
    half = ctx.half[il]
    qd = [
        np.abs(v0 * Tl[:, 0, j] + v1 * Tl[:, 1, j] + v2 * Tl[:, 2, j]) - half[:, j]
        for j in range(3)
    ]
    out = [np.maximum(qj, 0.0) for qj in qd]
    d = np.sqrt(out[0] ** 2 + out[1] ** 2 + out[2] ** 2) + np.minimum(
        np.maximum(np.maximum(qd[0], qd[1]), qd[2]), 0.0
    )
    near = np.flatnonzero(d <= reach)
    near = near[np.lexsort((pid[near], il[near]))]
    il, d, cloud = il[near], d[near], pid[near]
    cuts = np.searchsorted(il, np.arange(1, len(Tb)))
    return np.split(cloud, cuts), np.split(d, cuts)


def test_kernels_equal_the_numpy_searches_on_every_pregrasp(mug_plan):
    from pregrasp_core.geometry import to_frame
    from pregrasp_core.planner.approach import prepare
    from pregrasp_core.planner.slicing import finger_slices
    from pregrasp_core.planner.verify import CONTACT_TIE, _link_distances, _link_distances_flat

    ctx, pool = mug_plan
    rng = np.random.default_rng(0)
    n_points = n_links = n_ties = 0
    for i in range(len(pool)):  # loop over the pre-grasps
        T0, q0 = pool.T_world_hand[i], pool.q[i]
        c0 = to_frame(ctx.cells.centre, T0)
        # the compiled frame change of the cells (prepare's) gives these bits, and the balls'
        # bounds c0 -/+ radius
        rad = ctx.cells.radius[:, None]
        c_k, lo_k, hi_k = ctx_kernels().cells_in_frame(ctx.cells.centre, ctx.cells.radius, T0)
        assert c_k.tobytes() == c0.tobytes()
        assert lo_k.tobytes() == (c0 - rad).tobytes() and hi_k.tobytes() == (c0 + rad).tobytes()
        for window in (0.01, 0.03, 0.15):
            s_ref = _ref_approach_sweep(ctx, T0, q0, c0, window)
            Tb, lo, hi = ctx.boxes(q0)
            c = ctx.params.approach_clearance
            rad = ctx.cells.radius[:, None]
            cells = ctx.cells
            s_new = ctx_kernels().approach(
                ctx.xyz, cells.order, cells.start, cells.count, c0 - rad, c0 + rad, T0,
                lo - c, hi + c, hi[:, 2] + c + window, Tb, ctx.half + c,
            )  # fmt: skip
            assert s_new == s_ref or (np.isinf(s_ref) and np.isinf(s_new))
        p = prepare(ctx, pool, i)
        if not hasattr(p, "view"):
            continue
        for view, T in ((p.view, p.T), (p.view.moved(0.005), p.T)):  # also a retreat
            ref = _ref_slices(ctx, view, p.gt, p.spread)
            got = finger_slices(ctx, T, view, p.q0, p.gt, p.spread)
            for (pts, n), sl in zip(ref, got, strict=True):
                np.testing.assert_array_equal(sl.points_2d[: sl.n_obj], pts)
                assert sl.n_slice == n
                n_points += len(pts)
            # link distances at the preshape and at a random closing
            q = p.q0.copy()
            for f in ctx.hand.fingers_for(p.gt):
                q[list(f.flex_index)] = rng.uniform(f.lower, f.upper)
            for qq in (p.q0, q):
                ids_r, d_r = _ref_link_distances(ctx, view, qq, 0.003)
                ids_n, d_n = _link_distances(ctx, view, qq, 0.003)
                for a, b, x, y in zip(ids_r, ids_n, d_r, d_n, strict=True):
                    np.testing.assert_array_equal(a, b)
                    np.testing.assert_array_equal(x, y)
                    n_links += len(a)
                # each link's least distance and contact point (the compiled choice)
                least_r, picks_r, ties = _ref_contact_choice(ctx, T, qq, ids_r, d_r)
                ids, d, first = _link_distances_flat(ctx, view, qq, 0.003)
                centres = np.ascontiguousarray((T @ ctx.boxes(qq)[0])[:, :3, 3])
                least, pick = ctx_kernels().link_contacts(
                    ids, d, first, ctx.xyz, centres, ctx.params.contact_distance, CONTACT_TIE
                )
                np.testing.assert_array_equal(least, least_r)
                assert [(j, int(ids[k])) for j, k in enumerate(pick) if k >= 0] == picks_r
                n_ties += ties
    assert n_points > 10000 and n_links > 1000  # the comparisons saw real data
    assert n_ties > 0  # and contact patches (ties within CONTACT_TIE)


def _ref_contact_choice(ctx, T, q, ids, dists):
    """verify._contacts' choice and the least distances before issue 15, session 7 (numpy per
    link): ``(least (L,), [(link, cloud index)], patches with more than one point)``."""
    from pregrasp_core.planner.verify import CONTACT_TIE

    centres = (T @ ctx.boxes(q)[0])[:, :3, 3]
    least = np.array([d.min() if len(d) else np.inf for d in dists])
    picks, ties = [], 0
    for j, (sel, d) in enumerate(zip(ids, dists, strict=True)):
        if len(d) and d.min() <= ctx.params.contact_distance:
            tie = np.flatnonzero(d <= d.min() + CONTACT_TIE)
            if len(tie) > 1:
                off = np.sum((ctx.points[sel[tie]] - centres[j]) ** 2, axis=1)
                k = int(tie[np.lexsort((sel[tie], off))[0]])
                ties += 1
            else:
                k = int(tie[0])
            picks.append((j, int(sel[k])))
    return least, picks, ties


def ctx_kernels():
    from pregrasp_core.planner.kernels import kernels

    return kernels()


def _numpy_any_hit_ragged(B, cfg, pts, rows, n_row, links):
    """The numpy form of ``batch_hits.any_hit_ragged`` that the compiled loop replaced (issue
    15, session 7): every (point, sample) pair expanded and tested with ``pair_hits``."""
    from pregrasp_core.hand.batch_hits import Configs, pair_hits

    R, C = cfg.d1x.shape
    out = cfg.palm_mid | cfg.palm_dis
    out &= np.arange(C)[None, :] < n_row[:, None]
    flat = Configs(*(getattr(cfg, k).reshape(-1, 1) for k in Configs.__dataclass_fields__))
    rp = n_row[rows]
    pair_pt = np.repeat(pts, rp)
    j = np.arange(int(rp.sum())) - np.repeat(np.cumsum(rp) - rp, rp)
    cfg_i = np.repeat(rows, rp) * C + j
    mid, dis = pair_hits(B, flat, cfg_i, pair_pt, links)
    mid |= dis
    np.put(out, cfg_i[mid[:, 0]], True)
    return out


@pytest.mark.parametrize("seed", range(4))
def test_compiled_ragged_hits_equal_the_numpy_pairs(hand, seed):
    """``any_hit_ragged`` (one compiled loop) gives the numpy pairs' answer on random slices,
    configurations near the points, ragged sample counts, each link alone and both, palm on and
    off, margins 0 and 1 mm, points placed on the links' boundaries."""
    from pregrasp_core.hand.batch_hits import Configs, SliceBatch, any_hit_ragged

    rng = np.random.default_rng(300 + seed)
    S = 12
    fingers = tuple(hand.fingers[int(k)] for k in rng.integers(0, 3, S))
    geom = np.array(
        [(f.knuckle_length, f.middle_length, f.distal_length, 0.5 * f.thickness) for f in fingers]
    )
    sizes = rng.integers(0, 300 if seed % 2 else 4, S)  # even seeds: boundary points only
    P = rng.uniform(-0.03, 0.12, size=(int(sizes.sum()), 2))
    seg = np.repeat(np.arange(S), sizes)
    Q = rng.uniform(-0.5, 1.6, size=(S, 9, 2))
    # put some points exactly on a link's side at one of the configurations
    for k in rng.choice(len(P), size=min(40, len(P)), replace=False):
        s, c = seg[k], int(rng.integers(9))
        a = Q[s, c, 0]
        P[k] = rng.uniform(0, geom[s, 1]) * np.array([np.cos(a), np.sin(a)]) + geom[s, 3] * (
            np.array([-np.sin(a), np.cos(a)])
        )
    # at q = (0, 0) the middle link's tests read the coordinates themselves (cos 0 = 1, sin 0
    # = 0): points exactly on its bounds, so that a changed comparison would show
    Q[:, 0] = 0.0
    n_hits = 0
    for margin in (0.0, 0.001):
        for k in rng.choice(len(P), size=min(60, len(P)) if seed % 2 else len(P), replace=False):
            s = seg[k]
            along = rng.choice([-margin, geom[s, 1] + margin, rng.uniform(0.0, geom[s, 1])])
            side = rng.choice([-1.0, 1.0]) * (geom[s, 3] + margin)
            P[k] = (along, side) if rng.random() < 0.5 else (side, along)
        for palm in (True, False):
            B = SliceBatch(
                fingers=fingers, Lk=geom[:, 0], Lm=geom[:, 1], Ld=geom[:, 2], h=geom[:, 3],
                upper=np.array([f.upper for f in fingers]), P=P,
                x=np.ascontiguousarray(P[:, 0]), y=np.ascontiguousarray(P[:, 1]), seg=seg,
                start=np.concatenate([[0], np.cumsum(sizes)]),
                margin=margin, palm=palm,
            )  # fmt: skip
            rows_sl = np.sort(rng.choice(S, size=8, replace=False))
            row_of = np.full(S, -1)
            row_of[rows_sl] = np.arange(8)
            pts = np.flatnonzero(row_of[seg] >= 0)
            pts = pts[rng.random(len(pts)) < 0.8]
            rows = row_of[seg[pts]]
            n_row = rng.integers(1, 10, 8)
            for links in ((True, True), (True, False), (False, True)):
                cfg = Configs.of(B, rows_sl, Q[rows_sl], links)
                got = any_hit_ragged(B, cfg, pts, rows, n_row, links)
                want = _numpy_any_hit_ragged(B, cfg, pts, rows, n_row, links)
                np.testing.assert_array_equal(got, want)
                n_hits += int(want.sum())
    assert n_hits > 0
