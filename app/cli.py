"""The ``pregrasp`` command line: a thin layer over :mod:`pregrasp_core`.

Each subcommand lives in ``app/commands/<name>.py`` and provides ``add_parser(subparsers)``,
which registers its options and sets ``func`` to a function ``run(args) -> int``. The options
are generated from dataclasses (the core's parameters, the commands' own input and output
options) by :mod:`app.commands.options`; a value a dataclass rejects is a ``PregraspError``
naming the flag, printed here as one line (exit 2).
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys

from pregrasp_core.errors import PregraspError

COMMANDS = ("decompose", "pregrasps", "plan", "view")


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    """The parser of every subcommand, or of the subcommand ``only`` alone (what :func:`main`
    builds when the command line names one: the other commands' modules are not imported)."""
    parser = argparse.ArgumentParser(
        prog="pregrasp",
        description="Pre-grasp generation for unknown 3D objects (after Sainul, Deb & Deb 2019).",
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="log progress to stderr")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in COMMANDS if only is None else (only,):
        importlib.import_module(f"app.commands.{name}").add_parser(sub)
    return parser


def chosen_command(argv: list[str]) -> str | None:
    """The subcommand ``argv`` names (its first word that is not an option: the top-level
    options take no value), or None when it names none of :data:`COMMANDS` (then the parser
    of every command is built, for the help and the error message)."""
    word = next((a for a in argv if not a.startswith("-")), None)
    return word if word in COMMANDS else None


def main(argv: list[str] | None = None) -> int:
    parser = build_parser(chosen_command(sys.argv[1:] if argv is None else argv))
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.INFO if args.verbose else logging.WARNING,
        format="%(levelname)s %(name)s: %(message)s",
    )
    try:
        return int(args.func(args) or 0)
    except PregraspError as exc:
        print(f"pregrasp {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
