"""Batched self-collision (``Hand.self_collisions_many``) and its separating-axis pre-filter.

The contract is python-fcl's answer: for every configuration, the batched call, the single call
and a brute-force python-fcl check of every checked link pair (no pre-filter at all, written
here) list the same pairs in the same order. The configurations are seeded random ones across
the joint limits, closed-hand-like ones, the preshapes, and near-touching ones (a finger's
flexion bisected to the first contact with another link, then stepped 1e-14 to 1e-3 of the
path before and after it). The separating-axis test is also checked alone on random box pairs
(parallel, perpendicular, touching, nearly touching) against python-fcl: every pair it calls
apart is apart for python-fcl, and pairs farther apart than 0.1 mm are all called apart.
"""

from __future__ import annotations

import fcl
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import pregrasp_core.hand.collision as collision_module
from pregrasp_core.hand import GRASP_TYPES, load_hand


@pytest.fixture(scope="module")
def hand():
    return load_hand()


def _fcl_box(half: np.ndarray, R: np.ndarray, c: np.ndarray) -> fcl.CollisionObject:
    return fcl.CollisionObject(fcl.Box(*(2.0 * half)), fcl.Transform(R, c))


def _fcl_hit(a: fcl.CollisionObject, b: fcl.CollisionObject) -> bool:
    return fcl.collide(a, b, fcl.CollisionRequest(), fcl.CollisionResult()) > 0


def _brute_force(hand, q: np.ndarray) -> list[tuple[str, str]]:
    """python-fcl on every checked pair, boxes placed from the box poses; no pre-filter."""
    Tb = hand.box_poses(q)
    objs = {
        n: _fcl_box(hand.link_box_half[i], Tb[i, :3, :3], Tb[i, :3, 3])
        for i, n in enumerate(hand.link_names)
    }
    return [(a, b) for a, b in hand.self_collision_pairs_checked if _fcl_hit(objs[a], objs[b])]


def _closed_like(hand, rng: np.random.Generator, n: int) -> np.ndarray:
    """Hands closed on something: spread of a grasp type, flexions in the closing half."""
    lo = np.asarray(hand.lower, dtype=np.float64)
    hi = np.asarray(hand.upper, dtype=np.float64)
    Q = rng.uniform(lo + 0.25 * (hi - lo), lo + 0.8 * (hi - lo), size=(n, hand.n_joints))
    spreads = np.array([hand.spread_for(g) for g in GRASP_TYPES])
    Q[:, hand.spread_index] = rng.choice(spreads, size=n)
    return Q


def _check_all_ways(hand, Q: np.ndarray, monkeypatch) -> list[list[tuple[str, str]]]:
    """many == [single] == brute force, with the separating-axis filter forced on and off."""
    expected = [_brute_force(hand, q) for q in Q]
    for min_pairs in (0, 10**9):  # filter on every batch / never (python-fcl on every candidate)
        monkeypatch.setattr(collision_module, "SAT_MIN_PAIRS", min_pairs)
        assert hand.self_collisions_many(Q) == expected
        assert hand.self_collisions_many(Q, hand.box_poses(Q)) == expected
        assert [hand.self_collisions(q) for q in Q] == expected
    monkeypatch.undo()
    assert hand.self_collisions_many(Q) == expected  # the default threshold
    return expected


@pytest.mark.parametrize("seed", range(3))
def test_many_equals_single_and_brute_force_on_random_configurations(hand, monkeypatch, seed):
    rng = np.random.default_rng(seed)
    Q = np.concatenate(
        [
            rng.uniform(hand.lower, hand.upper, size=(150, hand.n_joints)),
            _closed_like(hand, rng, 150),
            np.stack([hand.preshape(g) for g in GRASP_TYPES]),
            np.stack([hand.lower, hand.upper]),
        ]
    )
    expected = _check_all_ways(hand, Q, monkeypatch)
    n_hit = sum(bool(e) for e in expected)
    assert 0.1 * len(Q) < n_hit < 0.9 * len(Q)  # both outcomes compared, many times
    assert all(e == [] for e in expected[300:304])  # the preshapes are collision-free
    assert len({p for e in expected for p in e}) >= 10  # many different link pairs collide


def _first_contact(hand, q0: np.ndarray, q1: np.ndarray) -> float | None:
    """Path parameter s of the first self-contact on q0 + s (q1 - q0) by bisection of the
    brute-force check (None unless q0 is free and q1 collides); bracket width 1e-15."""
    if _brute_force(hand, q0) or not _brute_force(hand, q1):
        return None
    lo, hi = 0.0, 1.0
    while hi - lo > 1e-15:
        mid = 0.5 * (lo + hi)
        if mid in (lo, hi):
            break
        if _brute_force(hand, q0 + mid * (q1 - q0)):
            hi = mid
        else:
            lo = mid
    return hi


def test_many_equals_brute_force_near_the_first_contact(hand, monkeypatch):
    """Close one finger from a random hand until it first touches another link (30 motions);
    configurations 1e-14 to 1e-3 of the path before and after the contact (the boxes about
    1e-16 to 1e-4 m apart or overlapping) give python-fcl's answer in all three calls."""
    rng = np.random.default_rng(21)
    lo = np.asarray(hand.lower, dtype=np.float64)
    hi = np.asarray(hand.upper, dtype=np.float64)
    steps = np.concatenate([-np.logspace(-3, -14, 12), [0.0], np.logspace(-14, -3, 12)])
    configs, touched = [], []
    tries = 0
    while len(touched) < 30 and tries < 400:  # loop over sampled closing motions (a few dozen)
        tries += 1
        q0 = rng.uniform(lo, lo + 0.6 * (hi - lo))
        flex = list(hand.fingers[int(rng.integers(len(hand.fingers)))].flex_index)
        q1 = q0.copy()
        q1[flex] = np.maximum(rng.uniform(lo[flex], hi[flex]), q0[flex])  # the finger closes
        s = _first_contact(hand, q0, q1)
        if s is None:
            continue
        touched.append(tuple(_brute_force(hand, q0 + s * (q1 - q0))))
        configs.extend(q0 + np.clip(s + steps, 0.0, 1.0)[:, None] * (q1 - q0))
    assert len(touched) == 30
    assert len(set(touched)) >= 6  # contacts between several different link pairs
    Q = np.array(configs)
    expected = _check_all_ways(hand, Q, monkeypatch)
    per_contact = np.array([bool(e) for e in expected]).reshape(len(touched), len(steps))
    assert not per_contact[:, :12].any() and per_contact[:, 12:].all()  # apart, then touching


def _random_box_pairs(rng: np.random.Generator, n: int):
    """n box pairs with pair index last (as ``obb_apart`` takes them), in kinds that stress
    the test: random, parallel, perpendicular (exact 90 degree turns), nearly parallel
    (1e-12..1e-3 rad), each placed so that their extents along a direction u just meet, then
    moved by a signed gap from -1 mm to 1 mm (including 0 and +-1e-12..1e-9 m) along a face
    normal of a or b (``on_face``: that normal is one of the 15 axes and parts them by the gap)
    or along a random direction."""
    ha = rng.uniform(0.002, 0.05, size=(n, 3))
    hb = rng.uniform(0.002, 0.05, size=(n, 3))
    Ra = Rotation.random(n, random_state=rng).as_matrix()
    kind = rng.integers(0, 4, size=n)
    turn = Rotation.random(n, random_state=rng).as_matrix()
    perm = np.array([np.eye(3)[rng.permutation(3)] * rng.choice([-1, 1], size=3) for _ in range(n)])
    perm *= np.linalg.det(perm)[:, None, None]  # proper rotations
    angle = 10.0 ** rng.uniform(-12, -3, size=(n, 1))
    tiny = Rotation.from_rotvec(rng.normal(size=(n, 3)) * angle).as_matrix()
    rel = np.stack([turn, np.broadcast_to(np.eye(3), (n, 3, 3)), perm, tiny])[kind, np.arange(n)]
    Rb = Ra @ rel
    # direction of the move: a face normal of a, of b, or a random direction
    rows = np.arange(n)
    pick = rng.integers(0, 3, size=n)
    u = np.stack(
        [
            Ra[rows, :, rng.integers(0, 3, size=n)],
            Rb[rows, :, rng.integers(0, 3, size=n)],
            rng.normal(size=(n, 3)),
        ]
    )[pick, rows]
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    # support radii along u: the boxes touch when their centres are ra + rb apart along u
    ra = (np.abs(np.einsum("nki,nk->ni", Ra, u)) * ha).sum(axis=1)
    rb = (np.abs(np.einsum("nki,nk->ni", Rb, u)) * hb).sum(axis=1)
    gaps = [-1e-3, -1e-6, -1e-9, -1e-12, 0.0, 1e-12, 1e-10, 1e-9, 2e-9, 1e-8, 1e-6, 1e-3]
    gap = rng.choice(gaps, size=n)
    ca = rng.uniform(-0.1, 0.1, size=(n, 3))
    cb = ca + u * (ra + rb + gap)[:, None]
    return Ra, ca, ha, Rb, cb, hb, gap, pick < 2


def test_separating_axis_filter_agrees_with_python_fcl_on_random_box_pairs():
    rng = np.random.default_rng(3)
    Ra, ca, ha, Rb, cb, hb, gap, on_face = _random_box_pairs(rng, 3000)
    apart = collision_module.obb_apart(
        Ra.transpose(1, 2, 0), ca.T, ha.T, Rb.transpose(1, 2, 0), cb.T, hb.T
    )
    hit = np.array(
        [
            _fcl_hit(_fcl_box(ha[n], Ra[n], ca[n]), _fcl_box(hb[n], Rb[n], cb[n]))
            for n in range(len(gap))  # loop over box pairs: python-fcl is the reference
        ]
    )
    assert not (apart & hit).any()  # every pair called apart is apart for python-fcl
    assert 0.1 < hit.mean() < 0.9  # many intersecting and touching pairs among them
    # a face normal parting the boxes by 2e-9 m or more: called apart (the test is exact)
    assert apart[on_face & (gap >= 2e-9)].all()
    assert not hit[on_face & (gap > 0)].any()
    # pairs far apart (python-fcl distance over 0.1 mm) are all called apart
    far = []
    for n in np.flatnonzero(~hit):  # loop over the pairs python-fcl finds apart
        res = fcl.DistanceResult()
        d = fcl.distance(
            _fcl_box(ha[n], Ra[n], ca[n]), _fcl_box(hb[n], Rb[n], cb[n]),
            fcl.DistanceRequest(), res,
        )  # fmt: skip
        far.append((n, d))
    far_idx = np.array([n for n, d in far if d > 1e-4])
    assert len(far_idx) > 200
    assert apart[far_idx].all()
    # the filter is not trivially conservative: it decides most apart pairs near the margin
    assert apart[(gap >= 1e-8) & ~hit].mean() > 0.5


def test_separating_axis_filter_on_hand_made_pairs():
    """Cubes of the fingers' size (half side h = 1 cm) in known relative poses: face to face,
    b's edge on a's face, and two edges crossed at 90 and at 84 degrees (only the
    cross-product axis parts them), each at gaps -1e-6, 0, 1e-12, 2e-9 and 1e-6 m along the
    contact normal. The filter calls apart exactly the pairs more than the margin (1e-9 m)
    apart; python-fcl finds every positive gap apart."""
    h = 0.01
    I3 = np.eye(3)
    Rz45 = Rotation.from_euler("z", 45, degrees=True).as_matrix()
    Rx45 = Rotation.from_euler("x", 45, degrees=True).as_matrix()
    r45 = h * np.sqrt(2.0)  # a 45-degree-turned cube reaches this far along the turned axes
    ex, ey = np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0])
    cases = [  # (Ra, Rb, contact normal, centre distance at contact)
        (I3, I3, ex, 2 * h),  # face to face
        (I3, Rz45, ex, h + r45),  # b's z edge on a's +x face
        (Rz45, Rx45, ey, 2 * r45),  # a's z edge crosses b's x edge
        # the same with b's edge tilted about y until |z x edge| = 0.1: the margin is metres
        # along the unit axis (the unnormalised separation is 0.1 x the gap)
        (Rz45, Rotation.from_euler("y", np.arccos(0.1)).as_matrix() @ Rx45, ey, 2 * r45),
    ]
    gaps = ((-1e-6, False), (0.0, False), (1e-12, False), (2e-9, True), (1e-6, True))
    rows = [(Ra, Rb, u * (d + g), ok) for Ra, Rb, u, d in cases for g, ok in gaps]
    Ra = np.array([r[0] for r in rows])
    Rb = np.array([r[1] for r in rows])
    cb = np.array([r[2] for r in rows])
    expected = np.array([r[3] for r in rows])
    ca, half = np.zeros_like(cb), np.full_like(cb, h)
    got = collision_module.obb_apart(
        Ra.transpose(1, 2, 0), ca.T, half.T, Rb.transpose(1, 2, 0), cb.T, half.T
    )
    np.testing.assert_array_equal(got, expected)
    hit = np.array(
        [
            _fcl_hit(_fcl_box(half[n], Ra[n], ca[n]), _fcl_box(half[n], Rb[n], cb[n]))
            for n in range(len(rows))
        ]
    )
    np.testing.assert_array_equal(hit, np.array([g <= 0 for _, _, _, _ in cases for g, _ in gaps]))


def test_shapes_and_empty_batch(hand):
    J, L = hand.n_joints, len(hand.link_names)
    assert hand.self_collisions_many(np.zeros((0, J))) == []
    assert hand.self_collisions_many(np.zeros((0, J)), np.zeros((0, L, 4, 4))) == []
    Q = np.stack([hand.preshape("spherical")] * 3)
    assert hand.self_collisions_many(Q) == [[], [], []]
    with pytest.raises(ValueError, match=rf"Q must have shape \(B, {J}\), got \({J},\)"):
        hand.self_collisions_many(Q[0])
    with pytest.raises(ValueError, match=rf"Q must have shape \(B, {J}\), got \(3, 5\)"):
        hand.self_collisions_many(Q[:, :5])
    with pytest.raises(
        ValueError, match=rf"box_poses must have shape \(3, {L}, 4, 4\), got \({L}, 4, 4\)"
    ):
        hand.self_collisions_many(Q, hand.box_poses(Q[0]))
    with pytest.raises(ValueError, match=rf"box_poses must have shape \(0, {L}, 4, 4\)"):
        hand.self_collisions_many(np.zeros((0, J)), np.zeros((1, L, 4, 4)))


def test_one_pair_checked_alone_gets_the_verdict_of_python_fcl(hand, monkeypatch):
    """``collisions_of(Tb, only=[k])`` (the planner's check of one colliding pair along a
    finger's path) says pair k collides exactly where brute-force python-fcl says so, with the
    separating-axis filter on and off, for every checked pair on closed-hand-like hands."""
    rng = np.random.default_rng(7)
    Q = _closed_like(hand, rng, 120)
    expected = [_brute_force(hand, q) for q in Q]
    checker = hand.self_collision_checker
    Tb = hand.box_poses(Q)
    n_hit = 0
    for min_pairs in (0, 10**9):  # filter always / never
        monkeypatch.setattr(collision_module, "SAT_MIN_PAIRS", min_pairs)
        for k, pair in enumerate(checker.pairs):  # loop over the checked pairs
            got = checker.collisions_of(Tb, np.array([k]))
            assert [bool(g) for g in got] == [pair in e for e in expected]
            assert all(g in ([], [pair]) for g in got)
            n_hit += sum(bool(g) for g in got)
    assert n_hit > 20  # colliding pairs were among them
