"""``svcode bench``: work–precision benchmark of every method and knob in every regime.

The benchmark itself (scenes, regimes, rows, report) is :mod:`svcode_core.evaluation.bench`.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from ..config import load_system
from ..evaluation import bench


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    """Register ``svcode bench``."""
    parser = subparsers.add_parser(
        "bench",
        help="work–precision benchmark of every method and knob in every regime",
        description=__doc__.split("\n\n")[0],
    )
    parser.add_argument("--quick", action="store_true",
                        help="small version: two scenes, fewer knobs, every regime (minutes)")
    parser.add_argument("--regimes", nargs="+", choices=list(bench.REGIMES),
                        default=list(bench.REGIMES),
                        help="instruments the test frames come from (default: all)")
    parser.add_argument("--all-knobs", action="store_true",
                        help="in the matched regime, also SV-CoDe's time-only knobs (mask "
                        "cache off, bf16, skipping off)")  # fmt: skip
    parser.add_argument("--rank-sweep", action="store_true",
                        help="in the matched regime, also LSV-ADMM with K = 1 and 6")
    parser.add_argument("--out", type=Path, default=Path("bench/results"), help="output folder")
    parser.add_argument("--system", default="cm2-mini", help="preset or system JSON")
    parser.add_argument("--weights", type=Path, help="trained SV-CoDe model for its rows")
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads (default 1)")
    parser.add_argument("--methods", nargs="*", choices=bench.METHOD_FAMILIES,
                        default=list(bench.DEFAULT_FAMILIES),
                        help="method families to run (default: all but admm-defaults, "
                        "LSV-ADMM as `svcode reconstruct` runs it, minutes per frame; none: "
                        "only the --ablations rows, e.g. with --merge)")  # fmt: skip
    parser.add_argument("--ablations", nargs="+", type=Path, default=[], metavar="WEIGHTS",
                        help="further SV-CoDe models (e.g. ablations), one row each at the "
                        "default knob")  # fmt: skip
    parser.add_argument("--learned", nargs="+", type=Path, default=[], metavar="WEIGHTS",
                        help="trained MultiWienerNet / SV-FourierNet model files (svcode "
                        "train --method multiwiener|fouriernet)")  # fmt: skip
    parser.add_argument("--merge", action="store_true",
                        help="keep the rows of other methods from an earlier report in "
                        "--out (same system and scenes); rows of the methods run now "
                        "replace theirs")  # fmt: skip
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Run the benchmark and write ``regimes.{json,md,png}`` to ``args.out``.

    The figure has one work–precision panel per regime.
    """
    if args.threads < 1:
        raise ValueError(f"--threads must be >= 1 (torch CPU threads), got {args.threads}")
    for path in [args.weights, *args.ablations, *args.learned]:
        if path is not None and not path.is_file():
            raise FileNotFoundError(f"weights not found: {path}")
    torch.set_num_threads(args.threads)
    report = bench.run_benchmark(
        load_system(args.system), args.quick, args.weights,
        methods=tuple(args.methods), ablations=tuple(args.ablations),
        learned=tuple(args.learned), regimes=tuple(args.regimes),
        all_knobs=args.all_knobs, rank_sweep=args.rank_sweep,
    )  # fmt: skip
    stem = bench.write_report(report, args.out, args.merge)
    print(f"wrote {stem}.json, .md and .png ({report['total_seconds'] / 60:.1f} min)")
    return 0
