"""The ``svcode`` command line: one sub-command a module.

Each sub-command module exposes ``add_parser(subparsers)`` (registers its arguments and
sets ``func``) and is listed in :data:`COMMANDS`.
"""

from __future__ import annotations

import argparse
import importlib
import sys

COMMANDS = ("simulate", "reconstruct", "demo", "dataset", "train", "bench")


def build_parser() -> argparse.ArgumentParser:
    """The ``svcode`` argument parser with every sub-command registered."""
    parser = argparse.ArgumentParser(
        prog="svcode",
        description="SV-CoDe for computational miniature mesoscopes (CM²).",
    )
    subparsers = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in COMMANDS:
        importlib.import_module(f"{__name__}.{name}").add_parser(subparsers)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``svcode`` console script; returns the exit status."""
    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except (ValueError, FileNotFoundError) as err:
        print(f"svcode {args.command}: error: {err}", file=sys.stderr)
        return 2
