"""`pregrasp pregrasps`: the pipeline up to the pre-grasp pool (no planning).

Decomposition, shape classes, face masks with the support plane, traversal and the pool. With
``-o OUT.json`` writes the ``pregrasp/1`` result (tree with face masks, pool, timings per stage);
``-o -`` prints the JSON; without ``-o`` prints a readable summary (candidates, pool per node
and grasp type, drops per reason, times).

The face-mask and sampling options are shared with ``pregrasp plan``: :func:`add_pool_args`
registers them and :func:`pipeline_params` builds the whole ``PipelineParams`` from ``args``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from app.commands.common import (
    add_decomposition_args,
    add_input_args,
    add_output_arg,
    add_shape_args,
    decomposition_params,
    load_cloud,
    shape_params,
)
from pregrasp_core.errors import PregraspError
from pregrasp_core.facemask import FaceMaskParams
from pregrasp_core.pipeline import PipelineParams, PipelineResult, result_document, run_pipeline
from pregrasp_core.pregrasps import SamplingParams, TraversalPolicy
from pregrasp_core.result import to_jsonable, write_result

_FP = FaceMaskParams()
_SA = SamplingParams()


def add_pool_args(p: argparse.ArgumentParser) -> None:
    """Face-mask, support-plane and sampling options (defaults of the core's dataclasses)."""
    g = p.add_argument_group("face masks and support plane")
    g.add_argument(
        "--face-clearance",
        type=float,
        default=_FP.clearance,
        metavar="M",
        help="depth in front of a face that must be empty for it to be free (default %(default)s)",
    )
    g.add_argument(
        "--no-support",
        action="store_true",
        help="no support plane (a free-floating object); default: a table under the object",
    )
    g.add_argument(
        "--support-height",
        type=float,
        default=None,
        metavar="Z",
        help="height of the support plane along the up axis (default: the lowest cloud point)",
    )
    g.add_argument(
        "--up",
        type=float,
        nargs=3,
        default=list(_FP.up),
        metavar=("X", "Y", "Z"),
        help="world up direction, the support plane's normal (default 0 0 1)",
    )
    g = p.add_argument_group("traversal and sampling")
    g.add_argument(
        "--interval",
        type=float,
        default=_SA.interval,
        metavar="M",
        help="distance between samples on the enclosing surface (default %(default)s)",
    )
    g.add_argument(
        "--policy",
        choices=[t.value for t in TraversalPolicy],
        default=_SA.policy.value,
        help="which nodes get pre-grasps: the paper's two conditions, the leaves that fit, or "
        "all nodes (default %(default)s)",
    )
    g.add_argument(
        "--aperture-scale",
        type=float,
        default=_SA.aperture_scale,
        metavar="F",
        help="multiply the hand's aperture in the fit test (default %(default)s)",
    )
    g.add_argument(
        "--max-backoff",
        type=float,
        default=_SA.max_backoff,
        metavar="M",
        help="how far a pre-grasp may back off along its approach to clear the table and the "
        "cloud (default %(default)s)",
    )
    g.add_argument(
        "--no-fallback",
        action="store_true",
        help="only the grasp type of each part's shape class (the paper's fixed mapping)",
    )


_OPTION_OF_FIELD = {
    "clearance": "--face-clearance",
    "support_height": "--support-height",
    "up": "--up",
    "interval": "--interval",
    "aperture_scale": "--aperture-scale",
    "max_backoff": "--max-backoff",
    "policy": "--policy",
}


def _option_error(what: str, exc: ValueError) -> PregraspError:
    msg = str(exc)
    for field, option in _OPTION_OF_FIELD.items():
        if msg.startswith(field):
            msg = option + msg[len(field) :]
            break
    return PregraspError(f"invalid {what} option: {msg}")


def facemask_params(args: argparse.Namespace) -> FaceMaskParams:
    """``FaceMaskParams`` from ``args``; invalid values raise ``PregraspError``."""
    try:
        return FaceMaskParams(
            clearance=args.face_clearance,
            support=not args.no_support,
            up=tuple(args.up),
            support_height=args.support_height,
        )
    except ValueError as exc:
        raise _option_error("face-mask", exc) from None


def sampling_params(args: argparse.Namespace) -> SamplingParams:
    """``SamplingParams`` from ``args``; invalid values raise ``PregraspError``."""
    try:
        return SamplingParams(
            interval=args.interval,
            policy=args.policy,
            aperture_scale=args.aperture_scale,
            max_backoff=args.max_backoff,
            fallback=not args.no_fallback,
        )
    except ValueError as exc:
        raise _option_error("sampling", exc) from None


def pipeline_params(args: argparse.Namespace) -> PipelineParams:
    """The whole ``PipelineParams`` from the input/decomposition/shape/pool options."""
    return PipelineParams(
        decomposition=decomposition_params(args),
        shape=shape_params(args),
        facemask=facemask_params(args),
        sampling=sampling_params(args),
    )


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "pregrasps",
        help="generate the pre-grasp pool of an object (no planning)",
        description="Decomposition, PCA grasp types, face masks (with a support plane under the "
        "object unless --no-support), tree traversal and the pre-grasp pool sampled on the "
        "enclosing surfaces. Writes the pregrasp/1 JSON with -o, else prints a summary.",
    )
    add_input_args(p)
    add_decomposition_args(p)
    add_shape_args(p)
    add_pool_args(p)
    add_output_arg(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    params = pipeline_params(args)  # a bad option fails before any slow work
    t0 = time.perf_counter()
    cloud = load_cloud(args)
    t_load = time.perf_counter() - t0
    result = run_pipeline(cloud, params, until="pool")
    doc = result_document(result, params, extra_timings={"load": t_load})
    if args.output == "-":
        json.dump(to_jsonable(doc), sys.stdout, indent=1, allow_nan=False)
        sys.stdout.write("\n")
    elif args.output is not None:
        out = write_result(doc, args.output)
        print(f"wrote {out}: {len(result.tree.leaves())} parts, {len(result.pool)} pre-grasps")
    else:
        print(summary(result, {"load": t_load, **result.timings}))
    return 0


def summary(result: PipelineResult, timings: dict[str, float]) -> str:
    """A readable report: object, parts, candidates with reasons, pool per node and type."""
    tree, shapes, pool, trav = result.tree, result.shapes, result.pool, result.traversal
    masks = result.masks
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
