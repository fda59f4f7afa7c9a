"""The scene renderer: draws an :class:`app.state.AppState` into viser's 3D scene.

It owns every scene handle, each under a fixed name (see :data:`NAMES`), and updates them inside
``server.atomic()`` so a browser never sees half an update. It redraws only what changed between
the state it drew last and the new one (compared by identity: the state's parts are immutable),
batches similar objects (all face quads of one kind in one batched mesh; box edges, friction
cones and the ghosts of one grasp type as line segments) and sends the point
cloud with ``precision="float32"``. It never computes anything the core computes.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path
from typing import Any, Literal

import numpy as np
import viser
from scipy.spatial.transform import Rotation

from pregrasp_core.sensor.table import OBSTACLE_VOXEL

from .scene_data import (
    GHOST_THICKNESS,
    HIDDEN_POINTS,
    HIDDEN_RGB,
    animation_pose,
    assumed_contacts,
    attr_or_none,
    box_edge_segments,
    cloud_point_colors,
    cone_edge_count,
    contact_arrays,
    contact_tangents,
    face_layers,
    friction_coefficient,
    friction_cone_segments,
    ghost_colors,
    ghost_segments,
    ghost_selection,
    hand_ghost_segments,
    hidden_space_points,
    neighbour_hidden_points,
    node_color,
    node_colors,
    pool_types,
    pregrasp_of,
    scene_backdrop,
    selected_grasp,
    wxyz_from_matrices,
)
from .simulate_view import lift_frame
from .state import AppState

logger = logging.getLogger(__name__)

NAMES = {
    "cloud": "/object/cloud",
    "scene": "/object/scene",
    "hidden": "/object/hidden",
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

LIFT_HIDDEN = (
    "box_edges", "selected_edges", "faces_free", "faces_blocked", "subfaces", "contacts", "cones",
    "hidden",
)  # fmt: skip
"""Layers hidden (with the boxes and ghosts) while a simulated lift is shown: they are drawn
where the object rested, not where the simulation moves it."""
FREE_RGB = (60, 200, 90)
"""Colour of free faces (green)."""
BLOCKED_RGB = (220, 60, 60)
"""Colour of blocked faces (red)."""
SUBFACE_RGB = (255, 255, 255)
"""Colour of the outlines of usable sub-faces (white)."""
CONTACT_RGB = (255, 210, 0)
"""Colour of contact points and friction cones (yellow)."""
ASSUMED_CONTACT_RGB = (255, 90, 0)
"""Colour of the contacts (and their cones) on points assumed by a single view's completion
(orange): the grasp rests there on guessed geometry."""
SCENE_POINTS = 30000
"""Most points of a depth-camera scene (table, other objects) drawn behind the object."""
BOX_OPACITY = 0.12
"""Opacity of unselected boxes (the selected one is drawn at 0.35)."""
FLAT_MATERIAL: Literal["toon3"] = "toon3"
"""Material of the flat translucent layers (boxes, face quads): three.js' toon material, lit
by the same lights in three steps. On a flat face it draws one even shade, as the standard
(physically based) material nearly does, at about half its cost per pixel in software WebGL,
where these large translucent surfaces are most of a frame (docs/benchmarks.md, "Session 8:
viewer")."""
CLOUD_SHADING: Literal["flat"] = "flat"
"""Shading of the cloud's points: one even colour per point (viser's default "gradient" shades
each point like a ball, which costs a square root per pixel and carries no information)."""
HIDDEN_POINT_SIZE = 0.25
"""Size of the hidden space's points, in voxels (3 mm voxels: 0.75 mm points 3 mm apart, a
little smaller than the cloud's). viser's point clouds have no opacity: the gaps between the
points let the object and the hand show through the layer instead (0.4 voxel cost no
measurably more a frame: docs/benchmarks.md, "Session 10: the hidden-space layer")."""
TABLE_EXTENT = 1.5
"""Side of the table grid, in object diagonals (it shows the support plane; every pixel of it
is shaded in each frame)."""

_UNIT_QUAD_V = np.array([[-0.5, -0.5, 0.0], [0.5, -0.5, 0.0], [0.5, 0.5, 0.0], [-0.5, 0.5, 0.0]])
_UNIT_QUAD_F = np.array([[0, 1, 2], [0, 2, 3]], dtype=np.uint32)


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
        self._ghost_outlines: dict[tuple, np.ndarray] = {}  # preshape q -> hand-frame segments
        self._urdf: Any = None
        self._lift_key: tuple | None = None  # (playback, frame) drawn last; None: no lift
        self.n_ghosts_shown = 0
        """Number of ghosts currently in the scene."""
        self.ghost_indices = np.zeros(0, dtype=np.int64)
        """Pool indices of the ghosts drawn, in drawing order: ghost k of the handles of
        :meth:`ghost_handles` (concatenated) is pre-grasp ``ghost_indices[k]``."""
        self.n_contacts_shown = 0
        """Number of contact points currently in the scene."""
        self.n_assumed_contacts_shown = 0
        """Of those, the contacts on assumed points (drawn in :data:`ASSUMED_CONTACT_RGB`)."""
        self.n_scene_points_shown = 0
        """Points of the depth-camera scene (table, other objects) drawn behind the object."""
        self.n_hidden_points_shown = 0
        """Points of the hidden-space layer drawn (the boundary of ``PipelineResult.occupied``,
        at most :data:`~app.scene_data.HIDDEN_POINTS`)."""
        self.n_faces_shown = (0, 0)
        """(free, blocked) face quads currently in the scene."""
        self._up: tuple[float, ...] = (0.0, 0.0, 1.0)
        """The scene's up direction now (:meth:`_frame_object`)."""
        server.scene.set_up_direction("+z")
        configure_lighting(server)

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
        """The line-segment handles of the ghosts now in the scene (one per grasp type)."""
        return [h for k, h in sorted(self._handles.items()) if k.startswith("ghost:")]

    def render(self, state: AppState) -> None:
        """Bring the scene in line with ``state``, redrawing only the parts that changed."""
        last = self._last
        with self.server.atomic():
            if state.result is None:
                self._clear_all()
            elif last is None or last.result is None:
                self._draw_all(state)
            else:
                self._draw_changes(last, state)
            if state.result is not None:
                self._draw_lift(state)
        self._last = state

    def _draw_all(self, state: AppState) -> None:
        self._draw_cloud(state)
        self._draw_boxes(state)
        self._draw_faces(state)
        self._draw_hidden(state)
        self._draw_ghosts(state)
        self._draw_grasp(state)
        self._pose_hand(state)

    def _draw_changes(self, last: AppState, state: AppState) -> None:
        res, lres = state.result, last.result
        lv, v = last.view, state.view
        new_cloud = lres.cloud is not res.cloud
        level_changed = new_cloud or lres.tree is not res.tree
        level_changed = level_changed or last.shown_level != state.shown_level
        if new_cloud or support_of(state, None)[0].tolist() != list(self._up):
            self._draw_cloud(state)  # (and the camera and the table, along the new up)
        elif level_changed:
            self._recolor_cloud(state)
        if level_changed or lv.selected_node != v.selected_node:
            self._draw_boxes(state)
        masks_changed = attr_or_none(lres, "masks") is not attr_or_none(res, "masks")
        if level_changed or masks_changed or lv.show_face_masks != v.show_face_masks:
            self._draw_faces(state)
        if (
            attr_or_none(lres, "occupied") is not attr_or_none(res, "occupied")
            or lv.show_hidden_space != v.show_hidden_space
        ):
            self._draw_hidden(state)
        if (
            attr_or_none(lres, "pool") is not attr_or_none(res, "pool")
            or lv.show_ghosts != v.show_ghosts
            or lv.ghost_type != v.ghost_type
            or lv.ghost_node != v.ghost_node
        ):
            self._draw_ghosts(state)
        grasps_changed = attr_or_none(lres, "grasps") is not attr_or_none(res, "grasps")
        if grasps_changed or lv.selected_grasp != v.selected_grasp:
            self._draw_grasp(state)
            self._pose_hand(state)
        elif lv.anim_t != v.anim_t:
            self._pose_hand(state)

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
        if len(pts) == 0:  # a result file keeps no points: frame the boxes instead
            self._remove("cloud")
            box = state.tree.root.box  # a cube of the box's diagonal: framed as its cloud would be
            h = float(np.linalg.norm(box.extents)) / (2.0 * np.sqrt(3.0))
            self._frame_object(np.asarray(box.center) + np.array([[-h] * 3, [h] * 3]), state)
            return
        diag = float(np.linalg.norm(pts.max(axis=0) - pts.min(axis=0))) if len(pts) else 1.0
        self._handles["cloud"] = self.server.scene.add_point_cloud(
            NAMES["cloud"],
            points=pts,
            colors=self._cloud_colors(state),
            point_size=max(diag * 0.006, 1e-4),
            precision="float32",
            point_shape="rounded",
            point_shading=CLOUD_SHADING,
        )
        self._draw_scene(state, max(diag * 0.004, 1e-4))
        self._frame_object(np.asarray(state.cloud.points, dtype=np.float64), state)

    def _draw_scene(self, state: AppState, point_size: float) -> None:
        """The depth-camera scene around the object (table grey, other objects brown), or
        nothing for a cloud that is not a scene's object."""
        pts, cols = scene_backdrop(getattr(state.cloud, "sensor", None), SCENE_POINTS)
        self.n_scene_points_shown = len(pts)
        if not len(pts):
            self._remove("scene")
            return
        self._handles["scene"] = self.server.scene.add_point_cloud(
            NAMES["scene"],
            points=pts.astype(np.float32),
            colors=cols,
            point_size=point_size,
            precision="float32",
            point_shape="rounded",
            point_shading=CLOUD_SHADING,
        )

    def _frame_object(self, pts: np.ndarray, state: AppState) -> None:
        """Aim every camera at a new object, from above along its 'up' (:func:`support_of`),
        which becomes the scene's up direction, and put a table grid under it in the support
        plane."""
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        center, diag = (lo + hi) / 2.0, max(float(np.linalg.norm(hi - lo)), 1e-3)
        up, height = support_of(state, pts)
        turn = z_to(up)
        self._up = tuple(float(v) for v in up)
        self.server.scene.set_up_direction(up)
        eye = center + turn.apply(camera_offset(diag, float(self.server.initial_camera.fov)))
        cam = self.server.initial_camera
        cam.look_at, cam.position = center, eye
        for client in self.server.get_clients().values():
            # position first: a client camera's position setter moves its look_at along
            client.camera.position = eye
            client.camera.look_at = center
        self._handles["table"] = self.server.scene.add_grid(
            "/table",
            width=TABLE_EXTENT * diag,
            height=TABLE_EXTENT * diag,
            cell_size=diag / 20,
            section_size=diag / 4,
            wxyz=turn.as_quat(scalar_first=True),
            position=center - (float(center @ up) - height) * up,
            shadow_opacity=0.0,
        )

    def _recolor_cloud(self, state: AppState) -> None:
        if "cloud" not in self._handles:
            return
        self._handles["cloud"].colors = self._cloud_colors(state)

    def _cloud_colors(self, state: AppState) -> np.ndarray:
        """(N, 3) uint8: each point in the colour of the shown box holding it; the points
        assumed by a single view's completion in their own colour."""
        labels = state.tree.point_labels(state.shown_nodes())  # (N,) node id per point
        ids, inverse = np.unique(labels, return_inverse=True)
        return cloud_point_colors(node_colors(ids)[inverse], getattr(state.cloud, "assumed", None))

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
                dimensions=np.maximum(np.asarray(b.extents, dtype=np.float64), 1e-5),
                opacity=0.35 if i == sel else BOX_OPACITY,
                wxyz=wxyz_from_matrices(b.rotation[None])[0],
                position=b.center,
                material=FLAT_MATERIAL,
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
                material=FLAT_MATERIAL,
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

    def _draw_hidden(self, state: AppState) -> None:
        """The space hidden behind a single depth view that the pool and the planner kept the
        hand out of: the object's (``--occluded occupied``: its boundary voxels) and the other
        objects' (their hidden space, an obstacle in every setting), as one pale point cloud
        of at most ``HIDDEN_POINTS``, or nothing (a complete cloud, the layer switched off)."""
        occ = attr_or_none(state.result, "occupied")
        show = state.view.show_hidden_space
        pts = hidden_space_points(occ if show else None, HIDDEN_POINTS)
        others = neighbour_hidden_points(state.cloud) if show else np.zeros((0, 3))
        room = HIDDEN_POINTS - len(pts)
        if len(others) > room:
            others = others[np.linspace(0, len(others) - 1, max(room, 0)).astype(np.int64)]
        pts = np.concatenate([pts, others])
        self.n_hidden_points_shown = len(pts)
        if not len(pts):
            self._remove("hidden")
            return
        voxel = float(occ.voxel) if occ is not None else OBSTACLE_VOXEL
        self._handles["hidden"] = self.server.scene.add_point_cloud(
            NAMES["hidden"],
            points=pts.astype(np.float32),
            colors=HIDDEN_RGB,
            point_size=HIDDEN_POINT_SIZE * voxel,
            precision="float32",
            point_shape="rounded",
            point_shading=CLOUD_SHADING,
        )

    def _draw_ghosts(self, state: AppState) -> None:
        """The filtered pool (at most ``max_ghosts``, an even subsample) as line outlines: each
        ghost's palm box and finger chains at its preshape, posed at its ``T_world_hand``, in
        its grasp type's colour shaded by its face; one line-segments node per grasp type."""
        for key in [k for k in self._handles if k.startswith("ghost:")]:
            self._remove(key)
        self.n_ghosts_shown = 0
        self.ghost_indices = np.zeros(0, dtype=np.int64)
        pool = attr_or_none(state.result, "pool")
        if pool is None or not state.view.show_ghosts or self.hand is None or len(pool) == 0:
            return
        keep = ghost_selection(pool, state.view.ghost_type, state.view.ghost_node)
        idx = np.flatnonzero(keep)
        if len(idx) > self.max_ghosts:  # even subsample: keeps the browser smooth
            idx = idx[np.linspace(0, len(idx) - 1, self.max_ghosts).astype(np.int64)]
        if len(idx) == 0:
            return
        types = pool_types(pool)[idx]
        T = np.asarray(pool.T_world_hand, dtype=np.float64)[idx]
        q = np.round(np.asarray(pool.q, dtype=np.float64)[idx], 9)  # (K, J)
        shapes, group = np.unique(q, axis=0, return_inverse=True)  # a preshape per grasp type
        group = group.reshape(-1)
        local = np.stack([self._ghost_outline(shapes[g]) for g in group])  # (K, S, 2, 3)
        colors = np.empty((len(idx), 3), dtype=np.uint8)
        faces = np.asarray(pool.face)[idx]
        for gt in np.unique(types):  # loop over grasp types (at most four)
            colors[types == gt] = ghost_colors(str(gt), faces[types == gt])
        drawn = []
        for gt in np.unique(types):
            sel = np.flatnonzero(types == gt)
            S = local.shape[1]
            pts = np.concatenate([ghost_segments(local[k], T[k][None]) for k in sel])
            self._handles[f"ghost:{gt}"] = self.server.scene.add_line_segments(
                f"{NAMES['ghosts']}/{gt}",
                points=pts.astype(np.float32),
                colors=np.repeat(np.repeat(colors[sel], S, axis=0)[:, None], 2, axis=1),
                thickness=GHOST_THICKNESS,
                thickness_units="screen",
            )
            drawn.append(idx[sel])
        self.ghost_indices = np.concatenate(drawn)
        self.n_ghosts_shown = len(self.ghost_indices)

    def _ghost_outline(self, q: np.ndarray) -> np.ndarray:
        """The ghost's hand-frame segments at preshape ``q`` (cached per preshape)."""
        key = tuple(np.asarray(q, dtype=np.float64).tolist())
        seg = self._ghost_outlines.get(key)
        if seg is None:
            seg = hand_ghost_segments(self.hand, np.asarray(q, dtype=np.float64))
            self._ghost_outlines[key] = seg
        return seg

    def _draw_grasp(self, state: AppState) -> None:
        for key in ("contacts", "cones"):
            self._remove(key)
        self.n_contacts_shown = 0
        self.n_assumed_contacts_shown = 0
        g = selected_grasp(state)
        if g is None:
            self._hide_hand()
            return
        pts, nrm = contact_arrays(g)
        if len(pts):
            on_assumed = assumed_contacts(g, state.cloud)
            cols = np.where(on_assumed[:, None], ASSUMED_CONTACT_RGB, CONTACT_RGB).astype(np.uint8)
            m = cone_edge_count(state.params)
            self._handles["contacts"] = self.server.scene.add_point_cloud(
                NAMES["contacts"],
                points=pts.astype(np.float32),
                colors=cols,
                point_size=0.006,
                point_shape="circle",
                precision="float32",
            )
            mu = friction_coefficient(state.params)
            self._handles["cones"] = self.server.scene.add_line_segments(
                NAMES["cones"],
                points=friction_cone_segments(pts, nrm, mu, m, tangents=contact_tangents(g)).astype(
                    np.float32
                ),
                colors=np.repeat(np.repeat(cols, m + 1, axis=0)[:, None], 2, axis=1),
                thickness=1.5,
                thickness_units="screen",
            )
            self.n_contacts_shown = len(pts)
            self.n_assumed_contacts_shown = int(np.count_nonzero(on_assumed))

    def _ensure_urdf(self) -> Any:
        if self._urdf is None and self.hand is not None:
            self._handles["hand_frame"] = self.server.scene.add_frame(
                NAMES["hand"], show_axes=False
            )
            urdf_path = Path(getattr(self.hand, "urdf_path", "") or _default_urdf())
            self._urdf = HandMeshes(self.server, display_urdf(urdf_path), NAMES["hand"])
        return self._urdf

    def _draw_lift(self, state: AppState) -> None:
        """A shown simulated lift (``app.simulate_view``): the cloud posed by the object's
        simulated motion, the hand at the frame's pose, the object's overlays (boxes, faces,
        contacts, ghosts: drawn where the object rested) hidden; otherwise all as planned."""
        frame = lift_frame(state)
        shown = frame is None
        overlays = [self._handles.get(k) for k in LIFT_HIDDEN] + list(self._boxes.values())
        overlays += self.ghost_handles()
        for h in overlays:
            if h is not None:
                h.visible = shown
        key = None if frame is None else (id(frame.playback), frame.index)
        if key == self._lift_key:
            return
        was_lift, self._lift_key = self._lift_key is not None, key
        cloud = self._handles.get("cloud")
        if cloud is not None:
            T = np.eye(4) if frame is None else frame.T_world_object
            cloud.wxyz = wxyz_from_matrices(T[None, :3, :3])[0]
            cloud.position = T[:3, 3]
        if frame is not None or was_lift:
            self._pose_hand(state)

    def _hide_hand(self) -> None:
        frame = self._handles.get("hand_frame")
        if frame is not None:
            frame.visible = False

    def _pose_hand(self, state: AppState) -> None:
        g = selected_grasp(state)
        if g is None or self.hand is None:
            self._hide_hand()
            return
        frame = lift_frame(state)
        if frame is not None:
            T, q = frame.T_world_hand, frame.q
        else:
            T, q = animation_pose(g, pregrasp_of(state, g), state.view.anim_t)
        urdf = self._ensure_urdf()
        frame = self._handles["hand_frame"]
        frame.wxyz = wxyz_from_matrices(T[None, :3, :3])[0]
        frame.position = T[:3, 3]
        frame.visible = True
        urdf.update_cfg(np.asarray(q, dtype=np.float64))


HEMISPHERE_LIGHT = ((255, 255, 255), (90, 90, 100), 0.8)
"""Sky colour, ground colour and intensity of the hemisphere light that stands in for viser's
default environment map (with :data:`AMBIENT_LIGHT`, the fill of the faces the directional
lights miss)."""
AMBIENT_LIGHT = 0.3
"""Intensity of a white ambient light (so no face is black)."""


def configure_lighting(server: viser.ViserServer) -> None:
    """Lights that are cheap to draw in software WebGL: viser's two directional lights without
    shadows, and a hemisphere and an ambient light instead of the image-based environment map.

    In headless Chromium (SwiftShader) viser's defaults cost most of every frame: the shadow
    maps (three cascades, re-rendered each frame, and a filtered shadow lookup per fragment)
    and the environment map's per-fragment lighting of every mesh. Measured on the first
    screen of the browser tests (one session, adaptive pixel ratio): 300 ms a frame with both,
    160 ms without shadows, 80 ms without either, 13 ms with no layer drawn (docs/benchmarks.md,
    "Viewer: frame cost of the first screen"). No layer
    carries information in its shadow; the boxes, faces and hand keep their colours and
    shading by the directional lights."""
    server.scene.configure_default_lights(enabled=True, cast_shadow=False)
    server.scene.configure_environment_map(None)
    sky, ground, intensity = HEMISPHERE_LIGHT
    server.scene.add_light_hemisphere(  # three.js' sky is +y: turned to the world's +z
        "/lights/fill",
        sky_color=sky,
        ground_color=ground,
        intensity=intensity,
        wxyz=(np.sqrt(0.5), np.sqrt(0.5), 0.0, 0.0),
    )
    server.scene.add_light_ambient("/lights/ambient", intensity=AMBIENT_LIGHT)


FRAME_FILL = 0.85
"""Fraction of the camera's vertical field of view that the object's bounding sphere spans
when the camera frames a new object."""
VIEW_DIRECTION = np.array([1.0, -1.25, 0.8]) / np.linalg.norm([1.0, -1.25, 0.8])
"""Unit direction from the object's centre to the camera (front right, from above)."""


def support_of(state: AppState, pts: np.ndarray | None) -> tuple[np.ndarray, float]:
    """``(up, height)``: the support plane of ``state``'s face masks (its unit normal and its
    offset along it), else the plane perpendicular to ``params.facemask.up`` at the lowest of
    ``pts`` (0 without them)."""
    masks = attr_or_none(state.result, "masks")
    support = None if masks is None else masks.support
    if support is not None:
        return np.asarray(support.normal, dtype=np.float64), float(support.height)
    up = np.asarray(state.params.facemask.up, dtype=np.float64)
    up = up / np.linalg.norm(up)
    return up, 0.0 if pts is None or not len(pts) else float((pts @ up).min())


def z_to(up: np.ndarray) -> Rotation:
    """The shortest rotation that takes +z to the unit vector ``up`` (a half turn about x for
    -z)."""
    z = np.array([0.0, 0.0, 1.0])
    axis = np.cross(z, up)
    s, c = float(np.linalg.norm(axis)), float(z @ up)
    if s < 1e-12:
        return Rotation.identity() if c > 0 else Rotation.from_rotvec([np.pi, 0.0, 0.0])
    return Rotation.from_rotvec(axis / s * np.arctan2(s, c))


def camera_offset(diag: float, fov: float, fill: float = FRAME_FILL) -> np.ndarray:
    """(3,) camera position relative to the object's centre: along :data:`VIEW_DIRECTION`, at
    the distance where a sphere of diameter ``diag`` spans ``fill`` of the vertical field of
    view ``fov`` (radians)."""
    return VIEW_DIRECTION * (0.5 * diag / np.tan(0.5 * fill * fov))


HAND_ROUGHNESS = 0.7
"""Roughness of the drawn hand's (non-metallic) material."""


def display_urdf(path: Path) -> Any:
    """The hand's URDF (``yourdfpy.URDF``) with its visual meshes loaded, each in its URDF
    colour as a non-metallic material (:class:`HandMeshes` draws each mesh in that colour).

    The meshes carry only a colour, and a glTF material without ``metallicFactor`` is fully
    metallic: lit by the environment map it looked grey, but a metal has no diffuse light, so
    under :func:`configure_lighting` (no environment map) every face turned away from the
    directional lights would be black."""
    from functools import partial

    import trimesh
    import yourdfpy

    urdf = yourdfpy.URDF.load(
        path,
        build_scene_graph=True,
        load_meshes=True,
        filename_handler=partial(yourdfpy.filename_handler_magic, dir=path.parent),
    )
    for mesh in urdf.scene.geometry.values():
        rgba = np.asarray(mesh.visual.face_colors, dtype=np.uint8)[0]
        mesh.visual = trimesh.visual.TextureVisuals(
            material=trimesh.visual.material.PBRMaterial(
                baseColorFactor=rgba, metallicFactor=0.0, roughnessFactor=HAND_ROUGHNESS
            )
        )
    return urdf


HAND_MATERIAL: Literal["toon3"] = "toon3"
"""Material of the drawn hand's meshes (three.js' toon material in three steps): lit by the same
lights as with the standard material, at about half its cost per pixel in software WebGL, where
the hand is a large part of every frame while it moves (docs/benchmarks.md, "Session 8:
viewer")."""


class HandMeshes:
    """The hand's URDF drawn in viser as ``viser.extras.ViserUrdf`` draws it (a frame per joint,
    nested by the kinematic tree under ``root``, and each link's visual mesh under its link's
    frame), but with simple meshes in :data:`HAND_MATERIAL` in each mesh's URDF colour;
    :meth:`update_cfg` poses the joint frames at a configuration as ViserUrdf does."""

    def __init__(self, server: viser.ViserServer, urdf: Any, root: str) -> None:
        self._urdf = urdf
        parent_of = {j.child: j.parent for j in urdf.joint_map.values()}

        def path(link: str) -> str:  # the scene name of a link's frame
            names = [link]
            while names[-1] in parent_of:
                names.append(parent_of[names[-1]])
            return "/".join([root, *reversed(names[:-1])])

        self._joints = list(urdf.joint_map.values())
        self._frames = [
            server.scene.add_frame(path(j.child), show_axes=False) for j in self._joints
        ]
        scene = urdf.scene
        self.meshes = []
        """The mesh handles, one per visual mesh."""
        for name, mesh in scene.geometry.items():
            parent = scene.graph.transforms.parents[name]
            mesh = mesh.copy()
            mesh.apply_transform(urdf.get_transform(name, parent))
            rgba = np.asarray(mesh.visual.material.baseColorFactor, dtype=np.float64)
            self.meshes.append(
                server.scene.add_mesh_simple(
                    f"{path(parent)}/{name}",
                    vertices=np.asarray(mesh.vertices, dtype=np.float32),
                    faces=np.asarray(mesh.faces, dtype=np.uint32),
                    color=(int(rgba[0]), int(rgba[1]), int(rgba[2])),
                    material=HAND_MATERIAL,
                    cast_shadow=False,
                    receive_shadow=False,
                )
            )

    def update_cfg(self, q: np.ndarray) -> None:
        """Pose the joint frames at the joint configuration ``q`` (the URDF's actuated joints)."""
        self._urdf.update_cfg(np.asarray(q, dtype=np.float64))
        for joint, frame in zip(self._joints, self._frames, strict=True):
            T = self._urdf.get_transform(joint.child, joint.parent)
            frame.wxyz = wxyz_from_matrices(T[None, :3, :3])[0]
            frame.position = T[:3, 3]


def _default_urdf() -> Path:
    from pregrasp_core.paths import HAND_URDF

    return HAND_URDF


def _box_click_cb(cb: Callable[[int, Any], None], node_id: int) -> Callable[[Any], None]:
    return lambda event: cb(node_id, event.client)
