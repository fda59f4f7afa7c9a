"""The scene renderer: draws an :class:`app.state.AppState` into viser's 3D scene.

It owns every scene handle, each under a fixed name (see :data:`NAMES`), and updates them inside
``server.atomic()`` so a browser never sees half an update. It redraws only what changed between
the state it drew last and the new one (compared by identity: the state's parts are immutable),
batches similar objects (all face quads of one kind in one batched mesh, all ghosts of one
preshape in one batched mesh, box edges and friction cones as line segments) and sends the point
cloud with ``precision="float32"``. It never computes anything the core computes.
"""

from __future__ import annotations

import colorsys
import logging
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import viser
import viser.transforms as vtf

from .state import ALL, AppState

logger = logging.getLogger(__name__)

NAMES = {
    "cloud": "/object/cloud",
    "boxes": "/boxes",
    "box_edges": "/box_edges",
    "faces_free": "/facemasks/free",
    "faces_blocked": "/facemasks/blocked",
    "subfaces": "/facemasks/subfaces",
    "ghosts": "/ghosts",
    "grasp": "/grasp",
    "hand": "/grasp/hand",
    "contacts": "/grasp/contacts",
    "cones": "/grasp/cones",
}
"""Fixed scene names of everything the renderer draws."""

FREE_RGB = (60, 200, 90)
"""Colour of free faces (green)."""
BLOCKED_RGB = (220, 60, 60)
"""Colour of blocked faces (red)."""
SUBFACE_RGB = (255, 255, 255)
"""Colour of the outlines of usable sub-faces (white)."""
CONTACT_RGB = (255, 210, 0)
"""Colour of contact points and friction cones (yellow)."""
DETAILED_GHOSTS = 40
"""Up to this many ghosts use the hand's visual mesh; beyond, its collision boxes."""
GHOST_OPACITY = 0.3
"""Opacity of the pre-grasp hand ghosts."""
BOX_OPACITY = 0.12
"""Opacity of unselected boxes (the selected one is drawn at 0.35)."""
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


_UNIT_QUAD_V = np.array([[-0.5, -0.5, 0.0], [0.5, -0.5, 0.0], [0.5, 0.5, 0.0], [-0.5, 0.5, 0.0]])
_UNIT_QUAD_F = np.array([[0, 1, 2], [0, 2, 3]], dtype=np.uint32)


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


class SceneRenderer:
    """Draws app states into ``server.scene``; owns every scene handle by a fixed name.

    ``on_box_click(node_id, client)`` is called when a browser clicks a box.
    """

    def __init__(
        self,
        server: viser.ViserServer,
        hand: Any = None,
        on_box_click: Callable[[int, Any], None] | None = None,
        max_ghosts: int = 3000,
    ) -> None:
        self.server = server
        self.hand = hand
        self.on_box_click = on_box_click
        self.max_ghosts = int(max_ghosts)
        self._last: AppState | None = None
        self._boxes: dict[int, Any] = {}  # node id -> BoxHandle
        self._handles: dict[str, Any] = {}  # fixed name -> handle
        self._ghost_meshes: dict[tuple, Any] = {}  # (preshape q, detailed) -> hand mesh
        self._urdf: Any = None
        self.n_ghosts_shown = 0
        """Number of ghost instances currently in the scene."""
        self.n_contacts_shown = 0
        """Number of contact points currently in the scene."""
        self.n_faces_shown = (0, 0)
        """(free, blocked) face quads currently in the scene."""
        server.scene.set_up_direction("+z")

    # ------------------------------------------------------------------ public API
    @property
    def rendered(self) -> AppState | None:
        """The state the scene last finished drawing (the controller publishes a state before
        it is drawn; a reader that needs the picture to match waits until this is that state)."""
        return self._last

    @property
    def n_boxes(self) -> int:
        """Number of box nodes the scene holds right now."""
        return len(self._boxes)

    @property
    def box_ids(self) -> list[int]:
        """Node ids of the boxes the scene holds, ascending."""
        return sorted(self._boxes)

    def handle(self, key: str) -> Any:
        """The handle drawn under ``NAMES[key]`` (or ``None`` when not drawn)."""
        return self._handles.get(key)

    def ghost_handles(self) -> list[Any]:
        """The batched-mesh handles of the ghosts now in the scene (one per preshape)."""
        return [h for k, h in sorted(self._handles.items()) if k.startswith("ghost:")]

    def render(self, state: AppState) -> None:
        """Bring the scene in line with ``state``, redrawing only the parts that changed."""
        last = self._last
        with self.server.atomic():
            if state.result is None:
                self._clear_all()
            else:
                res = state.result
                lres = None if last is None else last.result
                new_cloud = lres is None or lres.cloud is not res.cloud
                new_tree = new_cloud or lres.tree is not res.tree
                lv = None if last is None else last.view
                v = state.view
                level_changed = new_tree or last.shown_level != state.shown_level
                if new_cloud:
                    self._draw_cloud(state)
                elif level_changed:
                    self._recolor_cloud(state)
                if level_changed or lv.selected_node != v.selected_node:
                    self._draw_boxes(state)
                masks_changed = lres is None or _get(lres, "masks") is not _get(res, "masks")
                if level_changed or masks_changed or lv.show_face_masks != v.show_face_masks:
                    self._draw_faces(state)
                pool_changed = lres is None or _get(lres, "pool") is not _get(res, "pool")
                if (
                    pool_changed
                    or lv.show_ghosts != v.show_ghosts
                    or lv.ghost_type != v.ghost_type
                    or lv.ghost_node != v.ghost_node
                ):
                    self._draw_ghosts(state)
                grasps_changed = lres is None or _get(lres, "grasps") is not _get(res, "grasps")
                if grasps_changed or lv.selected_grasp != v.selected_grasp:
                    self._draw_grasp(state)
                    self._pose_hand(state)
                elif lv.anim_t != v.anim_t:
                    self._pose_hand(state)
        self._last = state

    # ------------------------------------------------------------------ layers
    def _clear_all(self) -> None:
        for h in list(self._boxes.values()):
            h.remove()
        self._boxes.clear()
        for key in list(self._handles):
            self._remove(key)
        self._hide_hand()

    def _remove(self, key: str) -> None:
        h = self._handles.pop(key, None)
        if h is not None:
            h.remove()

    def _draw_cloud(self, state: AppState) -> None:
        pts = np.asarray(state.cloud.points, dtype=np.float32)
        diag = float(np.linalg.norm(pts.max(axis=0) - pts.min(axis=0))) if len(pts) else 1.0
        self._handles["cloud"] = self.server.scene.add_point_cloud(
            NAMES["cloud"],
            points=pts,
            colors=self._cloud_colors(state),
            point_size=max(diag * 0.006, 1e-4),
            precision="float32",
            point_shape="rounded",
        )
        self._frame_object(np.asarray(state.cloud.points, dtype=np.float64))

    def _frame_object(self, pts: np.ndarray) -> None:
        """Aim every camera at a new object and put a table grid under it."""
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        center, diag = (lo + hi) / 2.0, max(float(np.linalg.norm(hi - lo)), 1e-3)
        eye = center + diag * np.array([1.0, -1.25, 0.8])
        cam = self.server.initial_camera
        cam.look_at, cam.position = center, eye
        for client in self.server.get_clients().values():
            client.camera.look_at, client.camera.position = center, eye
        self._handles["table"] = self.server.scene.add_grid(
            "/table",
            width=3 * diag,
            height=3 * diag,
            cell_size=diag / 20,
            section_size=diag / 4,
            position=(center[0], center[1], lo[2]),
            shadow_opacity=0.0,
        )

    def _recolor_cloud(self, state: AppState) -> None:
        self._handles["cloud"].colors = self._cloud_colors(state)

    def _cloud_colors(self, state: AppState) -> np.ndarray:
        """(N, 3) uint8: each point in the colour of the shown box holding it."""
        labels = state.tree.point_labels(state.shown_nodes())  # (N,) node id per point
        ids, inverse = np.unique(labels, return_inverse=True)
        return node_colors(ids)[inverse]

    def _draw_boxes(self, state: AppState) -> None:
        tree = state.tree
        shown = state.shown_nodes()
        sel = state.view.selected_node
        for i in list(self._boxes):
            self._boxes.pop(i).remove()
        for i in shown:  # loop over the shown nodes (small set)
            b = tree.node(i).box
            h = self.server.scene.add_box(
                f"{NAMES['boxes']}/node_{i}",
                color=node_color(i),
                dimensions=tuple(float(e) for e in np.maximum(b.extents, 1e-5)),
                opacity=0.35 if i == sel else BOX_OPACITY,
                wxyz=wxyz_from_matrices(b.rotation[None])[0],
                position=b.center,
                cast_shadow=False,
                receive_shadow=False,
            )
            if self.on_box_click is not None:
                h.on_click(_box_click_cb(self.on_box_click, i))
            self._boxes[i] = h
        seg = box_edge_segments([tree.node(i).box for i in shown])
        cols = np.repeat(node_colors(np.array(shown)), 12, axis=0)
        if sel is not None and sel in shown:
            cols[shown.index(sel) * 12 : shown.index(sel) * 12 + 12] = 255
        self._handles["box_edges"] = self.server.scene.add_line_segments(
            NAMES["box_edges"],
            points=seg.astype(np.float32),
            colors=np.repeat(cols[:, None, :], 2, axis=1),
            thickness=2.0,
            thickness_units="screen",
        )
        if sel is not None and sel not in shown:
            b = tree.node(sel).box  # a selected node of another level: outline it in white
            self._handles["selected_edges"] = self.server.scene.add_line_segments(
                "/selected_edges",
                points=box_edge_segments([b]).astype(np.float32),
                colors=(255, 255, 255),
                thickness=3.0,
                thickness_units="screen",
            )
        else:
            self._remove("selected_edges")

    def _draw_faces(self, state: AppState) -> None:
        layers = face_layers(state) if state.view.show_face_masks else None
        if layers is None:
            for key in ("faces_free", "faces_blocked", "subfaces"):
                self._remove(key)
            self.n_faces_shown = (0, 0)
            return
        for key, T, size, rgb in (
            ("faces_free", layers.free, layers.free_sizes, FREE_RGB),
            ("faces_blocked", layers.blocked, layers.blocked_sizes, BLOCKED_RGB),
        ):
            if len(T) == 0:
                self._remove(key)
                continue
            self._handles[key] = self.server.scene.add_batched_meshes_simple(
                NAMES[key],
                vertices=_UNIT_QUAD_V,
                faces=_UNIT_QUAD_F,
                batched_wxyzs=wxyz_from_matrices(T[:, :3, :3]),
                batched_positions=T[:, :3, 3],
                batched_scales=size,
                batched_colors=rgb,
                opacity=0.6,
                side="double",
                cast_shadow=False,
                receive_shadow=False,
                lod="off",
            )
        self.n_faces_shown = (len(layers.free), len(layers.blocked))
        if len(layers.subface_segments):
            self._handles["subfaces"] = self.server.scene.add_line_segments(
                NAMES["subfaces"],
                points=layers.subface_segments.astype(np.float32),
                colors=SUBFACE_RGB,
                thickness=1.5,
                thickness_units="screen",
            )
        else:
            self._remove("subfaces")

    def _draw_ghosts(self, state: AppState) -> None:
        for key in [k for k in self._handles if k.startswith("ghost:")]:
            self._remove(key)
        self.n_ghosts_shown = 0
        pool = _get(state.result, "pool")
        if pool is None or not state.view.show_ghosts or self.hand is None or len(pool) == 0:
            return
        keep = ghost_selection(pool, state.view.ghost_type, state.view.ghost_node)
        idx = np.flatnonzero(keep)
        if len(idx) > self.max_ghosts:  # even subsample: keeps the browser smooth
            idx = idx[np.linspace(0, len(idx) - 1, self.max_ghosts).astype(np.int64)]
        types = pool_types(pool)
        T = np.asarray(pool.T_world_hand, dtype=np.float64)
        # one batched mesh per distinct preshape (a grasp type has one; robust to more)
        q = np.round(np.asarray(pool.q, dtype=np.float64)[idx], 9)  # (K, J)
        shapes, group = np.unique(q, axis=0, return_inverse=True)
        group = group.reshape(-1)
        for g in range(len(shapes)):  # loop over preshapes (a handful)
            sel = idx[group == g]
            gt = str(types[sel[0]])
            key = f"{gt}_{g}"
            mesh = self._ghost_mesh(shapes[g], detailed=len(idx) <= DETAILED_GHOSTS)
            self._handles[f"ghost:{key}"] = self.server.scene.add_batched_meshes_simple(
                f"{NAMES['ghosts']}/{key}",
                vertices=mesh.vertices,
                faces=mesh.faces,
                batched_wxyzs=wxyz_from_matrices(T[sel, :3, :3]),
                batched_positions=T[sel, :3, 3],
                batched_colors=ghost_colors(gt, np.asarray(pool.face)[sel]),
                opacity=GHOST_OPACITY,
                cast_shadow=False,
                receive_shadow=False,
                lod="off",  # simplified levels are built asynchronously in the browser
            )
            self.n_ghosts_shown += len(sel)

    def _ghost_mesh(self, q: np.ndarray, detailed: bool) -> Any:
        """The hand at preshape ``q`` (hand frame): the visual mesh when few ghosts are drawn,
        the link boxes (12 triangles per link) for large pools, so thousands stay smooth."""
        key = (tuple(np.asarray(q, dtype=np.float64).tolist()), detailed)
        mesh = self._ghost_meshes.get(key)
        if mesh is None:
            q = np.asarray(q, dtype=np.float64)
            mesh = self.hand.hand_mesh(q) if detailed else self.hand.collision_mesh(q)
            self._ghost_meshes[key] = mesh
        return mesh

    def _draw_grasp(self, state: AppState) -> None:
        for key in ("contacts", "cones"):
            self._remove(key)
        self.n_contacts_shown = 0
        g = selected_grasp(state)
        if g is None:
            self._hide_hand()
            return
        pts, nrm = contact_arrays(g)
        if len(pts):
            self._handles["contacts"] = self.server.scene.add_point_cloud(
                NAMES["contacts"],
                points=pts.astype(np.float32),
                colors=CONTACT_RGB,
                point_size=0.006,
                point_shape="circle",
                precision="float32",
            )
            mu = friction_coefficient(state.params)
            self._handles["cones"] = self.server.scene.add_line_segments(
                NAMES["cones"],
                points=friction_cone_segments(pts, nrm, mu).astype(np.float32),
                colors=CONTACT_RGB,
                thickness=1.5,
                thickness_units="screen",
            )
            self.n_contacts_shown = len(pts)

    def _ensure_urdf(self) -> Any:
        if self._urdf is None and self.hand is not None:
            from viser.extras import ViserUrdf

            self._handles["hand_frame"] = self.server.scene.add_frame(
                NAMES["hand"], show_axes=False
            )
            urdf_path = Path(getattr(self.hand, "urdf_path", "") or _default_urdf())
            self._urdf = ViserUrdf(self.server, urdf_path, root_node_name=NAMES["hand"])
        return self._urdf

    def _hide_hand(self) -> None:
        frame = self._handles.get("hand_frame")
        if frame is not None:
            frame.visible = False

    def _pose_hand(self, state: AppState) -> None:
        g = selected_grasp(state)
        if g is None or self.hand is None:
            self._hide_hand()
            return
        pre = _pregrasp_of(state, g)
        T, q = animation_pose(g, pre, state.view.anim_t)
        urdf = self._ensure_urdf()
        frame = self._handles["hand_frame"]
        frame.wxyz = wxyz_from_matrices(T[None, :3, :3])[0]
        frame.position = T[:3, 3]
        frame.visible = True
        urdf.update_cfg(np.asarray(q, dtype=np.float64))


GHOST_RGB = {
    "cylindrical": (80, 160, 255),
    "spherical": (255, 140, 60),
    "three_finger_tip": (170, 110, 255),
    "two_finger_tip": (60, 220, 200),
}
"""Ghost colour per grasp type."""


FACE_SHADE = np.array([1.0, 0.55, 0.85, 0.4, 0.7, 0.25])
"""Brightness factor of the ghosts sampled from face 0..5 (+x, -x, +y, -y, +z, -z)."""


def ghost_colors(grasp_type: str, faces: np.ndarray) -> np.ndarray:
    """(K, 3) uint8 ghost colours: the grasp type's hue, shaded by the face of origin, so that
    neighbouring hands from different faces stay apart in a dense pool."""
    base = np.asarray(GHOST_RGB.get(grasp_type, (200, 200, 200)), dtype=np.float64)
    shade = FACE_SHADE[np.clip(np.asarray(faces, dtype=np.int64), 0, 5)]  # (K,)
    return np.clip(base[None] * (0.45 + 0.55 * shade[:, None]), 0, 255).astype(np.uint8)


# ---------------------------------------------------------------------- pure helpers
def _get(obj: Any, name: str) -> Any:
    return None if obj is None else getattr(obj, name, None)


def friction_coefficient(params: Any, default: float = 0.5) -> float:
    """The friction coefficient of the quality measure (``params.planner.quality.mu``)."""
    q = getattr(getattr(params, "planner", None), "quality", None)
    return float(getattr(q, "mu", default))


def _default_urdf() -> Path:
    from pregrasp_core.paths import HAND_URDF

    return HAND_URDF


def _box_click_cb(cb: Callable[[int, Any], None], node_id: int) -> Callable[[Any], None]:
    return lambda event: cb(node_id, event.client)


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
    grasps = _get(result, "grasps")
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


def friction_cone_segments(
    points: np.ndarray, normals: np.ndarray, mu: float, m: int = 8, height: float = CONE_HEIGHT
) -> np.ndarray:
    """(C (m + 1), 2, 3) line segments drawing a friction cone of half-angle atan(mu) per contact.

    Each cone has its apex at the contact and opens along the contact normal; its ``m`` edges
    are ``n + mu (cos t a + sin t b)`` (the linearised cone of the quality measure), plus the axis.
    """
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    n = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    helper = np.where(np.abs(n[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]])  # (C, 3)
    a = np.cross(n, helper)
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    b = np.cross(n, a)
    t = 2 * np.pi * np.arange(m) / m  # (m,)
    edges = n[:, None] + mu * (
        np.cos(t)[None, :, None] * a[:, None] + np.sin(t)[None, :, None] * b[:, None]
    )
    edges = np.concatenate([edges, n[:, None]], axis=1)  # (C, m + 1, 3)
    edges *= height / np.linalg.norm(edges, axis=2, keepdims=True)
    starts = np.broadcast_to(p[:, None], edges.shape)
    # the cone is drawn outside the object: the normal points into it, so draw along -n
    return np.stack([starts, starts - edges], axis=2).reshape(-1, 2, 3)


def _pregrasp_of(state: AppState, grasp: Any) -> Any:
    pool = _get(state.result, "pool")
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
    masks = _get(state.result, "masks")
    if masks is None:
        return None
    tree = state.tree
    shown = state.shown_nodes()
    boxes = [tree.node(i).box for i in shown]
    pos, R, size = face_quads(boxes)
    T = np.zeros((len(pos), 4, 4))
    T[:, :3, :3], T[:, :3, 3], T[:, 3, 3] = R, pos, 1.0
    blocked = (
        np.concatenate([_blocked_faces(masks, i) for i in shown])
        if shown
        else np.zeros(0, dtype=bool)
    )
    return FaceLayers(
        free=T[~blocked],
        free_sizes=size[~blocked],
        blocked=T[blocked],
        blocked_sizes=size[blocked],
        subface_segments=_subface_segments(state, shown),
    )


def _blocked_faces(masks: Any, node: int) -> np.ndarray:
    """(6,) bool: which faces of ``node`` are blocked (``FaceMasks.blocked[node]``)."""
    return np.asarray(masks.blocked[node], dtype=bool).reshape(6)


def _mask_matrix(masks: Any, node: int) -> np.ndarray:
    """(6, 5) int face mask of ``node`` (row f = [f, l, d, r, u], 1 = blocked)."""
    return np.asarray(masks.mask(node)).reshape(6, 5)


def _subface_segments(state: AppState, shown: list[int], shrink: float = 0.85) -> np.ndarray:
    """(S, 2, 3) outlines of the usable sub-faces of the shown nodes for their grasp types.

    Each usable cell is drawn shrunk by ``shrink`` about its centre (so neighbouring cells stay
    apart) and lifted off its face by twice :data:`FACE_OFFSET`.
    """
    from pregrasp_core.facemask import subface_rectangles, usable_subfaces

    res = state.result
    shapes = _get(res, "shapes")
    if shapes is None:
        return np.zeros((0, 2, 3))
    rects = []
    for i in shown:  # loop over the shown nodes (small set)
        node = state.tree.node(i)
        gt = shapes[i].grasp_type
        usable = usable_subfaces(_blocked_faces(res.masks, i), gt)
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
