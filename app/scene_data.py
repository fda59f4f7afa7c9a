"""Pure helpers of the scene: colours, box edges, face quads, ghost filters, contact cones and the
animation pose, computed from the core's results as plain numpy arrays.

Nothing here touches viser's scene or holds state, so each helper is tested on its own (see
``tests/app/test_controller.py``); :mod:`app.scene` draws what these return.
"""

from __future__ import annotations

import colorsys
from dataclasses import dataclass
from typing import Any

import numpy as np
import viser.transforms as vtf

from .state import ALL, AppState

FACE_OFFSET = 1e-3
"""Face-mask quads float this far (metres) outside their face so they do not z-fight."""
CONE_HEIGHT = 0.015
"""Drawn length (metres) of a friction cone's axis."""


def node_color(i: int) -> tuple[int, int, int]:
    """A distinct, stable RGB colour (0-255) for node ``i`` (golden-ratio hues)."""
    h = (0.13 + 0.618033988749895 * int(i)) % 1.0
    r, g, b = colorsys.hsv_to_rgb(h, 0.65, 0.95)
    return (int(r * 255), int(g * 255), int(b * 255))


def node_colors(ids: np.ndarray) -> np.ndarray:
    """(K, 3) uint8 colours of node ids ``ids`` (K,); id -1 gives grey."""
    ids = np.asarray(ids, dtype=np.int64)
    out = np.full((len(ids), 3), 150, dtype=np.uint8)
    for k, i in enumerate(ids.tolist()):  # loop over nodes only (small set)
        if i >= 0:
            out[k] = node_color(i)
    return out


def wxyz_from_matrices(R: np.ndarray) -> np.ndarray:
    """(B, 4) wxyz quaternions of rotation matrices ``R`` (B, 3, 3)."""
    R = np.asarray(R, dtype=np.float64)
    if R.ndim != 3 or R.shape[1:] != (3, 3):
        raise ValueError(f"R must have shape (B, 3, 3), got {R.shape}")
    if len(R) == 0:
        return np.zeros((0, 4))
    return np.asarray(vtf.SO3.from_matrix(R).wxyz, dtype=np.float64).reshape(-1, 4)


def box_edge_segments(boxes: list[Any]) -> np.ndarray:
    """(12 K, 2, 3) world segments of the 12 edges of each ``OrientedBox`` in ``boxes``."""
    if not boxes:
        return np.zeros((0, 2, 3))
    corners = np.stack([b.corners() for b in boxes])  # (K, 8, 3); bit k of corner = axis k sign
    pairs = np.array(
        [(a, a | (1 << ax)) for ax in range(3) for a in range(8) if not a & (1 << ax)]
    )  # (12, 2): corner pairs differing in one axis bit
    return corners[:, pairs].reshape(-1, 2, 3)


def face_quads(boxes: list[Any], offset: float = FACE_OFFSET) -> tuple[np.ndarray, ...]:
    """Pose and size of the 6 face quads of each box, in the face numbering of ``facemask``.

    Returns ``(positions (6K, 3), R (6K, 3, 3), sizes (6K, 3))`` for a unit quad lying in its
    local xy plane with +z along the face's outward normal; face ``f`` of box ``k`` is row
    ``6 k + f``. Face ``f`` has outward normal ``sign * axis`` with axis ``f // 2`` and sign
    ``+`` for even ``f`` (faces 0..5 = +x, -x, +y, -y, +z, -z of the box frame).
    """
    pos, rots, sizes = [], [], []
    for b in boxes:  # loop over boxes (small set)
        R, he = b.rotation, b.half_extents
        for f in range(6):
            ax, sign = f // 2, (1.0 if f % 2 == 0 else -1.0)
            u, v = [a for a in range(3) if a != ax]
            n = sign * R[:, ax]
            x = R[:, u]
            y = np.cross(n, x)
            pos.append(b.center + n * (he[ax] + offset))
            rots.append(np.stack([x, y, n], axis=1))
            sizes.append((2 * he[u], 2 * he[v], 1.0))
    if not pos:
        return np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros((0, 3))
    return np.array(pos), np.array(rots), np.array(sizes)


@dataclass(frozen=True)
class FaceLayers:
    """What the face-mask layer draws for the shown boxes (computed from the core's masks)."""

    free: np.ndarray
    """(F, 4, 4) poses of unit quads of free faces, scaled by ``free_sizes``."""
    free_sizes: np.ndarray
    """(F, 3) per-axis scale of the free quads."""
    blocked: np.ndarray
    """(B, 4, 4) poses of the blocked faces."""
    blocked_sizes: np.ndarray
    """(B, 3) per-axis scale of the blocked quads."""
    subface_segments: np.ndarray
    """(S, 2, 3) outline segments of the usable sub-faces."""


GHOST_RGB = {
    "cylindrical": (80, 160, 255),
    "spherical": (255, 140, 60),
    "three_finger_tip": (170, 110, 255),
    "two_finger_tip": (60, 220, 200),
}
"""Ghost colour per grasp type."""


FACE_SHADE = np.array([1.0, 0.55, 0.85, 0.4, 0.7, 0.25])
"""Brightness factor of the ghosts sampled from face 0..5 (+x, -x, +y, -y, +z, -z)."""


GHOST_THICKNESS = 2.5
"""Line width (screen pixels) of the ghosts' outlines."""


def _box_corner_pairs() -> np.ndarray:
    """(12, 2) corner pairs of a box's edges (bit k of a corner's index = the sign of axis k)."""
    return np.array([(a, a | (1 << ax)) for ax in range(3) for a in range(8) if not a & (1 << ax)])


def hand_ghost_segments(hand: Any, q: np.ndarray) -> np.ndarray:
    """(12 + L - 1, 2, 3) segments of one ghost in the hand frame at joints ``q`` (J,): the 12
    edges of the palm's collision box (its inner face at z = 0, the approach along +z), then,
    for each finger link in link order, the axis of its collision box along its longest side
    (base to tip): the finger chains, thumb on -y and the two spreading fingers on +y."""
    Tb = np.asarray(hand.box_poses(np.asarray(q, dtype=np.float64)), dtype=np.float64)
    half = np.asarray(hand.link_box_half, dtype=np.float64)  # (L, 3)
    bits = (np.arange(8)[:, None] >> np.arange(3)[None, :]) & 1  # (8, 3)
    corners = Tb[0, :3, :3] @ ((2 * bits - 1) * half[0]).T + Tb[0, :3, 3:4]  # (3, 8)
    palm = corners.T[_box_corner_pairs()]  # (12, 2, 3)
    ax = np.argmax(half[1:], axis=1)  # (L - 1,) the long axis of each finger link's box
    along = Tb[1:, :3, :3][np.arange(len(ax)), :, ax] * half[1:][np.arange(len(ax)), ax][:, None]
    mid = Tb[1:, :3, 3]
    fingers = np.stack([mid - along, mid + along], axis=1)  # (L - 1, 2, 3)
    return np.concatenate([palm, fingers])


def ghost_segments(local: np.ndarray, T_world_hand: np.ndarray) -> np.ndarray:
    """(K S, 2, 3) world segments of K ghosts: the hand-frame segments ``local`` (S, 2, 3)
    moved by each pose of ``T_world_hand`` (K, 4, 4); ghost k is rows ``k S .. (k + 1) S``."""
    T = np.asarray(T_world_hand, dtype=np.float64).reshape(-1, 4, 4)
    p = np.einsum("kij,sej->ksei", T[:, :3, :3], np.asarray(local, dtype=np.float64))
    return (p + T[:, None, None, :3, 3]).reshape(-1, 2, 3)


def ghost_colors(grasp_type: str, faces: np.ndarray) -> np.ndarray:
    """(K, 3) uint8 ghost colours: the grasp type's hue, shaded by the face of origin, so that
    neighbouring hands from different faces stay apart in a dense pool."""
    base = np.asarray(GHOST_RGB.get(grasp_type, (200, 200, 200)), dtype=np.float64)
    shade = FACE_SHADE[np.clip(np.asarray(faces, dtype=np.int64), 0, 5)]  # (K,)
    return np.clip(base[None] * (0.45 + 0.55 * shade[:, None]), 0, 255).astype(np.uint8)


def attr_or_none(obj: Any, name: str) -> Any:
    """``obj.<name>``, or ``None`` when ``obj`` is ``None`` or has no such attribute."""
    return None if obj is None else getattr(obj, name, None)


def friction_coefficient(params: Any, default: float = 0.5) -> float:
    """The friction coefficient of the quality measure (``params.planner.quality.mu``)."""
    q = getattr(getattr(params, "planner", None), "quality", None)
    return float(getattr(q, "mu", default))


def pool_types(pool: Any) -> np.ndarray:
    """(P,) str array of the pool's grasp types (``PreGraspPool.grasp_type`` is one)."""
    return np.asarray(pool.grasp_type).astype(str)


def ghost_selection(pool: Any, grasp_type: str, node: int | None) -> np.ndarray:
    """(P,) bool: the pre-grasps of ``pool`` passing the grasp-type and node filters."""
    types = pool_types(pool)
    keep = np.ones(len(types), dtype=bool)
    if grasp_type != ALL:
        keep &= types == str(grasp_type)
    if node is not None:
        keep &= np.asarray(pool.node) == int(node)
    return keep


def ranked_grasps(result: Any) -> list[Any]:
    """The successful grasps of a pipeline result, best first (empty when not planned)."""
    grasps = attr_or_none(result, "grasps")
    if grasps is None:
        return []
    ranked = getattr(grasps, "ranked", None)
    if ranked is not None:
        return list(ranked() if callable(ranked) else ranked)
    ok = [g for g in grasps if getattr(g, "rank", None) is not None]
    return sorted(ok, key=lambda g: g.rank)


def selected_grasp(state: AppState) -> Any:
    """The grasp chosen in the ranked table, or ``None``."""
    k = state.view.selected_grasp
    if k is None or state.result is None:
        return None
    ranked = ranked_grasps(state.result)
    return ranked[k] if 0 <= k < len(ranked) else None


def contact_arrays(grasp: Any) -> tuple[np.ndarray, np.ndarray]:
    """(C, 3) contact points and (C, 3) unit normals of a grasp (world frame)."""
    cs = list(getattr(grasp, "contacts", ()) or ())
    if not cs:
        return np.zeros((0, 3)), np.zeros((0, 3))
    pts = np.array([np.asarray(c.point, dtype=np.float64) for c in cs])
    nrm = np.array([np.asarray(c.normal, dtype=np.float64) for c in cs])
    nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-12)
    return pts, nrm


def contact_tangents(grasp: Any) -> np.ndarray | None:
    """(C, 3) first friction-cone edge directions of a grasp's contacts (``Contact.tangent``,
    the directions the quality measure scored with), or ``None`` when a contact has none."""
    cs = list(getattr(grasp, "contacts", ()) or ())
    ts = [getattr(c, "tangent", None) for c in cs]
    if not cs or any(t is None for t in ts):
        return None
    return np.array([np.asarray(t, dtype=np.float64).reshape(3) for t in ts])


def cone_edge_count(params: Any, default: int = 8) -> int:
    """The number of edges of the linearised friction cones scored
    (``params.planner.quality.n_edges``)."""
    q = getattr(getattr(params, "planner", None), "quality", None)
    return int(getattr(q, "n_edges", default))


def friction_cone_segments(
    points: np.ndarray,
    normals: np.ndarray,
    mu: float,
    m: int = 8,
    height: float = CONE_HEIGHT,
    tangents: np.ndarray | None = None,
) -> np.ndarray:
    """(C (m + 1), 2, 3) line segments drawing the linearised friction cone of each contact.

    The ``m`` edges are the quality measure's own (``pregrasp_core.quality.friction_cone_edges``
    with the contacts' ``tangents``: the first edge lies along the tangent, as scored), each
    scaled to ``height``, plus the axis; the apex is at the contact.
    """
    from pregrasp_core.quality import friction_cone_edges

    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    n = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    if len(p) == 0:
        return np.zeros((0, 2, 3))
    n = n / np.linalg.norm(n, axis=1, keepdims=True)
    edges = friction_cone_edges(n, float(mu), int(m), tangents)  # (C, m, 3), normal part 1
    edges = np.concatenate([edges, n[:, None]], axis=1)  # (C, m + 1, 3)
    edges *= height / np.linalg.norm(edges, axis=2, keepdims=True)
    starts = np.broadcast_to(p[:, None], edges.shape)
    # the cone is drawn outside the object: the normal points into it, so draw along -n
    return np.stack([starts, starts - edges], axis=2).reshape(-1, 2, 3)


def pregrasp_of(state: AppState, grasp: Any) -> Any:
    """The pool's pre-grasp that ``grasp`` was planned from, or ``None``."""
    pool = attr_or_none(state.result, "pool")
    i = getattr(grasp, "pregrasp", None)
    if i is None:
        i = getattr(grasp, "pregrasp_index", None)
    if pool is None or i is None:
        return None
    return pool[int(i)]


def animation_pose(grasp: Any, pregrasp: Any, t: float) -> tuple[np.ndarray, np.ndarray]:
    """Hand pose ``T_world_hand`` (4, 4) and joints ``q`` (J,) at animation phase ``t`` in [0, 1].

    [0, 0.5]: the open hand (preshape) moves along its approach from the pre-grasp pose to the
    grasp pose; [0.5, 1]: the joints go linearly from the preshape to the closed configuration.
    """
    t = float(np.clip(t, 0.0, 1.0))
    T_end = np.asarray(grasp.T_world_hand, dtype=np.float64)
    q_end = np.asarray(grasp.q, dtype=np.float64)
    if pregrasp is None:
        return T_end, q_end
    T_start = np.asarray(pregrasp.T_world_hand, dtype=np.float64)
    q_start = np.asarray(pregrasp.q, dtype=np.float64)
    if t <= 0.5:
        s = t / 0.5
        T = T_end.copy()
        T[:3, 3] = (1 - s) * T_start[:3, 3] + s * T_end[:3, 3]
        T[:3, :3] = T_start[:3, :3] if s < 0.5 else T_end[:3, :3]
        return T, q_start
    s = (t - 0.5) / 0.5
    return T_end, (1 - s) * q_start + s * q_end


def face_layers(state: AppState) -> FaceLayers | None:
    """The face quads (free/blocked) and usable sub-face outlines of the shown boxes."""
    masks = attr_or_none(state.result, "masks")
    if masks is None:
        return None
    tree = state.tree
    shown = state.shown_nodes()
    boxes = [tree.node(i).box for i in shown]
    pos, R, size = face_quads(boxes)
    T = np.zeros((len(pos), 4, 4))
    T[:, :3, :3], T[:, :3, 3], T[:, 3, 3] = R, pos, 1.0
    blocked = (
        np.concatenate([blocked_faces(masks, i) for i in shown])
        if shown
        else np.zeros(0, dtype=bool)
    )
    return FaceLayers(
        free=T[~blocked],
        free_sizes=size[~blocked],
        blocked=T[blocked],
        blocked_sizes=size[blocked],
        subface_segments=subface_segments(state, shown),
    )


def blocked_faces(masks: Any, node: int) -> np.ndarray:
    """(6,) bool: which faces of ``node`` are blocked (``FaceMasks.blocked[node]``)."""
    return np.asarray(masks.blocked[node], dtype=bool).reshape(6)


def mask_matrix(masks: Any, node: int) -> np.ndarray:
    """(6, 5) int face mask of ``node`` (row f = [f, l, d, r, u], 1 = blocked)."""
    return np.asarray(masks.mask(node)).reshape(6, 5)


def subface_segments(state: AppState, shown: list[int], shrink: float = 0.85) -> np.ndarray:
    """(S, 2, 3) outlines of the usable sub-faces of the shown nodes for their grasp types,
    under the rule the masks were computed with (``FaceMasks.usable``).

    Each usable cell is drawn shrunk by ``shrink`` about its centre (so neighbouring cells stay
    apart) and lifted off its face by twice :data:`FACE_OFFSET`.
    """
    from pregrasp_core.facemask import subface_rectangles, usable_subfaces

    res = state.result
    shapes = attr_or_none(res, "shapes")
    if shapes is None:
        return np.zeros((0, 2, 3))
    rects = []
    for i in shown:  # loop over the shown nodes (small set)
        node = state.tree.node(i)
        gt = shapes[i].grasp_type
        usable = (  # the rule the pool was sampled with (whole faces or covered cells)
            res.masks.usable(i, gt)
            if hasattr(res.masks, "usable")
            else usable_subfaces(blocked_faces(res.masks, i), gt)
        )
        for f, r in enumerate(subface_rectangles(node.box, gt)):  # 6 faces
            r = r[usable[f]]  # (S, 4, 3) corners of the usable cells
            if len(r):
                n = node.box.rotation @ np.eye(3)[f // 2] * (1.0 if f % 2 == 0 else -1.0)
                c = r.mean(axis=1, keepdims=True)
                rects.append(c + shrink * (r - c) + 2 * FACE_OFFSET * n)
    if not rects:
        return np.zeros((0, 2, 3))
    r = np.concatenate(rects)  # (S, 4, 3)
    return np.stack([r, np.roll(r, -1, axis=1)], axis=2).reshape(-1, 2, 3)


# ---------------------------------------------------------------------- depth-camera scenes
ASSUMED_RGB = (55, 55, 70)
"""Colour of the points assumed by the completion of a single view (dark slate; the parts'
colours are all bright, :func:`node_color`): the unseen back."""
TABLE_RGB = (200, 200, 200)
"""Colour of the scene's table points (light grey), drawn around the object."""
OTHER_RGB = (175, 140, 100)
"""Colour of the scene's points that are neither the table nor the kept object (brown)."""
FLYING_RGB = (235, 60, 150)
"""Colour of a scene's flying pixels, dropped by ``--flying-pixels`` (magenta: neither a part's
hue nor the table's or the other objects')."""
HIDDEN_RGB = (185, 225, 255)
"""Colour of the space hidden behind a single depth view, drawn when it was planned with
``--occluded occupied`` (pale blue: paler than every part's colour, bluer than the table's
grey)."""
HIDDEN_POINTS = 5_000
"""Most points of the hidden-space layer: the centres of the hidden region's boundary voxels,
an even subsample past this. The 45 generated views of docs/partial-views.md have 2,701-10,211
boundary voxels (median 4,827), the depth demo 6,600, the thermos, frypan and teddy views
9,604-46,233 (median 21,564). On the depth demo the layer costs software WebGL 55-70 ms a frame
at 2,500-6,600 points (docs/benchmarks.md, "Session 10: the hidden-space layer"; the first
screen about 600 ms): the count matters little up to there, the cap bounds the large views;
a subsample still shows the region, its points a few millimetres further apart."""
MIN_PICK_CLUSTER = 10
"""Clusters of fewer points (the table's noise tail, specks) are not offered to a click."""
PICK_ANGLE = 0.02
"""Radians (about 1.1 degrees): a click picks a point seen at most this far from its ray."""

PICK_DEPTH = 0.02
"""Metres: the points a click ray meets within this depth of the nearest one are its front
surface (an object behind it is never picked through it)."""

UNITS: dict[str, float | None] = {"auto": None, "m": 1.0, "cm": 0.01, "mm": 0.001}
"""The scale field's units: the factor to metres (``auto`` = the loader's millimetre rule)."""


def cloud_point_colors(part_colors: np.ndarray, assumed: np.ndarray | None) -> np.ndarray:
    """(N, 3) uint8: the points in their part's colour, the assumed ones in :data:`ASSUMED_RGB`."""
    out = np.array(part_colors, dtype=np.uint8, copy=True)
    if assumed is not None:
        out[np.asarray(assumed, dtype=bool)] = ASSUMED_RGB
    return out


def assumed_contacts(grasp: Any, cloud: Any) -> np.ndarray:
    """(C,) bool: which contacts of ``grasp`` touch a point assumed by the completion
    (``Contact.point_index`` into the cloud's ``assumed`` mask); all False for a complete cloud."""
    cs = list(getattr(grasp, "contacts", ()) or ())
    mask = getattr(cloud, "assumed", None)
    if mask is None or not cs:
        return np.zeros(len(cs), dtype=bool)
    mask = np.asarray(mask, dtype=bool)
    idx = np.array([int(c.point_index) for c in cs], dtype=np.int64)
    ok = (idx >= 0) & (idx < len(mask))
    return np.where(ok, mask[np.clip(idx, 0, len(mask) - 1)], False)


def scene_backdrop(sensor: Any, max_points: int = 30000) -> tuple[np.ndarray, np.ndarray]:
    """The scene around a depth-camera object: ``(points (K, 3), colours (K, 3) uint8)`` of the
    scene's points that are not the kept object (the table grey, the rest brown) and of its
    flying pixels when ``--flying-pixels`` dropped them (magenta, every one up to half of
    ``max_points``), an even subsample of at most ``max_points`` in all; empty arrays when there
    is no scene."""
    seg = attr_or_none(sensor, "segmentation")
    if seg is None:
        return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.uint8)
    fly = attr_or_none(sensor, "flying")
    fly = np.zeros((0, 3)) if fly is None else np.asarray(fly, dtype=np.float64)
    if len(fly) > max_points // 2:
        fly = fly[np.linspace(0, len(fly) - 1, max_points // 2).astype(np.int64)]
    idx = np.flatnonzero(~np.asarray(seg.object_mask, dtype=bool))
    room = max_points - len(fly)
    if len(idx) > room:
        idx = idx[np.linspace(0, len(idx) - 1, room).astype(np.int64)]
    table = np.asarray(seg.table_mask, dtype=bool)[idx]
    cols = np.empty((len(idx) + len(fly), 3), dtype=np.uint8)
    cols[: len(idx)] = np.where(table[:, None], TABLE_RGB, OTHER_RGB)
    cols[len(idx) :] = FLYING_RGB
    return np.concatenate([np.asarray(seg.points, dtype=np.float64)[idx], fly]), cols


def neighbour_hidden_points(cloud: Any) -> np.ndarray:
    """(K, 3) the space hidden behind the other objects of a single view's scene, which the
    pool and the planner keep the hand out of (the last ``scene.n_obstacles_hidden`` points of
    ``cloud.obstacles``: ``docs/limits.md``, "The rest of the scene as obstacles"); empty when
    there is none."""
    obstacles = attr_or_none(cloud, "obstacles")
    info = attr_or_none(cloud, "info") or {}
    n = int((info.get("scene") or {}).get("n_obstacles_hidden", 0) or 0)
    if obstacles is None or n <= 0:
        return np.zeros((0, 3))
    return np.asarray(obstacles, dtype=np.float64)[-n:]


def hidden_space_points(occupied: Any, max_points: int = HIDDEN_POINTS) -> np.ndarray:
    """(K, 3) what the hidden-space layer draws of an ``OccupiedSpace``: the centres of the
    hidden region's boundary voxels (hidden voxels with a face neighbour that is not hidden,
    the grid's border counting as not hidden; every one of them is an obstacle point of the
    pool and the planner), an even subsample of at most ``max_points`` in the grid's order;
    empty for ``None``."""
    if occupied is None:
        return np.zeros((0, 3))
    from scipy import ndimage

    grid = np.asarray(occupied.grid, dtype=bool)
    ijk = np.argwhere(grid & ~ndimage.binary_erosion(grid, border_value=0))
    if len(ijk) > max_points:
        ijk = ijk[np.linspace(0, len(ijk) - 1, max(int(max_points), 0)).astype(np.int64)]
    origin = np.asarray(occupied.origin, dtype=np.float64)
    frame = np.asarray(occupied.frame, dtype=np.float64)
    return origin + (ijk * float(occupied.voxel)) @ frame.T


def ray_pick(
    points: np.ndarray,
    origin: Any,
    direction: Any,
    candidates: np.ndarray | None = None,
    max_angle: float = PICK_ANGLE,
    depth: float = PICK_DEPTH,
) -> int | None:
    """The index of the point a click ray hits, or ``None`` when no point is near the ray.

    Among the ``candidates`` (bool mask; default all) seen within ``max_angle`` radians of the
    ray from ``origin`` along ``direction``, the front surface is the nearest one's depth plus
    ``depth`` metres; of the points on it, the one seen closest to the ray (the point under the
    cursor, not one of an object behind it).
    """
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    o = np.asarray(origin, dtype=np.float64).reshape(3)
    d = np.asarray(direction, dtype=np.float64).reshape(3)
    norm = float(np.linalg.norm(d))
    if not (np.all(np.isfinite(o)) and np.isfinite(norm) and norm > 0.0) or len(p) == 0:
        return None
    d = d / norm
    rel = p - o
    t = rel @ d  # (N,) depth along the ray
    perp = np.linalg.norm(rel - t[:, None] * d, axis=1)
    ok = (t > 0.0) & (perp <= np.tan(max_angle) * np.maximum(t, 0.0))
    if candidates is not None:
        ok &= np.asarray(candidates, dtype=bool)
    if not np.any(ok):
        return None
    hits = np.flatnonzero(ok)
    front = hits[t[hits] <= t[hits].min() + depth]
    return int(front[np.argmin(perp[front] / t[front])])


def pickable(sensor: Any) -> np.ndarray | None:
    """(N,) bool over the scene's points that a click may pick: those of clusters above the
    table of at least :data:`MIN_PICK_CLUSTER` points; ``None`` when there is no scene."""
    seg = attr_or_none(sensor, "segmentation")
    if seg is None:
        return None
    labels = np.asarray(seg.cluster_labels, dtype=np.int64)
    counts = np.bincount(labels[labels >= 0], minlength=1)
    big = np.zeros(len(labels), dtype=bool)
    big[labels >= 0] = counts[labels[labels >= 0]] >= MIN_PICK_CLUSTER
    return big


def kept_cluster(sensor: Any) -> tuple[int, int, int] | None:
    """``(label, its points, clusters found)`` of the cluster the scene's object was built on
    (clusters are numbered 0, 1, ... by decreasing size), or ``None`` without a scene."""
    seg = attr_or_none(sensor, "segmentation")
    if seg is None:
        return None
    labels = np.asarray(seg.cluster_labels, dtype=np.int64)
    mine = labels[np.asarray(seg.object_mask, dtype=bool) & (labels >= 0)]
    if len(mine) == 0:
        return None
    k = int(np.bincount(mine).argmax())
    return k, int(np.count_nonzero(labels == k)), int(labels.max()) + 1


def parse_scale(value: Any) -> float | None:
    """The scale field's value as a factor: a unit of :data:`UNITS` (``auto`` = ``None``) or a
    number; ``ValueError`` otherwise (the bounds are checked by the caller)."""
    text = str(value).strip().lower()
    if text in UNITS:
        return UNITS[text]
    if isinstance(value, bool):
        raise ValueError(f"scale must be a number or one of {list(UNITS)}, got {value!r}")
    try:
        return float(value)
    except (TypeError, ValueError):
        raise ValueError(f"scale must be a number or one of {list(UNITS)}, got {value!r}") from None


def unit_label(scale: float | None) -> str:
    """The unit the scale field shows for ``scale`` (``custom`` for another factor)."""
    for name, s in UNITS.items():
        if s == scale:
            return name
    return "custom"


def unit_fix(cloud: Any, scale: float | None) -> tuple[float, str] | None:
    """The one-click fix of the loader's unit hint, ``(scale, button label)``, or ``None``.

    With no scale given (``scale`` None) the loader either scaled a cloud it recognised as
    millimetres by 0.001 (``info["scale"]``): the fix reads it as metres; or left a cloud longer
    than ``MILLIMETRE_EXTENT`` as it was, with the hint that it looks like millimetres: the fix
    reads it as millimetres.
    """
    from pregrasp_core.io import MILLIMETRE_EXTENT

    if cloud is None or scale is not None:
        return None
    applied = float((getattr(cloud, "info", {}) or {}).get("scale", 1.0) or 1.0)
    if applied == 0.001:
        return 1.0, "read as metres (scale 1)"
    extent = float(np.max(np.ptp(np.asarray(cloud.points), axis=0)))
    if applied == 1.0 and extent > MILLIMETRE_EXTENT:
        return 0.001, "read as millimetres (scale 0.001)"
    return None
