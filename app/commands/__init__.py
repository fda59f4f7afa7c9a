"""Subcommands of the ``pregrasp`` CLI: one module each with ``add_parser(subparsers)``."""
