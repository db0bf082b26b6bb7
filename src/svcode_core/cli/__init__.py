"""The ``svcode`` command line: one sub-command a module.

Each sub-command module exposes ``add_parser(subparsers)`` (registers its arguments and
sets ``func``) and is listed in :data:`COMMANDS`.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from pathlib import Path

from ..config import SystemConfig, available_presets, load_system

COMMANDS = ("simulate", "reconstruct", "demo", "dataset", "train", "bench", "calibrate")


def add_system_arguments(
    parser: argparse.ArgumentParser,
    default: str | None = "cm2-mini",
    preset_help: str = "system preset (default: cm2-mini)",
) -> None:
    """``--preset NAME`` or ``--system FILE.json``, mutually exclusive."""
    source = parser.add_mutually_exclusive_group()
    source.add_argument("--preset", default=default, choices=available_presets(),
                        help=preset_help)  # fmt: skip
    source.add_argument("--system", type=Path, help="system JSON file instead of a preset")


def chosen_system(args: argparse.Namespace) -> SystemConfig | None:
    """The system of :func:`add_system_arguments`' options; ``None`` if neither is set."""
    choice = args.system or args.preset
    return load_system(choice) if choice else None


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
