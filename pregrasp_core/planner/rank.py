"""Exact scores where they decide what the user sees, bounds elsewhere (issue 15).

The planner scores every kept grasp at the cheapest level that still decides force closure
(:data:`~pregrasp_core.quality.LEVEL_CHEAPEST`: an upper bound of epsilon and of the volume when
one proves the grasp's force closure either way, else the exact hull), then
:func:`settle_exact` makes exact, best first, the grasps that can still enter

* the best ``QualityParams.exact_top`` of the ranking, and
* the first place of each grasp type,

by branch and bound: the grasps are sorted by their scores (exact or upper bound; epsilon, then
volume, then contacts, then pre-grasp index, as :func:`~pregrasp_core.planner.plan.rank_grasps`
sorts them); while the first K of a group are not all exact, each of them that is not is
refined one level (the half-cone bounds, then the exact hull) and the group is sorted again.
A refined score is never above its bound, so a grasp among the first K stays there until it is
exact, and once the first K are exact every other grasp's bound -- hence its exact score -- is
below the K-th: the first K are the exact ranking's first K, in the same order. The set of
refined grasps depends only on the scores, never on the threads. ``exact_all`` scores every
kept grasp exactly from the start. See ``docs/quality.md``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from ..quality import (
    LEVEL_CHEAPEST,
    LEVEL_EXACT,
    LEVEL_HALF_CONES,
    QUALITY_BOUNDS,
    GraspQuality,
    QualityParams,
    contact_wrenches,
    forget_cheap_bounds,
    grasp_quality,
    object_frame,
    wrench_quality,
)
from .types import Grasp

Frame = tuple[np.ndarray, float] | None
"""The torque origin and scale (the object's centroid and radius), None = about the contacts."""


def quality_frame(params: QualityParams, points: np.ndarray) -> Frame:
    """GraspIt's torque frame of the cloud ``points`` (N, 3) when ``params.torque_origin`` is
    'object' (docs/quality.md), else None (torques about the contacts)."""
    if params.torque_origin == "object" and len(points) > 0:
        return object_frame(points)
    return None


SMALL_POOL_FACTOR: int = 3
"""A pool of at most this many times ``exact_top`` pre-grasps is scored exactly from the start:
there, most kept grasps end exact anyway (they are in the best ``exact_top``, or few are force
closure and the rest are ranked by volume, whose bounds are loose), and the bounds would only
add their cost (measured on the demo objects: 0.5-0.8 times the speed of exact scores for
pools of 9 to 52 pre-grasps, docs/benchmarks.md). Speed only: the ranking is the same."""


def first_level(params: QualityParams, n_pool: int | None = None) -> int:
    """The level every kept grasp is scored at first: exact with ``exact_all`` or for a pool
    of ``n_pool <= SMALL_POOL_FACTOR * exact_top`` pre-grasps, else the cheapest level that
    decides force closure."""
    if params.exact_all or (n_pool is not None and n_pool <= SMALL_POOL_FACTOR * params.exact_top):
        return LEVEL_EXACT
    return LEVEL_CHEAPEST


def grasp_wrenches(params: QualityParams, frame: Frame, g: Grasp) -> np.ndarray:
    """The edge wrenches (K * m, 6) of ``g``'s contacts (:func:`contact_wrenches`), with the
    first cone edges along the contacts' tangents and torques about ``frame``."""
    center, radius = frame if frame is not None else (None, None)
    return contact_wrenches(
        np.array([c.point for c in g.contacts]).reshape(-1, 3),
        np.array([c.normal for c in g.contacts]).reshape(-1, 3),
        params,
        tangents=np.array([c.tangent for c in g.contacts]).reshape(-1, 3),
        center=center,
        radius=radius,
    )


def with_quality(g: Grasp, q: GraspQuality) -> Grasp:
    """``g`` with the scores, exactness and detail of ``q``."""
    return dataclasses.replace(
        g,
        epsilon=q.epsilon,
        volume=q.volume,
        detail=q.reason,
        epsilon_exact=q.epsilon_exact,
        volume_exact=q.volume_exact,
        quality_bound=q.bound,
    )


def score_grasp(params: QualityParams, frame: Frame, level: int, g: Grasp) -> Grasp:
    """``g`` with the epsilon, volume, exactness and quality detail of its contacts at
    ``level`` (:func:`pregrasp_core.quality.grasp_quality`)."""
    pts = np.array([c.point for c in g.contacts]).reshape(-1, 3)
    nrm = np.array([c.normal for c in g.contacts]).reshape(-1, 3)
    tng = np.array([c.tangent for c in g.contacts]).reshape(-1, 3)
    center, radius = frame if frame is not None else (None, None)
    q = grasp_quality(pts, nrm, params, tangents=tng, center=center, radius=radius, level=level)
    return with_quality(g, q)


def is_exact(g: Grasp) -> bool:
    """Whether both scores of ``g`` are exact."""
    return g.epsilon_exact and g.volume_exact


def rank_key(g: Grasp) -> tuple[float, float, int, int]:
    """Sort key of the ranking, best first: epsilon, volume, contacts (descending), then the
    pre-grasp index."""
    return (-g.epsilon, -g.volume, -g.n_contacts, g.pregrasp)


def next_level(g: Grasp) -> int:
    """The level that refines ``g``: a force-closure grasp gets the half-cone bounds after the
    directions' bound (its epsilon bound then typically falls from about 3.7 to 1.3 times the
    exact value, which drops most of them out of the best), then the exact hull; a grasp proven
    not force closure (its epsilon exactly 0, ranked by volume) goes straight to the exact
    hull, the half-cone bound of the volume being too loose to drop it."""
    fc_bound = g.quality_bound == QUALITY_BOUNDS[0] and not g.epsilon_exact
    return LEVEL_HALF_CONES if fc_bound else LEVEL_EXACT


QualityJob = tuple[np.ndarray, int, int, int]
"""The arguments of one :func:`~pregrasp_core.quality.wrench_quality` call: the edge wrenches,
the number of contacts, the cone edges per contact and the level."""

Qualities = Callable[[list[QualityJob]], list[GraspQuality]]
"""Scores a list of jobs, in order (e.g. shared among processes, ``planner/plan.py``)."""


def run_quality_job(job: QualityJob) -> GraspQuality:
    """:func:`~pregrasp_core.quality.wrench_quality` of one job."""
    return wrench_quality(*job)


def settle_exact(
    grasps: Sequence[Grasp],
    params: QualityParams,
    frame: Frame,
    ex: ThreadPoolExecutor | None = None,
    qualities: Qualities | None = None,
) -> tuple[list[Grasp], int]:
    """``(grasps, n_refined)``: ``grasps`` (pool order) with exact scores for every grasp that
    can enter the best ``params.exact_top`` or the first place of its grasp type (module
    docstring); the refinements of one round run on ``ex`` when given, or are handed to
    ``qualities`` (the same :func:`~pregrasp_core.quality.wrench_quality` calls, in order)."""
    out = list(grasps)
    kept = [i for i, g in enumerate(out) if g.kept]
    groups: list[tuple[list[int], int]] = [(kept, int(params.exact_top))]
    for t in sorted({out[i].grasp_type for i in kept}):  # loop over the (<= 4) grasp types
        groups.append(([i for i in kept if out[i].grasp_type == t], 1))
    wrenches: dict[int, np.ndarray] = {}  # built once per refined grasp

    def job(i: int, exact: bool) -> QualityJob:
        g = out[i]
        if i not in wrenches:
            wrenches[i] = grasp_wrenches(params, frame, g)
        level = LEVEL_EXACT if exact else next_level(g)
        return wrenches[i], g.n_contacts, params.n_edges, level

    n_refined = 0
    for members, k in groups:  # loop over the groups (the ranking, then each type)
        # a group no larger than k is all in its first k: straight to the exact hull
        exact = len(members) <= k
        while k > 0:  # each round refines every inexact grasp among the group's first k
            top = sorted(members, key=lambda i: rank_key(out[i]))[:k]
            todo = [i for i in top if not is_exact(out[i])]
            if not todo:
                break
            jobs = [job(i, exact) for i in todo]
            if qualities is not None:
                done = qualities(jobs)
            elif ex is not None and len(jobs) > 1:
                done = list(ex.map(run_quality_job, jobs))
            else:
                done = [run_quality_job(j) for j in jobs]
            for i, q in zip(todo, done, strict=True):
                out[i] = with_quality(out[i], q)
            n_refined += len(todo)
    forget_cheap_bounds()  # (the refinements reused the plan's cheapest bounds: dropped now)
    return out, n_refined


def score_text(value: float, exact: bool, spec: str) -> str:
    """A score for people: ``format(value, spec)``, prefixed by ``<= `` when it is an upper
    bound rather than the exact value (so that a bound is never shown as if exact)."""
    text = format(float(value), spec)
    return text if exact else f"<= {text}"
