"""Options shared by the subcommands: the input cloud, the decomposition and the shape classes.

Each ``add_*_args(parser)`` registers a group of options whose defaults come from the core's
parameter dataclasses; the matching builder turns the parsed ``args`` back into that dataclass,
re-raising invalid values as :class:`PregraspError` so the CLI prints a one-line error (exit 2).
"""

from __future__ import annotations

import argparse

from pregrasp_core.decomposition import DecompositionParams
from pregrasp_core.errors import PregraspError
from pregrasp_core.io import DEFAULT_N_POINTS, PointCloud, load_point_cloud
from pregrasp_core.paths import DEFAULT_OBJECT
from pregrasp_core.shape import ShapeParams

_DP = DecompositionParams()
_SP = ShapeParams()


def add_input_args(p: argparse.ArgumentParser, required: bool = True) -> None:
    """INPUT (a point-cloud or mesh file; optional when ``required`` is False, then the default
    object), --points, --seed, --scale."""
    g = p.add_argument_group("input")
    if required:
        g.add_argument(
            "input",
            metavar="INPUT",
            help="point cloud or mesh file (PLY, PCD, XYZ, "
            "TXT, CSV, NPY, NPZ, OBJ, STL, OFF, GLB, GLTF)",
        )
    else:
        g.add_argument(
            "input",
            metavar="INPUT",
            nargs="?",
            default=None,
            help=f"point cloud or mesh file (default: {DEFAULT_OBJECT.name})",
        )
    g.add_argument(
        "--points",
        type=int,
        default=DEFAULT_N_POINTS,
        metavar="N",
        help="points sampled on a mesh / kept of a cloud (default %(default)s)",
    )
    g.add_argument(
        "--seed", type=int, default=0, metavar="S", help="sampling seed (default %(default)s)"
    )
    g.add_argument(
        "--scale",
        type=float,
        default=None,
        metavar="F",
        help="multiply coordinates by F, e.g. 0.001 for millimetres",
    )


def add_decomposition_args(p: argparse.ArgumentParser) -> None:
    """--volume-ratio, --min-points, --max-depth (defaults of ``DecompositionParams``)."""
    g = p.add_argument_group("decomposition")
    g.add_argument(
        "--volume-ratio",
        type=float,
        default=_DP.volume_ratio,
        metavar="R",
        help="accept a split when V(children)/V(parent) < R (default %(default)s)",
    )
    g.add_argument(
        "--min-points",
        type=int,
        default=_DP.min_points,
        metavar="M",
        help="points each child keeps at least (default %(default)s)",
    )
    g.add_argument(
        "--max-depth",
        type=int,
        default=_DP.max_depth,
        metavar="D",
        help="maximal tree depth (default %(default)s)",
    )


def add_shape_args(p: argparse.ArgumentParser) -> None:
    """--ratio-1d, --ratio-2d, --small-size (defaults of ``ShapeParams``)."""
    g = p.add_argument_group("shape classes (PCA)")
    g.add_argument(
        "--ratio-1d",
        type=float,
        default=_SP.max_ratio_1d,
        metavar="A",
        help="1D when sqrt(l2/l1) < A (default %(default)s)",
    )
    g.add_argument(
        "--ratio-2d",
        type=float,
        default=_SP.max_ratio_2d,
        metavar="B",
        help="2D when sqrt(l3/l2) < B (default %(default)s)",
    )
    g.add_argument(
        "--small-size",
        type=float,
        default=_SP.small_size,
        metavar="METRES",
        help="3D parts up to this largest side are 3D-small (default %(default)s)",
    )


def add_output_arg(p: argparse.ArgumentParser) -> None:
    """``-o/--output OUT.json``: where the pregrasp/1 result goes (``-`` for stdout)."""
    p.add_argument(
        "-o",
        "--output",
        metavar="OUT.json",
        default=None,
        help="write the result JSON here ('-' for stdout)",
    )


def input_path(args: argparse.Namespace) -> str:
    """The input file of ``args`` (the default object when INPUT was optional and omitted)."""
    return str(DEFAULT_OBJECT if args.input is None else args.input)


def load_cloud(args: argparse.Namespace) -> PointCloud:
    """Load the cloud named by ``args`` (see :func:`add_input_args`)."""
    return load_point_cloud(
        input_path(args), n_points=args.points, seed=args.seed, scale=args.scale
    )


def decomposition_params(args: argparse.Namespace) -> DecompositionParams:
    """``DecompositionParams`` from ``args``; invalid values raise ``PregraspError``."""
    try:
        return DecompositionParams(
            volume_ratio=args.volume_ratio, min_points=args.min_points, max_depth=args.max_depth
        )
    except ValueError as exc:
        raise PregraspError(f"invalid decomposition option: {_option_names(exc)}") from None


def shape_params(args: argparse.Namespace) -> ShapeParams:
    """``ShapeParams`` from ``args``; invalid values raise ``PregraspError``."""
    try:
        return ShapeParams(
            max_ratio_1d=args.ratio_1d, max_ratio_2d=args.ratio_2d, small_size=args.small_size
        )
    except ValueError as exc:
        raise PregraspError(f"invalid shape option: {_option_names(exc)}") from None


_OPTION_OF_FIELD = {
    "volume_ratio": "--volume-ratio",
    "min_points": "--min-points",
    "max_depth": "--max-depth",
    "max_ratio_1d": "--ratio-1d",
    "max_ratio_2d": "--ratio-2d",
    "small_size": "--small-size",
}


def _option_names(exc: ValueError) -> str:
    """The dataclass's message with field names replaced by the CLI option names."""
    msg = str(exc)
    for field, option in _OPTION_OF_FIELD.items():
        if msg.startswith(field):
            return option + msg[len(field) :]
    return msg
