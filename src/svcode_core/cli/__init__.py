"""The ``svcode`` command line: one sub-command a module.

Each sub-command module exposes ``add_parser(subparsers)`` (registers its arguments and
sets ``func``) and is listed in :data:`COMMANDS`.

Exit status: 0 on success; 2 for a user error (bad option or input, a file that is
missing, unreadable or unwritable, a full disk, an unavailable device, an optional part
not installed), reported in one line on stderr (``--debug`` shows the traceback instead);
130 when interrupted (Ctrl-C), 143 when terminated (SIGTERM, e.g. ``kill``): both release
the output locks and keep an interrupted reconstruction's partial files, to resume; 1 with
a traceback for anything else (a bug: please report it).
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import signal
import sys
import threading
import warnings
from collections.abc import Callable, Iterator, Mapping, Sequence
from pathlib import Path

from ..config import ConfigError, SystemConfig, available_presets, load_system
from ..extras import NotInstalled
from ..run.allocator import reuse_freed_memory

#: every sub-command and its line in ``svcode --help``; its module is imported only when the
#: command is named (what the modules import costs seconds: torch, scipy, scikit-image)
SUMMARIES = {
    "simulate": "simulate a raw CM² measurement with its ground truth",
    "reconstruct": "reconstruct a raw CM² frame or frame stack",
    "demo": "simulate a scene, reconstruct it with the bundled model, score it",
    "dataset": "simulate training data for a system",
    "train": "train SV-CoDe or a learned baseline on a simulated dataset",
    "bench": "work–precision benchmark of every method and knob in every regime",
    "calibrate": "calibrate a system from a point-source scan",
}
COMMANDS = tuple(SUMMARIES)


def add_system_arguments(
    parser: argparse.ArgumentParser,
    default: str | None = "cm2-mini",
    what: str = "the system",
    default_text: str | None = None,
) -> None:
    """``--system NAME|FILE.json``, the same in every command: a preset name or a system
    JSON file; ``--preset`` is the same option. ``what`` says what the system is for,
    ``default_text`` what the default is (else the ``default``'s name)."""
    default_text = default_text or f"default: {default}"
    parser.add_argument(
        "--system", "--preset", dest="system", default=default, metavar="NAME|FILE.json",
        help=f"{what}: a preset ({', '.join(available_presets())}) or a system JSON file "
        f"({default_text})",
    )


def add_progress_argument(parser: argparse.ArgumentParser, what: str = "progress bar") -> None:
    """``--no-progress`` (``--quiet`` is the same option), the same in every command."""
    parser.add_argument("--no-progress", "--quiet", dest="no_progress", action="store_true",
                        help=f"hide the {what}")  # fmt: skip


def add_object_argument(parser: argparse.ArgumentParser, default: str, what: str = "",
                        image: bool = False) -> None:
    """``--object KIND`` (``--objects`` is the same option), the same in every command: a
    phantom kind or, with ``image``, also a 2-D image file."""
    from ..phantoms import KINDS  # scipy and scikit-image: only for the commands with it

    kinds = ",".join(KINDS)
    if image:
        parser.add_argument("--object", "--objects", dest="object", default=default,
                            metavar=f"{{{kinds},PATH}}",
                            help=f"phantom kind{what}, or a 2-D TIFF/PNG to use as the object "
                            f"(default: {default})")  # fmt: skip
    else:
        parser.add_argument("--object", "--objects", dest="object", default=default,
                            choices=KINDS, help=f"phantom kind{what} (default: {default})")


def chosen_system(args: argparse.Namespace) -> SystemConfig | None:
    """The system of :func:`add_system_arguments`' option; ``None`` if it is not set."""
    return load_system(args.system) if args.system else None


def system_file(args: argparse.Namespace) -> Path | None:
    """The file ``--system`` names, if it names one (not a preset): an input of the run."""
    return Path(args.system) if args.system and Path(args.system).is_file() else None


@contextlib.contextmanager
def in_option_words(options: Mapping[str, str]) -> Iterator[None]:
    """Reword a :class:`~svcode_core.config.ConfigError` about one of ``options``' fields
    (``"val_fraction: must ..."``) with the option's name (``"--val-fraction: must ..."``).

    Parameters
    ----------
    options : mapping
        Configuration field → command-line option.
    """
    try:
        yield
    except ConfigError as err:
        field, colon, rest = str(err).partition(": ")
        if not colon or field not in options:
            raise
        raise ConfigError(f"{options[field]}: {rest}") from None


def build_parser(commands: Sequence[str] = COMMANDS) -> argparse.ArgumentParser:
    """The ``svcode`` argument parser with ``commands`` (default: every sub-command)
    registered in full; the others are listed with their summary only."""
    parser = argparse.ArgumentParser(
        prog="svcode",
        description="SV-CoDe for computational miniature mesoscopes (CM²).",
    )
    debug_help = "show the full traceback of an error instead of a one-line message"
    parser.add_argument("--debug", action="store_true", help=debug_help)
    subparsers = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in COMMANDS:
        if name in commands:
            importlib.import_module(f"{__name__}.{name}").add_parser(subparsers)
        else:
            subparsers.add_parser(name, help=SUMMARIES[name])
    for command in subparsers.choices.values():  # also accepted after the command
        command.add_argument("--debug", action="store_true", default=argparse.SUPPRESS,
                             help=debug_help)  # fmt: skip
    return parser


def _commands_needed(argv: Sequence[str]) -> Sequence[str]:
    """The sub-command ``argv`` names, when it names one; else none (``svcode --help`` and
    the list of choices need only the summaries)."""
    first = next((arg for arg in argv if not arg.startswith("-")), None)
    return (first,) if first in COMMANDS else ()


def describe_error(err: BaseException) -> str:
    """A one-line description of a user error (an ``OSError`` without its errno prefix)."""
    if isinstance(err, OSError) and err.strerror:
        if err.filename is not None:
            return f"{err.filename}: {err.strerror}"
        return err.strerror
    return " ".join(str(err).split()) or type(err).__name__


def _one_line_warnings(command: str) -> Callable[..., None]:
    """A ``warnings.showwarning`` that prints each distinct warning once, on one line (a
    frame checked twice, or every frame of a stack, says the same thing only once)."""
    shown: set[str] = set()

    def show(message, category, filename, lineno, file=None, line=None) -> None:
        text = f"svcode {command}: warning: {message}"
        if text not in shown:
            shown.add(text)
            print(text, file=file or sys.stderr)

    return show


def _check_device(args: argparse.Namespace) -> None:
    """Refuse an unavailable ``--device`` before any work (every command that has one)."""
    device = getattr(args, "device", None)
    if isinstance(device, str):
        from ..methods.base import resolve_device

        resolve_device(device)


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised like an interruption: every ``with`` and ``finally`` block runs."""


@contextlib.contextmanager
def _terminate_as_interrupt() -> Iterator[None]:
    """SIGTERM raises :class:`Terminated` meanwhile (by default it ends the process at
    once, leaving its output locks behind)."""
    if threading.current_thread() is not threading.main_thread():
        yield  # only the main thread may change signal handlers
        return

    def terminate(signum, frame) -> None:
        raise Terminated

    previous = signal.signal(signal.SIGTERM, terminate)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, signal.SIG_DFL if previous is None else previous)


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``svcode`` console script; returns the exit status.

    User errors (:class:`ValueError`, :class:`OSError`,
    :class:`~svcode_core.extras.NotInstalled`) become one line on stderr and exit
    status 2, an interruption exits with 130, SIGTERM with 143; with ``--debug`` they
    raise. The process
    keeps freed memory for reuse (:func:`~svcode_core.run.allocator.reuse_freed_memory`).
    """
    argv = sys.argv[1:] if argv is None else argv
    args = build_parser(_commands_needed(argv)).parse_args(argv)
    reuse_freed_memory()
    debug = getattr(args, "debug", False)
    with warnings.catch_warnings(), _terminate_as_interrupt():
        warnings.showwarning = _one_line_warnings(args.command)
        try:
            _check_device(args)
            return int(args.func(args) or 0)
        except (ValueError, OSError, NotInstalled) as err:
            if debug:
                raise
            print(f"svcode {args.command}: error: {describe_error(err)}", file=sys.stderr)
            return 2
        except KeyboardInterrupt as err:
            if debug:
                raise
            terminated = isinstance(err, Terminated)
            print(f"svcode {args.command}: {'terminated' if terminated else 'interrupted'}",
                  file=sys.stderr)  # fmt: skip
            return 143 if terminated else 130
