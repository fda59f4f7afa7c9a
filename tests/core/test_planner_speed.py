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
