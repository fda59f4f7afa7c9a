"""Grasp quality against the analytic oracles of docs/quality.md (tests/data/quality_oracles.json),
rigid-motion invariance, degenerate sets and an independent linear-programming check of force
closure."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.optimize import linprog
from scipy.spatial import ConvexHull, QhullError
from scipy.spatial.transform import Rotation

from pregrasp_core import quality
from pregrasp_core.quality import (
    QualityParams,
    contact_wrenches,
    cross3,
    friction_cone_edges,
    grasp_quality,
    hull_quality,
    object_frame,
    tangent_frames,
)

ORACLES = json.loads((Path(__file__).parents[1] / "data" / "quality_oracles.json").read_text())
CASES = {c["name"]: c for c in ORACLES["cases"]}


def _score(case, points=None, normals=None, tangents=None):
    params = QualityParams(mu=case["mu"], n_edges=case["m"], torque_scale=case["rho"])
    return grasp_quality(
        np.asarray(case["points"] if points is None else points, dtype=float),
        np.asarray(case["normals"] if normals is None else normals, dtype=float),
        params,
        tangents=np.asarray(case["tangents"] if tangents is None else tangents, dtype=float),
        torques=case["torques"],
    )


@pytest.mark.parametrize("name", sorted(CASES))
def test_oracle_values(name):
    case = CASES[name]
    q = _score(case)
    assert q.epsilon == pytest.approx(case["epsilon"], abs=1e-6)
    assert q.force_closure
    assert q.volume > 0.0
    assert q.n_contacts == len(case["points"])


def test_antipodal_closed_form_over_mu_and_m():
    """eps = min(1, mu cos(pi/m)) for the antipodal pair in force space, for several mu and m."""
    case = CASES["antipodal_pair_forces_only"]
    for mu in (0.2, 0.5, 1.0, 1.5):
        for m in (4, 6, 8, 16):
            q = grasp_quality(
                np.array(case["points"]),
                np.array(case["normals"]),
                QualityParams(mu=mu, n_edges=m),
                tangents=np.array(case["tangents"]),
                torques=False,
            )
            assert q.epsilon == pytest.approx(min(1.0, mu * np.cos(np.pi / m)), abs=1e-8)


def test_default_tangent_rule_reproduces_tetrahedral_oracle():
    """Without tangents the world rule (e_x projected) applies; the tetrahedral oracle uses it."""
    case = CASES["sphere_four_tetrahedral"]
    q = grasp_quality(
        np.array(case["points"]), np.array(case["normals"]), QualityParams(torque_scale=1.0)
    )
    assert q.epsilon == pytest.approx(case["epsilon"], abs=1e-6)


def test_hull_scores_agree_with_default_qhull():
    """Scores equal those of qhull's default (merging) build to 1e-8."""
    rng = np.random.default_rng(3)
    for _ in range(5):
        p = rng.normal(size=(5, 3))
        p /= np.linalg.norm(p, axis=1, keepdims=True)
        w = contact_wrenches(p, -p)
        eps, vol, _ = hull_quality(w)
        hull = ConvexHull(w)
        ref_eps = float((-hull.equations[:, -1]).min())
        assert eps == pytest.approx(max(ref_eps, 0.0), abs=1e-8)
        assert vol == pytest.approx(hull.volume, rel=1e-8)


def _random_rigid(rng):
    R = Rotation.random(random_state=rng).as_matrix()
    t = rng.uniform(-2.0, 2.0, size=3)
    return R, t


@pytest.mark.parametrize("name", sorted(CASES))
def test_rigid_motion_invariance(name):
    case = CASES[name]
    base = _score(case)
    rng = np.random.default_rng(11)
    p, n, a = (np.asarray(case[k], dtype=float) for k in ("points", "normals", "tangents"))
    for _ in range(5):
        R, t = _random_rigid(rng)
        q = _score(case, p @ R.T + t, n @ R.T, a @ R.T)
        assert q.epsilon == pytest.approx(base.epsilon, abs=1e-8)
        assert q.volume == pytest.approx(base.volume, rel=1e-7)


def test_rigid_motion_invariance_random_grasps():
    """Random contact sets on a sphere, scored, then moved rigidly (tangents moved with them)."""
    rng = np.random.default_rng(5)
    for _ in range(6):
        k = int(rng.integers(3, 7))
        p = rng.normal(size=(k, 3)) * [0.03, 0.05, 0.02] + rng.normal(size=3)
        n = rng.normal(size=(k, 3))
        a = rng.normal(size=(k, 3))
        base = grasp_quality(p, n, tangents=a)
        R, t = _random_rigid(rng)
        moved = grasp_quality(p @ R.T + t, n @ R.T, tangents=a @ R.T)
        assert moved.epsilon == pytest.approx(base.epsilon, abs=1e-8)
        assert moved.volume == pytest.approx(base.volume, rel=1e-6, abs=1e-12)
        perm = rng.permutation(k)
        permuted = grasp_quality(p[perm], n[perm], tangents=a[perm])
        assert permuted.epsilon == pytest.approx(base.epsilon, abs=1e-8)


def origin_strictly_inside_lp(w: np.ndarray) -> bool:
    """Independent force-closure test: no direction u with w . u <= -s for all wrenches, s > 0.

    maximise s subject to w u + s <= 0, -1 <= u <= 1; the origin is strictly inside the hull iff
    the optimum is 0 and the wrenches span the space.
    """
    m, d = w.shape
    res = linprog(
        np.r_[np.zeros(d), -1.0],
        A_ub=np.c_[w, np.ones(m)],
        b_ub=np.zeros(m),
        bounds=[(-1, 1)] * d + [(None, 1)],
        method="highs",
    )
    return -res.fun < 1e-9 and np.linalg.matrix_rank(w - w.mean(axis=0)) == d


def test_force_closure_agrees_with_linear_programming():
    rng = np.random.default_rng(7)
    n_fc = 0
    for trial in range(30):
        k = int(rng.integers(3, 6))
        p = rng.normal(size=(k, 3))
        p /= np.linalg.norm(p, axis=1, keepdims=True)
        # normals into the object, tilted so that some sets are force closure and some not
        n = -p + rng.normal(scale=0.8 if trial % 2 else 0.2, size=(k, 3))
        q = grasp_quality(p, n)
        w = contact_wrenches(p, n / np.linalg.norm(n, axis=1, keepdims=True))
        fc = origin_strictly_inside_lp(w)
        if abs(q.epsilon) > 1e-6 or not fc:
            assert q.force_closure == fc, (trial, q)
        n_fc += fc
    assert 3 <= n_fc <= 27  # both outcomes were exercised


def test_epsilon_is_a_lower_bound_of_the_support_function():
    """eps = min over unit u of max_j w_j . u; random directions can only give larger values."""
    rng = np.random.default_rng(9)
    case = CASES["sphere_four_tetrahedral"]
    params = QualityParams(torque_scale=1.0)
    w = contact_wrenches(np.array(case["points"]), np.array(case["normals"]), params)
    eps, _, _ = hull_quality(w)
    u = rng.normal(size=(20000, 6))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    support = (u @ w.T).max(axis=1)
    assert support.min() >= eps - 1e-12
    assert support.min() < eps * 1.15  # and random directions come close to it


def test_degenerate_sets_score_zero_without_exception():
    params = QualityParams()
    # no contact, one contact
    assert grasp_quality(np.zeros((0, 3)), np.zeros((0, 3))).epsilon == 0.0
    one = grasp_quality(np.array([[0.0, 0, 0]]), np.array([[0.0, 0, 1]]))
    assert (one.epsilon, one.volume, one.force_closure) == (0.0, 0.0, False)
    # two antipodal contacts with torques: rank 5, degenerate
    two = grasp_quality(np.array([[1.0, 0, 0], [-1, 0, 0]]), np.array([[-1.0, 0, 0], [1, 0, 0]]))
    assert (two.epsilon, two.volume) == (0.0, 0.0)
    assert "rank" in two.reason
    # frictionless contacts: every edge equals the normal, rank <= 3
    p = np.array([[1.0, 0, 0], [-0.5, 0.8, 0], [-0.5, -0.8, 0], [0, 0, 1]])
    q0 = grasp_quality(p, -p, QualityParams(mu=0.0))
    assert (q0.epsilon, q0.volume) == (0.0, 0.0)
    # all normals the same way: every force has f_z = 1, a flat (rank 5) hull
    rng = np.random.default_rng(1)
    pts = rng.normal(size=(5, 3))
    same = grasp_quality(pts, np.tile([0.0, 0.0, 1.0], (5, 1)), params)
    assert (same.epsilon, same.volume) == (0.0, 0.0)
    # normals all in the upper half space: full-rank hull, origin outside -> eps 0, volume > 0
    up = rng.normal(size=(5, 3)) * [1.0, 1.0, 0.2] + [0.0, 0.0, 1.0]
    upper = grasp_quality(pts, up, params)
    assert upper.epsilon == 0.0 and not upper.force_closure and upper.reason == ""
    assert upper.volume > 0.0
    # coincident contacts: every torque is zero
    coinc = grasp_quality(np.zeros((4, 3)), rng.normal(size=(4, 3)))
    assert coinc.epsilon == 0.0
    # a zero normal or a NaN point: 0, not an exception
    bad = grasp_quality(np.eye(3), np.array([[0.0, 0, 0], [0, 1, 0], [0, 0, 1]]))
    assert bad.epsilon == 0.0 and "invalid" in bad.reason
    nan = grasp_quality(np.array([[np.nan, 0, 0], [0, 1, 0], [0, 0, 1]]), np.eye(3))
    assert nan.epsilon == 0.0
    # a coplanar wrench set handed to the hull directly
    assert hull_quality(np.c_[rng.normal(size=(20, 5)), np.zeros(20)])[:2] == (0.0, 0.0)


@settings(max_examples=40, deadline=None)
@given(
    k=st.integers(0, 6),
    seed=st.integers(0, 2**31 - 1),
    mu=st.floats(0.0, 2.0),
    m=st.integers(3, 10),
)
def test_never_raises_and_is_bounded(k, seed, mu, m):
    rng = np.random.default_rng(seed)
    p = rng.normal(size=(k, 3))
    n = rng.normal(size=(k, 3))
    q = grasp_quality(p, n, QualityParams(mu=mu, n_edges=m))
    assert q.epsilon >= 0.0 and q.volume >= 0.0
    # no facet can be farther from the origin than the farthest wrench
    if k:
        w = contact_wrenches(
            p, n / np.linalg.norm(n, axis=1, keepdims=True), QualityParams(mu=mu, n_edges=m)
        )
        assert q.epsilon <= np.linalg.norm(w, axis=1).max() + 1e-9


def test_cone_edges_have_unit_normal_component_and_frames_are_right_handed():
    rng = np.random.default_rng(2)
    n = rng.normal(size=(10, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    n[0] = [1.0, 0.0, 0.0]  # the e_y fallback of the world rule
    f = friction_cone_edges(n, 0.5, 8)
    assert np.allclose(np.einsum("kmi,ki->km", f, n), 1.0)
    assert np.allclose(np.linalg.norm(f - n[:, None, :], axis=2), 0.5)
    frames = tangent_frames(n)
    assert np.allclose(np.linalg.det(frames), 1.0)
    assert np.allclose(np.einsum("kij,kil->kjl", frames, frames), np.eye(3))


def test_input_shapes_are_checked():
    with pytest.raises(ValueError, match=r"points must have shape \(K, 3\), got \(3,\)"):
        grasp_quality(np.zeros(3), np.zeros((1, 3)))
    with pytest.raises(ValueError, match="same shape"):
        grasp_quality(np.zeros((2, 3)), np.zeros((3, 3)))
    with pytest.raises(ValueError, match="mu must be"):
        QualityParams(mu=-1.0)
    with pytest.raises(ValueError, match="n_edges must be"):
        QualityParams(n_edges=2)


def test_exact_hull_gives_the_merged_hulls_epsilon_and_volume():
    """The unmerged hull (``Q0``, the default) against qhull's merged triangulated hull (``Qt``,
    scipy's default) on random contact sets of 3 to 6 contacts: same epsilon and volume to
    1e-12 whenever the unmerged hull is accepted, to 1e-8 through the joggled fallback."""
    rng = np.random.default_rng(7)
    params = QualityParams()
    compared = exact = 0
    for _ in range(120):
        k = int(rng.integers(3, 7))
        p = rng.normal(size=(k, 3))
        p /= np.linalg.norm(p, axis=1)[:, None]
        n = -p + 0.3 * rng.normal(size=(k, 3))
        w = contact_wrenches(p, n, params)
        q = grasp_quality(p, n, params)
        merged = ConvexHull(w, qhull_options="Qt")
        eps_merged = max(0.0, float((-merged.equations[:, -1]).min()))
        tol = 1e-12 if quality._exact_hull(w) is not None else 1e-8
        exact += tol == 1e-12
        assert q.epsilon == pytest.approx(eps_merged, abs=tol)
        assert q.volume == pytest.approx(merged.volume, rel=tol)
        compared += eps_merged > 0
    assert compared > 10  # the comparison covers force-closure sets, not only zeros
    assert exact > 100  # and mostly the exact path


def test_precision_failure_falls_back_to_the_joggled_hull():
    """A planner grasp (tests/data/quality_q0_failure.json) whose unmerged hull qhull rejects as
    concave by rounding: the score comes from the joggled hull and equals the merged hull's."""
    case = json.loads((Path(__file__).parents[1] / "data" / "quality_q0_failure.json").read_text())
    p, n, t = (np.asarray(case[k], dtype=float) for k in ("points", "normals", "tangents"))
    params = QualityParams(mu=case["mu"], n_edges=case["m"])
    w = contact_wrenches(p, n, params, tangents=t)
    with pytest.raises(QhullError, match="precision error"):
        ConvexHull(w, qhull_options=quality.QHULL_OPTIONS)
    assert quality._exact_hull(w) is None
    q = grasp_quality(p, n, params, tangents=t)
    merged = ConvexHull(w, qhull_options="Qt")
    assert q.reason == "" and q.n_contacts == len(p)
    assert q.epsilon == pytest.approx(max(0.0, float((-merged.equations[:, -1]).min())), abs=1e-8)
    assert q.volume == pytest.approx(merged.volume, rel=1e-8)


def test_an_inconsistent_exact_hull_is_not_used(monkeypatch):
    """When the unmerged hull leaves a wrench outside a facet (here: one facet moved inwards by
    1e-6), the joggled hull is used instead."""
    rng = np.random.default_rng(3)
    p = rng.normal(size=(4, 3))
    p /= np.linalg.norm(p, axis=1)[:, None]
    n = -p + 0.2 * rng.normal(size=(4, 3))
    w = contact_wrenches(p, n)
    good = hull_quality(w)
    real = quality.ConvexHull

    class Moved:
        def __init__(self, hull):
            self.equations = hull.equations.copy()
            self.equations[0, -1] += 1e-6  # the facet moves inwards: its vertices are outside
            self.volume = hull.volume - 0.5  # a wrong score, which must not come out

    def fake(points, qhull_options=None):
        hull = real(points, qhull_options=qhull_options)
        return Moved(hull) if qhull_options == quality.QHULL_OPTIONS else hull

    monkeypatch.setattr(quality, "ConvexHull", fake)
    assert quality._exact_hull(w) is None
    eps, vol, reason = hull_quality(w)
    assert reason == "" and eps == pytest.approx(good[0], abs=1e-8)
    assert vol == pytest.approx(good[1], rel=1e-8)


def _object_points(name: str) -> np.ndarray:
    """Points of the oracle's object: the cube of half-edge 1 (its 8 corners and 6 face centres)
    or the unit sphere (antipodal pairs of a Fibonacci lattice), both centred at the origin."""
    if name.startswith("cube"):
        corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)
        return np.r_[corners, np.eye(3), -np.eye(3)]
    i = np.arange(500) + 0.5
    phi, th = np.arccos(1 - 2 * i / 1000), np.pi * (1 + 5**0.5) * i
    u = np.c_[np.cos(th) * np.sin(phi), np.sin(th) * np.sin(phi), np.cos(phi)]
    return np.r_[u, -u]


@pytest.mark.parametrize("name", sorted(n for n in CASES if CASES[n]["torques"]))
def test_object_centred_torques_reproduce_the_oracles(name):
    """GraspIt's convention: torques about the object's centroid, rho = its largest radius (the
    object's own points, not the oracle's rho): the oracle values hold."""
    case = CASES[name]
    center, radius = object_frame(_object_points(name))
    assert radius == pytest.approx(case["rho"], abs=1e-9)
    q = grasp_quality(
        np.asarray(case["points"], float),
        np.asarray(case["normals"], float),
        QualityParams(mu=case["mu"], n_edges=case["m"]),
        tangents=np.asarray(case["tangents"], float),
        center=center,
        radius=radius,
    )
    assert q.epsilon == pytest.approx(case["epsilon"], abs=1e-6)


def test_object_centred_epsilon_is_rigid_motion_invariant_and_sees_the_centre_of_mass():
    """Moving contacts and object together leaves epsilon unchanged; moving only the object's
    centroid away from the contacts (a heavier far end) lowers it: the grasp then has to resist
    gravity's torque with a longer lever (torques of the same contact forces grow)."""
    case = CASES["sphere_four_tetrahedral"]
    pts, nrm = np.asarray(case["points"], float), np.asarray(case["normals"], float)
    tng = np.asarray(case["tangents"], float)
    prm = QualityParams(mu=case["mu"], n_edges=case["m"])
    base = grasp_quality(pts, nrm, prm, tangents=tng, center=np.zeros(3), radius=1.0)
    R = Rotation.from_euler("zyx", [0.4, -1.1, 2.0]).as_matrix()
    t = np.array([0.3, -0.2, 0.5])
    moved = grasp_quality(pts @ R.T + t, nrm @ R.T, prm, tangents=tng @ R.T, center=t, radius=1.0)
    assert moved.epsilon == pytest.approx(base.epsilon, abs=1e-9)
    far = grasp_quality(pts, nrm, prm, tangents=tng, center=np.array([0.0, 0.0, 0.6]), radius=1.0)
    assert 0.0 <= far.epsilon < base.epsilon
    with pytest.raises(ValueError, match="center must be 3 finite numbers"):
        grasp_quality(pts, nrm, prm, center=np.array([0.0, np.nan, 0.0]))
    with pytest.raises(ValueError, match="torque_origin must be one of"):
        QualityParams(torque_origin="palm")


def _numpy_contact_wrenches(p, n, mu, m, tangents, c, rho):
    """The numpy construction of the edge wrenches that the compiled loops replaced (issue 15,
    session 7): ``tangent_frames``, the cone's einsum, ``cross3`` and the division."""
    frames = tangent_frames(n, tangents)
    t = 2.0 * np.pi * np.arange(m) / m
    coef = np.stack([mu * np.cos(t), mu * np.sin(t), np.ones_like(t)], axis=1)
    f = np.einsum("kij,mj->kmi", frames, coef)
    tau = cross3((p - c)[:, None, :], f) / max(rho, 1e-9)
    return np.concatenate([f, tau], axis=2).reshape(-1, 6)


def test_compiled_wrenches_equal_the_numpy_construction_to_the_bit():
    """contact_wrenches (compiled frames and torques) gives the bytes of the numpy code it
    replaced, on random contact sets with the corner cases of the tangent rule (normals near
    e_x, tangents parallel to the normal, zero and tiny tangents, unnormalised normals)."""
    rng = np.random.default_rng(7)
    for trial in range(300):  # loop over random contact sets
        k = int(rng.integers(1, 8))
        p = rng.normal(size=(k, 3)) * 10.0 ** rng.uniform(-3, 1)
        n = rng.normal(size=(k, 3)) * 10.0 ** rng.uniform(-2, 2, size=(k, 1))
        t = rng.normal(size=(k, 3))
        if trial % 5 == 0:
            n[0] = [1.0, 1e-3, -2e-3]  # |n . e_x| > 0.9: the e_y fallback
        if trial % 7 == 0:
            t[0] = 3.0 * n[0]  # parallel to the normal: the world rule
        if trial % 11 == 0:
            t[-1] = 0.0 if trial % 2 else 1e-310
        c = rng.normal(size=3) * 0.1
        rho = float(rng.uniform(0.01, 1.0))
        mu = float(rng.choice([0.0, 0.3, 0.5, 1.2]))
        m = int(rng.integers(3, 11))
        params = QualityParams(mu=mu, n_edges=m)
        for tng in (t, None):
            got = contact_wrenches(p, n, params, tangents=tng, center=c, radius=rho)
            want = _numpy_contact_wrenches(p, n, mu, m, tng, c, rho)
            assert got.shape == want.shape and got.tobytes() == want.tobytes()
