"""The pre-grasp pool: :class:`PreGrasp` (one) and :class:`PreGraspPool` (all of an object)."""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from ..hand import grasp_type_name
from .surfaces import SURFACES

DROP_REASONS: tuple[str, ...] = ("blocked_subface", "support", "object_collision")
"""Reasons a sample is dropped, in the order the filters run: its sub-face is not usable (its
face or an adjacent face it borders is blocked); the open hand reaches below the support plane;
the open hand holds a cloud point."""


@dataclass(frozen=True)
class PreGrasp:
    """One pre-grasp: where the open hand starts and how it is shaped."""

    T_world_hand: np.ndarray
    """(4, 4) float64: pose of the hand's root link (palm) in the world."""
    approach: np.ndarray
    """(3,) float64, unit, world: the approach direction (the hand's +z axis)."""
    grasp_type: str
    """The grasp type (a :class:`~pregrasp_core.shape.GraspType` value)."""
    spread: float
    """Radians: the spread of the two spreading fingers in the preshape."""
    q: np.ndarray
    """(J,) float64, radians: preshape joint positions in ``Hand.joint_names`` order."""
    node: int
    """Id of the tree node the pre-grasp was sampled for."""
    face: int
    """Face of that node's box (see ``docs/conventions.md``)."""
    subface: int
    """Sub-face of that face (``row * n_cols + col``)."""
    surface: str
    """The enclosing-surface patch (one of :data:`SURFACES`)."""
    backoff: float = 0.0
    """Metres the hand was moved back along its approach from the enclosing surface."""
    approach_limit: float = float("inf")
    """Metres: the planner's approach ends here at the latest (pinches of thin parts: the
    fingertips go no deeper than the part; ``inf`` = until contact)."""


@dataclass(frozen=True)
class PreGraspPool:
    """All pre-grasps of an object, stacked (P pre-grasps, J actuated joints)."""

    T_world_hand: np.ndarray
    """(P, 4, 4) float64: hand (palm) poses in the world."""
    approach: np.ndarray
    """(P, 3) float64, unit, world: approach directions (= hand +z)."""
    grasp_type: np.ndarray
    """(P,) str: grasp types (``pregrasp_core.shape.GRASP_TYPES`` values)."""
    spread: np.ndarray
    """(P,) float64, radians: spread of the preshape."""
    q: np.ndarray
    """(P, J) float64, radians: preshape joint positions in ``joint_names`` order."""
    node: np.ndarray
    """(P,) int64: tree node of each pre-grasp."""
    face: np.ndarray
    """(P,) int64: face of the node's box."""
    subface: np.ndarray
    """(P,) int64: sub-face of that face."""
    surface: np.ndarray
    """(P,) int64: index into :data:`SURFACES`."""
    joint_names: tuple[str, ...]
    """Names of the J joints of ``q``."""
    backoff: np.ndarray | None = None
    """(P,) float64, metres: how far the hand was moved back along its approach from the
    enclosing surface to clear the table and the cloud (``None`` = zeros)."""
    approach_limit: np.ndarray | None = None
    """(P,) float64, metres: the longest approach the planner makes from each pre-grasp (``inf``
    = until contact, the paper's; finite for the pinches across a thin part, whose fingertips
    must stay on it). ``None`` = all ``inf``."""
    candidates: tuple[int, ...] = ()
    """Ids of the nodes that were sampled."""
    fallback: dict[int, str] = field(default_factory=dict)
    """Node id -> the grasp type used instead of the node's own, for the candidates whose own
    type left no pre-grasp (see ``SamplingParams.fallback``)."""
    dropped: dict[str, int] = field(default_factory=dict)
    """Number of samples dropped per reason (keys of :data:`DROP_REASONS`)."""

    def __post_init__(self) -> None:
        P = len(self.node)
        if self.backoff is None:
            object.__setattr__(self, "backoff", np.zeros(P))
        if self.approach_limit is None:
            object.__setattr__(self, "approach_limit", np.full(P, np.inf))
        shapes = {
            "backoff": (P,),
            "approach_limit": (P,),
            "T_world_hand": (P, 4, 4),
            "approach": (P, 3),
            "grasp_type": (P,),
            "spread": (P,),
            "node": (P,),
            "face": (P,),
            "subface": (P,),
            "surface": (P,),
            "q": (P, len(self.joint_names)),
        }
        for name, shp in shapes.items():
            got = np.shape(getattr(self, name))
            if got != shp:
                raise ValueError(f"PreGraspPool.{name} must have shape {shp}, got {got}")

    @property
    def _limit(self) -> np.ndarray:
        """``approach_limit`` as an array (``__post_init__`` replaced ``None`` by inf)."""
        assert self.approach_limit is not None
        return self.approach_limit

    @property
    def _backoff(self) -> np.ndarray:
        """``backoff`` as an array (``__post_init__`` replaced ``None`` by zeros)."""
        assert self.backoff is not None
        return self.backoff

    def __len__(self) -> int:
        return int(len(self.node))

    def __getitem__(self, i: int) -> PreGrasp:
        i = int(i)
        if not -len(self) <= i < len(self):
            raise IndexError(f"pre-grasp index {i} out of range for a pool of {len(self)}")
        return PreGrasp(
            T_world_hand=self.T_world_hand[i].copy(),
            approach=self.approach[i].copy(),
            grasp_type=str(self.grasp_type[i]),
            spread=float(self.spread[i]),
            q=self.q[i].copy(),
            node=int(self.node[i]),
            face=int(self.face[i]),
            subface=int(self.subface[i]),
            surface=SURFACES[int(self.surface[i])],
            backoff=float(self._backoff[i]),
            approach_limit=float(self._limit[i]),
        )

    def __iter__(self) -> Iterator[PreGrasp]:
        return (self[i] for i in range(len(self)))

    def select(self, index: np.ndarray) -> PreGraspPool:
        """The pool restricted to ``index`` (bool mask (P,) or integer indices)."""
        idx = np.asarray(index)
        return replace(
            self,
            T_world_hand=self.T_world_hand[idx],
            approach=self.approach[idx],
            grasp_type=self.grasp_type[idx],
            spread=self.spread[idx],
            q=self.q[idx],
            node=self.node[idx],
            face=self.face[idx],
            subface=self.subface[idx],
            surface=self.surface[idx],
            backoff=self._backoff[idx],
            approach_limit=self._limit[idx],
            dropped=dict(self.dropped),
            fallback=dict(self.fallback),
        )

    def filter(
        self, grasp_type: str | None = None, node: int | Sequence[int] | None = None
    ) -> PreGraspPool:
        """The pre-grasps of one grasp type and/or node(s) (``None`` = any)."""
        keep = np.ones(len(self), dtype=bool)
        if grasp_type is not None:
            keep &= self.grasp_type == grasp_type_name(grasp_type)
        if node is not None:
            keep &= np.isin(self.node, np.atleast_1d(np.asarray(node, dtype=np.int64)))
        return self.select(keep)

    def counts(self) -> dict[str, dict]:
        """Pool size per node and per grasp type."""
        nodes, n_counts = np.unique(self.node, return_counts=True)
        types, t_counts = np.unique(self.grasp_type, return_counts=True)
        return {
            "per_node": {int(k): int(v) for k, v in zip(nodes, n_counts, strict=True)},
            "per_type": {str(k): int(v) for k, v in zip(types, t_counts, strict=True)},
        }

    @classmethod
    def empty(cls, joint_names: Sequence[str]) -> PreGraspPool:
        """A pool with no pre-grasps."""
        J = len(joint_names)
        return cls(
            T_world_hand=np.zeros((0, 4, 4)),
            approach=np.zeros((0, 3)),
            grasp_type=np.zeros(0, dtype="<U16"),
            spread=np.zeros(0),
            q=np.zeros((0, J)),
            node=np.zeros(0, dtype=np.int64),
            face=np.zeros(0, dtype=np.int64),
            subface=np.zeros(0, dtype=np.int64),
            surface=np.zeros(0, dtype=np.int64),
            joint_names=tuple(joint_names),
            dropped={r: 0 for r in DROP_REASONS},
        )

    def to_dict(self) -> dict:
        """JSON-ready dict for the ``pool`` section of the result file."""
        names = list(self.joint_names)
        return {
            "count": len(self),
            "candidates": list(self.candidates),
            "dropped": {k: int(v) for k, v in self.dropped.items()},
            "fallback": {str(k): v for k, v in self.fallback.items()},
            **self.counts(),
            "pregrasps": [
                {
                    "index": i,
                    "T_world_hand": self.T_world_hand[i].tolist(),
                    "approach": self.approach[i].tolist(),
                    "grasp_type": str(self.grasp_type[i]),
                    "spread": float(self.spread[i]),
                    "node": int(self.node[i]),
                    "face": int(self.face[i]),
                    "subface": int(self.subface[i]),
                    "surface": SURFACES[int(self.surface[i])],
                    "backoff": float(self._backoff[i]),
                    "approach_limit": (
                        float(self._limit[i]) if np.isfinite(self._limit[i]) else None
                    ),
                    "preshape": dict(zip(names, map(float, self.q[i]), strict=True)),
                }
                for i in range(len(self))
            ],
        }
