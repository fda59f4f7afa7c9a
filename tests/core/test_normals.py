"""Cloud normals against analytic surfaces (sphere, plane, torus), rigid motions, references."""

from __future__ import annotations

import functools
import threading

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pregrasp_core.errors import DegenerateGeometryError
from pregrasp_core.normals import NormalParams, estimate_normals
from pregrasp_core.paths import OBJECTS_DIR, demo_objects


def _sphere(n: int, r: float = 0.04) -> tuple[np.ndarray, np.ndarray]:
    """Fibonacci points on a sphere and their analytic outward normals."""
    i = np.arange(n) + 0.5
    phi = np.arccos(1 - 2 * i / n)
    th = np.pi * (1 + 5**0.5) * i
    u = np.c_[np.cos(th) * np.sin(phi), np.sin(th) * np.sin(phi), np.cos(phi)]
    return r * u, u


def _torus(n: int, big: float = 0.05, small: float = 0.015, seed: int = 0):
    """Points on a torus about z and their analytic outward normals."""
    rng = np.random.default_rng(seed)
    u, v = rng.uniform(0, 2 * np.pi, size=(2, n))
    normal = np.c_[np.cos(v) * np.cos(u), np.cos(v) * np.sin(u), np.sin(v)]
    centre = np.c_[big * np.cos(u), big * np.sin(u), np.zeros(n)]
    return centre + small * normal, normal


def _angles_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", a, b), -1, 1)))


@pytest.mark.parametrize("orient", ["propagate", "centroid"])
def test_sphere_normals_are_radial_and_outward(orient):
    pts, ref = _sphere(3000)
    cn = estimate_normals(pts, NormalParams(k=12, orient=orient))
    assert cn.orient == orient
    assert np.allclose(np.linalg.norm(cn.normals, axis=1), 1.0)
    assert _angles_deg(cn.normals, ref).max() < 3.0
    assert np.all(cn.curvature >= 0) and np.all(cn.curvature <= 1 / 3 + 1e-12)


def test_plane_normals_are_consistent_and_curvature_zero():
    rng = np.random.default_rng(0)
    pts = np.c_[rng.uniform(-0.05, 0.05, size=(2000, 2)), np.zeros(2000)]
    cn = estimate_normals(pts, NormalParams(orient="propagate"))
    assert np.allclose(np.abs(cn.normals[:, 2]), 1.0)
    assert np.all(np.sign(cn.normals[:, 2]) == np.sign(cn.normals[0, 2]))  # one side only
    assert cn.curvature.max() < 1e-12


def test_torus_propagation_orients_the_inner_ring_where_the_centroid_rule_fails():
    pts, ref = _torus(6000)
    prop = estimate_normals(pts, NormalParams(k=12, orient="propagate"))
    ang = _angles_deg(prop.normals, ref)
    assert np.mean(ang < 15.0) > 0.99
    cent = estimate_normals(pts, NormalParams(k=12, orient="centroid"))
    # the centroid rule points the inner half of the tube into the object
    assert np.mean(_angles_deg(cent.normals, ref) > 90.0) > 0.2


def test_reference_normals_fix_the_sign():
    pts, ref = _torus(3000, seed=1)
    cn = estimate_normals(pts, reference=ref)  # auto -> reference
    assert cn.orient == "reference"
    assert np.mean(_angles_deg(cn.normals, ref) < 15.0) > 0.99
    flipped = estimate_normals(pts, reference=-ref)
    assert np.allclose(flipped.normals, -cn.normals)


def test_rigid_motion_moves_normals_with_the_cloud():
    pts, _ = _torus(3000, seed=2)
    base = estimate_normals(pts)
    rng = np.random.default_rng(4)
    for _ in range(3):
        R = Rotation.random(random_state=rng).as_matrix()
        t = rng.uniform(-1, 1, size=3)
        moved = estimate_normals(pts @ R.T + t)
        assert np.allclose(moved.normals, base.normals @ R.T, atol=1e-6)
        assert np.allclose(moved.curvature, base.curvature, atol=1e-9)


def test_disconnected_components_are_each_oriented_outwards():
    a, na = _sphere(800, r=0.02)
    b, nb = _sphere(800, r=0.03)
    pts = np.r_[a - [0.2, 0, 0], b + [0.2, 0, 0]]
    cn = estimate_normals(pts, NormalParams(k=10, orient="propagate"))
    assert _angles_deg(cn.normals, np.r_[na, nb]).max() < 5.0


def test_errors():
    with pytest.raises(DegenerateGeometryError, match="at least k = 16 points.*has 5"):
        estimate_normals(np.random.default_rng(0).normal(size=(5, 3)))
    with pytest.raises(ValueError, match=r"shape \(N, 3\), got \(10, 2\)"):
        estimate_normals(np.zeros((10, 2)))
    with pytest.raises(ValueError, match="orient must be one of"):
        NormalParams(orient="outwards")
    with pytest.raises(ValueError, match="needs reference normals"):
        estimate_normals(_sphere(100)[0], NormalParams(orient="reference"))
    with pytest.raises(ValueError, match="reference normals must have shape"):
        estimate_normals(_sphere(100)[0], reference=np.zeros((3, 3)))


def test_propagation_on_the_default_mug_agrees_with_its_mesh_normals():
    """The mug with a handle (concave, 4-5 mm walls): propagation without the mesh normals
    agrees in sign with the mesh's face normals on at least 98 % of the points at the default
    20,000 points (at 8,000 points the spacing nears the wall thickness and it fails)."""
    from pregrasp_core.io import load_point_cloud
    from pregrasp_core.paths import DEFAULT_OBJECT

    cloud = load_point_cloud(DEFAULT_OBJECT, n_points=20000, seed=0)
    cn = estimate_normals(cloud.points, NormalParams(orient="propagate"))
    assert np.mean(np.einsum("ij,ij->i", cn.normals, cloud.normals) > 0) > 0.98
    ref = estimate_normals(cloud.points, reference=cloud.normals)
    assert np.median(_angles_deg(ref.normals, cloud.normals)) < 5.0


def _thin_plate(n: int, thickness: float, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Points on both faces (and the rim) of a 10 x 10 cm plate of the given thickness, with
    their analytic outward normals."""
    rng = np.random.default_rng(seed)
    a, t = 0.05, thickness / 2
    m = n // 2
    top = np.c_[rng.uniform(-a, a, (m, 2)), np.full(m, t)]
    bot = np.c_[rng.uniform(-a, a, (m, 2)), np.full(m, -t)]
    nrm = np.r_[np.tile([0.0, 0.0, 1.0], (m, 1)), np.tile([0.0, 0.0, -1.0], (m, 1))]
    return np.r_[top, bot], nrm


@pytest.mark.parametrize("thickness", [0.004, 0.006])
def test_visibility_orients_both_faces_of_a_thin_plate(thickness):
    """A plate a few millimetres thick sampled on both faces: the neighbourhoods of the two faces
    overlap, and a viewer sees each face from its own side only."""
    pts, nrm = _thin_plate(8000, thickness)
    R = Rotation.from_euler("xyz", [0.3, -0.5, 0.9]).as_matrix()
    cn = estimate_normals(pts @ R.T, NormalParams(orient="visibility"))
    assert np.mean(np.einsum("ij,ij->i", cn.normals, nrm @ R.T) > 0) > 0.99


def test_visibility_orients_the_torus_and_the_sphere():
    pts, nrm = _torus(6000)
    cn = estimate_normals(pts, NormalParams(orient="visibility"))
    assert np.mean(np.einsum("ij,ij->i", cn.normals, nrm) > 0) > 0.995
    pts, nrm = _sphere(3000)
    cn = estimate_normals(pts)  # auto: no reference, no viewpoint -> visibility
    assert cn.orient == "visibility"
    assert _angles_deg(cn.normals, nrm).max() < 10.0


def test_viewpoint_normals_face_the_camera():
    """A single view: the half of a sphere a camera at +x sees; every normal faces the camera
    (they are the outward normals there)."""
    pts, nrm = _sphere(4000)
    cam = np.array([0.5, 0.0, 0.0])
    keep = np.einsum("ij,ij->i", cam - pts, nrm) > 0
    cn = estimate_normals(pts[keep], NormalParams(viewpoint=(0.5, 0.0, 0.0)))
    assert cn.orient == "viewpoint"
    assert np.all(np.einsum("ij,ij->i", cn.normals, cam - pts[keep]) >= 0)
    assert np.mean(np.einsum("ij,ij->i", cn.normals, nrm[keep]) > 0) > 0.999
    with pytest.raises(ValueError, match="needs a viewpoint"):
        NormalParams(orient="viewpoint")
    with pytest.raises(ValueError, match="viewpoint must be 3 finite numbers"):
        NormalParams(viewpoint=(0.0, np.nan, 1.0))


def _exterior(mesh, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """(N,) bool: the point is on the object's outer surface, not on a face that lies inside
    the solid (the probe 1 mm out along the face's normal is outside it, see :func:`_inside`)."""
    if len(mesh.split(only_watertight=False)) < 2:
        return np.ones(len(points), dtype=bool)
    return ~_inside(mesh, points + 1e-3 * normals)


def _inside(mesh, q: np.ndarray) -> np.ndarray:
    """(Q,) bool: inside the solid. The demo meshes are unions of interpenetrating bodies, some
    closed (inside: trimesh's ray test), some open and closing each other (the bottle's shoulder
    and neck; inside: their generalised winding number above 1/2), plus flat membranes between
    bodies (the disc at the foot of the bottle's neck), which bound nothing."""
    inside = np.zeros(len(q), dtype=bool)
    open_tris = []
    for b in mesh.split(only_watertight=False):
        if b.is_watertight:
            if b.volume < 0:
                b.invert()
            inside |= b.contains(q)
        elif abs(b.volume) > 1e-12:  # an open body with a volume, not a flat membrane
            open_tris.append(b.triangles)
    if open_tris:
        inside |= _winding_number(np.concatenate(open_tris), q) > 0.5
    return inside


def _winding_number(tris: np.ndarray, q: np.ndarray) -> np.ndarray:
    """(Q,) generalised winding number of triangles (T, 3, 3) at points (Q, 3) (Van Oosterom and
    Strackee's solid angle; chunked over the points)."""
    out = np.empty(len(q))
    for s in range(0, len(q), 2000):
        a, b, c = (tris[None, :, i, :] - q[s : s + 2000, None, :] for i in range(3))
        la, lb, lc = (np.linalg.norm(x, axis=2) for x in (a, b, c))
        det = np.einsum("qti,qti->qt", a, np.cross(b, c))
        den = (
            la * lb * lc
            + np.einsum("qti,qti->qt", a, b) * lc
            + np.einsum("qti,qti->qt", b, c) * la
            + np.einsum("qti,qti->qt", c, a) * lb
        )
        out[s : s + 2000] = np.arctan2(det, den).sum(axis=1) / (2 * np.pi)
    return out


def _bare_demo_cloud(path):
    """A demo mesh sampled to 20,000 points as the pipeline samples it, its normals dropped (what a
    PLY with xyz only gives), and the true outward normals of the sampled faces."""
    from pregrasp_core.io import PointCloud, load_point_cloud

    cloud = load_point_cloud(path, n_points=20000, seed=0)
    bare = PointCloud(points=cloud.points, normals=None, source=cloud.source)
    return bare, np.asarray(cloud.normals)


DEMO_NAMES = [p.stem for p in demo_objects()]


@functools.cache
def _hand():
    from pregrasp_core.hand import Hand

    return Hand.load()


@pytest.mark.parametrize("name", DEMO_NAMES)
def test_visibility_on_demo_objects_agrees_with_the_true_mesh(name):
    """Demo meshes sampled WITHOUT normals (as a PLY with xyz only): the orientation agrees with
    the true mesh's outward face normals on at least 99 % of the points of the outer surface
    (docs/benchmarks.md lists the figure per object; faces inside the solid are left out)."""
    import trimesh

    path = OBJECTS_DIR / f"{name}.obj"
    bare, true = _bare_demo_cloud(path)
    cn = estimate_normals(bare.points, NormalParams())
    assert cn.orient == "visibility"
    mesh = trimesh.load(path, force="mesh", process=True)
    ext = _exterior(mesh, np.asarray(bare.points), true)
    assert ext.mean() > 0.7
    agree = np.einsum("ij,ij->i", cn.normals, true) > 0
    assert agree[ext].mean() >= 0.99


THERMOS_CREASE = pytest.mark.xfail(
    strict=False,
    reason="known defect, issue 11 open: at the thermos's shoulder the ring under the lid "
    "overhangs the chamfered body's top by 1.5-2.6 mm, a notch narrower than the point spacing "
    "(3.1 mm) and the visibility's pixels (6.2 mm); contact points there take the mean of the "
    "crest rule's normal (away from their neighbours' centroid, wrong in the notch) and the "
    "touching link's push (wrong where a box corner presses the ring from below): 1-2 wrong "
    "contacts remain on each cloud, where both are wrong; which ones turns on the last bit of "
    "the floating-point results (docs/limits.md, 'Normals in creases')",
)
"""The known failure of the contact-normal tests on the thermos (docs/limits.md, "Normals in
creases")."""


def _wrong_contacts(points: np.ndarray, true: np.ndarray, mesh) -> list[tuple[int, str, int]]:
    """The whole pipeline at default settings on ``points`` (N, 3) without normals: (rank, link,
    point) of every contact of a kept grasp whose normal does not point into the object, against
    the true outward normal ``true`` (N, 3) of the face its point was sampled on; for a point
    sampled on a face inside the solid (which has no outward normal: the thermos's ring sits on
    its body), the force direction must enter the solid (0.5 mm along it is inside ``mesh``)."""
    from pregrasp_core.io import PointCloud
    from pregrasp_core.pipeline import run_pipeline

    res = run_pipeline(PointCloud(points=points, normals=None), hand=_hand(), until="grasps")
    assert res.grasps is not None
    kept = [res.grasps.grasps[i] for i in res.grasps.ranking]
    assert kept, "no kept grasp to check"
    contacts = [(rank, c) for rank, g in enumerate(kept) for c in g.contacts]
    pid = np.array([c.point_index for _, c in contacts])
    n_in = np.array([c.normal for _, c in contacts])
    ext = _exterior(mesh, points[pid], true[pid])
    into = np.einsum("ij,ij->i", n_in, true[pid]) < 0.0
    if not ext.all():
        into[~ext] = _inside(mesh, points[pid[~ext]] + 5e-4 * n_in[~ext])
    return [
        (rank, c.link, c.point_index)
        for (rank, c), ok in zip(contacts, into, strict=True)
        if not ok
    ]


@pytest.mark.slow
@pytest.mark.parametrize(
    "name", [pytest.param(n, marks=THERMOS_CREASE) if n == "thermos" else n for n in DEMO_NAMES]
)
def test_every_contact_normal_of_every_kept_grasp_points_into_the_true_mesh(name):
    """The whole pipeline at default settings on a demo mesh sampled WITHOUT normals: every
    contact normal of every kept grasp points into the object (issue 11), see
    :func:`_wrong_contacts`."""
    import trimesh

    path = OBJECTS_DIR / f"{name}.obj"
    bare, true = _bare_demo_cloud(path)
    mesh = trimesh.load(path, force="mesh", process=True)
    wrong = _wrong_contacts(np.asarray(bare.points), true, mesh)
    assert not wrong, f"{len(wrong)} contact normals point out of the mesh: {wrong[:10]}"


@pytest.mark.slow
@pytest.mark.parametrize("move", ["+1 ulp", "-1 ulp", "motion 0", "motion 1", "motion 2"])
@THERMOS_CREASE
def test_thermos_contact_normals_survive_a_last_bit_and_rigid_motions(move, tmp_path):
    """The contact-normal test on the thermos's cloud moved by one unit in the last place, and
    on the thermos mesh turned about the vertical (it still stands on the table) and shifted
    before it is sampled (a rigid motion of the input file: the same surface, other rounding).
    A fix of the crease normals must pass every one of these, not only the cloud as sampled,
    whose outcome turns on the last bit (docs/limits.md, "Normals in creases";
    ``benchmarks/bench_crease_contacts.py`` prints the same figures)."""
    import trimesh

    path = OBJECTS_DIR / "thermos.obj"
    if move.endswith("ulp"):
        bare, true = _bare_demo_cloud(path)
        pts = np.nextafter(np.asarray(bare.points), np.inf if move[0] == "+" else -np.inf)
        mesh = trimesh.load(path, force="mesh", process=True)
    else:
        rng = np.random.default_rng(int(move.split()[1]))
        T = np.eye(4)
        T[:3, :3] = Rotation.from_euler("z", rng.uniform(0.0, 2.0 * np.pi)).as_matrix()
        T[:3, 3] = rng.uniform(-0.5, 0.5, size=3)
        moved = trimesh.load(path, force="mesh", process=True)
        moved.apply_transform(T)
        path = tmp_path / "thermos_moved.obj"
        moved.export(path)
        bare, true = _bare_demo_cloud(path)
        pts = np.asarray(bare.points)
        mesh = trimesh.load(path, force="mesh", process=True)
    wrong = _wrong_contacts(pts, true, mesh)
    assert not wrong, f"{len(wrong)} contact normals point out of the mesh: {wrong[:10]}"


@pytest.mark.slow
@pytest.mark.parametrize("name", ["thermos", "mug_handle", "bowl"])
def test_contact_normals_at_crests_lie_nearer_the_true_mesh_than_the_clouds(name):
    """At a crest point (an edge, a rolled rim, a notch: flat at no scale) a cloud without
    normals has only the crest rule's direction; a contact there takes the mean of it and the
    direction in which the touching link pushes the point. Against the true mesh's outward
    normal of the face each point was sampled on: those contact normals lie nearer it than
    the cloud's normals at the same points (median cosine), and no more of them point out of
    the object. Points on faces inside the solid (the thermos's ring sits on its body) have no
    outward normal and are left out."""
    import trimesh

    from pregrasp_core.pipeline import run_pipeline

    path = OBJECTS_DIR / f"{name}.obj"
    bare, true = _bare_demo_cloud(path)
    mesh = trimesh.load(path, force="mesh", process=True)
    res = run_pipeline(bare, hand=_hand(), until="grasps")
    assert res.grasps is not None and res.crest is not None and res.normals is not None
    kept = [res.grasps.grasps[i] for i in res.grasps.ranking]
    at = [c for g in kept for c in g.contacts if res.crest[c.point_index]]
    assert len(at) > 100  # fingers close on rims and edges
    pid = np.array([c.point_index for c in at])
    pts = np.asarray(bare.points)
    ext = _exterior(mesh, pts[pid], true[pid])
    out = -true[pid[ext]]  # the true direction into the object
    ours = np.einsum("ij,ij->i", np.array([c.normal for c in at])[ext], out)
    cloud = np.einsum("ij,ij->i", -res.normals[pid[ext]], out)
    assert np.allclose(np.linalg.norm([c.normal for c in at], axis=1), 1.0)
    assert np.median(ours) > np.median(cloud) + 0.02, (np.median(ours), np.median(cloud))
    assert np.sum(ours <= 0.0) <= np.sum(cloud <= 0.0)


def test_grid_neighbours_equal_a_kd_tree():
    """The compiled grid search gives the k-d tree's exact neighbours, also for far outliers
    (handed to the tree) and duplicated points (the point itself stays first)."""
    from scipy.spatial import cKDTree

    from pregrasp_core.normals import nearest_neighbours

    pts, _ = _torus(5000, seed=3)
    pts = np.r_[pts, [[2.0, 0.0, 0.0], [-3.0, 1.0, 0.5]], pts[:50]]  # outliers, duplicates
    dist, idx = nearest_neighbours(pts, 24)
    d_ref, i_ref = cKDTree(pts).query(pts, k=25)  # one more: ties at the 24th
    assert np.allclose(dist, d_ref[:, :24], atol=1e-15)
    assert np.all(idx[:, 0] == np.arange(len(pts)))
    plain = np.all(np.diff(d_ref, axis=1) > 0, axis=1)  # no tie: the same neighbours, in order
    assert plain.mean() > 0.7
    assert np.array_equal(idx[plain], i_ref[plain, :24])


def test_neighbours_of_a_cloud_with_a_far_clump_and_many_duplicates():
    """A cloud whose grid the far outliers would make coarse (one crowded cell), and a clump of
    40 copies of one point: still the exact neighbours, the point itself first."""
    from scipy.spatial import cKDTree

    from pregrasp_core.normals import nearest_neighbours

    pts, _ = _sphere(3000)
    pts = np.r_[pts, [[500.0, 0.0, 0.0], [0.0, -800.0, 3.0]], np.tile(pts[:1], (40, 1))]
    dist, idx = nearest_neighbours(pts, 16)
    d_ref, _ = cKDTree(pts).query(pts, k=16)
    assert np.allclose(dist, d_ref, atol=1e-12)
    assert np.all(idx[:, 0] == np.arange(len(pts)))
    assert np.allclose(np.linalg.norm(pts[idx] - pts[:, None], axis=2), dist, atol=1e-12)


def test_compiled_pca_equals_numpy_eigh():
    """The closed-form 3x3 eigen-solution at one scale equals numpy's eigh (normal up to sign,
    surface variation), on a noisy sphere where every neighbourhood is a different matrix."""
    from scipy.spatial import cKDTree

    from pregrasp_core import normal_kernels

    rng = np.random.default_rng(5)
    pts, _ = _sphere(3000)
    pts = pts + rng.normal(scale=1e-3, size=pts.shape)
    _, nbr = cKDTree(pts).query(pts, k=16)
    nb = pts[nbr] - pts[nbr].mean(axis=1, keepdims=True)
    evals, evecs = np.linalg.eigh(np.einsum("nki,nkj->nij", nb, nb))
    normals, variation = normal_kernels.pca_scales(pts, nbr, np.array([16]), 0.0)
    assert np.allclose(np.abs(np.einsum("ij,ij->i", normals, evecs[:, :, 0])), 1.0, atol=1e-8)
    assert np.allclose(variation, evals[:, 0] / evals.sum(axis=1), atol=1e-10)


def test_normals_do_not_depend_on_the_threads():
    """A cloud without normals (the default object, sampled without them) gets the same normals,
    to the bit, on 1, 2 and 3 threads (the kernels' rows and the visibility's groups of views
    are summed in a fixed order), and the same neighbours as a k-d tree; the threads are gone
    when it returns."""
    from scipy.spatial import cKDTree

    from pregrasp_core.normals import nearest_neighbours
    from pregrasp_core.paths import DEFAULT_OBJECT

    bare, true = _bare_demo_cloud(DEFAULT_OBJECT)
    pts = np.asarray(bare.points)
    alive = threading.active_count()
    runs = [estimate_normals(pts, NormalParams(), threads=t) for t in (1, 2, 3)]
    assert threading.active_count() == alive  # no thread left running (the planner forks)
    for cn in runs[1:]:
        assert np.array_equal(cn.normals, runs[0].normals)
        assert np.array_equal(cn.curvature, runs[0].curvature)
    assert np.mean(np.einsum("ij,ij->i", runs[0].normals, true) > 0) > 0.99
    d1, i1 = nearest_neighbours(pts, 24, threads=1)
    d2, i2 = nearest_neighbours(pts, 24, threads=2)
    assert np.array_equal(d1, d2) and np.array_equal(i1, i2)
    d_ref, i_ref = cKDTree(pts).query(pts, k=24)
    assert np.allclose(d1, d_ref, atol=1e-15)
    assert np.array_equal(i1[:, 0], np.arange(len(pts)))


@pytest.mark.parametrize("orient", ["reference", "viewpoint"])
def test_plain_pca_normals_do_not_depend_on_the_threads(orient):
    """The rules with a sign given (the mesh's normals, a camera) compute their PCA in row
    chunks on threads: the same bits as one call of the compiled PCA over the rows of one query
    of scipy's k-d tree, on 1, 2 and 3 threads; the vectors those of numpy's ``eigh`` (LAPACK)
    of the centred covariance, the surface variation its eigenvalues'; the signs from the
    mesh's normals (or facing the camera), and no thread left running."""
    from scipy.spatial import cKDTree

    from pregrasp_core import normal_kernels as nk
    from pregrasp_core.io import load_point_cloud
    from pregrasp_core.paths import DEFAULT_OBJECT

    cloud = load_point_cloud(DEFAULT_OBJECT, n_points=6000, seed=3)
    pts, ref = np.asarray(cloud.points), np.asarray(cloud.normals)
    eye = np.array([0.4, -0.3, 0.5])
    params = NormalParams(orient=orient, viewpoint=tuple(eye) if orient == "viewpoint" else None)
    _, nbr = cKDTree(pts).query(pts, k=params.k)
    plain, variation = nk.pca_scales(pts, nbr, np.array([params.k]), 0.0)
    # the reference: LAPACK's eigenvectors of the centred covariance, batched
    nb = pts[nbr]
    centred = nb - nb.mean(axis=1, keepdims=True)
    evals, evecs = np.linalg.eigh(np.einsum("nki,nkj->nij", centred, centred) / params.k)
    # (at 6,000 points half the neighbourhoods span both walls of the mug: eigenvalues within a
    # factor of 2, the vectors still equal to about 1e-15)
    cos = np.abs(np.einsum("ij,ij->i", plain, evecs[:, :, 0]))
    assert np.all(cos > 1.0 - 1e-12)
    assert np.allclose(variation, evals[:, 0].clip(0.0) / evals.sum(axis=1), rtol=0, atol=1e-12)
    alive = threading.active_count()
    runs = [estimate_normals(pts, params, reference=ref, threads=t) for t in (1, 2, 3)]
    assert threading.active_count() == alive
    toward = ref if orient == "reference" else eye - pts
    for cn in runs:
        assert cn.orient == orient
        assert np.array_equal(np.abs(cn.normals), np.abs(plain))
        assert np.array_equal(cn.curvature, variation)
        assert np.all(np.einsum("ij,ij->i", cn.normals, toward) >= 0.0)
        assert np.array_equal(cn.normals, runs[0].normals)


@pytest.mark.parametrize("shape", [(40, 40, 2), (12, 12, 4)])
def test_grid_neighbours_break_ties_by_index(shape):
    """Points on a lattice (many equal distances): each row is the point itself, then the
    others by (distance, index), exactly as a sort of all distances gives it, for any number of
    threads and rows asked in any order; on a thin sheet the grid settles every row, on the
    block its cells (sized for a surface) are too small and the rows go to the k-d tree."""
    from pregrasp_core.normals import nearest_neighbours

    g = np.arange(max(shape), dtype=np.float64) * 2.0**-10  # exact differences: exact ties
    axes = [g[:s] for s in shape]
    pts = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    pts = np.r_[pts, pts[:5]]  # duplicates: the point itself still comes first
    d2 = ((pts[:, None, :] - pts[None, :, :]) ** 2).sum(axis=2)
    k = 20
    for threads in (1, 2):
        rows = np.random.default_rng(1).permutation(len(pts))
        dist, idx = nearest_neighbours(pts, k, rows, threads=threads)
        for r, i in enumerate(rows):
            others = np.flatnonzero(np.arange(len(pts)) != i)
            order = others[np.lexsort((others, d2[i, others]))][: k - 1]
            assert idx[r, 0] == i
            assert np.array_equal(idx[r, 1:], order)
            assert np.allclose(dist[r], np.sqrt(np.r_[0.0, d2[i, order]]), atol=1e-15)
