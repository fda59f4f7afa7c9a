"""The result file's ``grasps`` and ``best`` sections (see ``docs/result-schema.md``)."""

from __future__ import annotations

from typing import TYPE_CHECKING

from .types import Grasp, GraspSet, PlannerParams

if TYPE_CHECKING:
    from ..hand import Hand


def grasp_to_dict(g: Grasp, hand: Hand) -> dict[str, object]:
    """One grasp as a JSON-ready dict (see ``docs/result-schema.md``, "grasps")."""
    return {
        "pregrasp": g.pregrasp,
        "grasp_type": g.grasp_type,
        "status": "kept" if g.kept else "rejected",
        "rejection": g.rejection,
        "detail": g.detail,
        "rank": g.rank,
        "epsilon": g.epsilon,
        "volume": g.volume,
        "n_contacts": g.n_contacts,
        "T_world_hand": g.T_world_hand.tolist(),
        "approach_distance": g.approach_distance,
        "approach_stop": g.approach_stop,
        "joints": hand.full_cfg(g.q),
        "fingers": [
            {
                "finger": f.finger,
                "n_slice": f.n_slice,
                "q": f.q.tolist(),
                "links_touched": list(f.links_touched),
                "palm_stop": f.palm_stop,
                "support_stop": f.support_stop,
                "at_limits": f.at_limits,
                "corrected": f.corrected,
            }
            for f in g.fingers
        ],
        "contacts": [
            {
                "link": c.link,
                "point": c.point.tolist(),
                "normal": c.normal.tolist(),
                "point_index": c.point_index,
                "distance": c.distance,
            }
            for c in g.contacts
        ],
    }


def grasps_sections(
    gs: GraspSet, hand: Hand, params: PlannerParams | None = None
) -> dict[str, object]:
    """The ``grasps``, ``best`` and ``best_reason`` top-level sections of the result file
    (``best``: the best force-closure grasp or ``None``)."""
    prm = PlannerParams() if params is None else params
    best = gs.best
    return {
        "grasps": {
            "n_pregrasps": len(gs),
            "n_kept": int(len(gs.ranking)),
            "n_force_closure": gs.n_force_closure,
            "rejected": dict(gs.rejected),
            "ranking": gs.ranking.tolist(),
            "quality": {
                "mu": prm.quality.mu,
                "n_edges": prm.quality.n_edges,
                "torque_scale": prm.quality.torque_scale,
            },
            "items": [grasp_to_dict(g, hand) for g in gs.grasps],
        },
        "best": best,
        "best_reason": gs.best_reason,
    }
