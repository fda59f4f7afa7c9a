"""Contact normals of kept grasps on demo clouds without normals, under tiny and rigid moves.

    .venv/bin/python benchmarks/bench_crease_contacts.py [--objects thermos] [--motions 3]
                                                        [--points 20000]
    .venv/bin/python benchmarks/bench_crease_contacts.py --objects odd_l,odd_steps,odd_groove
    .venv/bin/python benchmarks/bench_crease_contacts.py --objects bowl,can_soda --noise 0.002

For each object: the demo mesh sampled to ``--points`` points (seed 0) as the pipeline samples
it, its normals dropped (a PLY with xyz only), then the whole pipeline at default settings on
that cloud as it is, moved by +1 and by -1 unit in the last place (``np.nextafter``), and after
``--motions`` random rigid motions (a turn about the vertical, which keeps the object standing
on the table, and a translation; mesh and true normals moved with it). Per cloud: the kept
grasps, their contacts, the contacts whose normal does not point into the true mesh (rank,
link, point; marked * where the point's normal is the crest rule's, see ``docs/design.md``,
normals), as ``tests/core/test_normals.py`` checks them, the points of the outer surface whose
normal disagrees with the true mesh's, the contacts at crest-rule points and the kept grasps
they belong to (what a planner that took no contact there would lose), the median cosine of
those contacts' normals (on the outer surface) with the true inward normal, beside that of the
cloud's own normals at the same points (the contact takes the mean of the cloud's and the
link's push there, ``docs/planner.md`` step 6), and the wall seconds.
A fix of the normals in creases (``docs/limits.md``, "Normals in creases") must give no wrong
contact on every one of these clouds: one cloud alone passes or fails on the last bit of the
floating-point results.

Besides the demo objects, three shapes with creases made here (trimesh booleans, manifold3d):
``odd_l``, two boxes unioned into an L (a 90-degree concave crease along a line); ``odd_steps``,
a cylinder of radius 3 cm standing on one of 5 cm (a concave circular crease, convex rims);
``odd_groove``, a cylinder of radius 4 cm with a groove 2 mm high and 3 mm deep round its middle
(narrower than the point spacing, like the thermos's shoulder).
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # one BLAS thread, before numpy loads

import argparse  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # this checkout's pregrasp_core, not an installed one
sys.path.insert(0, str(ROOT / "tests" / "core"))  # the contact check of test_normals.py


def odd_shape(name: str, folder: Path) -> Path:
    """An OBJ file of one of the shapes with creases (see the module docstring)."""
    import trimesh
    from trimesh.creation import box, cylinder

    def at(m: trimesh.Trimesh, x: float, y: float, z: float) -> trimesh.Trimesh:
        m.apply_translation([x, y, z])
        return m

    if name == "odd_l":
        mesh = trimesh.boolean.union(
            [
                at(box([0.12, 0.04, 0.04]), 0.0, 0.0, 0.02),
                at(box([0.04, 0.04, 0.10]), 0.04, 0.0, 0.07),
            ]
        )
    elif name == "odd_steps":
        mesh = trimesh.boolean.union(
            [at(cylinder(0.05, 0.03, sections=96), 0.0, 0.0, 0.015),
             at(cylinder(0.03, 0.06, sections=96), 0.0, 0.0, 0.06)]
        )  # fmt: skip
    elif name == "odd_groove":
        body = at(cylinder(0.04, 0.12, sections=96), 0.0, 0.0, 0.06)
        ring = trimesh.boolean.difference(
            [cylinder(0.045, 0.002, sections=96), cylinder(0.037, 0.004, sections=96)]
        )
        mesh = trimesh.boolean.difference([body, at(ring, 0.0, 0.0, 0.06)])
    else:
        raise SystemExit(f"unknown shape {name!r}")
    path = folder / f"{name}.obj"
    mesh.export(path)
    return path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--objects", default="thermos", help="comma-separated demo object names")
    ap.add_argument("--motions", type=int, default=3, help="random rigid motions per object")
    ap.add_argument("--points", type=int, default=20000, help="points sampled on each mesh")
    ap.add_argument(
        "--noise", type=float, default=0.0,
        help="metres: Gaussian noise on every coordinate of the sampled cloud (seed 1), as a "
        "fused scan's; the true normals stay those of the faces sampled",
    )  # fmt: skip
    args = ap.parse_args()

    import trimesh
    from scipy.spatial.transform import Rotation
    from test_normals import _exterior, _hand, _inside

    from pregrasp_core.io import PointCloud, load_point_cloud
    from pregrasp_core.normals import estimate_normals
    from pregrasp_core.paths import OBJECTS_DIR
    from pregrasp_core.pipeline import run_pipeline

    folder = Path(tempfile.mkdtemp(prefix="bench_crease_"))
    print(f"# load average before: {os.getloadavg()}")
    for name in args.objects.split(","):
        path = odd_shape(name, folder) if name.startswith("odd_") else OBJECTS_DIR / f"{name}.obj"
        sampled = load_point_cloud(path, n_points=args.points, seed=0)
        bare = PointCloud(points=sampled.points, normals=None, source=sampled.source)
        true0 = np.asarray(sampled.normals)
        mesh0 = trimesh.load(path, force="mesh", process=True)
        pts0 = np.asarray(bare.points)
        if args.noise > 0.0:
            pts0 = pts0 + np.random.default_rng(1).normal(scale=args.noise, size=pts0.shape)
        clouds = {
            "as sampled": (pts0, true0, mesh0),
            "+1 ulp": (np.nextafter(pts0, np.inf), true0, mesh0),
            "-1 ulp": (np.nextafter(pts0, -np.inf), true0, mesh0),
        }
        rng = np.random.default_rng(0)
        for m in range(args.motions):
            R = Rotation.from_euler("z", rng.uniform(0.0, 2.0 * np.pi)).as_matrix()
            t = rng.uniform(-0.5, 0.5, size=3)
            T = np.eye(4)
            T[:3, :3], T[:3, 3] = R, t
            mesh = mesh0.copy()
            mesh.apply_transform(T)
            clouds[f"rigid motion {m + 1}"] = (pts0 @ R.T + t, true0 @ R.T, mesh)
        print(
            f"\n| {name}, {args.points:,} points | kept grasps | contacts "
            "| wrong contacts (rank, link, point; *: crest rule) | wrong outer points "
            "| contacts at crest-rule points (their grasps) "
            "| their median cosine to the true normal: contact / cloud | s |"
            "\n|---|---:|---:|---|---:|---:|---:|---:|"
        )
        for label, (pts, true, mesh) in clouds.items():
            w0 = time.perf_counter()
            ext_all = _exterior(mesh, pts, true)
            cn = estimate_normals(pts)
            bad_pts = int(np.sum((np.einsum("ij,ij->i", cn.normals, true) <= 0.0) & ext_all))
            crest = cn.crest  # the points whose normal is the crest rule's (docs/design.md)
            assert crest is not None
            cloud = PointCloud(points=pts, normals=None, source=bare.source)
            res = run_pipeline(cloud, hand=_hand(), until="grasps")
            assert res.grasps is not None
            kept = [res.grasps.grasps[i] for i in res.grasps.ranking]
            contacts = [(rank, c) for rank, g in enumerate(kept) for c in g.contacts]
            pid = np.array([c.point_index for _, c in contacts], dtype=np.int64)
            n_in = np.array([c.normal for _, c in contacts]).reshape(-1, 3)
            ext = _exterior(mesh, pts[pid], true[pid])
            into = np.einsum("ij,ij->i", n_in, true[pid]) < 0.0
            if not ext.all():
                into[~ext] = _inside(mesh, pts[pid[~ext]] + 5e-4 * n_in[~ext])
            wrong = [
                f"{r} {c.link} {c.point_index}{'*' if crest[c.point_index] else ''}"
                for (r, c), ok in zip(contacts, into, strict=True)
                if not ok
            ]
            at_crest = crest[pid]
            n_grasps = len({r for (r, _), c in zip(contacts, at_crest, strict=True) if c})
            # on the outer surface: the contact's normal and the cloud's against the true one
            sel = at_crest & ext
            inward = -true[pid[sel]]
            cos_used = np.einsum("ij,ij->i", n_in[sel], inward)
            cos_cloud = np.einsum("ij,ij->i", -cn.normals[pid[sel]], inward)
            cosines = (
                f"{np.median(cos_used):.2f} / {np.median(cos_cloud):.2f}" if sel.any() else "-"
            )
            print(
                f"| {label} | {len(kept)} | {len(contacts)} | {len(wrong)}"
                f"{': ' + ', '.join(wrong) if wrong else ''} | {bad_pts} "
                f"| {int(at_crest.sum())} ({n_grasps}) | {cosines} "
                f"| {time.perf_counter() - w0:.0f} |",
                flush=True,
            )
    print(f"\n# load average after: {os.getloadavg()}")


if __name__ == "__main__":
    main()
