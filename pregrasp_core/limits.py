"""Limits that keep the memory and the time of every stage finite, in one place.

Two kinds (each limit, what happens past it and how to change it: ``docs/limits.md``):

- **Parameter bounds.** Every field of a stage's parameter dataclass is checked in its
  ``__post_init__`` with :func:`check_int` / :func:`check_real` against the bounds below; a value
  outside them raises ``ValueError`` naming the field (``"max_depth must be an integer in [0, 64],
  got 100"``). The bounds are fixed: they only reject values that are typos or that no cloud can
  need.
- **Work limits** (:class:`WorkLimits`). A stage estimates its work before its large allocations
  and raises :class:`~pregrasp_core.errors.WorkLimitError` naming the parameters to change when
  the estimate passes a limit. The limits are not parameters of the result (they never change
  one, they only refuse work), so they are not written to result files; pass a ``WorkLimits`` to
  ``decompose``, ``compute_face_masks`` or ``run_pipeline`` to change them.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

# ----------------------------------------------------------------------------- parameter bounds

MIN_BOX_POINTS: int = 4
"""The fewest points a box of the decomposition may hold: a box that is not flat needs 4 points
(fewer are identical, collinear or coplanar); the lower bound of ``min_points``."""

MAX_MIN_POINTS: int = 1_000_000_000
"""Upper bound of ``DecompositionParams.min_points``: a larger value can only mean "never split"
on any cloud pregrasp can hold in memory, so it is a typo."""

MAX_TREE_DEPTH: int = 64
"""Upper bound of ``DecompositionParams.max_depth``. The work of the decomposition is bounded by
``WorkLimits.max_parts`` whatever the depth; deeper trees only make the ancestor walks of the
later stages (O(depth) per node) longer."""

MAX_LENGTH: float = 10.0
"""Metres: upper bound of the lengths of the face masks (``clearance``, ``overlap_tolerance``,
``support_tolerance``) and of the shape classes (``small_size``). The hand spans about 0.2 m; a
length of kilometres would make every slab cover every box (or overflow to inf in the
separating-axis test)."""

MAX_ASSUMED_CLEARANCE: float = 0.02
"""Metres: upper bound of ``PlannerParams.assumed_clearance``, the distance the hand keeps from
a completion's assumed points (a finger is about 2 cm wide; more would keep it off the back)."""

MAX_CONTACT_LENGTH: float = 0.05
"""Metres: upper bound of the planner's contact lengths (``approach_clearance``,
``closing_margin``, ``contact_distance``, ``penetration_tol``, ``slice_resolution``). A finger
link is about 2 cm thick: a point 5 cm from a link is not touching it, and with
``contact_distance`` at 1e30 every link "touched" every point (19 of 34 box grasps in force
closure with 10 contacts each)."""
MAX_RETREAT: float = 1.0
"""Metres: upper bound of ``PlannerParams.max_lift`` (the retreat from the support, in 5 mm
steps: at most 200)."""
MAX_CLOSING_STEPS: int = 4096
"""Upper bound of ``PlannerParams.closing_steps`` (samples of each closing phase): the closing
tables are ``slice points x (closing_steps + 1)`` per link, 3.7 MB at the bound for a slice of
114 points; ``10**8`` asked for 85 GiB and ended the run with a ``MemoryError``."""
MAX_THREADS: int = 1024
"""Upper bound of ``PlannerParams.threads`` (the planner uses at most 64 workers anyway)."""
MAX_FRICTION: float = 10.0
"""Upper bound of ``QualityParams.mu``: rubber on rubber is about 1 to 2; the cone's half-angle
at 10 is 84 degrees, so a larger value scores the same grasps."""
MAX_CONE_EDGES: int = 32
"""Upper bound of ``QualityParams.n_edges`` (edges of each linearised friction cone). The 6D hull
grows fast with them: 10 contacts take 0.02 s at 8 edges, 1.4 s at 32, 5.1 s at 64 and 34 s at
128 (one core, 2026-12-06), and epsilon changes by 0.2 % from 32 to 64; ``10**7`` ended the run
with a ``MemoryError``."""
MAX_HEIGHT: float = 1.0e6
"""Metres: bound of ``|FaceMaskParams.support_height|`` (finite and far from float overflow)."""

MIN_SCALE: float = 1.0e-6
"""Lower bound of the input's ``scale`` (``--scale``, the viewer's scale field): a factor of a
micrometre per unit; smaller ones only turn a cloud into one point (identical points)."""

MAX_SCALE: float = 1.0e6
"""Upper bound of the input's ``scale``: beyond any unit a file is written in (kilometres need
1,000); a larger factor only pushes a cloud toward ``MAX_COORDINATE`` (1e9 m)."""

MAX_GRID: int = 64
"""Upper bound of the MVBB's ``kernel_grid`` and ``polish_grid`` (columns per side): the kernel
keeps up to ``6 * grid**2`` points (24,576 at 64), which every polish step projects."""

MAX_COARSE_GRID: int = 16
"""Upper bound of ``MvbbParams.coarse_grid``: its kernel (up to 1,536 points) is hulled, and the
sweep's tables grow with the hull's vertices."""

MAX_SNAP_GRID: int = 32
"""Upper bound of ``MvbbParams.snap_grid``: the snap hulls up to 6,144 points."""

MAX_ANGLES: int = 60
"""Upper bound of ``MvbbParams.n_angles`` (in-plane angles per candidate normal over 90
degrees; 1.5 degree steps at 60): the sweep's tables are ``sweep_batch x 2 n_angles x hull
vertices``."""

MAX_CANDIDATES: int = 10_000
"""Upper bound of ``MvbbParams.max_normals`` (hull-face normals swept)."""

MAX_BATCH: int = 128
"""Upper bound of ``MvbbParams.sweep_batch`` (normals per sweep batch; memory is linear in it).
With every MVBB field at its bound, a box of 200,000 points on a sphere (all kernel points on
the hull, the worst case) peaks at 193 MB (tracemalloc) and takes 3 s of CPU; at the defaults,
32 MB and 0.13 s."""

MAX_REFINE: int = 16
"""Upper bound of ``MvbbParams.n_refine`` and ``snap_max`` (boxes polished / snapped)."""

MAX_ITERATIONS: int = 100_000
"""Upper bound of ``MvbbParams.max_iterations`` (pattern-search iterations per call)."""

MAX_ROUNDS: int = 16
"""Upper bound of ``MvbbParams.max_rounds`` and ``refine_restart_level``."""

MIN_STEP: float = 1e-9
"""Radians: the smallest pattern-search step (``step_min``); the number of step levels is
``log2(step_start / step_min)``, at most 30 at the bounds."""

MAX_STEP: float = math.pi / 4.0
"""Radians: the largest rotation step and snap angle (45 degrees, the symmetry of a box face)."""

MAX_FACTOR: float = 1000.0
"""Upper bound of the MVBB's ``sweep_slack`` (a fraction of the best volume; 1000 already
sweeps every candidate)."""

MAX_REACH: float = 1e12
"""Upper bound of the MVBB's ``active_reach`` (steps): a reach past the cloud's size keeps every
point in the active sets (the memory stays that of the cloud), so any larger value acts alike."""

MAX_SEED: int = 2**63 - 1
"""Upper bound of the sensor stages' ``seed`` (numpy's generators take any such integer)."""
MAX_SIGMAS: float = 100.0
"""Upper bound of the table segmentation's noise multiples (``band_sigmas``, ``foot_sigmas``):
100 standard deviations of the fitted plane's noise is already the whole scene."""
MAX_SPACINGS: float = 1000.0
"""Upper bound of the factors counted in point spacings (``SegmentParams.neighbour_spacings``,
``CompletionParams.cell_factor`` and ``edge_factor``)."""
MIN_CELL_FACTOR: float = 0.05
"""Lower bound of ``CompletionParams.cell_factor`` (cells of the range image, in point
spacings): the image has ``1 / cell_factor**2`` cells per point, 400 at the bound; finer cells
only leave holes between the points' triangles."""
MAX_NEIGHBOURS: int = 10_000
"""Upper bound of ``SegmentParams.min_neighbours`` (neighbours a kept point needs)."""
MAX_RANSAC_ITERATIONS: int = 100_000
"""Upper bound of ``SegmentParams.iterations`` (plane hypotheses of the RANSAC)."""


# ----------------------------------------------------------------------------- work limits

MAX_PARTS: int = 256
"""Default of :attr:`WorkLimits.max_parts`: parts (leaves) of one decomposition. The default
parameters (``max_depth`` 8) give at most 2**8 = 256; 256 parts of a 20,000-point cloud take
about 5 s to split and the face masks a few seconds more."""

MAX_PARTS_LIMIT: int = 65_536
"""Upper bound of :attr:`WorkLimits.max_parts` (the face masks' work is quadratic in parts)."""

MAX_FACE_MASK_PAIRS: int = 4_000_000
"""Default of :attr:`WorkLimits.max_face_mask_pairs`: (node, blocker box) pairs the face masks
test, ``nodes x boxes of the cut``; a 256-part tree has at most 511 x 256 = 130,816. The stage
works on chunks of pairs, so its memory does not grow with the pairs (about 10 MB); its time is
about 0.7 microseconds per pair on one core (the 2,135 parts of 4,269 nodes of issue 16, 9.1
million pairs: 6.4 s of CPU), so about 3 s at the limit."""

MAX_DECOMPOSITION_BYTES: int = 3 * 2**29
"""Default of :attr:`WorkLimits.max_decomposition_bytes` (1.5 GiB): estimated peak memory of a
decomposition (:func:`decomposition_bytes`)."""

DECOMPOSITION_BYTES_PER_POINT: int = 512
"""Working memory of the decomposition per cloud point (bytes), besides the node indices: the
MVBB of the root takes 250-420 bytes per point (tracemalloc, 2 x 10^4 and 2 x 10^5 points)."""


def decomposition_bytes(n_points: int, max_depth: int, max_parts: int) -> int:
    """Upper estimate of the peak memory (bytes) of decomposing ``n_points`` points.

    Working memory (:data:`DECOMPOSITION_BYTES_PER_POINT` per point) plus the nodes' point
    indices: the nodes of one depth hold each point at most once (8 bytes), and a tree of at most
    ``max_parts`` leaves and ``max_depth`` levels has at most ``min(max_depth, max_parts - 1) + 1``
    depths.
    """
    depths = min(max_depth, max_parts - 1) + 1
    return n_points * (DECOMPOSITION_BYTES_PER_POINT + 8 * depths)


def format_bytes(n: int) -> str:
    """``n`` bytes for a message: ``"1.50 GiB"`` or ``"12.3 MiB"``."""
    return f"{n / 2**30:.2f} GiB" if n >= 2**30 else f"{n / 2**20:.1f} MiB"


@dataclass(frozen=True)
class WorkLimits:
    """Limits of the work one run may do (see :mod:`pregrasp_core.limits`); not written to
    result files. The defaults keep a run of the default object under a few seconds and far
    below 2 GiB whatever the parameters."""

    max_parts: int = MAX_PARTS
    """The decomposition stops with ``WorkLimitError`` when it would make more parts (leaves)
    than this; in [1, 65,536]."""
    max_face_mask_pairs: int = MAX_FACE_MASK_PAIRS
    """The face masks refuse trees whose ``nodes x cut boxes`` exceeds this; >= 1."""
    max_decomposition_bytes: int = MAX_DECOMPOSITION_BYTES
    """The decomposition refuses clouds whose estimated peak memory
    (:func:`decomposition_bytes`) exceeds this many bytes; >= 1 MiB."""

    def __post_init__(self) -> None:
        object.__setattr__(
            self, "max_parts", check_int("max_parts", self.max_parts, 1, MAX_PARTS_LIMIT)
        )
        object.__setattr__(
            self,
            "max_face_mask_pairs",
            check_int("max_face_mask_pairs", self.max_face_mask_pairs, 1, 2**62),
        )
        object.__setattr__(
            self,
            "max_decomposition_bytes",
            check_int("max_decomposition_bytes", self.max_decomposition_bytes, 2**20, 2**62),
        )


MAX_EXACT_TOP: int = 1_000_000
"""Upper bound of ``QualityParams.exact_top`` (grasps whose scores are exact whatever their
bounds): more than any pool holds, so a larger value is a typo; ``exact_all`` makes every
score exact."""


# ----------------------------------------------------------------------------- checks


def moved_field(obj: object, first: str, second: str) -> str:
    """Which of two fields of the dataclass ``obj`` a failed check between them should name: the
    one that differs from its default (``second`` when both or neither do), so that a value the
    user set is the one the message names."""
    defaults = {f.name: f.default for f in dataclasses.fields(obj)}  # type: ignore[arg-type]
    moved_first = getattr(obj, first) != defaults.get(first)
    moved_second = getattr(obj, second) != defaults.get(second)
    return first if moved_first and not moved_second else second


def real_or_nan(value: object) -> float:
    """``value`` as a ``float`` when it is a real number (an integer beyond the float range as
    +-inf), else NaN: a check ``math.isfinite(real_or_nan(v)) and ...`` then refuses ``None``,
    text, lists and booleans with its own message instead of a ``TypeError``."""
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        return math.nan
    try:
        return float(value)
    except OverflowError:
        return math.inf if value > 0 else -math.inf


def check_int(name: str, value: object, lo: int, hi: int) -> int:
    """``value`` as an ``int`` in ``[lo, hi]``; otherwise a ``ValueError`` naming ``name``, the
    bounds and the value (``bool`` and non-integral numbers are refused)."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or not lo <= value <= hi:
        raise ValueError(f"{name} must be an integer in [{lo:,}, {hi:,}], got {value!r}")
    return int(value)


def check_real(
    name: str,
    value: object,
    lo: float,
    hi: float,
    *,
    lo_open: bool = False,
    what: str = "a number",
    unit: str = "",
) -> float:
    """``value`` as a finite ``float`` in ``[lo, hi]`` (``(lo, hi]`` when ``lo_open``);
    otherwise a ``ValueError`` naming ``name``, what it is, the bounds and the value."""
    if isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, bool):
        try:
            v = float(value)
        except OverflowError:  # an int beyond the float range
            v = math.inf
        if math.isfinite(v) and (lo < v if lo_open else lo <= v) and v <= hi:
            return v
    interval = f"{'(' if lo_open else '['}{lo:g}, {hi:g}]"
    raise ValueError(f"{name} must be {what} in {interval}{unit}, got {value!r}")
