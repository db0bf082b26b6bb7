"""``svcode bench``: work–precision benchmark of every method and knob in every regime.

The benchmark itself (scenes, regimes, rows, report) is the engine ``svcode_bench.regimes``,
which is not part of the installed package: it lies beside the benchmark scripts in a
source checkout's ``bench`` folder (:func:`engine`), so ``svcode bench`` runs from a
checkout installed with ``pip install -e ".[bench]"``.
"""

from __future__ import annotations

import argparse
import importlib
import json
import sys
from pathlib import Path
from types import ModuleType

from ..extras import NotInstalled
from ..methods.registry import LEARNED_METHODS, METHODS, method
from . import SUMMARIES, add_progress_argument, add_system_arguments

#: a source checkout's benchmark folder (``bench`` beside ``src/``): the engine
#: ``svcode_bench``, the scripts, and the committed report in ``results``
CHECKOUT_BENCH = Path(__file__).resolve().parents[3] / "bench"
#: the report a source checkout commits
CHECKOUT_RESULTS = CHECKOUT_BENCH / "results"
#: ``--methods``' rows beyond the ``--method`` names: LSV-ADMM's slow end, minutes a frame
SYSTEM_K = "admm-system-k"
#: the names ``--methods`` also takes: the benchmark's families (``deconvolution``: Wiener
#: and Richardson–Lucy, ``learned``: every ``--learned`` file) and an earlier name
_ALIASES = {"deconvolution": ("wiener", "rl"), "learned": LEARNED_METHODS,
            "admm-defaults": (SYSTEM_K,)}  # fmt: skip
#: the benchmark family that runs each ``--methods`` name
_FAMILY = {"svcode": "svcode", "admm": "admm", "wiener": "deconvolution", "rl": "deconvolution",
           **dict.fromkeys(LEARNED_METHODS, "learned"), SYSTEM_K: SYSTEM_K}  # fmt: skip
#: what ``--methods`` runs when not given
DEFAULT_METHODS = tuple(METHODS)


def engine(module: str = "svcode_bench.regimes") -> ModuleType:
    """The benchmark engine's ``module`` (default its ``regimes``; ``"svcode_bench"`` is
    the light package, without torch; ``"ring_gap"`` and the other script names are the
    checkout's scripts): importable as it is, or from the checkout's ``bench`` folder
    (added to the end of ``sys.path``).

    Raises
    ------
    svcode_core.extras.NotInstalled
        Outside a source checkout, with what to do instead.
    """
    try:
        return importlib.import_module(module)
    except ModuleNotFoundError as err:
        if err.name != module.split(".")[0]:
            raise
    if not (CHECKOUT_BENCH / "svcode_bench").is_dir():
        raise NotInstalled('svcode bench runs the benchmark engine of a source checkout '
                           '(bench/svcode_bench), not installed with the package: clone the '
                           'repository and run it there after pip install -e ".[bench]"')
    sys.path.append(str(CHECKOUT_BENCH))
    return importlib.import_module(module)


def _method_names(text: str) -> tuple[str, ...]:
    """``--methods`` item → ``--method`` names (or ``admm-system-k``)."""
    if text in _FAMILY:
        return (text,)
    if text in _ALIASES:
        return _ALIASES[text]
    raise argparse.ArgumentTypeError(f"{text!r} is none of {', '.join(_FAMILY)}")


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    """Register ``svcode bench``."""
    parser = subparsers.add_parser(
        "bench",
        help=SUMMARIES["bench"],
        description=__doc__.split("\n\n")[0]
        + " Writes regimes.{json,md,png} to --out, never over a report on another system; "
        "the checkout's committed report (bench/results) only when named with --out, and "
        "then only a full run or --merge. At paper scale (cm2-v2) the plan is "
        "smaller: three scenes, two regimes, LSV-ADMM at 10 iterations and at SV-CoDe's "
        "time, Wiener, SV-CoDe (about half an hour on one thread).",
    )
    # the regimes are the benchmark's (its light package, not the engine); without it, run()
    # says how to get the engine
    try:
        regimes = list(engine("svcode_bench").REGIMES)
    except NotInstalled:
        regimes = None
    parser.add_argument("--quick", action="store_true",
                        help="small version: two scenes, fewer knobs, every regime (minutes); "
                        "at paper scale one scene")  # fmt: skip
    parser.add_argument("--regimes", nargs="+", choices=regimes,
                        help="instruments the test frames come from (default: all; at paper "
                        "scale, e.g. cm2-v2, matched and realistic)")  # fmt: skip
    parser.add_argument("--all-knobs", action="store_true",
                        help="in the matched regime, also SV-CoDe's time-only knobs (mask "
                        "cache off, bf16, skipping off)")  # fmt: skip
    parser.add_argument("--rank-sweep", action="store_true",
                        help="in the matched regime, also LSV-ADMM with K = 1 and 6")
    parser.add_argument("--out", type=Path, default=Path("svcode-bench"),
                        help="output folder (default: ./svcode-bench)")
    add_system_arguments(parser)
    parser.add_argument("--weights", type=Path, help="trained SV-CoDe model for its rows")
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads (default 1)")
    parser.add_argument("--methods", nargs="*", type=_method_names, metavar="METHOD",
                        help="the --method names whose rows to run: "
                        + ", ".join(f"{name} ({method(name).label})" for name in METHODS)
                        + f", or {SYSTEM_K}: LSV-ADMM at "
                        "the system's K with up to 200 iterations, minutes per frame "
                        "(default: all but that; none: only the --ablations rows, e.g. with "
                        "--merge)")  # fmt: skip
    parser.add_argument("--ablations", nargs="+", type=Path, default=[], metavar="WEIGHTS",
                        help="further SV-CoDe models (e.g. ablations), one row each at the "
                        "default knob")  # fmt: skip
    parser.add_argument("--learned", nargs="+", type=Path, default=[], metavar="WEIGHTS",
                        help="trained MultiWienerNet / SV-FourierNet model files (svcode "
                        "train --method multiwiener|fouriernet)")  # fmt: skip
    parser.add_argument("--merge", action="store_true",
                        help="keep the rows of other methods from an earlier report in "
                        "--out (same system and scenes); rows of the methods run now "
                        "replace theirs, and LSV-ADMM at SV-CoDe's time is read out again "
                        "at SV-CoDe's new seconds")  # fmt: skip
    parser.add_argument("--ring-gap", action="store_true",
                        help="also the same content at the centre and in the outer ring "
                        "(bench/ring_gap.py) for the methods run: OUT/ring_gap.{json,md}")
    parser.add_argument("--exposure", action="store_true",
                        help="also the exposure and photon sweeps (bench/exposure.py) for "
                        "the methods run: OUT/exposure.{json,md}")
    add_progress_argument(parser, "progress lines")
    parser.set_defaults(func=run)


def chosen_methods(args: argparse.Namespace) -> tuple[str, ...]:
    """The ``--method`` names (and ``admm-system-k``) ``--methods`` asks for, in order."""
    if args.methods is None:
        return DEFAULT_METHODS
    return tuple(dict.fromkeys(name for names in args.methods for name in names))


def check_out(args: argparse.Namespace, system: str, regimes: tuple[str, ...]) -> None:
    """Refuse to write over a report on another system than ``system``, and to replace the
    checkout's committed report with a partial one: into ``bench/results`` only a full run
    (the plan's ``regimes``, the default methods, not ``--quick``) or ``--merge``.

    Raises
    ------
    ValueError
        With what to do instead.
    """
    earlier = args.out / "regimes.json"
    if earlier.is_file():
        theirs = json.loads(earlier.read_text(encoding="utf-8")).get("system")
        if theirs != system:
            raise ValueError(f"--out {args.out} holds a report on system {theirs!r}, not "
                             f"{system!r}: choose another --out (e.g. {args.out / system})")
    if args.merge or args.out.resolve() != CHECKOUT_RESULTS:
        return
    partial = [why for why, is_partial in (
        ("--quick", args.quick),
        ("--regimes", args.regimes is not None and tuple(args.regimes) != regimes),
        ("--methods", chosen_methods(args) != DEFAULT_METHODS)) if is_partial]  # fmt: skip
    if partial:
        raise ValueError(f"--out {args.out} holds the checkout's committed report: a run with "
                         f"{' and '.join(partial)} would replace it with a partial one; add "
                         "--merge to replace only the rows run, or choose another --out")


def run(args: argparse.Namespace) -> int:
    """Run the benchmark and write ``regimes.{json,md,png}`` to ``args.out``.

    The figure has one work–precision panel per regime.
    """
    import torch

    from ..config import load_system

    bench = engine()
    if args.threads < 1:
        raise ValueError(f"--threads must be >= 1 (torch CPU threads), got {args.threads}")
    system = load_system(args.system)
    check_out(args, system.name, bench.plan_for(system, args.quick).regimes)
    for path in [args.weights, *args.ablations, *args.learned]:
        if path is not None and not path.is_file():
            raise FileNotFoundError(f"weights not found: {path}")
    names = chosen_methods(args)
    families = tuple(dict.fromkeys(_FAMILY[name] for name in names))
    torch.set_num_threads(args.threads)
    report = bench.run_benchmark(
        system, args.quick, args.weights,
        progress=(lambda line: None) if args.no_progress else print,
        methods=families, ablations=tuple(args.ablations),
        learned=tuple(args.learned), regimes=args.regimes and tuple(args.regimes),
        all_knobs=args.all_knobs, rank_sweep=args.rank_sweep,
    )  # fmt: skip
    if "deconvolution" in families:  # the family runs both: keep the rows asked for
        left_out = {method(name).label for name in ("wiener", "rl") if name not in names}
        report["rows"] = [row for row in report["rows"] if row["method"] not in left_out]
    stem = bench.write_report(report, args.out, args.merge)
    print(f"wrote {stem}.json, .md and .png ({report['total_seconds'] / 60:.1f} min)")
    for script, asked in (("ring_gap", args.ring_gap), ("exposure", args.exposure)):
        if asked:
            engine(script).main(probe_options(args, names, script))
    return 0


def probe_options(args: argparse.Namespace, names: tuple[str, ...], script: str) -> list[str]:
    """The options of the checkout's ``bench/<script>.py`` that measure what this run
    measured: the same system, SV-CoDe (the bundled model, and ``--weights`` beside it
    in the ring gap), LSV-ADMM and the ``--learned`` files as ``--methods`` asks, the
    regimes (ring gap), the report ``OUT/<script>`` and ``--merge``."""
    options = ["--system", str(args.system), "--out", str(args.out / script)]
    options += [] if "svcode" in names else ["--no-svcode"]
    options += [] if "admm" in names else ["--no-admm"]
    learned = [str(path) for path in args.learned]
    options += ["--learned", *learned] if learned else []
    if script == "ring_gap":
        options += ["--weights", str(args.weights)] if args.weights else []
        options += ["--regimes", *args.regimes] if args.regimes else []
    return options + (["--merge"] if args.merge else [])
