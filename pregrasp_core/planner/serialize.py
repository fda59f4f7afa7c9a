"""The result file's ``grasps`` and ``best`` sections (see ``docs/result-schema.md``)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING

from .types import Grasp, GraspSet, PlannerParams

if TYPE_CHECKING:
    from ..hand import Hand


@dataclass(frozen=True)
class SimulatedRanking:
    """What a lift test of the best ranked grasps adds to the result file (``pregrasp plan
    --simulate K``; ``docs/result-schema.md``, "simulation"). The grasp set it goes with is
    already re-ranked (the simulated grasps that lifted first)."""

    outcomes: Mapping[int, Mapping[str, object]]
    """Index into ``GraspSet.grasps`` -> the outcome of that grasp's simulated lift
    (``SimulationResult.to_dict()``: ``success``, ``outcome``, ``rise``, ``slip``, ...); the
    grasps that were not simulated are absent."""
    best: int | None
    """The best grasp under the re-ranking (replaces ``GraspSet.best``)."""
    best_reason: str
    """Why, in one sentence (replaces ``GraspSet.best_reason``)."""
    params: object
    """The ``SimulationParams`` of the test (written as ``parameters.simulation``)."""

    @property
    def n_lifted(self) -> int:
        """Number of simulated grasps that lifted the object."""
        return sum(bool(o["success"]) for o in self.outcomes.values())


def grasp_to_dict(
    g: Grasp, hand: Hand, simulation: Mapping[str, object] | None = None
) -> dict[str, object]:
    """One grasp as a JSON-ready dict (see ``docs/result-schema.md``, "grasps"); ``simulation``:
    the outcome of its simulated lift, or None when it was not simulated."""
    return {
        "pregrasp": g.pregrasp,
        "grasp_type": g.grasp_type,
        "status": "kept" if g.kept else "rejected",
        "rejection": g.rejection,
        "detail": g.detail,
        "rank": g.rank,
        "epsilon": g.epsilon,
        "volume": g.volume,
        "epsilon_exact": g.epsilon_exact,
        "volume_exact": g.volume_exact,
        "quality_bound": g.quality_bound,
        "n_contacts": g.n_contacts,
        "n_assumed_contacts": sum(c.assumed for c in g.contacts),
        "simulation": None if simulation is None else dict(simulation),
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
                "assumed": c.assumed,
                **({"crest": True} if c.crest else {}),
            }
            for c in g.contacts
        ],
    }


def grasps_sections(
    gs: GraspSet,
    hand: Hand,
    params: PlannerParams | None = None,
    simulation: SimulatedRanking | None = None,
) -> dict[str, object]:
    """The ``grasps``, ``best`` and ``best_reason`` top-level sections of the result file
    (``best``: the best force-closure grasp or ``None``). With ``simulation`` (``gs`` re-ranked
    by a lift test) each simulated grasp carries its outcome, and ``best`` and ``best_reason``
    are the simulation's."""
    prm = PlannerParams() if params is None else params
    outcomes: Mapping[int, Mapping[str, object]] = {}
    best, best_reason = gs.best, gs.best_reason
    if simulation is not None:
        outcomes = simulation.outcomes
        best, best_reason = simulation.best, simulation.best_reason
    return {
        "grasps": {
            "n_pregrasps": len(gs),
            "n_kept": int(len(gs.ranking)),
            "n_force_closure": gs.n_force_closure,
            "rejected": dict(gs.rejected),
            "ranking": gs.ranking.tolist(),
            "n_simulated": len(outcomes),
            "n_lifted": 0 if simulation is None else simulation.n_lifted,
            "quality": {
                "mu": prm.quality.mu,
                "n_edges": prm.quality.n_edges,
                "torque_scale": prm.quality.torque_scale,
                "exact_top": prm.quality.exact_top,
                "exact_all": prm.quality.exact_all,
                "n_exact": sum(g.kept and g.epsilon_exact and g.volume_exact for g in gs),
            },
            "items": [grasp_to_dict(g, hand, outcomes.get(i)) for i, g in enumerate(gs.grasps)],
        },
        "best": best,
        "best_reason": best_reason,
    }
