"""`pregrasp decompose`: split a cloud into a tree of boxes and classify the parts by PCA.

With ``-o OUT.json`` writes the ``pregrasp/1`` result (input, parameters, timings per stage,
tree); ``-o -`` prints the JSON to stdout; without ``-o`` prints a readable summary.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from pregrasp_core.decomposition import BoxTree, DecompositionParams, decompose
from pregrasp_core.io import PointCloud
from pregrasp_core.result import result_document, to_jsonable, write_result
from pregrasp_core.shape import NodeShape, classify_tree

from .common import INPUT_OPTIONS, add_input_args, input_path, pipeline_options
from .options import Flag, HelpFormatter, Options


@dataclass(frozen=True)
class DecomposeOutput:
    """Where ``pregrasp decompose`` writes its result."""

    output: str | None = None
    """Write the pregrasp/1 result JSON here ('-' for stdout); without it, print a summary."""
    include_indices: bool = False
    """Store each node's point indices in the JSON."""


PIPELINE_OPTIONS = pipeline_options(("decomposition", "shape"))
"""The decomposition and shape-class options."""

OUTPUT_OPTIONS: Options[DecomposeOutput] = Options(
    DecomposeOutput,
    "output",
    "output",
    flags={
        "output": Flag(("-o", "--output"), "OUT.json"),
        "include_indices": Flag(store_true=True),
    },
)


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "decompose",
        formatter_class=HelpFormatter,
        help="split a cloud into a tree of oriented boxes and classify the parts",
        description="Fit-and-split decomposition into minimum-volume boxes, PCA shape class and "
        "grasp type per node. Writes the pregrasp/1 JSON with -o, else prints a summary.",
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
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    cloud = inp.load(input_path(args))
    t1 = time.perf_counter()
    tree = decompose(cloud.points, params.decomposition)
    t2 = time.perf_counter()
    shapes = classify_tree(tree, cloud.points, params.shape)
    t3 = time.perf_counter()
    timings.update(load=t1 - t0, decompose=t2 - t1, classify=t3 - t2)
    doc = result_document(
        cloud,
        {"decomposition": params.decomposition, "shape": params.shape},
        timings,
        tree,
        shapes,
        include_indices=out.include_indices,
        seed=inp.seed,
    )
    if out.output == "-":
        json.dump(to_jsonable(doc), sys.stdout, indent=1, allow_nan=False)
        sys.stdout.write("\n")
    elif out.output is not None:
        written = write_result(doc, out.output)
        print(f"wrote {written}: {len(tree.leaves())} parts, {len(tree.nodes)} nodes")
    else:
        print(summary(cloud, inp.seed, params.decomposition, timings, tree, shapes))
    return 0


def summary(
    cloud: PointCloud,
    seed: int,
    par: DecompositionParams,
    timings: dict[str, float],
    tree: BoxTree,
    shapes: tuple[NodeShape, ...],
) -> str:
    """A short readable report: object, points, parts, the tree, times."""
    info = cloud.info
    kind = f"{info['kind']}, {info.get('format')}" if info.get("kind") else str(info.get("format"))
    lines = [
        f"object:  {Path(cloud.source).name} ({kind}), {len(cloud.points)} points, seed {seed}",
        f"parts:   {len(tree.leaves())} ({tree.n_splits} split{'' if tree.n_splits == 1 else 's'}; "
        f"volume ratio "
        f"{par.volume_ratio}, min points {par.min_points}, max depth {par.max_depth})",
        "",
        f"  {'node':<14} {'class':<9} {'grasp type':<17} {'extents (mm)':>20} {'points':>8}",
    ]
    stack = [0]  # depth-first, children in order, for an indented listing
    while stack:
        nd = tree.node(stack.pop())
        stack.extend(reversed(nd.children))
        sh = shapes[nd.id]
        e = nd.box.extents * 1000.0
        ext = f"{e[0]:.0f} x {e[1]:.0f} x {e[2]:.0f}"
        name = "  " * nd.depth + f"{nd.id}" + ("" if nd.children else " *")
        lines.append(
            f"  {name:<14} {sh.shape_class.value:<9} {sh.grasp_type.value:<17} {ext:>20} "
            f"{nd.n_points:>8}"
        )
    lines.append("  (* = leaf, a part)")
    times = ", ".join(f"{k} {v * 1000:.1f} ms" for k, v in timings.items())
    lines += ["", f"times:   {times}; total {sum(timings.values()) * 1000:.1f} ms"]
    for w in info.get("warnings", []):
        lines.append(f"warning: {w}")
    return "\n".join(lines)
