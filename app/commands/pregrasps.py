"""`pregrasp pregrasps`: the pipeline up to the pre-grasp pool (no planning).

Decomposition, shape classes, face masks with the support plane, traversal and the pool. With
``-o OUT.json`` writes the ``pregrasp/1`` result (tree with face masks, pool, timings per stage);
``-o -`` prints the JSON; without ``-o`` prints a readable summary (candidates, pool per node
and grasp type, drops per reason, times).

The options of the stages come from :mod:`app.commands.common` (generated from the core's
parameter dataclasses), the same definition ``pregrasp plan`` and ``pregrasp view`` use.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pregrasp_core.decomposition import BoxTree
from pregrasp_core.facemask import FaceMasks
from pregrasp_core.pipeline import PipelineResult, result_document, run_pipeline
from pregrasp_core.pregrasps import PreGraspPool, Traversal
from pregrasp_core.result import to_jsonable, write_result
from pregrasp_core.shape import NodeShape

from .common import INPUT_OPTIONS, POOL_STAGES, add_input_args, input_path, pipeline_options
from .options import Flag, HelpFormatter, Options


@dataclass(frozen=True)
class PregraspsOutput:
    """Where ``pregrasp pregrasps`` writes its result."""

    output: str | None = None
    """Write the pregrasp/1 result JSON here ('-' for stdout); without it, print a summary."""


PIPELINE_OPTIONS = pipeline_options(POOL_STAGES)
"""The options of every stage up to the pool."""

OUTPUT_OPTIONS: Options[PregraspsOutput] = Options(
    PregraspsOutput, "output", "output", flags={"output": Flag(("-o", "--output"), "OUT.json")}
)


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "pregrasps",
        formatter_class=HelpFormatter,
        help="generate the pre-grasp pool of an object (no planning)",
        description="Decomposition, PCA grasp types, face masks (with a support plane under the "
        "object unless --no-support), tree traversal and the pre-grasp pool sampled on the "
        "enclosing surfaces. Writes the pregrasp/1 JSON with -o, else prints a summary.",
    )
    add_input_args(p)
    PIPELINE_OPTIONS.add_to(p)
    OUTPUT_OPTIONS.add_to(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    # options first: a bad value fails before any slow work
    params = PIPELINE_OPTIONS.build(args)
    inp = INPUT_OPTIONS.build(args)
    out = OUTPUT_OPTIONS.build(args)
    t0 = time.perf_counter()
    cloud = inp.load(input_path(args))
    t_load = time.perf_counter() - t0
    result = run_pipeline(cloud, params, until="pool")
    doc = result_document(result, params, extra_timings={"load": t_load})
    if out.output == "-":
        json.dump(to_jsonable(doc), sys.stdout, indent=1, allow_nan=False)
        sys.stdout.write("\n")
    elif out.output is not None:
        written = write_result(doc, out.output)
        tree, _, _, _, pool = pool_stages(result)
        print(f"wrote {written}: {len(tree.leaves())} parts, {len(pool)} pre-grasps")
    else:
        print(summary(result, {"load": t_load, **result.timings}))
    return 0


def pool_stages(
    result: PipelineResult,
) -> tuple[BoxTree, tuple[NodeShape, ...], FaceMasks, Traversal, PreGraspPool]:
    """(tree, shapes, masks, traversal, pool) of a result run at least to the ``pool`` stage."""
    tree, shapes, masks = result.tree, result.shapes, result.masks
    trav, pool = result.traversal, result.pool
    if tree is None or shapes is None or masks is None or trav is None or pool is None:
        raise ValueError("the result has no pool: run the pipeline at least to 'pool'")
    return tree, shapes, masks, trav, pool


def summary(result: PipelineResult, timings: dict[str, float]) -> str:
    """A readable report: object, parts, candidates with reasons, pool per node and type."""
    tree, shapes, masks, trav, pool = pool_stages(result)
    support = masks.support
    lines = [
        f"object:   {Path(result.cloud.source).name}, {len(result.cloud.points)} points",
        f"parts:    {len(tree.leaves())} ({len(tree.nodes)} nodes)",
        "support:  "
        + (
            "none"
            if support is None
            else f"normal {np.round(support.normal, 3).tolist()} at {support.height:.4f} m"
        ),
        f"policy:   {trav.policy.value}",
        "",
        f"  {'node':<8} {'grasp type':<30} {'blocked faces':<14} {'pool':>5}  traversal",
    ]
    per_node = pool.counts()["per_node"]
    for nd in tree.nodes:
        blocked = "".join(str(int(b)) for b in masks.blocked[nd.id])
        gt = shapes[nd.id].grasp_type.value
        if nd.id in pool.fallback:
            gt = f"{gt}->{pool.fallback[nd.id]}"
        name = "  " * nd.depth + str(nd.id) + ("" if nd.children else " *")
        lines.append(
            f"  {name:<8} {gt:<30} {blocked:<14} {per_node.get(nd.id, 0):>5}  {trav.reasons[nd.id]}"
        )
    lines.append("  (* = leaf; blocked faces in the order +x -x +y -y +z -z of the box frame)")
    per_type = ", ".join(f"{k} {v}" for k, v in pool.counts()["per_type"].items()) or "none"
    drops = ", ".join(f"{k} {v}" for k, v in pool.dropped.items())
    times = ", ".join(f"{k} {v * 1000:.1f} ms" for k, v in timings.items())
    lines += [
        "",
        f"pool:     {len(pool)} pre-grasps ({per_type})",
        f"dropped:  {drops}",
        f"times:    {times}; total {sum(timings.values()) * 1000:.1f} ms",
    ]
    return "\n".join(lines)
