"""The "compare with" layer: the best grasps of a second result file of the same object, drawn
beside the current scene in their own colour (closed hands and their contacts), and the table of
both results' best grasps.

It draws under ``/compare`` only, redraws when the compared file (or the current result) changes
and never touches the main scene's names (``app.scene.NAMES``).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .safe_text import md_text
from .scene_data import contact_arrays, ranked_grasps, wxyz_from_matrices
from .state import AppState

COMPARE_RGB = (230, 40, 200)
"""Colour of the compared result's hands and contacts (magenta: no other layer uses it)."""
COMPARE_GRASPS = 3
"""How many of the compared result's best grasps are drawn."""
COMPARE_OPACITY = 0.55
"""Opacity of the compared result's hands."""


def best_rows(state: AppState) -> list[tuple[str, Any, str, int, int]]:
    """(label, grasp, file name, rank, force-closure count) of the current result's best grasp
    and of the compared file's, for the comparison table (the grasp is ``None`` when a result
    has no kept grasp)."""
    rows: list[tuple[str, Any, str, int, int]] = []
    if state.compare is None:
        return rows
    shown = state.loaded.name if state.loaded is not None else getattr(state.source, "name", "")
    for label, name, result in (
        ("shown", shown, state.result),
        ("compared", state.compare.name, state.compare.result),
    ):
        ranked = ranked_grasps(result) if result is not None else []
        n_fc = sum(float(g.epsilon) > 0 for g in ranked)
        rows.append((label, ranked[0] if ranked else None, name, 0, n_fc))
    return rows


def compare_markdown(state: AppState) -> str:
    """The table of both results' best grasps (markdown, text escaped), "" when not comparing."""
    rows = best_rows(state)
    if not rows:
        return ""
    out = [
        f"**comparing with {md_text(state.compare.name)}** (its best {COMPARE_GRASPS} grasps "
        "drawn in magenta)",
        "",
        "| result | file | best type | contacts | epsilon | volume | force-closure |",
        "|---|---|---|---|---|---|---|",
    ]
    for label, g, name, _rank, n_fc in rows:
        if g is None:
            out.append(f"| {label} | {md_text(name)} | none | | | | {n_fc} |")
            continue
        t = getattr(g.grasp_type, "value", g.grasp_type)
        out.append(
            f"| {label} | {md_text(name)} | {md_text(t)} | {len(g.contacts)} | "
            f"{float(g.epsilon):.4f} | {float(g.volume):.2e} | {n_fc} |"
        )
    if state.planned and rows[0][1] is None:
        out.append("")
        out.append("The shown result has no kept grasp.")
    return "\n".join(out)


class CompareLayer:
    """Draws ``state.compare``'s best grasps into ``server.scene`` under ``/compare``."""

    def __init__(self, server: Any, hand: Any) -> None:
        self.server = server
        self.hand = hand
        self._drawn: Any = None  # the ResultFile drawn, compared by identity
        self._handles: list[Any] = []
        self.n_hands = 0
        """Number of compared hands in the scene."""
        self.n_contacts = 0
        """Number of compared contacts in the scene."""

    def render(self, state: AppState) -> None:
        """Bring the layer in line with ``state.compare`` (called after every state change)."""
        if state.compare is self._drawn:
            return
        with self.server.atomic():
            for h in self._handles:
                h.remove()
            self._handles = []
            self.n_hands = self.n_contacts = 0
            self._drawn = state.compare
            if state.compare is None or self.hand is None:
                return
            grasps = ranked_grasps(state.compare.result)[:COMPARE_GRASPS]
            pts = []
            for k, g in enumerate(grasps):  # a few hands
                mesh = self.hand.hand_mesh(np.asarray(g.q, dtype=np.float64))
                T = np.asarray(g.T_world_hand, dtype=np.float64)
                self._handles.append(
                    self.server.scene.add_mesh_simple(
                        f"/compare/hand_{k}",
                        vertices=np.asarray(mesh.vertices, dtype=np.float32),
                        faces=np.asarray(mesh.faces, dtype=np.uint32),
                        color=COMPARE_RGB,
                        opacity=COMPARE_OPACITY,
                        wxyz=wxyz_from_matrices(T[None, :3, :3])[0],
                        position=T[:3, 3],
                        cast_shadow=False,
                        receive_shadow=False,
                    )
                )
                pts.append(contact_arrays(g)[0])
            self.n_hands = len(grasps)
            p = np.concatenate(pts) if pts else np.zeros((0, 3))
            if len(p):
                self._handles.append(
                    self.server.scene.add_point_cloud(
                        "/compare/contacts",
                        points=p.astype(np.float32),
                        colors=COMPARE_RGB,
                        point_size=0.006,
                        point_shape="circle",
                        precision="float32",
                    )
                )
            self.n_contacts = len(p)


__all__ = ["COMPARE_GRASPS", "COMPARE_RGB", "CompareLayer", "best_rows", "compare_markdown"]
