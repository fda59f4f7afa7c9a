"""`pregrasp decompose` (PLACEHOLDER until issue 2 lands: replace this whole module)."""

from __future__ import annotations

import argparse

from pregrasp_core.errors import PregraspError


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("decompose", help="(not built yet: issue 2)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    raise PregraspError("'pregrasp decompose' is not built yet (issue 2)")
