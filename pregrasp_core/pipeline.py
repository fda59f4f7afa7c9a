"""The staged pipeline: cloud -> tree -> shapes -> face masks -> traversal and pre-grasp pool.

Each stage is a pure function of the previous stages' results and of its own parameters, so
:func:`run_pipeline` can reuse the stages of a ``previous`` result whose inputs did not change
(the app re-runs only what a threshold change affects). Stages, in order (:data:`ALL_STAGES`):

========== ====================================== ==========================================
stage      computes                               depends on
========== ====================================== ==========================================
decompose  ``tree`` (BoxTree)                     cloud, ``params.decomposition``
classify   ``shapes`` (NodeShape per node)        decompose, ``params.shape``
facemask   ``masks`` (FaceMasks, support plane)   decompose, ``params.facemask``
pool       ``traversal`` and ``pool``             classify, facemask, ``params.sampling``, hand
grasps     ``normals`` and ``grasps`` (GraspSet)  pool, ``params.planner`` (normals: cloud and
                                                  ``params.planner.normals`` only)
========== ====================================== ==========================================

``timings`` holds the seconds each stage took when it was computed (a reused stage keeps the
time it took then; ``reused`` names the stages taken from ``previous``).

The normals depend on nothing but the cloud: a run up to ``grasps`` that has to compute them
starts them on a thread of their own (:class:`_Background`) before the decomposition and joins
it before the planner (which needs them, and forks copies of the process, which must then run
one thread only). Their kernels (the k-d tree, the batched PCA, the compiled grid search and
votes) release Python's global lock, so on two cores they run beside the decomposition, the
face masks and the pool; the normals are the same bits either way.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from .decomposition import BoxTree, DecompositionParams, decompose
from .errors import WorkLimitError
from .facemask import FaceMaskParams, FaceMasks, compute_face_masks, support_plane
from .io import PointCloud
from .limits import WorkLimits
from .normals import PLAIN_RULES, CloudNormals, NormalParams, estimate_normals, orient_rule
from .planner import GraspSet, PlannerParams, grasps_sections, plan_grasps
from .planner.assumed import without_occupied
from .planner.serialize import SimulatedRanking
from .pregrasps import PreGraspPool, SamplingParams, Traversal, build_pool, traverse
from .pregrasps.traversal import no_fit_hint
from .result import JsonDocument
from .result import result_document as _result_document
from .sensor.occluded import OCCLUDED_MODES, OccupiedSpace, occupied_space
from .shape import NodeShape, ShapeParams, classify_tree

if TYPE_CHECKING:  # the hand (python-fcl, URDF) is loaded only when the pool stage runs
    from .hand import Hand

logger = logging.getLogger(__name__)

STAGES: tuple[str, ...] = ("decompose", "classify", "facemask", "pool")
"""The stages up to the pre-grasp pool, in order (``run_pipeline``'s default ``until``)."""

ALL_STAGES: tuple[str, ...] = (*STAGES, "grasps")
"""Every stage, the planner's ``grasps`` last; ``run_pipeline(until=...)`` stops after the
named one."""


@dataclass(frozen=True)
class PipelineParams:
    """Parameters of every stage (each a frozen dataclass with documented defaults)."""

    decomposition: DecompositionParams = field(default_factory=DecompositionParams)
    """Fit-and-split decomposition."""
    shape: ShapeParams = field(default_factory=ShapeParams)
    """PCA shape classes (``small_size`` also decides which children are small)."""
    facemask: FaceMaskParams = field(default_factory=FaceMaskParams)
    """Face masks and the support plane."""
    sampling: SamplingParams = field(default_factory=SamplingParams)
    """Traversal policy and pre-grasp sampling."""
    planner: PlannerParams = field(default_factory=PlannerParams)
    """Slicing contact planner, quality measure and cloud normals."""
    occluded: str = "auto"
    """A single view's unseen space: ``completed`` = free but for the completion's assumed
    points; ``occupied`` = an obstacle for the pool and the planner (the hand stays out of it;
    contacts only on real points; docs/partial-views.md); ``auto`` (the default) = planned
    with ``occupied`` and again with ``completed`` when no kept grasp is force closure or the
    hidden space passes its work limit (``PipelineResult.occluded_used`` says which). No
    effect on complete clouds (every setting plans them as ``completed``)."""

    def __post_init__(self) -> None:
        if self.occluded not in OCCLUDED_MODES:
            raise ValueError(f"occluded must be one of {OCCLUDED_MODES}, got {self.occluded!r}")

    def as_dict(self) -> dict[str, object]:
        """Section name -> parameters dataclass (for the result file's ``parameters``)."""
        return {
            "decomposition": self.decomposition,
            "shape": self.shape,
            "facemask": self.facemask,
            "sampling": self.sampling,
            "planner": self.planner,
        }


@dataclass(frozen=True)
class PipelineResult:
    """What the pipeline computed; a stage not reached is ``None``."""

    cloud: PointCloud
    """The input cloud (world frame, metres)."""
    params: PipelineParams
    """The parameters of this run."""
    tree: BoxTree | None = None
    """The decomposition tree (stage ``decompose``)."""
    shapes: tuple[NodeShape, ...] | None = None
    """Shape class and grasp type per node id (stage ``classify``)."""
    masks: FaceMasks | None = None
    """Face masks of every node and the support plane (stage ``facemask``)."""
    traversal: Traversal | None = None
    """Candidate nodes and the reason for every node (stage ``pool``)."""
    pool: PreGraspPool | None = None
    """The pre-grasp pool (stage ``pool``)."""
    normals: np.ndarray | None = None
    """(N, 3) outward unit normals of the cloud (stage ``grasps``)."""
    crest: np.ndarray | None = None
    """(N,) bool: the points whose normal is the crest rule's (``CloudNormals.crest``; a cloud
    without normals oriented by visibility), whose contacts also follow the touching link
    (stage ``grasps``); None for every other orientation."""
    grasps: GraspSet | None = None
    """Every pre-grasp planned: kept grasps ranked, rejections with reasons (stage ``grasps``)."""
    timings: dict[str, float] = field(default_factory=dict)
    """Seconds per stage (when it was computed)."""
    reused: tuple[str, ...] = ()
    """Stages taken unchanged from the ``previous`` result."""
    hand: Hand | None = None
    """The hand the pool was built for, or ``None``."""
    occupied: OccupiedSpace | None = None
    """The hidden space of a single view that the pool and the planner kept the hand out of
    (``params.occluded == "occupied"``; ``sensor/occluded.py``), the very object they used (the
    viewer draws it, nothing computes it again); ``None`` for a complete cloud, for
    ``completed`` and for a run that stops before the pool. Not in the result file."""
    occluded_used: str = "completed"
    """The setting the stages from the pool on were run with: ``occupied`` or ``completed``
    (``params.occluded`` unless it is ``auto``: then ``occupied`` for a single view, or
    ``completed`` when the occupied plan had no force-closure grasp, only weak ones, or its
    hidden space passed the work limit); ``completed`` for a complete cloud whatever the
    setting."""
    fallback: str | None = None
    """Why an ``auto`` run planned with ``completed`` after ``occupied``: ``"no_force_closure"``
    (no kept grasp of the occupied plan was force closure), ``"weak_force_closure"`` (its best
    epsilon was below :data:`AUTO_MIN_EPSILON` and the completed plan's best is higher) or
    ``"work_limit"`` (the hidden space passed ``MAX_OCCLUDED_VOXELS``); ``None`` otherwise."""


def _same_cloud(a: PointCloud, b: PointCloud) -> bool:
    if a is b:
        return True
    pa, pb = np.asarray(a.points), np.asarray(b.points)
    return pa.shape == pb.shape and bool(np.array_equal(pa, pb))


def _stage_index(until: str) -> int:
    if until not in ALL_STAGES:
        raise ValueError(f"until must be one of {ALL_STAGES}, got {until!r}")
    return ALL_STAGES.index(until)


def run_pipeline(
    cloud: PointCloud,
    params: PipelineParams | None = None,
    hand: Hand | None = None,
    until: str = "pool",
    previous: PipelineResult | None = None,
    progress: Callable[[float], None] | None = None,
    limits: WorkLimits | None = None,
    planner: Callable[..., GraspSet] | None = None,
) -> PipelineResult:
    """Run the stages up to ``until`` (one of :data:`ALL_STAGES`), reusing those of ``previous``
    whose inputs are unchanged.

    hand: the hand (loaded with ``Hand.load()`` when ``None`` and the
    ``pool`` stage runs). progress: called with the fraction of stages done (0..1). limits: the
    work limits of the stages (default ``WorkLimits()``; ``docs/limits.md``); a stage that would
    pass one raises ``WorkLimitError`` before its large allocations. planner: called by the
    grasps stage in place of ``plan_grasps``, with its arguments, for the same ``GraspSet``
    (the viewer's planner process, ``app/planner_proc.py``); ``None`` = ``plan_grasps``.
    """
    params = with_cloud(PipelineParams() if params is None else params, cloud)
    last = _stage_index(until)
    prev = previous
    if prev is not None and not _same_cloud(prev.cloud, cloud):
        prev = None
    # the normals need only the cloud: on a thread of their own beside the stages up to the pool
    background = None
    if last >= 4 and not _normals_reusable(prev, params):
        nprm = params.planner.normals
        background = _Background(view_cloud_normals, cloud, nprm, background_threads(cloud, nprm))
    try:
        if params.occluded == "auto" and cloud.sensor is not None and last >= 4:
            return _run_auto(
                cloud, params, hand, last, prev, progress, limits, background,
                planner or plan_grasps,
            )  # fmt: skip
        return _run_stages(
            cloud, params, hand, last, prev, progress, limits, background,
            planner or plan_grasps, mode=planned_mode(cloud, params),
        )  # fmt: skip
    finally:
        if background is not None:  # joined whatever happened: no thread outlives the run
            background.join()


def planned_mode(cloud: PointCloud, params: PipelineParams) -> str:
    """The setting a run of ``params`` on ``cloud`` starts with: ``completed`` for a complete
    cloud (no sensor view) whatever ``params.occluded``; for a view ``occupied`` when
    ``params.occluded`` is ``auto`` (the pool a run up to ``pool`` shows; the planner may still
    fall back, :func:`run_pipeline`), else ``params.occluded``."""
    if cloud.sensor is None:
        return "completed"
    return "occupied" if params.occluded == "auto" else params.occluded


class _HiddenSpaceLimit(WorkLimitError):
    """The view's hidden space passed its work limit (``auto`` falls back to ``completed``;
    any other caller sees the ``WorkLimitError`` it is)."""


AUTO_MIN_EPSILON: float = 0.0
"""``occluded="auto"``: an occupied plan whose best grasp's epsilon is below this is weak
force closure; the completed plan is then made too and taken when its best epsilon is higher.
0 (the default) turns the rule off: only an occupied plan without force closure falls back.
Measured with the lift simulated on the true meshes (``docs/partial-views.md``, "Weak force
closure under `auto`"): at 0.01 the completed plan's best grasp lifts the true object more
often (90 against 87 of 117 generated views) at no cost in the true-mesh checks there, but on
a view outside them it puts a finger 4 mm into the true mug, where the occupied plan's grasp
(epsilon 0.002) stays clear and drops it; which of the two the default should favour is a
decision left open."""

FALLBACK_REASONS: dict[str, str] = {
    "no_force_closure": "with it occupied no grasp was force closure",
    "weak_force_closure": "with it occupied the best epsilon was below {floor}",
    "work_limit": "its occupied space passed the work limit",
}
"""``PipelineResult.fallback`` -> why, in words (the viewer's status line)."""


def occluded_note(result: PipelineResult) -> str:
    """How a single view's unseen back was planned, in words for a status line ("" for a
    complete cloud and before the pool): ``"unseen back occupied"``, or ``"unseen back
    completed"`` with why when ``auto`` fell back."""
    if result.cloud.sensor is None or result.pool is None:
        return ""
    text = f"unseen back {result.occluded_used}"
    if result.fallback is not None:
        why = FALLBACK_REASONS[result.fallback].format(floor=AUTO_MIN_EPSILON)
        text += f" (--occluded auto: {why})"
    return text


def _run_auto(
    cloud: PointCloud,
    params: PipelineParams,
    hand: Hand | None,
    last: int,
    prev: PipelineResult | None,
    progress: Callable[[float], None] | None,
    limits: WorkLimits | None,
    background: _Background | None,
    planner: Callable[..., GraspSet],
) -> PipelineResult:
    """``occluded="auto"`` on a single view up to the grasps: the stages with the hidden space
    occupied, then, when no kept grasp is force closure (or the hidden space passes its work
    limit), the pool and the planner again with ``completed``, reusing the stages before the
    pool (and the normals) of the first run. When the occupied plan's best epsilon is below
    :data:`AUTO_MIN_EPSILON`, the completed plan is made the same way and kept only when its
    best epsilon is higher. A ``previous`` auto result of the very same parameters that fell
    back goes straight to ``completed`` (all its stages reused)."""

    def stages(mode: str, hand: Hand | None, base: PipelineResult | None) -> PipelineResult:
        """The stages with the hidden space as ``mode`` says, from ``base``'s results."""
        return _run_stages(
            cloud, params, hand, last, base, progress, limits, background, planner, mode=mode
        )

    if (
        prev is not None
        and prev.params == params
        and prev.occluded_used == "completed"
        and prev.grasps is not None
    ):
        return dataclasses.replace(stages("completed", hand, prev), fallback=prev.fallback)
    try:
        first = stages("occupied", hand, prev)
    except _HiddenSpaceLimit as exc:
        logger.info("occluded auto: %s; planning with the completed back", exc)
        return dataclasses.replace(stages("completed", hand, prev), fallback="work_limit")
    eps = _best_epsilon(first)
    if eps > 0.0 and eps >= AUTO_MIN_EPSILON:
        return first
    reason = "no_force_closure" if eps == 0.0 else "weak_force_closure"
    logger.info("occluded auto: %s with the hidden space occupied", reason)
    # the completed plan from the stages before the pool of the first run; a previous
    # completed result whose stages the first run reused also lends its pool and grasps
    base = first
    before_pool = ("decompose", "classify", "facemask")
    if (
        prev is not None
        and prev.occluded_used == "completed"
        and all(s in first.reused for s in before_pool)
        and _normals_reusable(prev, params)
    ):
        base = prev
    res = stages("completed", first.hand, base)
    if eps > 0.0 and _best_epsilon(res) <= eps:  # the weak occupied grasp is still the better
        return first  # one: keep the safer plan
    timings = dict(res.timings)
    for name in before_pool + ("normals",):  # computed (or reused) by the first run
        if name in first.timings:
            timings[name] = first.timings[name]
    timings["occupied_attempt"] = sum(
        first.timings.get(s, 0.0) for s in ("pool", "grasps") if s not in first.reused
    )
    reused = tuple(s for s in res.reused if s not in before_pool or s in first.reused)
    return dataclasses.replace(res, timings=timings, reused=reused, fallback=reason)


def _best_epsilon(result: PipelineResult) -> float:
    """Epsilon of the result's best grasp (``GraspSet.best``, force closure), 0 without one."""
    gs = result.grasps
    assert gs is not None
    return 0.0 if gs.best is None else float(gs.grasps[gs.best].epsilon)


def _normals_reusable(prev: PipelineResult | None, params: PipelineParams) -> bool:
    """Whether ``prev`` (of the same cloud) holds the normals ``params`` asks for."""
    return (
        prev is not None
        and prev.normals is not None
        and prev.params.planner.normals == params.planner.normals
    )


class _Background:
    """``fn(*args)`` on a thread of its own, started at once; :meth:`result` joins it and gives
    its value and its wall-clock seconds (or raises what it raised)."""

    def __init__(self, fn: Callable[..., Any], *args: Any) -> None:
        self._value: Any = None
        self._error: BaseException | None = None
        self._seconds = 0.0

        def run() -> None:
            t0 = time.perf_counter()
            try:
                self._value = fn(*args)
            except BaseException as exc:  # raised again by result(), in the caller's thread
                self._error = exc
            self._seconds = time.perf_counter() - t0

        self._thread = threading.Thread(target=run, name="pipeline-normals", daemon=True)
        self._thread.start()

    def join(self) -> None:
        self._thread.join()

    def result(self) -> tuple[Any, float]:
        self.join()
        if self._error is not None:
            raise self._error
        return self._value, self._seconds


def _run_stages(
    cloud: PointCloud,
    params: PipelineParams,
    hand: Hand | None,
    last: int,
    prev: PipelineResult | None,
    progress: Callable[[float], None] | None,
    limits: WorkLimits | None,
    background: _Background | None,
    planner: Callable[..., GraspSet] = plan_grasps,
    mode: str = "completed",
) -> PipelineResult:
    """The stages of :func:`run_pipeline` up to ``ALL_STAGES[last]`` (``prev``: the previous
    result of the same cloud or None); the normals from ``background`` when it computes them;
    the grasps by ``planner`` (``plan_grasps`` or a stand-in with its arguments); the pool and
    the grasps with the hidden space as ``mode`` says (``completed`` or ``occupied``; a
    previous result's pool is reused only when it was built with the same)."""
    points = np.asarray(cloud.points, dtype=np.float64)
    pp = prev.params if prev is not None else None
    hidden: list[OccupiedSpace | None] = []  # the view's hidden space (once, when needed)
    if prev is not None and prev.occupied is not None and prev.occluded_used == mode:
        hidden.append(prev.occupied)  # the same cloud and setting: the same space

    scene_obstacles = (  # (PointCloud keeps them as a read-only float64 (K, 3) array)
        cloud.obstacles if cloud.obstacles is not None and len(cloud.obstacles) else None
    )

    def obstacles() -> tuple[np.ndarray, OccupiedSpace | None]:
        """The points the pool and the planner must clear (the cloud's, then the hidden
        space's, then the rest of the scene's), and the hidden space or None."""
        if not hidden:
            try:
                hidden.append(occupied_of(cloud, params, mode))
            except WorkLimitError as exc:  # auto falls back on this one (a WorkLimitError)
                raise _HiddenSpaceLimit(str(exc)) from exc
        occ = hidden[0]
        parts = [points]
        if occ is not None:
            parts.append(occ.points)
        if scene_obstacles is not None:
            parts.append(scene_obstacles)
        return (points if len(parts) == 1 else np.concatenate(parts)), occ

    timings: dict[str, float] = {}
    reused: list[str] = []
    out: dict[str, Any] = {}

    def stage(
        name: str, can_reuse: bool, fields: tuple[str, ...], compute: Callable[[], dict[str, Any]]
    ) -> bool:
        """Reuse ``fields`` from ``prev`` when ``can_reuse``, else compute and time them."""
        if can_reuse and prev is not None and all(getattr(prev, f) is not None for f in fields):
            out.update({f: getattr(prev, f) for f in fields})
            timings[name] = prev.timings.get(name, 0.0)
            reused.append(name)
            return True
        t0 = time.perf_counter()
        out.update(compute())
        timings[name] = time.perf_counter() - t0
        logger.info("stage %s: %.3f s", name, timings[name])
        return False

    def tick(i: int) -> None:
        if progress is not None:
            progress((i + 1) / (last + 1))

    ok = stage(
        "decompose",
        pp is not None and pp.decomposition == params.decomposition,
        ("tree",),
        lambda: {"tree": decompose(points, params.decomposition, limits)},
    )
    tick(0)
    tree_same = ok
    if last >= 1:
        ok_cls = stage(
            "classify",
            tree_same and pp is not None and pp.shape == params.shape,
            ("shapes",),
            lambda: {"shapes": classify_tree(out["tree"], points, params.shape)},
        )
        tick(1)
    if last >= 2:

        def _masks() -> dict[str, Any]:
            sp = support_plane(points, params.facemask)
            masks = compute_face_masks(
                out["tree"], sp, params.facemask, limits=limits, points=points
            )
            return {"masks": masks}

        ok_fm = stage(
            "facemask",
            tree_same and pp is not None and pp.facemask == params.facemask,
            ("masks",),
            _masks,
        )
        tick(2)
    if last >= 3:
        if hand is None:
            hand = prev.hand if prev is not None and prev.hand is not None else _load_hand()
        run_hand: Hand = hand  # the hand of the pool and grasps stages

        def _pool() -> dict[str, Any]:
            trav = traverse(out["tree"], out["shapes"], run_hand, params.sampling, params.shape)
            pool = build_pool(
                obstacles()[0],
                out["tree"],
                out["shapes"],
                out["masks"],
                run_hand,
                params.sampling,
                trav,
                params.shape,
            )
            if not trav.candidates:
                hint = no_fit_hint(out["tree"], out["shapes"], run_hand, params.sampling)
                logger.warning("%s: %s", cloud.source, hint)
            return {"traversal": trav, "pool": pool}

        stage(
            "pool",
            ok_cls
            and ok_fm
            and prev is not None
            and pp is not None
            and pp.sampling == params.sampling
            and prev.occluded_used == mode
            and prev.hand is hand,
            ("traversal", "pool"),
            _pool,
        )
        tick(3)
    normals_same = _normals_reusable(prev, params)
    if last < 4 and normals_same:
        # carried through a run that stops before the planner (the viewer's threshold change
        # shows the new pool first, then plans from that result: no second normal estimation)
        assert prev is not None
        out["normals"], out["crest"] = prev.normals, prev.crest
        timings["normals"] = prev.timings.get("normals", 0.0)
    if last >= 4:
        # normals depend on the cloud only (computed once per cloud; timed as "normals")
        if normals_same:
            assert prev is not None
            out["normals"], out["crest"] = prev.normals, prev.crest
            timings["normals"] = prev.timings.get("normals", 0.0)
        else:  # computed on their own thread since the run started: joined here
            assert background is not None
            cn, timings["normals"] = background.result()
            out["normals"], out["crest"] = cn.normals, cn.crest

        def _plan_progress(done: int, total: int) -> None:
            if progress is not None:
                progress((4 + done / max(total, 1)) / (last + 1))

        def _grasps() -> dict[str, Any]:
            assert hand is not None  # loaded by the pool stage above
            masks = out["masks"]
            normals, assumed, crest = out["normals"], cloud.assumed, out["crest"]
            geom, occ = obstacles()
            n_extra = len(geom) - len(points)  # the obstacle points after the cloud's
            if n_extra:  # (planner/assumed.py: never contacts)
                extra = [] if occ is None else [occ.normals]
                if scene_obstacles is not None:
                    extra.append(_obstacle_normals(scene_obstacles, cloud, masks))
                normals = np.concatenate([normals, *extra])
                seen = np.zeros(len(points), dtype=bool) if assumed is None else assumed
                assumed = np.concatenate([seen, np.zeros(n_extra, dtype=bool)])
                if crest is not None:
                    crest = np.concatenate([crest, np.zeros(n_extra, dtype=bool)])
            gs = planner(
                geom,
                normals,
                out["pool"],
                run_hand,
                params.planner,
                support=None if masks is None else masks.support,
                progress=_plan_progress,
                assumed=assumed,
                crest=crest,
            )
            if n_extra:
                gs = without_occupied(
                    gs, points, out["normals"], cloud.assumed, run_hand, params.planner,
                    len(out["pool"]), out["crest"],
                )  # fmt: skip
            return {"grasps": gs}

        stage(
            "grasps",
            "pool" in reused and pp is not None and pp.planner == params.planner,
            ("grasps",),
            _grasps,
        )
        tick(4)
    return PipelineResult(
        cloud=cloud,
        params=params,
        timings=timings,
        reused=tuple(reused),
        hand=hand if last >= 3 else (prev.hand if prev is not None else None),
        occupied=hidden[0] if hidden and last >= 3 else None,
        occluded_used=mode if cloud.sensor is not None else "completed",
        **out,
    )


def _obstacle_normals(obstacles: np.ndarray, cloud: PointCloud, masks: Any) -> np.ndarray:
    """(K, 3) unit normals for the scene's obstacle points: toward the camera of a single view,
    else the support plane's up, else +z. The planner never keeps a contact on them
    (``without_occupied``), so they only orient a contact it moves to the cloud."""
    if cloud.viewpoint is not None:
        d = np.asarray(cloud.viewpoint, dtype=np.float64) - obstacles
        length = np.linalg.norm(d, axis=1, keepdims=True)
        return np.where(length > 0.0, d / np.maximum(length, 1e-300), [0.0, 0.0, 1.0])
    sp = None if masks is None else getattr(masks, "support", None)
    up = np.asarray(getattr(sp, "normal", (0.0, 0.0, 1.0)), dtype=np.float64)
    return np.tile(up / np.linalg.norm(up), (len(obstacles), 1))


def occupied_of(
    cloud: PointCloud, params: PipelineParams, mode: str | None = None
) -> OccupiedSpace | None:
    """The hidden space of a single view as obstacle points (``sensor/occluded.py``) when the
    setting (``mode``, default :func:`planned_mode`: ``occupied`` for ``occupied`` and
    ``auto``) is ``occupied`` and ``cloud`` is a view, else None."""
    sv = cloud.sensor
    if mode is None:
        mode = planned_mode(cloud, params)
    if mode != "occupied" or sv is None:
        return None
    return occupied_space(sv.points[~sv.assumed], sv.points, sv.viewpoint, sv.plane)


def with_cloud(params: PipelineParams, cloud: PointCloud) -> PipelineParams:
    """``params`` completed by what a single view knows: the camera (``cloud.viewpoint``) as
    the normals' viewpoint unless one is given, and the scene's table
    (``cloud.sensor.plane``, or a complete scene's ``cloud.support``) as the support plane
    unless ``support_height`` is given."""
    normals = params.planner.normals
    if cloud.viewpoint is not None and normals.viewpoint is None:
        x, y, z = (float(v) for v in cloud.viewpoint)
        vp = (x, y, z)
        planner = dataclasses.replace(
            params.planner, normals=dataclasses.replace(normals, viewpoint=vp)
        )
        params = dataclasses.replace(params, planner=planner)
    if cloud.sensor is not None and params.facemask.support_height is None:
        params = dataclasses.replace(
            params, facemask=cloud.sensor.face_mask_params(params.facemask)
        )
    elif cloud.support is not None and params.facemask.support_height is None:
        n = cloud.support.normal  # a complete scene's table
        facemask = dataclasses.replace(
            params.facemask,
            support=True,
            up=(float(n[0]), float(n[1]), float(n[2])),
            support_height=float(cloud.support.height),
        )
        params = dataclasses.replace(params, facemask=facemask)
    return params


def view_normals(cloud: PointCloud, params: NormalParams, threads: int = 0) -> np.ndarray:
    """(N, 3) normals of ``cloud``; for a completed view, those of the visible points
    (oriented as ``params`` says, toward the camera by default) and, for the assumed points,
    their source's normal moved by the symmetry (``SensorView.full_normals``). ``threads``:
    those of the normals' kernels (0: the usable CPUs; the normals do not depend on it)."""
    return view_cloud_normals(cloud, params, threads).normals


def view_cloud_normals(cloud: PointCloud, params: NormalParams, threads: int = 0) -> CloudNormals:
    """:func:`view_normals` with the rest of their ``CloudNormals`` (the crest-rule points of
    a cloud without normals, which the planner takes; for a completed view, the visible
    points' flags followed by False for the assumed points)."""
    sv = cloud.sensor
    if sv is None or not np.any(sv.assumed):
        return estimate_normals(cloud.points, params, reference=cloud.normals, threads=threads)
    visible = np.asarray(cloud.points)[~sv.assumed]
    cn = estimate_normals(visible, params, threads=threads)
    crest = None
    if cn.crest is not None:
        crest = np.zeros(len(sv.assumed), dtype=bool)
        crest[~sv.assumed] = cn.crest
    return dataclasses.replace(cn, normals=sv.full_normals(cn.normals), crest=crest)


def background_threads(cloud: PointCloud, params: NormalParams) -> int:
    """Threads of the normals computed beside the stages up to the pool (:func:`run_pipeline`):
    one for the plain PCA of a cloud with normals or a viewpoint (a compiled pass of about 30 ms
    at 20,000 points, done before the stages beside it, about 50 ms: a second thread of its
    would only take the core they run on; measured on the default object, the stages around
    the planner 70 ms with two, 59 ms with one, docs/benchmarks.md), else the usable CPUs (the
    scale selection and visibility take several times as long)."""
    sv = cloud.sensor
    has_ref = cloud.normals is not None and (sv is None or not np.any(sv.assumed))
    return 1 if orient_rule(params, has_ref) in PLAIN_RULES else 0


def _load_hand() -> Hand:
    from .hand import Hand

    return Hand.load()


def pool_section(result: PipelineResult) -> dict[str, object]:
    """The ``pool`` section of the result file: support plane, traversal and pre-grasps."""
    if result.pool is None:
        raise ValueError("the result has no pool: run the pipeline with until='pool'")
    masks = result.masks
    return {
        "support_plane": None
        if masks is None or masks.support is None
        else masks.support.to_dict(),
        "traversal": None if result.traversal is None else result.traversal.to_dict(),
        **result.pool.to_dict(),
    }


def result_document(
    result: PipelineResult,
    params: PipelineParams | None = None,
    include_indices: bool = False,
    extra_timings: dict[str, float] | None = None,
    simulation: SimulatedRanking | None = None,
    plain: bool = True,
) -> JsonDocument:
    """The ``pregrasp/1`` document of a pipeline result (tree with face masks, pool, timings).

    extra_timings: stages run outside the pipeline (e.g. ``load``), listed first. simulation:
    the lift test of the best grasps (``result.grasps`` re-ranked by it): each simulated
    grasp's outcome, its ``best`` and ``parameters.simulation``. plain: as
    :func:`pregrasp_core.result.result_document` (``False``: the pool and grasps sections as
    built, for ``write_result`` or ``to_jsonable`` only).
    """
    params = result.params if params is None else params
    if result.tree is None:
        raise ValueError("the result has no tree: run the pipeline at least to 'decompose'")
    timings = {**(extra_timings or {}), **result.timings}
    extra: dict[str, object] = {}
    if result.pool is not None:
        extra["pool"] = pool_section(result)
    if result.grasps is not None:
        if result.hand is None:
            raise ValueError("the result has grasps but no hand: it was not made by run_pipeline")
        extra.update(grasps_sections(result.grasps, result.hand, params.planner, simulation))
    sections: dict[str, object] = dict(params.as_dict())
    if params.occluded != "auto":  # written only when not the default (docs/result-schema)
        sections["occluded"] = params.occluded
    if result.cloud.sensor is not None:  # a single view: the setting actually planned
        sections["occluded_used"] = result.occluded_used
    if simulation is not None:
        sections["simulation"] = simulation.params
    return _result_document(
        result.cloud,
        sections,
        timings,
        result.tree,
        result.shapes,
        face_masks=None if result.masks is None else result.masks.masks,
        include_indices=include_indices,
        extra_sections=extra,
        plain=plain,
    )
