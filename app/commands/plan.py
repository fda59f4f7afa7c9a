"""`pregrasp plan` (PLACEHOLDER until issue 5 lands: replace this whole module)."""

from __future__ import annotations

import argparse

from pregrasp_core.errors import PregraspError


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("plan", help="(not built yet: issue 5)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    raise PregraspError("'pregrasp plan' is not built yet (issue 5)")
