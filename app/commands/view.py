"""`pregrasp view [INPUT] [--host H] [--port P] [pipeline options]`: the browser inspection app.

It takes every input and pipeline option ``pregrasp plan`` takes (from the same definitions,
:data:`app.commands.common.INPUT_OPTIONS` and :func:`app.commands.common.pipeline_options`),
the depth-camera ones included (``--intrinsics``, ``--pick``, ``--scene``, ``--viewpoint``): the
app opens the input as ``pregrasp plan`` reads it and starts with those parameters, and its
widgets change them from there.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path

from pregrasp_core.errors import InputError

from .common import ALL_STAGES, INPUT_OPTIONS, add_input_args, pipeline_options
from .options import Flag, HelpFormatter, Options


@dataclass(frozen=True)
class ServeOptions:
    """Where the viewer listens (``app.server.ViewerConfig``'s ``host`` and ``port``)."""

    host: str = "127.0.0.1"
    """Interface to bind; the default keeps the app private to this machine (reach it from
    elsewhere over an SSH port-forward, see docs/usage.md)."""
    port: int = 8080
    """Port to listen on (the next free port is used when it is taken; 0 = any free port)."""

    def __post_init__(self) -> None:
        if not 0 <= self.port <= 65535:
            raise ValueError(f"port must be in [0, 65535], got {self.port}")


PIPELINE_OPTIONS = pipeline_options(ALL_STAGES)
"""The same pipeline options as ``pregrasp plan``."""

SERVE_OPTIONS: Options[ServeOptions] = Options(
    ServeOptions,
    "server",
    "serve",
    flags={"host": Flag(metavar="HOST"), "port": Flag(metavar="PORT")},
)


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "view",
        formatter_class=HelpFormatter,
        help="inspect decomposition, face masks, pre-grasps and grasps in the browser",
        description=(
            "Start the viser inspection app and print its URL and the SSH port-forward line. "
            "With no INPUT it opens the default object (a mug with a handle); a pregrasp/1 "
            "result file (RESULT.json, from `pregrasp plan -o`) is shown as it is, without "
            "recomputing. The pipeline options set the parameters the app starts with."
        ),
    )
    add_input_args(p, required=False, what="point cloud, mesh or pregrasp/1 result file (.json)")
    p.add_argument(
        "--compare",
        metavar="RESULT.json",
        default=None,
        help="a second pregrasp/1 result file of the same object: its best grasps are drawn "
        "beside the shown ones (magenta) with a table of both results' best grasps",
    )
    SERVE_OPTIONS.add_to(p)
    PIPELINE_OPTIONS.add_to(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    serve_options = SERVE_OPTIONS.build(args)  # every option checked before the server starts
    params = PIPELINE_OPTIONS.build(args)
    inp = INPUT_OPTIONS.build(args)
    sensor = inp.sensor()  # --intrinsics, --pick, --scene, --viewpoint, as `pregrasp plan`
    path = None if args.input is None else Path(args.input)
    if path is not None and not path.is_file():
        raise InputError(f"{path}: no such file; pass a point cloud, a mesh or a result file")
    compare = None if args.compare is None else Path(args.compare)
    if compare is not None and not compare.is_file():
        raise InputError(f"--compare {compare}: no such file; pass a pregrasp/1 result file")

    from app.server import ViewerConfig, serve  # viser only when the viewer runs

    serve(
        ViewerConfig(
            input=path,
            host=serve_options.host,
            port=serve_options.port,
            n_points=inp.points,
            seed=inp.seed,
            scale=inp.scale,
            sensor=sensor,
            params=params,
            plan_on_start=True,
            compare=compare,
        )
    )
    return 0
