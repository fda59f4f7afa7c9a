"""`pregrasp plan`: the whole pipeline (decomposition, shapes, face masks, pre-grasp pool,
slicing contact planner, quality) on one object or on every object of a folder.

One object: ``-o OUT.json`` writes the ``pregrasp/1`` result (tree, pool, grasps, best, timings
per stage); ``-o -`` prints the JSON; without ``-o`` a readable summary (parts, pool size, the
best grasps with type, contacts and epsilon).

A folder: every mesh or cloud in it (sorted by name) is planned in turn with a text progress bar
on stderr (files that do not read as a cloud, such as a ``manifest.csv``, are listed as
skipped); ``--report report.csv`` writes one row per object (object, points, parts, pool, kept,
force closure, best type, contacts, epsilon, volume, seconds, error), else the CSV goes to
stdout; ``-o DIR`` also writes ``DIR/<object>.json`` per object. ``--jobs J`` plans J objects
at a time in worker processes (each with a one-thread planner unless ``--threads`` says
otherwise); the report lists the objects in name order whatever order they finish in.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import functools
import io
import json
import multiprocessing
import sys
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path
from typing import Any, TextIO

from pregrasp_core.errors import InputError, PregraspError
from pregrasp_core.io import SUPPORTED_EXTENSIONS, load_point_cloud
from pregrasp_core.planner import PlannerParams
from pregrasp_core.quality import QualityParams
from pregrasp_core.result import to_jsonable, write_result

from . import common, pregrasps

_PP = PlannerParams()
_QP = QualityParams()

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
)
"""Columns of the batch report (CSV)."""


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "plan",
        help="plan grasps: decomposition, pre-grasp pool, slicing planner, quality",
        description="Run the whole pipeline on INPUT (a file, or a folder of objects) and rank "
        "the grasps by Ferrari-Canny epsilon (L1), then wrench-hull volume. Writes the "
        "pregrasp/1 JSON with -o, else prints a summary; on a folder writes a CSV report.",
    )
    common.add_input_args(p)
    common.add_decomposition_args(p)
    common.add_shape_args(p)
    pregrasps.add_pool_args(p)
    add_planner_args(p)
    g = p.add_argument_group("output")
    g.add_argument(
        "--top", type=int, default=5, metavar="K", help="grasps listed in the summary (default 5)"
    )
    g.add_argument(
        "-o",
        "--output",
        metavar="OUT",
        default=None,
        help="result JSON file ('-' = stdout); for a folder INPUT, a directory for one JSON "
        "per object",
    )
    g.add_argument(
        "--report",
        metavar="CSV",
        default=None,
        help="folder INPUT: write the per-object CSV report here (default: stdout)",
    )
    g.add_argument("--include-indices", action="store_true", help="store each node's point indices")
    p.set_defaults(func=run)


def add_planner_args(p: argparse.ArgumentParser) -> None:
    """Options of the planner and the quality measure (defaults of ``PlannerParams``)."""
    g = p.add_argument_group("planner and quality")
    g.add_argument(
        "--mu",
        type=float,
        default=_QP.mu,
        metavar="MU",
        help="friction coefficient (default %(default)s)",
    )
    g.add_argument(
        "--cone-edges",
        type=int,
        default=_QP.n_edges,
        metavar="M",
        help="edges of each linearised friction cone (default %(default)s)",
    )
    g.add_argument(
        "--clearance",
        type=float,
        default=_PP.approach_clearance,
        metavar="D",
        help="the approach stops this far from the cloud, metres (default %(default)s)",
    )
    g.add_argument(
        "--contact-distance",
        type=float,
        default=_PP.contact_distance,
        metavar="D",
        help="a link within D metres of the cloud makes a contact (default %(default)s)",
    )
    g.add_argument(
        "--penetration-tol",
        type=float,
        default=_PP.penetration_tol,
        metavar="D",
        help="largest depth of a cloud point inside the final hand, metres (default %(default)s)",
    )
    g.add_argument(
        "--threads",
        type=int,
        default=_PP.threads,
        metavar="T",
        help="planner threads; 0 = one per CPU, 1 = none (default %(default)s; results never "
        "depend on it)",
    )
    g.add_argument(
        "--jobs",
        type=int,
        default=1,
        metavar="J",
        help="for a folder INPUT: plan J objects at a time in worker processes (default "
        "%(default)s; with J > 1 each planner runs on one thread unless --threads is given)",
    )


def planner_params(args: argparse.Namespace) -> PlannerParams:
    """The ``PlannerParams`` of the parsed options; bad values become a ``PregraspError``."""
    try:
        return PlannerParams(
            approach_clearance=args.clearance,
            contact_distance=args.contact_distance,
            penetration_tol=args.penetration_tol,
            quality=QualityParams(mu=args.mu, n_edges=args.cone_edges),
            threads=args.threads,
        )
    except ValueError as exc:
        raise PregraspError(f"invalid planner option: {exc}") from exc


def pipeline_params(args: argparse.Namespace) -> Any:
    """``PipelineParams`` with every stage's options from ``args``."""
    return dataclasses.replace(pregrasps.pipeline_params(args), planner=planner_params(args))


def plan_one(path: str | Path, args: argparse.Namespace, hand: Any) -> tuple[Any, dict]:
    """Load and plan one object: (PipelineResult, timings with ``load`` first)."""
    t0 = time.perf_counter()
    cloud = load_point_cloud(path, n_points=args.points, seed=args.seed, scale=args.scale)
    return plan_loaded(cloud, time.perf_counter() - t0, args, hand)


def plan_loaded(cloud: Any, t_load: float, args: argparse.Namespace, hand: Any) -> tuple:
    """Plan a loaded cloud: (PipelineResult, timings with ``load`` first)."""
    from pregrasp_core.pipeline import run_pipeline

    result = run_pipeline(cloud, pipeline_params(args), hand, until="grasps")
    return result, {"load": t_load, **result.timings}


def result_doc(result: Any, timings: dict, args: argparse.Namespace) -> dict:
    """The ``pregrasp/1`` document of a planned result."""
    from pregrasp_core.pipeline import result_document

    return result_document(
        result,
        include_indices=args.include_indices,
        extra_timings={"load": timings["load"]},
    )


def run(args: argparse.Namespace) -> int:
    from pregrasp_core.hand import load_hand

    if args.top < 0:
        raise PregraspError(f"--top must be >= 0, got {args.top}")
    if args.jobs < 1:
        raise PregraspError(f"--jobs must be >= 1, got {args.jobs}")
    path = Path(common.input_path(args))
    pipeline_params(args)  # validate every option before any work
    hand = load_hand()
    if path.is_dir():
        return run_batch(path, args, hand)
    if args.jobs != 1:
        raise PregraspError("--jobs is for a folder INPUT")
    if args.report is not None:
        raise PregraspError("--report is for a folder INPUT; use -o OUT.json for one object")
    result, timings = plan_one(path, args, hand)
    if args.output is None:
        print(summary(result, timings, args.top))
        return 0
    doc = result_doc(result, timings, args)
    if args.output == "-":
        json.dump(to_jsonable(doc), sys.stdout, indent=1)
        sys.stdout.write("\n")
        return 0
    out = write_result(doc, args.output)
    gs = result.grasps
    best = gs.best
    tail = (
        f", best {gs.grasps[best].grasp_type} epsilon {gs.grasps[best].epsilon:.4f}"
        if best is not None
        else ", no grasp kept"
    )
    print(f"wrote {out}: {len(result.pool)} pre-grasps, {len(gs.ranking)} grasps kept{tail}")
    return 0


# ------------------------------------------------------------------------------ summary


def summary(result: Any, timings: dict, top: int) -> str:
    """A readable summary of a planned result."""
    cloud, tree, pool, gs = result.cloud, result.tree, result.pool, result.grasps
    lines = [
        f"object: {cloud.source} ({len(cloud.points)} points)",
        f"parts: {len(tree.leaves())} (tree of {len(tree.nodes)} nodes)",
        f"pool: {len(pool)} pre-grasps"
        + (f" (dropped {_counts(pool.dropped)})" if any(pool.dropped.values()) else ""),
        f"planned: {len(gs.ranking)} kept, {gs.n_force_closure} force closure"
        + (f"; rejected {_counts(gs.rejected)}" if any(gs.rejected.values()) else ""),
    ]
    best = gs.top(top)
    if best:
        lines.append(f"best {len(best)} grasps (#1 = best; by epsilon, then volume):")
        lines.append(
            f"  {'#':>4}  {'type':<17} {'node':>4} {'pre':>5} {'contacts':>8} "
            f"{'epsilon':>8} {'volume':>10}  links"
        )
        for g in best:
            links = ",".join(c.link for c in g.contacts)
            lines.append(
                f"  {g.rank + 1:>4}  {g.grasp_type:<17} {int(pool.node[g.pregrasp]):>4} "
                f"{g.pregrasp:>5} {g.n_contacts:>8} {g.epsilon:>8.4f} {g.volume:>10.3e}  {links}"
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


def type_lines(result: Any) -> list[str]:
    """One line per grasp type of the pool, best epsilon first: pre-grasps, kept, force
    closure, and its best grasp's epsilon, contacts and node (shape class)."""
    gs, pool, shapes = result.grasps, result.pool, result.shapes
    best_of: dict[str, Any] = {}
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
            cls = shapes[node].shape_class.value if shapes is not None else "?"
            text += (
                f"; best epsilon {b.epsilon:.4f} with {b.n_contacts} contacts (node {node}, {cls})"
            )
        out.append(text)
    return out


def _counts(d: dict) -> str:
    return ", ".join(f"{k} {v}" for k, v in d.items() if v)


# ------------------------------------------------------------------------------ batch


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


def report_row(name: str, result: Any, seconds: float) -> dict[str, Any]:
    """One CSV row of the batch report for a planned result."""
    gs = result.grasps
    row: dict[str, Any] = {
        "object": name,
        "points": len(result.cloud.points),
        "parts": len(result.tree.leaves()),
        "pool": len(result.pool),
        "kept": len(gs.ranking),
        "force_closure": gs.n_force_closure,
        "best_type": "",
        "best_contacts": 0,
        "best_epsilon": 0.0,
        "best_volume": 0.0,
        "seconds": round(seconds, 4),
        "error": "",
    }
    if gs.best is not None:
        g = gs.grasps[gs.best]
        row.update(
            best_type=g.grasp_type,
            best_contacts=g.n_contacts,
            best_epsilon=round(g.epsilon, 6),
            best_volume=float(f"{g.volume:.6g}"),
        )
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


def _batch_item(f: Path, args: argparse.Namespace, hand: Any, out_dir: Path | None) -> tuple:
    """Plan one file of a batch: ``(report row, failed)``. A file that does not read as a
    cloud or mesh gives a row with ``skipped: <reason>``; a later failure a row with the error."""
    t0 = time.perf_counter()
    error, failed = "", False
    try:
        cloud = load_point_cloud(f, n_points=args.points, seed=args.seed, scale=args.scale)
    except InputError as exc:  # not an object (a manifest, notes...): listed, skipped
        error = f"skipped: {exc}"
    else:
        try:
            result, timings = plan_loaded(cloud, time.perf_counter() - t0, args, hand)
            row = report_row(f.name, result, time.perf_counter() - t0)
            if out_dir is not None:
                write_result(result_doc(result, timings, args), out_dir / f"{f.stem}.json")
            return row, False
        except PregraspError as exc:  # a failed object does not stop the batch
            error, failed = str(exc), True
    row = {c: "" for c in REPORT_COLUMNS}
    row.update(object=f.name, seconds=round(time.perf_counter() - t0, 4), error=error)
    return row, failed


@functools.cache
def _worker_hand() -> Any:
    """The hand of a worker process (loaded once per process)."""
    from pregrasp_core.hand import load_hand

    return load_hand()


def _worker_item(f: Path, args: argparse.Namespace, out_dir: Path | None) -> tuple:
    """:func:`_batch_item` in a worker process."""
    return _batch_item(f, args, _worker_hand(), out_dir)


def run_batch(folder: Path, args: argparse.Namespace, hand: Any) -> int:
    """Plan every object of ``folder``; write the CSV report. Files that do not read as a cloud
    or mesh (a manifest, notes) are listed with ``skipped: <reason>``; the exit status is 1 when
    an object that loaded failed later, or when nothing could be planned."""
    files = objects_in(folder)
    out_dir = None
    if args.output is not None:
        if args.output == "-":
            raise PregraspError("-o - is for one object; for a folder give a directory")
        out_dir = Path(args.output)
        out_dir.mkdir(parents=True, exist_ok=True)
    bar = ProgressBar(len(files))
    results: list[tuple | None] = [None] * len(files)
    bar.update(0, "")
    jobs = min(int(args.jobs), len(files))
    if jobs <= 1:
        for k, f in enumerate(files):  # loop over objects
            results[k] = _batch_item(f, args, hand, out_dir)
            bar.update(k + 1, f.name)
    else:  # worker processes (spawned: no state shared with this one)
        if args.threads == _PP.threads:  # the default: one planner thread per process
            args = argparse.Namespace(**{**vars(args), "threads": 1})
        ctx = multiprocessing.get_context("spawn")
        with ProcessPoolExecutor(jobs, mp_context=ctx) as ex:
            futures = {ex.submit(_worker_item, f, args, out_dir): k for k, f in enumerate(files)}
            for done, fut in enumerate(as_completed(futures), start=1):  # as they finish
                k = futures[fut]
                results[k] = fut.result()
                bar.update(done, files[k].name)
    rows = [r[0] for r in results if r is not None]
    failed = sum(1 for r in results if r is not None and r[1])
    text = io.StringIO()
    writer = csv.DictWriter(text, fieldnames=list(REPORT_COLUMNS), lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    if args.report is None:
        sys.stdout.write(text.getvalue())
    else:
        Path(args.report).write_text(text.getvalue())
        n_fc = sum(1 for r in rows if r["best_epsilon"] not in ("", 0.0))
        n_ok = sum(1 for r in rows if not r["error"])
        skipped = sum(1 for r in rows if str(r["error"]).startswith("skipped:"))
        print(
            f"wrote {args.report}: {n_ok} objects planned"
            + (f" ({skipped} file{'s' if skipped > 1 else ''} skipped)" if skipped else "")
            + f", best grasp force closure on {n_fc}"
        )
    planned = sum(1 for r in rows if not r["error"])
    return 1 if failed or planned == 0 else 0
