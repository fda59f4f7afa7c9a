"""`pregrasp view` (PLACEHOLDER until issue 6 lands: replace this whole module)."""

from __future__ import annotations

import argparse

from pregrasp_core.errors import PregraspError


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("view", help="(not built yet: issue 6)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    raise PregraspError("'pregrasp view' is not built yet (issue 6)")
