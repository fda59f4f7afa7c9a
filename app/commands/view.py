"""`pregrasp view [INPUT] [--host H] [--port P]`: the browser inspection app (viser)."""

from __future__ import annotations

import argparse
from pathlib import Path

from pregrasp_core.errors import InputError


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "view",
        help="inspect decomposition, face masks, pre-grasps and grasps in the browser",
        description=(
            "Start the viser inspection app and print its URL and the SSH port-forward line. "
            "With no INPUT it opens the default object (a mug with a handle)."
        ),
    )
    p.add_argument("input", nargs="?", type=Path, help="point cloud or mesh file to open")
    p.add_argument(
        "--host",
        default="127.0.0.1",
        help="interface to bind (default 127.0.0.1: reach it from elsewhere over an SSH "
        "port-forward, see docs/usage.md)",
    )
    p.add_argument(
        "--port",
        type=int,
        default=8080,
        help="port (default 8080; the next free port is used when it is taken)",
    )
    p.add_argument("--points", type=int, default=20000, help="points sampled on a mesh")
    p.add_argument("--seed", type=int, default=0, help="seed of the mesh sampling")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from app.server import ViewerConfig, serve

    if args.input is not None and not Path(args.input).is_file():
        raise InputError(f"{args.input}: no such file; pass a point cloud or mesh file")
    if not 0 <= args.port <= 65535:
        raise InputError(f"--port must be in [0, 65535], got {args.port}")
    serve(
        ViewerConfig(
            input=args.input, host=args.host, port=args.port, n_points=args.points, seed=args.seed
        )
    )
    return 0
