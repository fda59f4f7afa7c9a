"""`pregrasp plan`: the whole pipeline (decomposition, shapes, face masks, pre-grasp pool,
slicing contact planner, quality) on one object or on every object of a folder.

One object: ``-o OUT.json`` writes the ``pregrasp/1`` result (tree, pool, grasps, best, timings
per stage); ``-o -`` prints the JSON; without ``-o`` a readable summary (parts, pool size, the
best grasps with type, contacts and epsilon).

``--simulate K`` runs the MuJoCo lift test (``pregrasp_core.simulate``, ``docs/simulation.md``)
on the best K ranked grasps and re-ranks them (:func:`rank_by_lift`): among the simulated
grasps those that lifted the object come first, then those that did not, then the others as the
planner ranked them; ``best`` is the best force-closure grasp that lifted, when one did. The
result file keeps each simulated grasp's outcome (``docs/result-schema.md``, "simulation").

A folder: every mesh or cloud in it (sorted by name) is planned in turn with a text progress bar
on stderr (files that do not read as a cloud, such as a ``manifest.csv``, are listed as
skipped); ``--report report.csv`` writes one row per object (object, points, parts, pool, kept,
force closure, best type, contacts, epsilon, volume, seconds, error, simulated, lifted), else
the CSV goes to stdout; ``-o DIR`` also writes ``DIR/<object>.json`` per object. ``--jobs J``
plans J objects at a time in worker processes (each with a one-thread planner unless
``--threads`` says otherwise); ``--scheduler ADDRESS`` plans them on the workers of a running
Dask distributed scheduler instead (see :func:`batch_executor`). Either way the workers return
each object's row and result document (and run its ``--simulate`` lift test) and this process
writes the files; the report lists the objects in name order whatever order they finish in.
An object that fails, whatever the exception (a reader failing on a malformed file, the planner
running out of memory), gets its error in the ``error`` column and a line on stderr, and the
batch goes on (exit 1 at the end).

The options are those of :mod:`app.commands.common` for the input and the stages (generated
from the parameter dataclasses) and :class:`PlanOutput` for what is written.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import csv
import dataclasses
import functools
import io
import json
import multiprocessing
import sys
import time
from collections.abc import Iterator
from concurrent.futures import Executor, ProcessPoolExecutor, as_completed
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, TextIO

import numpy as np

from pregrasp_core.errors import InputError, PregraspError
from pregrasp_core.hand import Hand, load_hand
from pregrasp_core.io import SUPPORTED_EXTENSIONS, PointCloud
from pregrasp_core.pipeline import (
    PipelineParams,
    PipelineResult,
    occluded_note,
    result_document,
    run_pipeline,
)
from pregrasp_core.planner import Grasp, GraspSet, PlannerParams
from pregrasp_core.planner.rank import score_text
from pregrasp_core.planner.serialize import SimulatedRanking
from pregrasp_core.result import JsonValue, to_jsonable, write_result

from .common import ALL_STAGES, INPUT_OPTIONS, InputOptions, add_input_args, pipeline_options
from .common import input_path as _input_path
from .options import Flag, HelpFormatter, Options
from .pregrasps import pool_stages

if TYPE_CHECKING:  # importing pregrasp_core.simulate imports MuJoCo: only when --simulate runs
    from pregrasp_core.simulate import SimulationParams, SimulationResult

REPORT_COLUMNS: tuple[str, ...] = (
    "object",
    "points",
    "parts",
    "pool",
    "kept",
    "force_closure",
    "best_type",
    "best_contacts",
    "best_epsilon",
    "best_volume",
    "seconds",
    "error",
    "simulated",
    "lifted",
)
"""Columns of the batch report (CSV); ``simulated`` and ``lifted`` count the grasps of
``--simulate`` (0 and 0 without it)."""


@dataclass(frozen=True)
class PlanOutput:
    """What ``pregrasp plan`` writes, and how it runs a folder."""

    top: int = 5
    """Grasps listed in the summary (>= 0)."""
    output: str | None = None
    """Result JSON file ('-' = stdout); for a folder INPUT, a directory for one JSON per
    object."""
    report: str | None = None
    """Folder INPUT: write the per-object CSV report here (default: stdout)."""
    include_indices: bool = False
    """Store each node's point indices in the JSON."""
    jobs: int = 1
    """For a folder INPUT: plan this many objects at a time in worker processes (>= 1; with
    more than one, each planner runs on one thread unless --threads is given)."""
    scheduler: str | None = None
    """For a folder INPUT: plan the objects on the workers of this running Dask distributed
    scheduler (e.g. tcp://10.0.0.5:8786) instead of local worker processes; needs pip install
    'pregrasp[batch]', and the input files at the same path on the workers."""
    simulate: int = 0
    """Test the best K ranked grasps with a MuJoCo lift (approach, close, lift 10 cm, hold 1 s;
    docs/simulation.md) and rank those that lifted first; each outcome goes into the result
    file. Costs about 0.1-0.2 s of CPU per grasp plus the object's collision model (0.1-10 s,
    once per object). 0 = off."""

    def __post_init__(self) -> None:
        if self.top < 0:
            raise ValueError(f"top must be >= 0, got {self.top}")
        if isinstance(self.simulate, bool) or self.simulate < 0:
            raise ValueError(
                f"simulate must be a number of grasps >= 0 (0 = off), got {self.simulate}"
            )
        if self.jobs < 1:
            raise ValueError(f"jobs must be >= 1, got {self.jobs}")
        if self.scheduler is not None and not self.scheduler.strip():
            raise ValueError("scheduler must be an address such as tcp://HOST:8786, got ''")
        if self.scheduler is not None and self.jobs != 1:
            raise ValueError(
                "scheduler cannot be combined with --jobs: the cluster's workers set how many "
                "objects run at a time"
            )


@dataclass(frozen=True)
class PlanRun:
    """Everything one planning run needs, as plain data (it goes to the worker processes)."""

    input: InputOptions
    """How a file becomes a cloud."""
    params: PipelineParams
    """The parameters of every stage."""
    output: PlanOutput
    """What is written."""


PIPELINE_OPTIONS = pipeline_options(ALL_STAGES)
"""The options of every stage of the pipeline (``pregrasp view`` takes the same)."""

OUTPUT_OPTIONS: Options[PlanOutput] = Options(
    PlanOutput,
    "output and folders",
    "output",
    flags={
        "top": Flag(metavar="K"),
        "output": Flag(("-o", "--output"), "OUT"),
        "report": Flag(metavar="CSV"),
        "include_indices": Flag(store_true=True),
        "jobs": Flag(metavar="J"),
        "scheduler": Flag(metavar="ADDRESS"),
        "simulate": Flag(metavar="K"),
    },
)


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "plan",
        formatter_class=HelpFormatter,
        help="plan grasps: decomposition, pre-grasp pool, slicing planner, quality",
        description="Run the whole pipeline on INPUT (a file, or a folder of objects) and rank "
        "the grasps by Ferrari-Canny epsilon (L1), then wrench-hull volume. Writes the "
        "pregrasp/1 JSON with -o, else prints a summary; on a folder writes a CSV report. "
        "--simulate K tests the best K grasps with a MuJoCo lift and ranks those that lifted "
        "first.",
    )
    add_input_args(p, what="point cloud or mesh file, or a folder of them")
    PIPELINE_OPTIONS.add_to(p)
    OUTPUT_OPTIONS.add_to(p)
    p.set_defaults(func=run)


def plan_run(args: argparse.Namespace) -> PlanRun:
    """The options of ``args`` as a :class:`PlanRun`; a bad value raises ``OptionError``."""
    output, params = OUTPUT_OPTIONS.build(args), PIPELINE_OPTIONS.build(args)
    q = params.planner.quality  # every grasp listed or simulated gets exact scores
    if max(output.top, output.simulate) > q.exact_top:
        q = dataclasses.replace(q, exact_top=max(output.top, output.simulate))
        params = dataclasses.replace(params, planner=dataclasses.replace(params.planner, quality=q))
    return PlanRun(input=INPUT_OPTIONS.build(args), params=params, output=output)


def plan_loaded(
    cloud: PointCloud, t_load: float, params: PipelineParams, hand: Hand, simulate: int = 0
) -> tuple[PipelineResult, dict[str, float], LiftTest | None]:
    """Plan a loaded cloud: (PipelineResult, timings with ``load`` first, the lift test of the
    best ``simulate`` grasps or None). With a lift test the result's grasps are re-ranked by it
    (:func:`rank_by_lift`) and the timings end with ``simulate``."""
    result = run_pipeline(cloud, params, hand, until="grasps")
    if simulate > 0:
        lift = lift_test(result, simulate, hand)
        result = dataclasses.replace(
            result, grasps=lift.grasps, timings={**result.timings, "simulate": lift.seconds}
        )
        return result, {"load": t_load, **result.timings}, lift
    return result, {"load": t_load, **result.timings}, None


def result_doc(
    result: PipelineResult,
    timings: dict[str, float],
    include_indices: bool,
    lift: LiftTest | None = None,
) -> dict[str, Any]:
    """The ``pregrasp/1`` document of a planned result (with the lift test's outcomes), its
    pool and grasps sections as built (numpy arrays): for ``write_result``, or ``to_jsonable``
    for plain JSON (the same text either way, without a plain copy of ~10^5 numbers first)."""
    return result_document(
        result,
        include_indices=include_indices,
        extra_timings={"load": timings["load"]},
        simulation=None if lift is None else lift.section(),
        plain=False,
    )


# ------------------------------------------------------------------------------ lift test


@dataclass(frozen=True)
class LiftTest:
    """The lift test of ``--simulate K`` on one object and the ranking it gives."""

    grasps: GraspSet
    """The planner's grasps re-ranked (:func:`rank_by_lift`): ``ranking`` and every kept
    grasp's ``rank`` changed, nothing else."""
    results: dict[int, SimulationResult]
    """Index into ``grasps.grasps`` -> the outcome of that grasp's lift (the simulated ones)."""
    best: int | None
    """The best grasp under the re-ranking (see :func:`rank_by_lift`)."""
    best_reason: str
    """Why, in one sentence."""
    params: SimulationParams
    """The parameters of the test."""
    seconds: float
    """Wall-clock seconds of the test (the object's collision model and every lift)."""

    @property
    def n_lifted(self) -> int:
        """Simulated grasps that lifted the object."""
        return sum(r.success for r in self.results.values())

    def section(self) -> SimulatedRanking:
        """What the result file records of the test."""
        return SimulatedRanking(
            outcomes={i: r.to_dict() for i, r in self.results.items()},
            best=self.best,
            best_reason=self.best_reason,
            params=self.params,
        )


def lift_test(result: PipelineResult, k: int, hand: Hand) -> LiftTest:
    """Simulate the lift of the best ``k`` ranked grasps of ``result`` (fewer when fewer were
    kept) with default ``SimulationParams`` and re-rank them by it."""
    from pregrasp_core.simulate import SimulationParams, simulate_grasps

    gs = _grasps(result)
    params = SimulationParams()
    t0 = time.perf_counter()
    top = [int(i) for i in gs.ranking[:k]]
    outcomes = simulate_grasps(result, top, hand, params) if top else []
    results = dict(zip(top, outcomes, strict=True))
    ranked, best, reason = rank_by_lift(gs, {i: r.success for i, r in results.items()})
    return LiftTest(ranked, results, best, reason, params, time.perf_counter() - t0)


def rank_by_lift(gs: GraspSet, lifted: dict[int, bool]) -> tuple[GraspSet, int | None, str]:
    """The ranking of ``gs`` after a lift test: ``lifted`` maps the index (into ``gs.grasps``)
    of each simulated grasp to whether it lifted the object.

    Ranking: the simulated grasps that lifted, then the simulated grasps that did not, then the
    grasps that were not simulated, each group in the planner's order (epsilon, then volume).
    Best: the first force-closure grasp (epsilon > 0) of the new ranking that lifted when there
    is one, else the planner's ``gs.best``. Returns (the re-ranked set, best, best_reason)."""
    order = [int(i) for i in gs.ranking]
    unknown = sorted(set(lifted) - set(order))
    if unknown:
        raise ValueError(f"simulated grasps {unknown} are not kept grasps of the set")
    ok = [i for i in order if lifted.get(i) is True]
    failed = [i for i in order if lifted.get(i) is False]
    ranking = ok + failed + [i for i in order if i not in lifted]
    rank_of = {i: r for r, i in enumerate(ranking)}
    grasps = tuple(
        dataclasses.replace(g, rank=rank_of[i]) if i in rank_of else g
        for i, g in enumerate(gs.grasps)
    )  # renumbers the kept grasps' records (a loop over records, not over points)
    ranked = dataclasses.replace(gs, grasps=grasps, ranking=np.asarray(ranking, dtype=np.int64))
    tally = f"{len(lifted)} simulated, {len(ok)} lifted"
    fc_ok = [i for i in ok if gs.grasps[i].epsilon > 0.0]
    if fc_ok:
        g = gs.grasps[fc_ok[0]]
        reason = (
            f"force closure and lifted in simulation: the best of {len(fc_ok)} force-closure "
            f"grasps that lifted ({tally}) has epsilon {g.epsilon:.4f} with {g.n_contacts} "
            "contacts"
        )
        return ranked, fc_ok[0], reason
    if not lifted:
        why = "no grasp simulated (no kept grasp)"
    elif ok:
        why = f"no force-closure grasp lifted in simulation ({tally}); best as ranked by epsilon"
    else:
        why = f"no simulated grasp lifted ({tally}); best as ranked by epsilon"
    return ranked, gs.best, f"{gs.best_reason}; {why}"


def run(args: argparse.Namespace) -> int:
    job = plan_run(args)  # every option checked before any work
    out = job.output
    path = Path(_input_path(args))
    hand = load_hand()
    if path.is_dir():
        return run_batch(path, job, hand)
    if out.jobs != 1:
        raise PregraspError("--jobs is for a folder INPUT")
    if out.scheduler is not None:
        raise PregraspError("--scheduler is for a folder INPUT")
    if out.report is not None:
        raise PregraspError("--report is for a folder INPUT; use -o OUT.json for one object")
    t0 = time.perf_counter()
    cloud = job.input.load(path)
    result, timings, lift = plan_loaded(
        cloud, time.perf_counter() - t0, job.params, hand, out.simulate
    )
    if out.output is None:
        print(summary(result, timings, out.top, lift))
        return 0
    doc = result_doc(result, timings, out.include_indices, lift)
    if out.output == "-":
        json.dump(to_jsonable(doc), sys.stdout, indent=1)
        sys.stdout.write("\n")
        return 0
    written = write_result(doc, out.output)
    gs = _grasps(result)
    best, reason = best_of(result, lift)
    tail = (
        f", best {gs.grasps[best].grasp_type} epsilon {gs.grasps[best].epsilon:.4f}"
        if best is not None
        else f", {reason}"
    )
    pool = result.pool
    if pool is not None and len(pool) == 0 and any(pool.dropped.values()):
        tail += f" (every sample dropped: {_counts(pool.dropped)})"  # (see docs/pregrasps.md)
    if lift is not None:
        tail += f"; {len(lift.results)} simulated, {lift.n_lifted} lifted"
    if note := occluded_note(result):
        tail += f"; {note}"
    print(
        f"wrote {written}: {len(result.pool or ())} pre-grasps, {len(gs.ranking)} grasps kept{tail}"
    )
    return 0


def best_of(result: PipelineResult, lift: LiftTest | None) -> tuple[int | None, str]:
    """(best, best_reason): the lift test's when there is one, else the planner's."""
    if lift is not None:
        return lift.best, lift.best_reason
    gs = _grasps(result)
    return gs.best, gs.best_reason


def _grasps(result: PipelineResult) -> GraspSet:
    if result.grasps is None:
        raise ValueError("the result has no grasps: run the pipeline to 'grasps'")
    return result.grasps


# ------------------------------------------------------------------------------ summary


def summary(
    result: PipelineResult, timings: dict[str, float], top: int, lift: LiftTest | None = None
) -> str:
    """A readable summary of a planned result (``lift``: its lift test, ``result`` re-ranked by
    it: a ``lift`` column, yes / no / - when not simulated)."""
    tree, _, _, _, pool = pool_stages(result)
    cloud, gs = result.cloud, _grasps(result)
    best_index, best_reason = best_of(result, lift)
    lines = [
        f"object: {cloud.source} ({len(cloud.points)} points)",
        f"parts: {len(tree.leaves())} (tree of {len(tree.nodes)} nodes)",
        f"pool: {len(pool)} pre-grasps"
        + (f" (dropped {_counts(pool.dropped)})" if any(pool.dropped.values()) else ""),
        f"planned: {len(gs.ranking)} kept, {gs.n_force_closure} force closure"
        + (f"; rejected {_counts(gs.rejected)}" if any(gs.rejected.values()) else ""),
    ]
    if lift is not None:
        lines.append(
            f"lift test (MuJoCo): {len(lift.results)} simulated, {lift.n_lifted} lifted "
            f"({lift.seconds:.1f} s)"
        )
        lines.append(f"best: {best_reason}")
    elif best_index is None:  # "no force-closure grasp: ..." (the ranking keeps epsilon 0)
        lines.append(best_reason)
    best = gs.top(top)
    if best:
        order = "by epsilon, then volume"
        if lift is not None:
            order = "simulated grasps that lifted first, then " + order
        lines.append(f"best {len(best)} grasps (#1 = best; {order}):")
        lift_head = f" {'lift':>4}" if lift else ""
        lines.append(
            f"  {'#':>4}  {'type':<17} {'node':>4} {'pre':>5} {'contacts':>8} "
            f"{'epsilon':>8} {'volume':>10}{lift_head}  links"
        )
        for g in best:
            links = ",".join(c.link for c in g.contacts)
            rank = -1 if g.rank is None else g.rank  # kept grasps all have a rank
            col = ""
            if lift is not None:  # grasps[i].pregrasp == i: the key of lift.results
                sim = lift.results.get(g.pregrasp)
                col = f" {'-' if sim is None else 'yes' if sim.success else 'no':>4}"
            lines.append(
                f"  {rank + 1:>4}  {g.grasp_type:<17} {int(pool.node[g.pregrasp]):>4} "
                f"{g.pregrasp:>5} {g.n_contacts:>8} "
                f"{score_text(g.epsilon, g.epsilon_exact, '.4f'):>8} "
                f"{score_text(g.volume, g.volume_exact, '.3e'):>10}{col}"
                f"  {links}"
            )
        lines.append("by grasp type (why the best has its type):")
        lines.extend("  " + line for line in type_lines(result))
    else:
        lines.append("no grasp kept")
    total = sum(timings.values())
    lines.append(
        "timings: " + ", ".join(f"{k} {v:.3f} s" for k, v in timings.items()) + f"; total "
        f"{total:.3f} s"
    )
    return "\n".join(lines)


def type_lines(result: PipelineResult) -> list[str]:
    """One line per grasp type of the pool, best epsilon first: pre-grasps, kept, force
    closure, and its best grasp's epsilon, contacts and node (shape class)."""
    _, shapes, _, _, pool = pool_stages(result)
    gs = _grasps(result)
    best_of: dict[str, Grasp] = {}
    count: dict[str, list[int]] = {}
    for g in gs.grasps:  # loop over grasps for a summary of a few lines
        c = count.setdefault(g.grasp_type, [0, 0, 0])
        c[0] += 1
        c[1] += g.kept
        c[2] += g.epsilon > 0.0
    for g in gs.ranked:
        best_of.setdefault(g.grasp_type, g)
    out = []
    for t in sorted(count, key=lambda t: -(best_of[t].epsilon if t in best_of else -1.0)):
        n, kept, fc = count[t]
        text = f"{t}: {n} pre-grasps, {kept} kept, {fc} force closure"
        b = best_of.get(t)
        if b is not None:
            node = int(pool.node[b.pregrasp])
            cls = shapes[node].shape_class.value
            text += (
                f"; best epsilon {b.epsilon:.4f} with {b.n_contacts} contacts (node {node}, {cls})"
            )
        out.append(text)
    return out


def _counts(d: dict[str, int]) -> str:
    return ", ".join(f"{k} {v}" for k, v in d.items() if v)


# ------------------------------------------------------------------------------ batch

Row = dict[str, object]
"""One row of the batch report: :data:`REPORT_COLUMNS` -> value."""


def objects_in(folder: Path) -> list[Path]:
    """The files of ``folder`` that ``load_point_cloud`` reads, sorted by name."""
    files = sorted(
        p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in SUPPORTED_EXTENSIONS
    )
    if not files:
        raise InputError(
            f"{folder}: no point cloud or mesh files (expected one of "
            f"{', '.join(SUPPORTED_EXTENSIONS)})"
        )
    return files


def report_row(
    name: str, result: PipelineResult, seconds: float, lift: LiftTest | None = None
) -> Row:
    """One CSV row of the batch report for a planned result (and its lift test: the best grasp
    is then the lift test's, see :func:`rank_by_lift`)."""
    tree, _, _, _, pool = pool_stages(result)
    gs = _grasps(result)
    best, _ = best_of(result, lift)
    row: Row = {
        "object": name,
        "points": len(result.cloud.points),
        "parts": len(tree.leaves()),
        "pool": len(pool),
        "kept": len(gs.ranking),
        "force_closure": gs.n_force_closure,
        "best_type": "",
        "best_contacts": 0,
        "best_epsilon": 0.0,
        "best_volume": 0.0,
        "seconds": round(seconds, 4),
        "error": "",
        "simulated": 0 if lift is None else len(lift.results),
        "lifted": 0 if lift is None else lift.n_lifted,
    }
    if best is not None:
        g = gs.grasps[best]
        row.update(
            best_type=g.grasp_type,
            best_contacts=g.n_contacts,
            best_epsilon=round(g.epsilon, 6),
            best_volume=float(f"{g.volume:.6g}"),
        )
    return row


def error_row(name: str, error: str, seconds: float) -> Row:
    """The report row of an object that was skipped or failed: only its name, time and error."""
    row: Row = {c: "" for c in REPORT_COLUMNS}
    row.update(object=name, seconds=round(seconds, 4), error=error)
    return row


class ProgressBar:
    """A text progress bar on a stream (stderr): redrawn in place on a terminal, one line per
    update otherwise (logs stay readable)."""

    def __init__(self, total: int, stream: TextIO | None = None, width: int = 30) -> None:
        self.total = max(int(total), 1)
        self.stream = sys.stderr if stream is None else stream
        self.width = width
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())

    def update(self, done: int, label: str = "") -> None:
        filled = int(round(self.width * done / self.total))
        bar = "#" * filled + "." * (self.width - filled)
        text = f"[{bar}] {done}/{self.total} {label}"
        if self.tty:
            self.stream.write("\r" + text.ljust(self.width + 40))
            if done >= self.total:
                self.stream.write("\n")
        else:
            self.stream.write(text + "\n")
        self.stream.flush()

    def note(self, text: str) -> None:
        """A line of its own (an object's error); on a terminal it replaces the bar, which the
        next update draws again below it."""
        if self.tty:
            self.stream.write("\r" + text.ljust(self.width + 40) + "\n")
        else:
            self.stream.write(text + "\n")
        self.stream.flush()


def _error_text(f: Path, exc: BaseException) -> str:
    """The report's error for ``exc``: the core's own message (it names the file and what to
    do), else the exception's type and message, so that an unexpected failure is still told."""
    text = str(exc) if isinstance(exc, PregraspError) else f"{type(exc).__name__}: {exc}"
    return text if f.name in text else f"{f}: {text}"


BatchItem = tuple[Row, bool, JsonValue]
"""What planning one file of a batch gives: ``(report row, failed, result document)``; the
document is plain JSON data (``None`` when the file failed or no ``-o DIR`` was asked for)."""


def _batch_item(f: Path, job: PlanRun, hand: Hand, with_doc: bool) -> BatchItem:
    """Plan one file of a batch. A file that does not read as a cloud or mesh gives a row with
    ``skipped: <reason>``; any other failure, while reading the file or planning it, a row with
    the error (``failed``); neither stops the batch. With ``with_doc`` the result document comes
    back as plain JSON data (the caller writes it: a worker on another machine need not see the
    output folder)."""
    t0 = time.perf_counter()
    try:
        cloud = job.input.load(f)
    except InputError as exc:  # not an object (a manifest, notes...): listed, skipped
        return error_row(f.name, f"skipped: {exc}", time.perf_counter() - t0), False, None
    except Exception as exc:  # a reader failing on a malformed file: told, the batch goes on
        return error_row(f.name, _error_text(f, exc), time.perf_counter() - t0), True, None
    try:
        result, timings, lift = plan_loaded(
            cloud, time.perf_counter() - t0, job.params, hand, job.output.simulate
        )
        row = report_row(f.name, result, time.perf_counter() - t0, lift)
        doc = None
        if with_doc:
            doc = to_jsonable(result_doc(result, timings, job.output.include_indices, lift))
        return row, False, doc
    except Exception as exc:  # a failed object does not stop the batch
        return error_row(f.name, _error_text(f, exc), time.perf_counter() - t0), True, None


@functools.cache
def _worker_hand() -> Hand:
    """The hand of a worker process (loaded once per process)."""
    return load_hand()


def _worker_item(f: Path, job: PlanRun, with_doc: bool) -> BatchItem:
    """:func:`_batch_item` in a worker process (local or on a Dask worker)."""
    return _batch_item(f, job, _worker_hand(), with_doc)


SCHEDULER_TIMEOUT_S = 5.0
"""How long ``--scheduler`` waits to reach the scheduler, and for it to have a worker."""


def batch_executor(out: PlanOutput, n_files: int) -> contextlib.AbstractContextManager[Executor]:
    """Where the objects of a batch run: ``n_files`` is the number of objects.

    The local default is a pool of ``min(--jobs, n_files)`` spawned worker processes (no state
    shared with this one); with ``--scheduler`` the workers of that Dask distributed scheduler
    (:func:`_dask_executor`). Both are ``concurrent.futures`` executors: the batch loop submits
    :func:`_worker_item` and reads the futures as they finish, the same code either way."""
    if out.scheduler is not None:
        return _dask_executor(out.scheduler)
    jobs = min(out.jobs, n_files)
    return ProcessPoolExecutor(jobs, mp_context=multiprocessing.get_context("spawn"))


@contextlib.contextmanager
def _dask_executor(address: str) -> Iterator[Executor]:
    """An executor on the workers of the Dask scheduler at ``address`` (imported only here:
    ``distributed`` is the optional ``batch`` extra). The address is probed first, so that an
    unreachable scheduler is one ``PregraspError`` after :data:`SCHEDULER_TIMEOUT_S`, not a
    client left half-open."""
    try:
        from distributed import Client
        from distributed.comm import connect
    except ImportError:
        raise PregraspError(
            "--scheduler needs Dask distributed: pip install 'pregrasp[batch]'"
        ) from None

    async def probe() -> None:
        comm = await connect(address, timeout=SCHEDULER_TIMEOUT_S)
        await comm.close()

    try:
        asyncio.run(probe())
    except (OSError, ValueError, TypeError) as exc:  # refused, timed out, a bad address
        raise PregraspError(
            f"--scheduler {address}: cannot reach the Dask scheduler ({exc})"
        ) from None
    try:
        client = Client(address, timeout=SCHEDULER_TIMEOUT_S, set_as_default=False)
    except (OSError, ValueError) as exc:
        raise PregraspError(f"--scheduler {address}: cannot connect a client ({exc})") from None
    try:
        try:
            client.wait_for_workers(1, timeout=SCHEDULER_TIMEOUT_S)
        except TimeoutError:
            raise PregraspError(
                f"--scheduler {address}: the scheduler has no worker after "
                f"{SCHEDULER_TIMEOUT_S:g} s; start one with dask worker {address}"
            ) from None
        # pure=False: every object is its own task, even two files with equal names and options
        with client.get_executor(pure=False) as ex:
            yield ex
    finally:
        client.close()


def _write_item(item: BatchItem, f: Path, out_dir: Path | None) -> tuple[Row, bool]:
    """Write the result document of a batch item to ``out_dir/<object>.json``: ``(row,
    failed)``. A file that cannot be written turns the row into an error row (the batch goes
    on)."""
    row, failed, doc = item
    if out_dir is None or not isinstance(doc, dict):  # no -o DIR, or the object failed
        return row, failed
    try:
        write_result(doc, out_dir / f"{f.stem}.json")
    except Exception as exc:
        err = error_row(f.name, _error_text(f, exc), 0.0)
        err["seconds"] = row["seconds"]
        return err, True
    return row, failed


def run_batch(folder: Path, job: PlanRun, hand: Hand) -> int:
    """Plan every object of ``folder``; write the CSV report. Files that do not read as a cloud
    or mesh (a manifest, notes) are listed with ``skipped: <reason>``; an object that fails is
    listed with its error (and told on stderr) and the others go on. The exit status is 1 when
    an object failed, or when nothing could be planned."""
    out = job.output
    files = objects_in(folder)
    out_dir = None
    if out.output is not None:
        if out.output == "-":
            raise PregraspError("-o - is for one object; for a folder give a directory")
        out_dir = Path(out.output)
        out_dir.mkdir(parents=True, exist_ok=True)
    with_doc = out_dir is not None
    bar = ProgressBar(len(files))
    results: list[tuple[Row, bool] | None] = [None] * len(files)

    def done(k: int, item: BatchItem, n_done: int) -> None:
        results[k] = row_failed = _write_item(item, files[k], out_dir)
        if row_failed[0]["error"]:
            bar.note(f"pregrasp plan: {'error: ' if row_failed[1] else ''}{row_failed[0]['error']}")
        bar.update(n_done, files[k].name)

    if out.scheduler is None and min(out.jobs, len(files)) <= 1:
        bar.update(0, "")
        for k, f in enumerate(files):  # loop over objects, in this process
            done(k, _batch_item(f, job, hand, with_doc), k + 1)
    else:  # worker processes: local (spawned, no state shared with this one) or a cluster's
        planner = job.params.planner
        if planner.threads == PlannerParams().threads:  # the default: one thread per process
            params = dataclasses.replace(
                job.params, planner=dataclasses.replace(planner, threads=1)
            )
            job = dataclasses.replace(job, params=params)
        with batch_executor(out, len(files)) as ex:
            bar.update(0, "")
            futures = {ex.submit(_worker_item, f, job, with_doc): k for k, f in enumerate(files)}
            for n_done, fut in enumerate(as_completed(futures), start=1):  # as they finish
                k = futures[fut]
                try:
                    item = fut.result()
                except Exception as exc:  # the worker itself died (killed, out of memory)
                    why = f"{files[k]}: worker process failed: {type(exc).__name__}: {exc}"
                    item = error_row(files[k].name, why, 0.0), True, None
                done(k, item, n_done)
    rows = [r[0] for r in results if r is not None]
    failed = sum(1 for r in results if r is not None and r[1])
    text = io.StringIO()
    writer = csv.DictWriter(text, fieldnames=list(REPORT_COLUMNS), lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    if out.report is None:
        sys.stdout.write(text.getvalue())
    else:
        Path(out.report).write_text(text.getvalue())
        n_fc = sum(1 for r in rows if r["best_epsilon"] not in ("", 0.0))
        n_ok = sum(1 for r in rows if not r["error"])
        skipped = sum(1 for r in rows if str(r["error"]).startswith("skipped:"))
        print(
            f"wrote {out.report}: {n_ok} objects planned"
            + (f" ({skipped} file{'s' if skipped > 1 else ''} skipped)" if skipped else "")
            + (f", {failed} failed" if failed else "")
            + f", best grasp force closure on {n_fc}"
        )
    planned = sum(1 for r in rows if not r["error"])
    return 1 if failed or planned == 0 else 0
