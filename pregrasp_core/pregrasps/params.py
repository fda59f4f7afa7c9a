"""Parameters of the pre-grasp stages: the traversal policy, :class:`SamplingParams` and the
bounds that keep the pool's work finite (``docs/limits.md``, "Limits of the pre-grasp pool")."""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass

import numpy as np

from ..limits import real_or_nan

SAMPLING_BOUNDS: dict[str, tuple[float, float]] = {
    "interval": (0.001, 1.0),
    "aperture_scale": (0.01, 10.0),
    "standoff": (0.0, 0.5),
    "collision_margin": (0.0, 0.02),
    "support_margin": (-0.1, 0.1),
    "max_backoff": (0.0, 0.5),
    "backoff_step": (0.001, 0.5),
}
"""Closed range ``(low, high)`` of every numeric :class:`SamplingParams` field (metres, or a
factor for ``aperture_scale``). Why each bound is where it is: ``docs/limits.md``. The number of
samples, which the interval alone does not bound (it grows with the object), is bounded by
``MAX_POOL_SAMPLES`` in :func:`~pregrasp_core.pregrasps.build_pool`."""

MAX_POOL_SAMPLES: int = 200_000
"""Largest number of samples (hand poses, both rolls, before any filter) that one pass of
:func:`~pregrasp_core.pregrasps.build_pool` generates over its candidates: about 0.3 GB and some
10 s of collision tests on one core (``docs/limits.md``); past it the pool raises
``PregraspError`` before allocating. 225 times the default mug's 888."""

POOL_BYTES_PER_SAMPLE: int = 1500
"""Bytes of peak memory per sample of the pool stage (the samples, their frames and the pool's
arrays through the filters; measured 1,140 to 1,190 on the default object), used for the
estimate in the error past :data:`MAX_POOL_SAMPLES`. The collision test adds a bounded batch on
top (``collision.collision_batch_bytes``)."""

MAX_BACKOFF_LEVELS: int = 100
"""Largest number of back-off levels ``floor(max_backoff / backoff_step)`` (each level is one
more collision test of the pre-grasps still colliding)."""


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
    """Metres: distance between neighbouring samples on the enclosing surface (0.001 to 1)."""
    policy: TraversalPolicy = TraversalPolicy.PAPER
    """Which nodes get pre-grasps (:class:`TraversalPolicy` or its string value)."""
    aperture_scale: float = 1.0
    """Multiplies the hand's aperture in the fit test of the traversal (0.01 to 10)."""
    standoff: float = 0.01
    """Metres: the palm origin sits this far outside the enclosing surface (0 to 0.5)."""
    collision_margin: float = 0.0
    """Metres: the hand's links are grown by this in the object-collision test (0 to 0.02)."""
    support_margin: float = 0.0
    """Metres: the hand's geometry must stay at least this far above the support plane
    (-0.1 to 0.1; negative tolerates reaching that far below it)."""
    max_backoff: float = 0.06
    """Metres: how far a pre-grasp may be moved back along its approach line (away from the
    part) to clear the support plane and the cloud; beyond it the pre-grasp is dropped (0 to
    0.5)."""
    backoff_step: float = 0.01
    """Metres: the back-offs tried are the multiples of this up to ``max_backoff`` (0.001 to 0.5;
    at most :data:`MAX_BACKOFF_LEVELS` of them)."""
    fallback: bool = True
    """When a candidate's own grasp type leaves no pre-grasp (every sample blocked or colliding),
    try the other types whose grip width fits the hand, in ``FALLBACK_ORDER``, and keep the
    first that gives any (recorded in ``PreGraspPool.fallback``); and when no part fits the
    hand with its own type, the parts another type fits become candidates for those types
    (:func:`~pregrasp_core.pregrasps.traversal.traverse`). ``False`` = the paper's fixed
    mapping only."""

    pinch: bool = True
    """Also give every candidate fingertip pinches from above, the preshape opened just wider
    than the part (``docs/pregrasps.md`` section 6b; only with a support plane). ``False`` =
    the paper's enclosing surfaces only."""

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
            if not (math.isfinite(real_or_nan(v)) and ok(v)):
                raise ValueError(f"{name} must be {what}, got {v!r}")
            lo, hi = SAMPLING_BOUNDS[name]
            if not lo <= v <= hi:
                raise ValueError(
                    f"{name} must be between {lo:g} and {hi:g}, got {v!r} (the bounds that keep "
                    "the pool's time and memory finite: docs/limits.md)"
                )
            object.__setattr__(self, name, float(v))
        levels = int(np.floor(self.max_backoff / self.backoff_step))
        if levels > MAX_BACKOFF_LEVELS:
            raise ValueError(
                f"max_backoff / backoff_step must give at most {MAX_BACKOFF_LEVELS} back-off "
                f"levels, got {self.max_backoff:g} / {self.backoff_step:g} = {levels}: lower "
                "max_backoff or raise backoff_step"
            )
        if not isinstance(self.fallback, (bool, np.bool_)):
            raise ValueError(f"fallback must be True or False, got {self.fallback!r}")
        object.__setattr__(self, "fallback", bool(self.fallback))
        if not isinstance(self.pinch, (bool, np.bool_)):
            raise ValueError(f"pinch must be True or False, got {self.pinch!r}")
        object.__setattr__(self, "pinch", bool(self.pinch))
        try:
            object.__setattr__(self, "policy", TraversalPolicy(self.policy))
        except ValueError:
            raise ValueError(
                f"policy must be one of {[p.value for p in TraversalPolicy]}, got {self.policy!r}"
            ) from None
