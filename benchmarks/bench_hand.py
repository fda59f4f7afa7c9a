"""Hand benchmark (issue 3): batch forward kinematics, point-in-link queries, the batched
hand-vs-cloud filter and the planar closing model, each beside a reference in the same run.

- Batch FK (``Hand.fk_array``) for B random configurations, against yourdfpy's per-configuration
  FK (``update_cfg`` + ``get_transform`` of every link), timed on a subset and given per
  configuration. The results are compared (max abs difference).
- ``points_in_links`` for a 20k-point cloud at one configuration.
- ``link_point_counts`` (hand-frame bounds, then exact box tests) for G hands around the
  default object, against a loop of per-pose ``points_in_links`` calls (brute force);
  counts must agree.
- ``close_finger`` on slices of M points.

Usage: .venv/bin/python benchmarks/bench_hand.py [--configs 10000] [--repeats 7] [--points 20000]
Timings are medians of ``--repeats`` runs of the process's CPU time; run with
``OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1`` for single-core figures.
"""

from __future__ import annotations

import argparse
import platform
import time

import numpy as np
import yourdfpy
from _timing import median_time

from pregrasp_core.hand import Hand
from pregrasp_core.paths import DEFAULT_OBJECT, HAND_URDF


def fmt(seconds: float) -> str:
    if seconds >= 1.0:
        return f"{seconds:.2f} s"
    if seconds >= 1e-3:
        return f"{seconds * 1e3:.2f} ms"
    return f"{seconds * 1e6:.1f} us"


def bench_fk(hand: Hand, n_configs: int, repeats: int, rng: np.random.Generator) -> None:
    urdf = yourdfpy.URDF.load(str(HAND_URDF), build_scene_graph=True, load_meshes=False)
    print("\n### Batch forward kinematics (all 10 links)\n")
    print(
        "| configurations | pregrasp batch FK | per configuration | yourdfpy loop (est.) "
        "| speed-up |"
    )
    print("|---:|---:|---:|---:|---:|")
    n_ref = 200
    Qref = rng.uniform(hand.lower, hand.upper, size=(n_ref, hand.n_joints))

    def ref_loop():
        for q in Qref:
            urdf.update_cfg(q)
            for n in hand.link_names:
                urdf.get_transform(n)

    t_ref = median_time(ref_loop, max(1, repeats // 3)) / n_ref
    T = hand.fk(Qref)
    err = 0.0
    for b, q in enumerate(Qref):
        urdf.update_cfg(q)
        for n in hand.link_names:
            err = max(err, float(np.abs(urdf.get_transform(n) - T[n][b]).max()))
    for B in (1, 100, 1000, n_configs):
        Q = rng.uniform(hand.lower, hand.upper, size=(B, hand.n_joints))
        t = median_time(lambda Q=Q: hand.fk_array(Q), repeats)
        print(f"| {B} | {fmt(t)} | {fmt(t / B)} | {fmt(t_ref * B)} | {t_ref * B / t:.0f}x |")
    print(f"\nmax |batch FK - yourdfpy| over {n_ref} configurations x 10 links: {err:.1e}")


def object_cloud(n_points: int) -> np.ndarray:
    try:
        from pregrasp_core.io import load_point_cloud

        return load_point_cloud(DEFAULT_OBJECT, n_points=n_points, seed=0).points
    except ImportError:  # io not there: sample the mesh with trimesh
        import trimesh

        mesh = trimesh.load(DEFAULT_OBJECT, force="mesh")
        return np.asarray(trimesh.sample.sample_surface(mesh, n_points, seed=0)[0])


def poses_around(
    cloud: np.ndarray, G: int, rng: np.random.Generator, lo: float, hi: float
) -> np.ndarray:
    """G hand poses whose approach (+z) aims at the cloud's centre from random directions, the
    palm at ``lo`` to ``hi`` times the cloud's radius (farthest point) from the centre."""
    c = cloud.mean(axis=0)
    r = np.linalg.norm(cloud - c, axis=1).max()
    d = rng.normal(size=(G, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    z = -d
    x = np.cross(z, rng.normal(size=(G, 3)))
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    y = np.cross(z, x)
    T = np.tile(np.eye(4), (G, 1, 1))
    T[:, :3, 0], T[:, :3, 1], T[:, :3, 2] = x, y, z
    T[:, :3, 3] = c + d * r * rng.uniform(lo, hi, size=(G, 1))
    assert np.allclose(np.linalg.det(T[:, :3, :3]), 1.0)
    return T


def bench_points(hand: Hand, n_points: int, repeats: int, rng: np.random.Generator) -> None:
    cloud = object_cloud(n_points)
    q = hand.preshape("spherical")
    print(f"\n### Point-in-link queries ({n_points} points of the default object)\n")
    print("| query | hands | time | per hand | reference (per-pose loop) | same counts |")
    print("|---|---:|---:|---:|---:|---|")
    c = cloud.mean(axis=0)
    p_hand = cloud - c + np.array([0.0, 0.0, 0.06])
    t = median_time(lambda: hand.points_in_links(p_hand, q, 0.002), repeats)
    print(f"| points_in_links (N, L) | 1 | {fmt(t)} | {fmt(t)} | - | - |")
    for G, lo, hi in ((100, 0.5, 1.0), (1000, 0.5, 1.0), (1000, 1.0, 1.5)):
        T = poses_around(cloud, G, rng, lo, hi)
        Q = np.tile(q, (G, 1))
        t = median_time(lambda T=T, Q=Q: hand.link_point_counts(cloud, T, Q, 0.002), repeats)

        def brute(T=T, G=G):
            out = np.empty((G, len(hand.link_names)), dtype=np.int64)
            for g in range(G):
                ph = (cloud - T[g, :3, 3]) @ T[g, :3, :3]
                out[g] = hand.points_in_links(ph, q, 0.002).sum(axis=0)
            return out

        t_ref = median_time(brute, 1)
        same = np.array_equal(hand.link_point_counts(cloud, T, Q, 0.002), brute())
        hit = hand.hands_hit_points(cloud, T, Q, 0.002).mean()
        print(
            f"| link_point_counts, palm at {lo}-{hi} r, {hit:.0%} hit | {G} | {fmt(t)} | "
            f"{fmt(t / G)} | {fmt(t_ref)} | {same} |"
        )


def bench_closing(hand: Hand, repeats: int, rng: np.random.Generator) -> None:
    print("\n### Planar closing model (one finger, 64 steps per phase, refined to 1e-4 rad)\n")
    print("| points in slice | time per close_finger | outcome |")
    print("|---:|---:|---|")
    f = hand.finger("f1")
    for M in (100, 1000, 10000):
        # a disc of points in front of the finger: the middle link touches, the distal wraps
        ang = rng.uniform(0, 2 * np.pi, M)
        rad = 0.03 * np.sqrt(rng.uniform(0, 1, M))
        P = np.stack([0.06 + rad * np.cos(ang), 0.055 + rad * np.sin(ang)], axis=1)
        q0 = np.array([-0.5, 0.0])
        t = median_time(lambda P=P, q0=q0: hand.close_finger(f, P, q0), repeats)
        c = hand.close_finger(f, P, q0)
        links = "+".join(k.link.split("_")[1] for k in c.contacts) or "none"
        print(f"| {M} | {fmt(t)} | contacts: {links} |")


def bench_self_collision(hand: Hand, n_points: int, repeats: int) -> None:
    """``self_collisions_many`` on B closed hands against loops of ``self_collisions`` (now)
    and of the pre-batch version (ball test + python-fcl, commit 4e2d75e, copied below as the
    reference), per configuration; box poses given, as the planner does. Hands: the final
    configurations of the planner's pre-grasps on the default object (tiled to 1,000), and
    random closing hands (spread of a grasp type, every flexion 0 to 1.2 rad; own seed, so the
    set does not depend on the other sections)."""
    import fcl

    import pregrasp_core.hand.collision as collision_module
    from pregrasp_core.hand import GRASP_TYPES
    from pregrasp_core.io import load_point_cloud
    from pregrasp_core.pipeline import PipelineParams, run_pipeline
    from pregrasp_core.planner import PlannerParams

    checker = hand.self_collision_checker
    ia, ib, reach = checker.a, checker.b, checker.reach
    pairs = hand.self_collision_pairs_checked

    def before(Tb: np.ndarray) -> list[tuple[str, str]]:  # one hand's box poses (L, 4, 4)
        near = np.flatnonzero(np.linalg.norm(Tb[ia, :3, 3] - Tb[ib, :3, 3], axis=1) - reach <= 1e-6)
        if len(near) == 0:
            return []
        objs = {
            int(li): fcl.CollisionObject(
                checker.boxes[li], fcl.Transform(Tb[li, :3, :3], Tb[li, :3, 3])
            )
            for li in np.unique(np.concatenate([ia[near], ib[near]]))
        }
        req = fcl.CollisionRequest()
        return [
            pairs[k]
            for k in near
            if fcl.collide(objs[int(ia[k])], objs[int(ib[k])], req, fcl.CollisionResult()) > 0
        ]

    cloud = load_point_cloud(DEFAULT_OBJECT, n_points=n_points, seed=0)
    params = PipelineParams(planner=PlannerParams(threads=1))
    result = run_pipeline(cloud, params=params, hand=hand, until="grasps")
    real = np.array([g.q for g in result.grasps.grasps])
    rng = np.random.default_rng(0)
    synth = np.zeros((1000, hand.n_joints))
    synth[:, hand.spread_index] = rng.choice([hand.spread_for(g) for g in GRASP_TYPES], 1000)
    for f in hand.fingers:  # loop over the 3 fingers
        synth[:, list(f.flex_index)] = rng.uniform(0.0, 1.2, size=(1000, 2))
    sets = (
        (f"planner's, mug ({len(real)} tiled)", np.resize(real, (1000, hand.n_joints))),
        ("closing, flexion 0-1.2 rad", synth),
    )
    print(
        f"\n### Self-collision, batched ({len(pairs)} checked link pairs; box poses given; "
        "times per configuration)\n"
    )
    print(
        "| hands | B | colliding | ball candidates | to python-fcl | self_collisions_many "
        "| loop of self_collisions | loop before (ball + fcl) | speed-up | same pairs |"
    )
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|---|")
    half = np.asarray(hand.link_box_half).T  # (3, L)
    for name, Qall in sets:
        for B in (64, 1000):
            Q, Tb = Qall[:B], hand.box_poses(Qall[:B])
            t_many = median_time(lambda Q=Q, Tb=Tb: hand.self_collisions_many(Q, Tb), repeats)
            t_one = median_time(
                lambda Q=Q, Tb=Tb: [hand.self_collisions(q, T) for q, T in zip(Q, Tb, strict=True)],
                repeats,
            )
            t_ref = median_time(lambda Tb=Tb: [before(T) for T in Tb], repeats)
            many = hand.self_collisions_many(Q, Tb)
            same = many == [hand.self_collisions(Q[b], Tb[b]) for b in range(B)]
            same &= many == [before(T) for T in Tb]
            # the work: candidates of the ball test, of them those the SAT leaves to python-fcl
            c = Tb[:, :, :3, 3]
            bb, kk = np.nonzero(np.linalg.norm(c[:, ia] - c[:, ib], axis=2) - reach <= 1e-6)
            Tt, la, lb = Tb.transpose(2, 3, 0, 1), ia[kk], ib[kk]
            apart = collision_module.obb_apart(
                Tt[:3, :3, bb, la], Tt[:3, 3, bb, la], half[:, la],
                Tt[:3, :3, bb, lb], Tt[:3, 3, bb, lb], half[:, lb],
            )  # fmt: skip
            hit = np.mean([bool(m) for m in many])
            print(
                f"| {name} | {B} | {hit:.0%} | {len(bb) / B:.1f} | {(~apart).sum() / B:.1f} | "
                f"{fmt(t_many / B)} | {fmt(t_one / B)} | {fmt(t_ref / B)} | "
                f"{t_ref / t_many:.1f}x | {same} |"
            )
    # one hand: the filter forced on (threshold 0) against off, by ball-candidate count; this
    # is what ``SAT_MIN_PAIRS`` is set from
    Q = rng.uniform(hand.lower, hand.upper, size=(3000, hand.n_joints))
    Tb = hand.box_poses(Q)
    c = Tb[:, :, :3, 3]
    n_cand = (np.linalg.norm(c[:, ia] - c[:, ib], axis=2) - reach <= 1e-6).sum(axis=1)
    print("\nOne hand (`self_collisions`, random configurations), separating-axis filter on/off:\n")
    print("| ball candidates | hands | filter on | filter off (ball + fcl) |")
    print("|---|---:|---:|---:|")
    default = collision_module.SAT_MIN_PAIRS
    for lo, hi in ((0, 6), (6, 12), (12, 18), (18, 24), (24, 37)):
        sel = np.flatnonzero((n_cand >= lo) & (n_cand < hi))[:100]
        times = []
        for threshold in (0, 10**9):  # filter on every call / never
            collision_module.SAT_MIN_PAIRS = threshold
            times.append(
                median_time(
                    lambda sel=sel: [hand.self_collisions(Q[b], Tb[b]) for b in sel], repeats
                )
            )
        collision_module.SAT_MIN_PAIRS = default
        on, off = (fmt(t / len(sel)) for t in times)
        print(f"| {lo}-{hi - 1} | {len(sel)} | {on} | {off} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--configs", type=int, default=10000)
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--points", type=int, default=20000)
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    hand = Hand.load()
    print(
        f"machine: {platform.machine()}, Python {platform.python_version()}, "
        f"numpy {np.__version__}, {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}"
    )
    bench_fk(hand, args.configs, args.repeats, rng)
    bench_points(hand, args.points, args.repeats, rng)
    bench_closing(hand, args.repeats, rng)
    q = hand.preshape("spherical")
    t = median_time(lambda: hand.self_collision(q), args.repeats)
    n_pairs = len(hand.self_collision_pairs_checked)
    print(f"\nself_collision (python-fcl, {n_pairs} pairs): {fmt(t)}")
    bench_self_collision(hand, args.points, args.repeats)


if __name__ == "__main__":
    main()
