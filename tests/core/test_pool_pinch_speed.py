"""The pool stage's caches and shortcuts (issue 15, session 14): each gives, to the bit, what the
code it replaced gave.

- the box poses and link corners kept per preshape (``collision.preshape_box_poses``,
  ``hand_corners``) against the forward kinematics of every call;
- the link cells built from the kept poses and the cells' layout kept per margin
  (``collision.link_cells``) against ``_link_cells_reference``;
- ``hand_min_height`` against its version with fresh corners;
- the pinches' local widths from sorted projections (``pinch._placed``) against the
  full-array version (``pinch._placed_reference``);

on random preshapes and poses and on every call the demo objects' pools make.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pregrasp_core.facemask import SupportPlane
from pregrasp_core.geometry import box_corners
from pregrasp_core.hand import load_hand
from pregrasp_core.io import load_point_cloud
from pregrasp_core.paths import demo_objects
from pregrasp_core.pipeline import PipelineParams, run_pipeline
from pregrasp_core.pregrasps import collision, pinch
from pregrasp_core.pregrasps.collision import hand_corners, hand_min_height, link_cells


@pytest.fixture(scope="module")
def hand():
    return load_hand()


def _random_q(hand, rng, n: int) -> np.ndarray:
    lo, hi = np.asarray(hand.lower), np.asarray(hand.upper)
    return rng.uniform(lo, hi, (n, len(lo)))


def _forget(hand) -> None:
    """Empty the caches of pinch preshapes and of box poses per preshape."""
    pinch._HAND_PINCHES.pop(hand, None)
    collision._HAND_POSES.pop(hand, None)


def _same(a: np.ndarray, b: np.ndarray) -> bool:
    return a.shape == b.shape and a.dtype == b.dtype and a.tobytes() == b.tobytes()


def test_a_full_pose_cache_keeps_what_it_holds_and_starts_again_for_a_new_preshape(hand):
    """The cache of box poses is bounded (``HAND_POSES_KEPT``): a preshape it holds is found even
    when it is full (the same array), a new one empties it first; the batched version keeps the
    same bound. (A hit on a full cache used to empty it: the test above failed when earlier
    tests had filled the shared hand's cache.)"""
    _forget(hand)
    rng = np.random.default_rng(5)
    Q = _random_q(hand, rng, collision.HAND_POSES_KEPT + 3)
    kept = [collision.preshape_box_poses(hand, q) for q in Q[: collision.HAND_POSES_KEPT]]
    assert len(collision._HAND_POSES[hand]) == collision.HAND_POSES_KEPT
    assert collision.preshape_box_poses(hand, Q[0].copy()) is kept[0]  # full, and found
    fresh = collision.preshape_box_poses(hand, Q[-1])  # full, and new: starts again
    assert len(collision._HAND_POSES[hand]) == 1 and _same(fresh, hand.box_poses(Q[-1]))
    many = collision.preshape_box_poses_many(hand, Q[: collision.HAND_POSES_KEPT + 2])
    assert len(collision._HAND_POSES[hand]) == collision.HAND_POSES_KEPT + 2  # one batch, whole
    for Tb, q in zip(many, Q, strict=False):
        assert _same(Tb, hand.box_poses(q))
    collision.preshape_box_poses_many(hand, Q[1:3])  # held: nothing to start again for
    assert len(collision._HAND_POSES[hand]) == collision.HAND_POSES_KEPT + 2
    collision.preshape_box_poses_many(hand, Q[:1] + 1e-3)  # new, over the bound: starts again
    assert len(collision._HAND_POSES[hand]) == 1
    _forget(hand)


def test_kept_poses_corners_and_cells_equal_fresh_ones_on_random_preshapes(hand):
    rng = np.random.default_rng(11)
    for q in _random_q(hand, rng, 60):
        Tb = collision.preshape_box_poses(hand, q)
        assert _same(Tb, hand.box_poses(q))
        assert not Tb.flags.writeable
        assert collision.preshape_box_poses(hand, q.copy()) is Tb  # kept by the bytes
        c = hand_corners(hand, q)
        assert _same(c, box_corners(hand.box_poses(q), hand.link_box_half))
        assert _same(c, collision._hand_corners_reference(hand, q))
        c[:] = 0.0  # a copy: the kept corners are not touched
        assert _same(hand_corners(hand, q), collision._hand_corners_reference(hand, q))
        for margin in (0.0, 0.002, 0.005):
            got, ref = link_cells(hand, q, margin), collision._link_cells_reference(hand, q, margin)
            assert _same(got[0], ref[0]) and _same(got[1], ref[1])


def test_batched_box_poses_and_preshapes_equal_one_by_one(hand):
    """The batched forward kinematics of new preshapes gives each row the bits of its own call,
    and the batched pinch preshapes (one self-collision check for all) those of
    ``pinch_preshape``, whatever the batch and the rows already kept."""
    rng = np.random.default_rng(14)
    for trial in range(60):
        _forget(hand)
        Q = _random_q(hand, rng, int(rng.integers(1, 30)))
        if trial % 3 == 0:  # some rows kept before, one repeated
            collision.preshape_box_poses(hand, Q[len(Q) // 2])
            Q = np.concatenate([Q, Q[:1]])
        Tb = collision.preshape_box_poses_many(hand, Q)
        for b, q in enumerate(Q):
            ref = hand.box_poses(q)
            assert _same(Tb[b], ref) and _same(collision.preshape_box_poses(hand, q), ref)
            assert _same(hand_corners(hand, q), collision._hand_corners_reference(hand, q))
    seen = {True: 0, False: 0}
    for kind in ("tip", "tripod"):
        for _ in range(20):
            _forget(hand)
            halves = list(rng.uniform(-0.01, 0.09, int(rng.integers(1, 12))))
            halves += halves[:2]  # repeated half widths
            got = pinch._preshapes(hand, kind, halves)
            _forget(hand)
            for h, g in zip(halves, got, strict=True):
                ref = pinch.pinch_preshape(hand, kind, h)
                seen[ref is None] += 1
                assert (g is None) == (ref is None)
                if ref is not None:
                    assert _same(g[0], ref[0]) and g[1] == ref[1]
    assert seen[True] > 5 and seen[False] > 20


def test_a_changed_preshape_is_not_served_the_kept_poses_of_another(hand):
    q = np.asarray(hand.preshape("spherical"), dtype=np.float64).copy()
    a = collision.preshape_box_poses(hand, q)
    q[0] = np.nextafter(q[0], np.inf)
    b = collision.preshape_box_poses(hand, q)
    assert b is not a and _same(b, hand.box_poses(q))


def test_min_height_equals_fresh_corners_on_random_hands(hand):
    rng = np.random.default_rng(12)
    Q = _random_q(hand, rng, 7)
    P = 400
    q = Q[rng.integers(0, len(Q), P)]
    T = np.tile(np.eye(4), (P, 1, 1))
    T[:, :3, :3] = Rotation.random(P, random_state=4).as_matrix()
    T[:, :3, 3] = rng.uniform(-0.2, 0.2, (P, 3))
    n = rng.normal(size=3)
    support = SupportPlane(n / np.linalg.norm(n), 0.013)
    got = hand_min_height(hand, T, np.full(P, "spherical"), q, support)
    assert _same(got, collision._hand_min_height_reference(hand, T, q, support))


def _same_pinches(a: list, b: list) -> bool:
    return len(a) == len(b) and all(
        _same(x[0], y[0]) and _same(np.asarray(x[1]), np.asarray(y[1])) and x[2:] == y[2:]
        for x, y in zip(a, b, strict=True)
    )


def test_placed_equals_the_reference_on_random_parts_and_at_band_edges(hand):
    """Random boxes, directions and clouds, and clouds with points put on the fingers' band
    edges (where the exact expressions must decide)."""
    from pregrasp_core.box import OrientedBox
    from pregrasp_core.pregrasps import SamplingParams

    rng = np.random.default_rng(13)
    params = SamplingParams()
    c = pinch._center(hand, "tip")
    fx = np.array([hand.flexion_plane(f, 0.0).origin[0] - c[0] for f in pinch.FINGERS])
    band = 0.5 * hand.finger("thumb").width
    checked = edges = 0
    for trial in range(80):
        R = Rotation.random(random_state=trial).as_matrix()
        ext = np.sort(rng.uniform(0.01, 0.16, 3))[::-1].copy()
        box = OrientedBox(center=rng.uniform(-0.2, 0.2, 3), rotation=R, extents=ext)
        n = int(rng.integers(1, 3000))
        pts = box.center + (rng.uniform(-0.5, 0.5, (n, 3)) * ext) @ R.T
        d = rng.normal(size=3)
        d /= np.linalg.norm(d)
        c_dir = np.cross(d, rng.normal(size=3))
        c_dir /= np.linalg.norm(c_dir)
        x_dir = np.cross(c_dir, -d)
        centre = box.center - (box.center @ d) * d
        if trial % 2:
            # a part 1 cm wide across c_dir, with points on the fingers' band edges (within
            # rounding) that stick out further across: whether each is under a finger decides
            # the width, so a misjudged edge changes the pinch
            length = float(rng.uniform(0.04, 0.16))
            u = rng.uniform(-0.5, 0.5, (n, 3)) * [length, 0.01, 0.03]
            pts = centre + u[:, :1] * x_dir + u[:, 1:2] * c_dir + u[:, 2:] * d
            half_run = max(0.5 * length - 0.5 * pinch.TIP_MIN_LENGTH, 0.0)
            offs = pinch.centred_grid(half_run, params.interval)
            k = 40
            e = np.empty((k, 3))
            for j in range(k):
                off, sign = float(offs[j % len(offs)]), (1.0, -1.0)[(j // len(offs)) % 2]
                edge = fx[j % 3] + (band if (j // 3) % 2 else -band)
                e[j] = centre + off * sign * x_dir + sign * edge * x_dir
                e[j] += (0.006 + 1e-4 * j) * c_dir * (1.0 if j % 2 else -1.0)
            pts = np.concatenate([pts, e])[rng.permutation(n + k)]
            edges += 1
        else:
            length = float(ext[0])
        heights = pts @ d
        z_top, z_bottom = float(heights.max()), float(heights.min())
        for floor in (z_bottom - 0.001, None):
            args = (hand, box, "tip", float(ext[1]), length, c_dir, x_dir, d, z_top, z_bottom,
                    floor, params, pts)  # fmt: skip
            _forget(hand)
            got = pinch._placed(*args)
            _forget(hand)  # the reference computes every preshape afresh
            ref = pinch._placed_reference(*args)
            assert _same_pinches(got, ref), trial
            checked += len(ref)
    assert checked > 100 and edges > 10


@pytest.mark.parametrize("path", demo_objects(), ids=lambda p: p.stem)
def test_every_pool_call_equals_its_reference(hand, path, monkeypatch):
    """Every ``_placed``, ``hand_min_height`` and ``link_cells`` call of the demo objects' pools
    (20,000 points, the pipeline's defaults) gives the reference's bits."""
    calls = {"placed": 0, "height": 0, "cells": 0}
    placed, height, cells = pinch._placed, collision.hand_min_height, collision.link_cells

    def check_placed(*a):
        got = placed(*a)
        _forget(a[0])  # the reference computes every preshape afresh
        assert _same_pinches(got, pinch._placed_reference(*a))
        calls["placed"] += 1
        return got

    def check_height(hand_, T, gt, q, support):
        got = height(hand_, T, gt, q, support)
        assert _same(got, collision._hand_min_height_reference(hand_, T, q, support))
        calls["height"] += 1
        return got

    def check_cells(hand_, q, margin=0.0):
        got = cells(hand_, q, margin)
        ref = collision._link_cells_reference(hand_, q, margin)
        assert _same(got[0], ref[0]) and _same(got[1], ref[1])
        calls["cells"] += 1
        return got

    from pregrasp_core.pregrasps import build

    monkeypatch.setattr(pinch, "_placed", check_placed)
    monkeypatch.setattr(build, "hand_min_height", check_height)
    monkeypatch.setattr(collision, "link_cells", check_cells)
    collision.hand_cell_cache(hand).clear()  # every preshape's cells are built (and checked)
    cloud = load_point_cloud(path, n_points=20000, seed=0)
    r = run_pipeline(cloud, PipelineParams(), hand, until="pool")
    assert len(r.pool) > 0
    assert calls["placed"] > 0 and calls["height"] > 0 and calls["cells"] > 0
