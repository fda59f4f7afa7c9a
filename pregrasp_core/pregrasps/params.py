"""Parameters of the pre-grasp stages: the traversal policy and :class:`SamplingParams`."""

from __future__ import annotations

import enum
from dataclasses import dataclass

import numpy as np


class TraversalPolicy(str, enum.Enum):
    """Which nodes of the tree get pre-grasps."""

    PAPER = "paper"
    """The paper's rule: every node is visited from the root down; a node is a candidate when
    (a) it is a leaf or one of its children is small, and (b) it fits the hand's aperture for its
    grasp type. A node failing (b) passes its children on (they are visited anyway)."""
    LEAVES = "leaves"
    """Only the leaves that fit the hand."""
    ALL = "all"
    """Every node, whatever its size (for exploration)."""

    def __str__(self) -> str:
        return self.value


@dataclass(frozen=True)
class SamplingParams:
    """Parameters of the traversal and of the pre-grasp sampling."""

    interval: float = 0.02
    """Metres: distance between neighbouring samples on the enclosing surface (> 0)."""
    policy: TraversalPolicy = TraversalPolicy.PAPER
    """Which nodes get pre-grasps (:class:`TraversalPolicy` or its string value)."""
    aperture_scale: float = 1.0
    """Multiplies the hand's aperture in the fit test of the traversal (> 0)."""
    standoff: float = 0.01
    """Metres: the palm origin sits this far outside the enclosing surface (>= 0)."""
    collision_margin: float = 0.0
    """Metres: the hand's links are grown by this in the object-collision test (>= 0)."""
    support_margin: float = 0.0
    """Metres: the hand's geometry must stay at least this far above the support plane
    (may be negative to tolerate touching it)."""
    max_backoff: float = 0.06
    """Metres: how far a pre-grasp may be moved back along its approach line (away from the
    part) to clear the support plane and the cloud; beyond it the pre-grasp is dropped."""
    backoff_step: float = 0.01
    """Metres: the back-offs tried are the multiples of this up to ``max_backoff`` (> 0)."""
    fallback: bool = True
    """When a candidate's own grasp type leaves no pre-grasp (every sample blocked or colliding),
    try the other types whose grip width fits the hand, in ``FALLBACK_ORDER``, and keep the
    first that gives any (recorded in ``PreGraspPool.fallback``). ``False`` = the paper's fixed
    mapping only."""

    def __post_init__(self) -> None:
        checks = (
            ("interval", lambda v: v > 0, "> 0"),
            ("aperture_scale", lambda v: v > 0, "> 0"),
            ("standoff", lambda v: v >= 0, ">= 0"),
            ("collision_margin", lambda v: v >= 0, ">= 0"),
            ("support_margin", lambda v: True, "finite"),
            ("max_backoff", lambda v: v >= 0, ">= 0"),
            ("backoff_step", lambda v: v > 0, "> 0"),
        )
        for name, ok, what in checks:
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float, np.floating, np.integer)):
                raise ValueError(f"{name} must be a number {what}, got {v!r}")
            if not (np.isfinite(v) and ok(v)):
                raise ValueError(f"{name} must be {what}, got {v!r}")
            object.__setattr__(self, name, float(v))
        object.__setattr__(self, "fallback", bool(self.fallback))
        try:
            object.__setattr__(self, "policy", TraversalPolicy(self.policy))
        except ValueError:
            raise ValueError(
                f"policy must be one of {[p.value for p in TraversalPolicy]}, got {self.policy!r}"
            ) from None
