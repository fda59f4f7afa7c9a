"""Bounded quality (issue 15): the bounds are bounds of the exact hull's scores, force closure
is decided exactly at every level, and the planner's ranking with bounds equals the exact
ranking (its first ``exact_top`` grasps and the best grasp of each type) on every demo object
and on synthetic grasp sets with ties."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial import ConvexHull
from scipy.spatial.transform import Rotation

from pregrasp_core.hand import load_hand
from pregrasp_core.io import load_point_cloud
from pregrasp_core.paths import demo_objects
from pregrasp_core.pipeline import PipelineParams, run_pipeline
from pregrasp_core.planner import Contact, Grasp, plan_grasps, rank_grasps
from pregrasp_core.planner.rank import (
    quality_frame,
    score_grasp,
    score_text,
    settle_exact,
)
from pregrasp_core.quality import (
    LEVEL_CHEAPEST,
    LEVEL_EXACT,
    LEVEL_HALF_CONES,
    QUALITY_BOUNDS,
    QualityParams,
    best_direction,
    contact_wrenches,
    direction_bound,
    grasp_quality,
    half_cone_bounds,
    hull_quality,
    walk_bound,
    wrench_frame,
)
from tests.core.test_quality import origin_strictly_inside_lp


def _contact_set(rng, k, spread=0.8):
    """k contacts on an ellipsoid-ish object, normals into it tilted by ``spread``, tangents
    random (as the planner's link axes), torques about a centre off the contacts."""
    p = rng.normal(size=(k, 3))
    p /= np.linalg.norm(p, axis=1, keepdims=True)
    p *= [0.04, 0.03, 0.06]
    n = -p / np.linalg.norm(p, axis=1, keepdims=True) + rng.normal(scale=spread, size=(k, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    t = rng.normal(size=(k, 3))
    center = rng.normal(scale=0.01, size=3)
    return p, n, t, center, 0.08


def test_bounds_bound_the_exact_scores_and_force_closure_stays_exact():
    """Seeded random contact sets (3 to 6 contacts, several mu and m): at every level the
    epsilon and volume are at least the exact hull's, equal to them where marked exact, and
    force closure equals the exact hull's and (on clear cases) an LP's; every kind of bound
    and the exact fallback occur."""
    rng = np.random.default_rng(15)
    kinds: dict[str, int] = {}
    n_fc = 0
    for trial in range(240):
        k = int(rng.integers(3, 7))
        mu = float(rng.choice([0.2, 0.5, 1.0]))
        m = int(rng.choice([5, 6, 8, 10]))
        p, n, t, c, r = _contact_set(rng, k, spread=0.3 if trial % 2 else 0.9)
        prm = QualityParams(mu=mu, n_edges=m)
        exact = grasp_quality(p, n, prm, tangents=t, center=c, radius=r)
        assert exact.epsilon_exact and exact.volume_exact and exact.bound == ""
        n_fc += exact.force_closure
        if trial % 4 == 0:  # an independent check of force closure on a quarter of them
            w = contact_wrenches(p, n, prm, tangents=t, center=c, radius=r)
            fc = origin_strictly_inside_lp(w)
            if abs(exact.epsilon) > 1e-6 or not fc:
                assert exact.force_closure == fc, trial
        for level in (LEVEL_CHEAPEST, LEVEL_HALF_CONES):
            q = grasp_quality(p, n, prm, tangents=t, center=c, radius=r, level=level)
            kinds[q.bound or "exact"] = kinds.get(q.bound or "exact", 0) + 1
            assert q.force_closure == exact.force_closure, (trial, level)
            assert q.epsilon >= exact.epsilon and q.volume >= exact.volume, (trial, level, q)
            if q.epsilon_exact:
                assert q.epsilon == exact.epsilon
            if q.volume_exact:
                assert q.volume == exact.volume
            assert q.bound in ("", *QUALITY_BOUNDS)
            assert (q.bound == "") == (q.epsilon_exact and q.volume_exact)
    assert 30 <= n_fc <= 210  # both outcomes exercised
    assert kinds.get("directions", 0) > 5 and kinds.get("half cones", 0) > 50
    assert kinds.get("exact", 0) > 0, kinds


def test_half_cone_hull_sandwiches_epsilon_and_volume():
    """The hull H of every other cone edge: its epsilon <= the full set's <= the smallest support
    over H's facet normals (origin inside; else H's is <= 0 too); vol(H) <= vol <= the scaled
    bound; the directions' bound >= eps (against qhull's default, merged hull)."""
    rng = np.random.default_rng(3)
    checked = 0
    for _ in range(80):
        p, n, t, c, r = _contact_set(rng, int(rng.integers(3, 6)), spread=0.4)
        prm = QualityParams()
        w = contact_wrenches(p, n, prm, tangents=t, center=c, radius=r)
        eps, vol, reason = hull_quality(w)
        if reason:
            continue
        true_eps = float((-ConvexHull(w, qhull_options="Qt").equations[:, -1]).min())
        bounds = half_cone_bounds(w, prm.n_edges)
        if true_eps > 0.0:
            assert direction_bound(w) >= true_eps - 1e-12
            assert direction_bound(w, wrench_frame(w, prm.n_edges)) >= true_eps - 1e-12
        if bounds is None:
            continue
        lower, upper, vol_upper = bounds
        if true_eps > 0.0:  # the origin inside the full hull: lower <= eps <= upper
            assert lower <= true_eps + 1e-12 and upper >= true_eps - 1e-12
        else:  # outside the full hull, so outside H too
            assert lower <= 1e-12
        sub = w.reshape(len(p), prm.n_edges, 6)[:, ::2].reshape(-1, 6)
        assert ConvexHull(sub).volume <= vol * (1 + 1e-9) and vol_upper >= vol * (1 - 1e-9)
        checked += 1
    assert checked > 40


def test_walk_bound_bounds_epsilon_and_finds_the_nearest_facet_of_a_box():
    """The walk on the polar set (:func:`walk_bound`): on the 64 corners of a turned 6D box with
    half-widths ``a`` (its facets at the distances ``a``, epsilon ``min(a)``) it ends on a facet
    from any start direction, on the nearest one when started near its normal, to rounding
    (every facet of a box is a local minimum of the distance: the walk is a local search); on
    random force-closure contact sets its value is >= qhull's epsilon (the merged hull, another
    computation), <= the directions' bound it starts from, and equal to epsilon on some."""
    rng = np.random.default_rng(11)
    corners = np.array(np.meshgrid(*[[-1.0, 1.0]] * 6, indexing="ij")).reshape(6, -1).T
    for _ in range(20):
        a = rng.uniform(0.2, 2.0, size=6)
        rot = Rotation.random(random_state=rng).as_matrix()
        q6 = np.zeros((6, 6))
        q6[:3, :3], q6[3:, 3:] = rot, rot  # a rotation of wrench space
        w = (corners * a) @ q6.T
        u0 = rng.normal(size=6)
        u0 /= np.linalg.norm(u0)
        value = walk_bound(w, u0)
        # it ends on a facet (a vertex of the polar set), no farther than where it started
        assert np.abs(a - value).min() <= 1e-12 * value
        assert value <= float((w @ u0).max()) * (1 + 1e-12)
        # started inside the nearest facet's cone, it ends on that facet
        near = q6[:, int(a.argmin())] + 0.1 * u0
        assert walk_bound(w, near / np.linalg.norm(near)) == pytest.approx(a.min(), rel=1e-12)
    on_facet = 0
    checked = 0
    for _ in range(200):
        p, n, t, c, r = _contact_set(rng, int(rng.integers(3, 7)), spread=0.4)
        prm = QualityParams()
        w = contact_wrenches(p, n, prm, tangents=t, center=c, radius=r)
        if hull_quality(w)[2]:
            continue
        true_eps = float((-ConvexHull(w, qhull_options="Qt").equations[:, -1]).min())
        if true_eps <= 1e-9:
            continue
        start, u0 = best_direction(w, wrench_frame(w, prm.n_edges))
        value = walk_bound(w, u0)
        assert true_eps - 1e-12 <= value <= start + 1e-15
        on_facet += value <= true_eps * (1 + 1e-9)
        checked += 1
    assert checked > 60 and on_facet > checked // 4, (checked, on_facet)


@settings(max_examples=60, deadline=None)
@given(
    k=st.integers(3, 6),
    seed=st.integers(0, 2**32 - 1),
    mu=st.floats(0.0, 1.5),
    m=st.integers(3, 10),
    spread=st.floats(0.0, 2.0),
)
def test_bounds_never_raise_and_bound(k, seed, mu, m, spread):
    rng = np.random.default_rng(seed)
    p, n, t, c, r = _contact_set(rng, k, spread)
    prm = QualityParams(mu=mu, n_edges=m)
    exact = grasp_quality(p, n, prm, tangents=t, center=c, radius=r)
    q = grasp_quality(p, n, prm, tangents=t, center=c, radius=r, level=LEVEL_CHEAPEST)
    assert q.force_closure == exact.force_closure
    assert q.epsilon >= exact.epsilon and q.volume >= exact.volume


def test_bounded_scores_are_rigid_motion_invariant():
    """The bounds are taken in a frame fixed to the grasp: moving the grasp rigidly (tangents
    with it) changes no bound, no level and no force-closure decision."""
    rng = np.random.default_rng(21)
    for _ in range(40):
        p, n, t, c, r = _contact_set(rng, int(rng.integers(3, 6)), spread=0.6)
        R = Rotation.random(random_state=rng).as_matrix()
        d = rng.uniform(-0.5, 0.5, size=3)
        a = grasp_quality(p, n, tangents=t, center=c, radius=r, level=LEVEL_CHEAPEST)
        b = grasp_quality(
            p @ R.T + d, n @ R.T, tangents=t @ R.T, center=R @ c + d, radius=r, level=0
        )
        assert (a.bound, a.force_closure) == (b.bound, b.force_closure)
        assert a.epsilon_exact == b.epsilon_exact
        assert b.epsilon == pytest.approx(a.epsilon, abs=1e-9)
        assert b.volume == pytest.approx(a.volume, rel=1e-6, abs=1e-15)


def test_quality_params_check_the_new_fields():
    assert QualityParams(exact_top=0).exact_top == 0
    for bad in (-1, 1.5, True, 10**7):
        with pytest.raises(ValueError, match=r"^exact_top must be an integer in \[0, "):
            QualityParams(exact_top=bad)
    assert QualityParams(exact_all=np.bool_(True)).exact_all is True
    with pytest.raises(ValueError, match="^exact_all must be True or False"):
        QualityParams(exact_all=1)


def test_score_text_marks_bounds():
    assert score_text(0.12345, True, ".3f") == "0.123"
    assert score_text(0.12345, False, ".3f") == "<= 0.123"


# ----------------------------------------------------------------------------- ranking


def _grasp(i, gt, p, n, t):
    contacts = tuple(Contact(p[j], n[j], f"link{j}", j, 0.0, t[j]) for j in range(len(p)))
    return Grasp(i, gt, np.eye(4), 0.0, "object", np.zeros(7), (), contacts, 0.0, 0.0, None, None)


def _best_per_type(grasps, ranking):
    best: dict[str, int] = {}
    for i in ranking:
        best.setdefault(grasps[i].grasp_type, int(i))
    return best


def _assert_same_ranking(bounded, exact, k):
    rb, re = rank_grasps(bounded), rank_grasps(exact)
    assert rb[:k].tolist() == re[:k].tolist()
    assert _best_per_type(bounded, rb) == _best_per_type(exact, re)
    for b, e in zip(bounded, exact, strict=True):
        assert (b.epsilon > 0) == (e.epsilon > 0)  # force closure is exact everywhere
        assert b.epsilon >= e.epsilon and b.volume >= e.volume
        if b.epsilon_exact:
            assert b.epsilon == e.epsilon
        if b.volume_exact:
            assert b.volume == e.volume
    for i in rb[:k]:
        assert bounded[i].epsilon_exact and bounded[i].volume_exact


@pytest.mark.parametrize("exact_top", [0, 1, 5, 20])
def test_settle_exact_gives_the_exact_ranking_on_sets_with_ties(exact_top):
    """Random grasps of three types, some duplicated (ties in every score: the pre-grasp index
    decides), some not force closure, some rejected: the bounded planner's ranking after
    settle_exact starts like the exact one and each type's best is the exact one's."""
    rng = np.random.default_rng(100 + exact_top)
    prm = QualityParams(exact_top=exact_top)
    frame = (np.zeros(3), 0.08)
    sets = [_contact_set(rng, int(rng.integers(3, 6)), 0.3 + 0.5 * (i % 3)) for i in range(70)]
    grasps = []
    for i in range(90):
        p, n, t, _, _ = sets[i % 70] if i < 85 else sets[i - 80]  # duplicates: ties
        g = _grasp(i, ("cylindrical", "spherical", "two_finger_tip")[i % 3], p, n, t)
        if i % 17 == 0:
            g = dataclasses.replace(g, rejection="penetration", contacts=())
        grasps.append(g)
    exact = [score_grasp(prm, frame, LEVEL_EXACT, g) if g.kept else g for g in grasps]
    first = [score_grasp(prm, frame, LEVEL_CHEAPEST, g) if g.kept else g for g in grasps]
    assert sum(not g.epsilon_exact for g in first) > 10  # bounds are in play
    settled, n_refined = settle_exact(first, prm, frame)
    _assert_same_ranking(settled, exact, exact_top)
    assert sum(g.kept and not g.volume_exact for g in settled) > 0  # some stay bounded
    again, _ = settle_exact(settled, prm, frame)  # settled: nothing left to refine
    assert again == settled


# ----------------------------------------------------------------------------- demo objects


@pytest.fixture(scope="module")
def demo_plans():
    """Every demo object planned once at the defaults (bounded scores), with the exact scores
    of every kept grasp computed from its own contacts (what ``exact_all`` gives)."""
    hand = load_hand()
    out = {}
    for path in demo_objects():  # loop over the 13 demo objects
        cloud = load_point_cloud(path, n_points=20000, seed=0)
        res = run_pipeline(cloud, PipelineParams(), hand, until="grasps")
        q = res.params.planner.quality
        frame = quality_frame(q, cloud.points)
        exact = [score_grasp(q, frame, LEVEL_EXACT, g) if g.kept else g for g in res.grasps]
        out[path.stem] = (res, exact)
    return hand, out


def test_bounded_ranking_equals_the_exact_ranking_on_every_demo_object(demo_plans):
    _, plans = demo_plans
    assert len(plans) == 13
    n_bounded = n_hulls = 0
    for name, (res, exact) in plans.items():
        gs = res.grasps
        k = res.params.planner.quality.exact_top
        _assert_same_ranking(list(gs.grasps), exact, k)
        # the bounds from the start on every object, small pools too (the planner scores a
        # pool of at most 3 x exact_top exactly at once, rank.SMALL_POOL_FACTOR)
        q = res.params.planner.quality
        frame = quality_frame(q, res.cloud.points)
        first = [score_grasp(q, frame, LEVEL_CHEAPEST, g) if g.kept else g for g in gs.grasps]
        _assert_same_ranking(settle_exact(first, q, frame)[0], exact, k)
        assert np.array_equal(gs.ranking, rank_grasps(gs.grasps)), name
        assert gs.n_force_closure == sum(g.epsilon > 0 for g in exact), name
        if gs.best is not None:
            assert gs.grasps[gs.best].epsilon == max(g.epsilon for g in exact), name
        n_bounded += sum(g.kept and g.quality_bound != "" for g in gs.grasps)
        n_hulls += sum(g.kept and g.n_contacts >= 3 for g in gs.grasps)
    assert n_bounded > n_hulls / 2  # the bounds spared most hulls


def test_exact_all_scores_every_grasp_exactly(demo_plans):
    """The planner with ``exact_all`` gives exactly the exact scores of the fixture (every kept
    grasp exact), so the bounded ranking above was compared with the real ``--exact-all``."""
    hand, plans = demo_plans
    res, exact = plans["mug"]
    prm = dataclasses.replace(res.params.planner, quality=QualityParams(exact_all=True), threads=1)
    support = res.masks.support if res.masks is not None else None
    full = plan_grasps(res.cloud.points, res.normals, res.pool, hand, prm, support=support)
    for a, b in zip(full.grasps, exact, strict=True):
        assert (a.epsilon, a.volume, a.epsilon_exact, a.volume_exact) == (
            b.epsilon, b.volume, True, True,
        )  # fmt: skip
    assert np.array_equal(full.ranking, rank_grasps(exact))


# ----------------------------------------------------------------------------- min-norm point


def test_min_norm_point_matches_a_quadratic_program_and_its_python_form():
    """Wolfe's algorithm (compiled) against SLSQP on min |P' lam|^2, lam >= 0, sum 1, for point
    sets around or away from the origin (2D to 6D); the uncompiled Python gives the same
    point."""
    from scipy.optimize import minimize

    from pregrasp_core.minnorm import MAX_ITERATIONS, compiled, min_norm_point

    rng = np.random.default_rng(4)
    far = 0
    for trial in range(25):
        d = int(rng.integers(2, 7))
        P = rng.normal(size=(int(rng.integers(d + 1, 30)), d)) + rng.normal(scale=2.0, size=d)
        x, corral, n, ok = compiled()(P, MAX_ITERATIONS)
        assert ok and 1 <= n <= d + 1
        lam = corral[:n, 1]
        assert np.all(lam > 0) and lam.sum() == pytest.approx(1.0)
        assert np.allclose(P[corral[:n, 0].astype(int)].T @ lam, x, atol=1e-12)
        m = len(P)
        ref = minimize(
            lambda v, P=P: float(np.sum((P.T @ v) ** 2)),
            np.full(m, 1.0 / m),
            jac=lambda v, P=P: 2.0 * P @ (P.T @ v),
            bounds=[(0.0, 1.0)] * m,
            constraints=[{"type": "eq", "fun": lambda v: v.sum() - 1.0}],
            method="SLSQP",
            options={"ftol": 1e-14, "maxiter": 500},
        )
        assert np.linalg.norm(x) == pytest.approx(np.linalg.norm(P.T @ ref.x), rel=1e-5, abs=1e-6)
        far += np.linalg.norm(x) > 0.1
        assert np.all(P @ x >= x @ x - 1e-9)  # optimality: no point beyond the plane through x
        if trial < 5:
            x2, corral2, n2, ok2 = min_norm_point(P, MAX_ITERATIONS)
            assert np.array_equal(x, x2) and n == n2 and ok == ok2
    assert 5 <= far <= 24  # origins outside and inside the hulls


def test_closure_certificate_agrees_with_linear_programming():
    """The hull-free decision of force closure: when it decides, it agrees with an LP (and its
    lower bound is below the exact epsilon); it decides most random planner-like sets."""
    from pregrasp_core.quality import closure_certificate

    rng = np.random.default_rng(11)
    decided = 0
    for trial in range(120):
        p, n, t, c, r = _contact_set(rng, int(rng.integers(3, 7)), 0.3 if trial % 2 else 0.9)
        w = contact_wrenches(p, n, QualityParams(), tangents=t, center=c, radius=r)
        fc, lower = closure_certificate(w)
        if fc is None:
            continue
        decided += 1
        eps, _, _ = hull_quality(w)
        assert fc == (eps > 0.0), trial
        if trial % 3 == 0:
            assert fc == origin_strictly_inside_lp(w), trial
        if fc:
            assert 0.0 < lower <= eps + 1e-12
    assert decided >= 100


def test_cross3_equals_numpy_cross_to_the_bit():
    """The wrenches' cross products (cross3) give exactly np.cross's values, so no exact score
    moved when it replaced np.cross (the broadcast shapes of contact_wrenches included)."""
    from pregrasp_core.quality import cross3

    rng = np.random.default_rng(2)
    for sa, sb in (((7, 3), (7, 3)), ((5, 1, 3), (5, 8, 3)), ((3,), (3,)), ((4, 3), (3,))):
        a = rng.normal(size=sa) * 10.0 ** rng.integers(-8, 8, size=sa)
        b = rng.normal(size=sb)
        assert np.array_equal(cross3(a, b), np.cross(a, b))


def _wrench_frame_numpy(wrenches, n_edges):
    """wrench_frame as written before session 10 (np.linalg.norm, np.stack and cross3)."""
    from pregrasp_core.quality import cross3
    from pregrasp_core.tolerances import GEOM_EPS

    f = np.asarray(wrenches, dtype=np.float64)[:n_edges, :3]
    n = f.mean(axis=0)
    a = f[0] - n
    na, nn = float(np.linalg.norm(a)), float(np.linalg.norm(n))
    if not (na > 1e-9 * max(nn, 1.0) and nn > GEOM_EPS):
        return np.eye(3)
    a, n = a / na, n / nn
    a = a - (a @ n) * n
    a /= np.linalg.norm(a)
    return np.stack([a, cross3(n, a), n], axis=1)


def test_wrench_frame_and_bounds_equal_the_numpy_forms_to_the_bit():
    """wrench_frame's scalar form gives the frame of the numpy form bit for bit, and the volume
    bound from the rank check's centred wrenches equals the one from the wrenches (real
    contact sets: random points, normals and tangents, several mu and cone sizes)."""
    from pregrasp_core.quality import box_volume_bound

    rng = np.random.default_rng(5)
    for trial in range(400):
        k = int(rng.integers(2, 7))
        prm = QualityParams(
            mu=float(rng.choice([0.0, 0.3, 0.5, 1.0])), n_edges=int(rng.integers(3, 10))
        )
        pts = rng.normal(size=(k, 3)) * 0.05
        nrm = rng.normal(size=(k, 3))
        nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
        w = contact_wrenches(
            pts, nrm, prm, tangents=rng.normal(size=(k, 3)), center=np.zeros(3), radius=0.1
        )
        got, ref = wrench_frame(w, prm.n_edges), _wrench_frame_numpy(w, prm.n_edges)
        assert got.tobytes() == ref.tobytes(), trial
        c = w - w.mean(axis=0)
        assert box_volume_bound(w, c) == box_volume_bound(w)


def _cheap_bounds_numpy(w, centred, n_edges):
    """The cheapest level's bounds by the numpy functions one after the other (what
    ``quality.wrench_quality`` computed before its compiled pass): ``(epsilon upper bound,
    volume upper bound, force closure or None, epsilon lower bound)``."""
    from pregrasp_core.quality import NOT_CLOSURE_BOUND, box_volume_bound, closure_certificate

    upper, u = best_direction(w, wrench_frame(w, n_edges))
    vol = box_volume_bound(w, centred)
    closure, lower = (False, 0.0) if upper <= NOT_CLOSURE_BOUND else closure_certificate(w)
    if closure:
        upper = min(upper, walk_bound(w, u))
    return upper, vol, closure, lower


def test_compiled_cheapest_bounds_agree_with_the_numpy_functions():
    """The planner's one-pass cheapest bounds (``minnorm.cheap_bounds``) against the numpy
    functions it replaces (:func:`_cheap_bounds_numpy`: rank test, principal box, directions'
    bound, closure certificate, walk) on random contact sets, some flat (rank < 6) and some not
    force closure: the same reason, the same force-closure decision, the volume and the lower
    bound equal to rounding, the upper bound equal to rounding where no walk ran; with the
    walk (a path that rounding may end elsewhere) both at least qhull's epsilon."""
    from pregrasp_core import quality

    rng = np.random.default_rng(23)
    seen = {"flat": 0, "not fc": 0, "fc": 0, "undecided": 0}
    for trial in range(300):
        k = int(rng.integers(2, 7))
        m = int(rng.choice([6, 8]))
        p, n, t, c, r = _contact_set(rng, k, spread=0.3 if trial % 2 else 0.9)
        if trial % 10 == 0:
            p[:, 2] = 0.0  # contacts and normals in a plane: a flat wrench set
            n[:, 2] = 0.0
            n /= np.linalg.norm(n, axis=1, keepdims=True)
        w = contact_wrenches(p, n, QualityParams(n_edges=m), tangents=t, center=c, radius=r)
        reason, got = quality._cheap_bounds_compiled(w, m)
        want_reason, centred = quality._centred_check(w)
        assert reason == want_reason, trial
        if reason:
            seen["flat"] += 1
            continue
        up, vol, closure, low = got
        up0, vol0, closure0, low0 = _cheap_bounds_numpy(w, centred, m)
        assert closure == closure0, trial
        assert vol == pytest.approx(vol0, rel=1e-12), trial
        assert low == pytest.approx(low0, rel=1e-9, abs=1e-15), trial
        exact = ConvexHull(w, qhull_options="Q0")
        eps = max(float((-exact.equations[:, -1]).min()), 0.0)
        assert vol >= exact.volume * (1.0 - 1e-9), trial
        if closure:
            seen["fc"] += 1
            assert min(up, up0) >= eps - 1e-12, trial
            assert low <= eps + 1e-12, trial
        else:
            seen["not fc" if closure is False else "undecided"] += 1
            assert up == pytest.approx(up0, rel=1e-12, abs=1e-15), trial
    assert min(seen.values()) >= 5, seen


def test_memo_of_the_cheapest_bounds_changes_no_score():
    """The cheapest bounds that ``wrench_quality`` keeps per wrench set (for the planner's
    refinements) give every level the scores a fresh computation gives: the same sets scored
    at levels 0, 1, 2 in a row (hits) and each from an empty memo (misses) agree field by
    field; the same wrenches with another edge count do not share an entry."""
    from pregrasp_core import quality

    rng = np.random.default_rng(11)
    n_hits = 0
    for trial in range(60):
        k = int(rng.integers(3, 7))
        m = int(rng.choice([6, 8]))
        p, n, t, c, r = _contact_set(rng, k, spread=0.3 if trial % 2 else 0.9)
        w = contact_wrenches(p, n, QualityParams(n_edges=m), tangents=t, center=c, radius=r)
        fresh = []
        for level in (LEVEL_CHEAPEST, LEVEL_HALF_CONES, LEVEL_EXACT):
            quality.forget_cheap_bounds()
            fresh.append(quality.wrench_quality(w, k, m, level))
        quality.forget_cheap_bounds()
        for level, want in zip((LEVEL_CHEAPEST, LEVEL_HALF_CONES, LEVEL_EXACT), fresh, strict=True):
            n_hits += level > LEVEL_CHEAPEST and len(quality._CHEAP_MEMO) > 0
            got = quality.wrench_quality(w.copy(), k, m, level)
            assert dataclasses.astuple(got) == dataclasses.astuple(want), (trial, level)
        # the same bytes with another edge count (another frame, other bounds): not a hit
        other = quality.wrench_quality(w, k, 2 * m if m == 6 else m // 2, LEVEL_CHEAPEST)
        quality.forget_cheap_bounds()
        want = quality.wrench_quality(w, k, 2 * m if m == 6 else m // 2, LEVEL_CHEAPEST)
        assert dataclasses.astuple(other) == dataclasses.astuple(want), trial
    assert n_hits >= 100
    quality.forget_cheap_bounds()
