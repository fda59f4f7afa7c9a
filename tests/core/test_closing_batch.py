"""The closing model batched over many slices (``Hand.close_fingers``): every result equals
``Hand.close_finger`` on its own slice (same ``q``, contacts, flags and path), on seeded random
slices of every kind (empty, touching at the start, only the distal can reach, palm stops with
the palm on and off, starts at and near the limits, margins 0 and 1 mm, couplings != 1), one call
per case and one mixed call of ~100 slices; plus errors that name the bad slice."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from pregrasp_core.hand import FingerClosing, Hand, load_hand

FINGERS = ("thumb", "f1", "f2")


@pytest.fixture(scope="module")
def hand() -> Hand:
    return load_hand()


def assert_same(a: FingerClosing, b: FingerClosing, where: str = "") -> None:
    """``a`` (batched) equals ``b`` (``close_finger``): q and path to 1e-12, everything else
    exactly."""
    assert a.finger == b.finger, where
    np.testing.assert_allclose(a.q, b.q, rtol=0, atol=1e-12, err_msg=where)
    assert a.path.shape == b.path.shape, where
    np.testing.assert_allclose(a.path, b.path, rtol=0, atol=1e-12, err_msg=where)
    for name in ("stopped_middle", "stopped_distal", "palm_stop", "at_limits", "start_in_contact"):
        assert getattr(a, name) == getattr(b, name), f"{where}: {name}"
    assert (a.contact_link, a.contact_index) == (b.contact_link, b.contact_index), where
    assert len(a.contacts) == len(b.contacts), where
    for ca, cb in zip(a.contacts, b.contacts, strict=True):
        assert (ca.link, ca.index) == (cb.link, cb.index), where
        np.testing.assert_array_equal(ca.point, cb.point, err_msg=where)


def _arc(rng: np.random.Generator, n: int, center, radius, spread=0.002) -> np.ndarray:
    """n points near a circle arc (an object's section seen in the flexion plane)."""
    a = rng.uniform(-np.pi, np.pi, n)
    r = radius + rng.normal(0.0, spread, n)
    return np.asarray(center) + np.stack([r * np.cos(a), r * np.sin(a)], axis=1)


def _random_slice(rng: np.random.Generator, hand: Hand, kind: str):
    """(finger, points_2d, q_start) of one kind (see the module docstring)."""
    f = hand.finger(FINGERS[rng.integers(3)])
    q0 = np.array([rng.uniform(-0.52, 0.3), rng.uniform(-0.26, 0.5)])
    if kind == "empty":
        P = np.zeros((0, 2))
    elif kind == "cloud":  # points around the finger, many out of reach
        P = rng.uniform([-0.06, -0.06], [0.13, 0.13], size=(int(rng.integers(1, 1500)), 2))
    elif kind == "object":  # a round section in front of the finger
        P = _arc(rng, int(rng.integers(20, 1200)), (rng.uniform(0.03, 0.09), 0.06), 0.03)
    elif kind == "start":  # a point inside the middle or the distal link at q_start
        d = np.array([np.cos(q0[0]), np.sin(q0[0])])
        on_mid = 0.02 * d
        a2 = q0[0] + q0[1]
        on_dis = 0.05 * d + 0.02 * np.array([np.cos(a2), np.sin(a2)])
        P = np.concatenate(
            [rng.uniform(-0.05, 0.12, (30, 2)), [on_mid if rng.random() < 0.5 else on_dis]]
        )
    elif kind == "distal":  # only the distal link reaches them (far out along the finger)
        a = rng.uniform(0.2, 1.2, 40)
        r = rng.uniform(0.075, 0.092, 40)
        P = np.stack([r * np.cos(a), r * np.sin(a)], axis=1)
    elif kind == "behind":  # nothing in the way: the palm (or the limits) stops the finger
        P = rng.uniform([-0.06, -0.08], [0.0, -0.03], size=(int(rng.integers(0, 50)), 2))
    elif kind == "limits":  # start at or near the upper limits
        q0 = f.upper - rng.choice([0.0, 1e-5, 0.05], size=2)
        P = rng.uniform(-0.05, 0.12, (int(rng.integers(0, 200)), 2))
    else:  # pragma: no cover - the kinds are listed below
        raise AssertionError(kind)
    return f.name, P, q0


KINDS = ("empty", "cloud", "object", "start", "distal", "behind", "limits")


@pytest.mark.parametrize("margin", [0.0, 0.001])
@pytest.mark.parametrize("palm", [True, False])
@pytest.mark.parametrize("coupling", [1.0, 0.6, 2.5])
def test_batch_equals_close_finger_per_slice(hand, margin, palm, coupling):
    rng = np.random.default_rng([int(margin * 1e4), int(palm), int(coupling * 10)])
    slices = [_random_slice(rng, hand, kind) for kind in KINDS for _ in range(4)]
    got = hand.close_fingers(slices, n_steps=24, margin=margin, coupling=coupling, palm=palm)
    assert len(got) == len(slices)
    seen = set()
    for i, (s, g) in enumerate(zip(slices, got, strict=True)):
        ref = hand.close_finger(*s, n_steps=24, margin=margin, coupling=coupling, palm=palm)
        assert_same(g, ref, f"slice {i} ({KINDS[i // 4]})")
        seen |= {
            name
            for name in ("stopped_middle", "stopped_distal", "palm_stop", "at_limits")
            if getattr(ref, name)
        }
        seen |= {"start_in_contact"} if ref.start_in_contact else set()
    # the cases really happen (the test would be weak otherwise)
    assert {"stopped_middle", "stopped_distal", "start_in_contact"} <= seen
    # with the palm on, the palm stops a free finger before its limits
    assert ("palm_stop" if palm else "at_limits") in seen


@pytest.mark.parametrize(("n_steps", "margin", "coupling"), [(1, 0.003, 20.0), (7, -0.001, 0.05)])
def test_batch_equals_close_finger_odd_parameters(hand, n_steps, margin, coupling):
    """One step per phase, a negative margin, extreme couplings."""
    rng = np.random.default_rng(n_steps)
    slices = [_random_slice(rng, hand, kind) for kind in KINDS for _ in range(3)]
    got = hand.close_fingers(slices, n_steps=n_steps, margin=margin, coupling=coupling)
    for i, (s, g) in enumerate(zip(slices, got, strict=True)):
        ref = hand.close_finger(*s, n_steps=n_steps, margin=margin, coupling=coupling)
        assert_same(g, ref, f"slice {i}")


def test_mixed_batch_of_about_100_slices(hand):
    """~100 slices of all fingers, sizes 0..1500, one call vs one call each, default steps."""
    rng = np.random.default_rng(7)
    kinds = rng.choice(KINDS, size=100)
    slices = [_random_slice(rng, hand, str(k)) for k in kinds]
    got = hand.close_fingers(slices, margin=0.001)
    for i, (s, g) in enumerate(zip(slices, got, strict=True)):
        assert_same(g, hand.close_finger(*s, margin=0.001), f"slice {i} ({kinds[i]})")
    # one slice alone in a batch gives the same as inside the batch
    for i in (0, 37, 99):
        assert_same(hand.close_fingers([slices[i]], margin=0.001)[0], got[i], f"alone {i}")


def test_batch_analytic_middle_contact(hand):
    """The middle link's inner face reaches (0.025, 0.03) at acos(H / R) - atan2(x, y)
    (worked by hand, as in test_hand), whatever else is in the batch."""
    p = np.array([[0.025, 0.03]])
    other = ("f2", np.array([[0.07, 0.0]]), np.zeros(2))
    c = hand.close_fingers([other, ("f1", p, np.zeros(2)), other], palm=False)[1]
    R, phi = np.hypot(0.025, 0.03), np.arctan2(0.025, 0.03)
    assert c.stopped_middle and c.contacts[0].link == "f1_middle" and c.contacts[0].index == 0
    assert c.q[0] == pytest.approx(np.arccos(0.01 / R) - phi, abs=2e-4)
    assert c.q[1] == pytest.approx(hand.finger("f1").upper[1])


def test_contact_index_refers_to_the_given_points(hand):
    """Contacts index the slice's own points_2d (points out of reach come first here)."""
    far = np.full((5, 2), 0.5)
    P = np.concatenate([far, [[0.075, 0.045]]])
    c = hand.close_fingers([("f1", far, np.zeros(2)), ("f2", P, np.zeros(2))])[1]
    assert c.stopped_distal and c.contact_index == 5
    np.testing.assert_array_equal(c.contact_point, P[5])


def test_batches_without_any_point_in_reach(hand):
    """Only empty slices, or only points out of reach: every finger closes free (palm or limits)."""
    far = np.full((4, 2), 0.3)
    for P in (np.zeros((0, 2)), far):
        slices = [(f, P, np.array([-0.5, 0.1])) for f in FINGERS]
        for palm in (True, False):
            got = hand.close_fingers(slices, palm=palm)
            for s, g in zip(slices, got, strict=True):
                assert_same(g, hand.close_finger(*s, palm=palm))
                assert g.contacts == () and (g.palm_stop if palm else g.at_limits)


@settings(max_examples=40, deadline=None, derandomize=True)
@given(
    pts=st.lists(
        hnp.arrays(
            np.float64, st.tuples(st.integers(0, 30), st.just(2)), elements=st.floats(-0.06, 0.12)
        ),
        min_size=1,
        max_size=4,
    ),
    q0=hnp.arrays(np.float64, (2,), elements=st.floats(-1.0, 2.0)),
    coupling=st.floats(0.3, 3.0),
    margin=st.sampled_from([0.0, 0.001, 0.004]),
)
def test_batch_equals_close_finger_hypothesis(hand, pts, q0, coupling, margin):
    slices = [(FINGERS[i % 3], P, q0 + 0.1 * i) for i, P in enumerate(pts)]
    got = hand.close_fingers(slices, n_steps=12, margin=margin, coupling=coupling)
    for i, (s, g) in enumerate(zip(slices, got, strict=True)):
        ref = hand.close_finger(*s, n_steps=12, margin=margin, coupling=coupling)
        assert_same(g, ref, f"slice {i}")


def test_empty_list_and_bad_input(hand):
    assert hand.close_fingers([]) == []
    good = ("f1", np.zeros((3, 2)), np.zeros(2))
    with pytest.raises(ValueError, match=r"slices\[1\]: points_2d must have shape \(M, 2\)"):
        hand.close_fingers([good, ("f1", np.zeros((4, 3)), np.zeros(2))])
    with pytest.raises(ValueError, match=r"slices\[2\]: q_start must have shape \(2,\)"):
        hand.close_fingers([good, good, ("f1", np.zeros((4, 2)), np.zeros(3))])
    with pytest.raises(ValueError, match=r"slices\[0\] must be \(finger, points_2d, q_start\)"):
        hand.close_fingers([("f1", np.zeros((4, 2)))])
    with pytest.raises(ValueError, match="unknown finger 'f3'"):
        hand.close_fingers([good, ("f3", np.zeros((4, 2)), np.zeros(2))])
    with pytest.raises(ValueError, match="n_steps must be >= 1"):
        hand.close_fingers([good], n_steps=0)
    with pytest.raises(ValueError, match="coupling must be > 0"):
        hand.close_fingers([good], coupling=0.0)


def test_equal_distances_pick_the_first_point(hand):
    """Duplicated points touch at equal distances: the contact is the first of them, as in
    close_finger (the batch settles such ties with close_finger's own distance)."""
    rng = np.random.default_rng(3)
    slices = []
    for f in FINGERS:
        P = _arc(rng, 300, (0.06, 0.06), 0.03)
        P = np.concatenate([P, P[::-1]])  # every point twice
        slices.append((f, P, np.array([-0.5, 0.0])))
    got = hand.close_fingers(slices, margin=0.001)
    for i, (s, g) in enumerate(zip(slices, got, strict=True)):
        ref = hand.close_finger(*s, margin=0.001)
        assert_same(g, ref, f"slice {i}")
        assert g.contacts and all(c.index < 300 for c in g.contacts)
