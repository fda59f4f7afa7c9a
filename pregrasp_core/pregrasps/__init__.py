"""Tree traversal and the pre-grasp pool (Sainul, Deb & Deb 2019, section III.D).

1. :func:`traverse` (``traversal``) decides which nodes of the decomposition tree get
   pre-grasps (the paper's two conditions by default, see :class:`TraversalPolicy`).
2. :func:`sample_node` (``surfaces``) samples the enclosing surface of a candidate's box for its
   grasp type (sphere, cylinder side and caps, circle) on the usable sub-faces at a fixed
   interval, each sample aiming the hand's approach at the box.
3. :func:`build_pool` (``build``) stacks the samples of all candidates, drops those whose open
   hand (in its preshape) holds a cloud point or reaches below the support plane (the batched
   tests of ``collision``), and counts every drop, into a :class:`PreGraspPool` (``pool``).

Parameters are one :class:`SamplingParams` (``params``), each field bounded
(:data:`SAMPLING_BOUNDS`); the pool checks its size before allocating (:func:`check_pool_size`,
:data:`MAX_POOL_SAMPLES`; ``docs/limits.md``). Everything is deterministic: no random numbers are
drawn. Frames and conventions are in ``docs/conventions.md`` and ``docs/pregrasps.md``.
"""

from .build import FALLBACK_ORDER, build_pool, check_pool_size, estimate_pool_bytes
from .collision import hand_corners, hand_hits_points, hand_min_height, link_cells
from .params import (
    MAX_BACKOFF_LEVELS,
    MAX_POOL_SAMPLES,
    SAMPLING_BOUNDS,
    SamplingParams,
    TraversalPolicy,
)
from .pool import DROP_REASONS, PreGrasp, PreGraspPool
from .surfaces import SURFACES, NodeSamples, count_samples, sample_node, total_samples
from .traversal import Traversal, grip_width, traverse

__all__ = [
    "DROP_REASONS",
    "FALLBACK_ORDER",
    "MAX_BACKOFF_LEVELS",
    "MAX_POOL_SAMPLES",
    "SAMPLING_BOUNDS",
    "SURFACES",
    "NodeSamples",
    "PreGrasp",
    "PreGraspPool",
    "SamplingParams",
    "Traversal",
    "TraversalPolicy",
    "build_pool",
    "check_pool_size",
    "count_samples",
    "estimate_pool_bytes",
    "grip_width",
    "hand_corners",
    "hand_hits_points",
    "hand_min_height",
    "link_cells",
    "sample_node",
    "total_samples",
    "traverse",
]
