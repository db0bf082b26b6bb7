"""``svcode dataset``: simulate a training dataset (noiseless views, targets, objects)."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..physics.departures import NAMED_SETS
from ..training.settings import STORE_DTYPES
from . import (
    SUMMARIES,
    add_object_argument,
    add_progress_argument,
    add_system_arguments,
    chosen_system,
    in_option_words,
)


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    """Register ``svcode dataset``."""
    parser = subparsers.add_parser(
        "dataset",
        help=SUMMARIES["dataset"],
        description=(
            "Simulate N frames of phantoms (by default mixed: cells, vessels, neurons, beads, "
            "scikit-image crops) through the system and store the noiseless sub-views, the "
            "demixing targets and the objects as .npy arrays with system.json and manifest.json. "
            "Noise is added by the trainer on every use. Rerun with the same arguments to "
            "finish an interrupted generation."
        ),
    )
    add_system_arguments(parser)
    parser.add_argument("--frames", type=int, required=True, help="number of frames N")
    parser.add_argument("--out", type=Path, required=True, help="dataset folder")
    parser.add_argument("--seed", type=int, default=0, help="seed of objects and split")
    add_object_argument(parser, "mixed", " of every frame")
    parser.add_argument("--val-fraction", type=float, default=0.1,
                        help="fraction of frames held out for validation (default: 0.1)")
    parser.add_argument("--departures", metavar="{" + ",".join(NAMED_SETS) + ",FILE}",
                        help="domain randomisation: every frame from its own draw of the true "
                        "instrument within these departures (a named set or a JSON file, "
                        "taken as ranges)")  # fmt: skip
    parser.add_argument("--instrument-frames", type=int, default=8,
                        help="consecutive frames sharing one draw of the optical departures "
                        "(default: 8; each draw costs a new forward model)")  # fmt: skip
    parser.add_argument("--dtype", choices=STORE_DTYPES, default="float32",
                        help="storage of the arrays: float16 halves the disk (a cm2-v2 "
                        "frame's arrays take 438 MB in float32), rounding them by 2^-11; "
                        "the trainer reads float32 (default: float32)")  # fmt: skip
    parser.add_argument("--workers", type=int, default=1, metavar="N",
                        help="processes simulating frames side by side, one thread each "
                        "(the same frames as one process; default 1)")
    parser.add_argument("--view-margin", type=int, default=0, metavar="PX",
                        help="store the sub-views and demixing targets PX pixels past each "
                        "window, for SV-CoDe models trained with --view-margin (at most the "
                        "system's kernel margin; default: 0)")  # fmt: skip
    add_progress_argument(parser)
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Generate (or finish) the dataset and print a summary."""
    from ..physics.departures import load_departures
    from ..training import DataRecipe, generate_dataset

    system = chosen_system(args)
    departures = None if args.departures is None else load_departures(args.departures, system)
    recipe = DataRecipe(frames=args.frames, seed=args.seed, val_fraction=args.val_fraction,
                        object_kind=args.object, departures=departures,
                        instrument_frames=args.instrument_frames, dtype=args.dtype,
                        view_margin=args.view_margin)
    options = {field: "--" + field.replace("_", "-")
               for field in ("frames", "seed", "val_fraction", "instrument_frames",
                             "view_margin", "workers")}
    with in_option_words(options):
        recipe.validate()
        data = generate_dataset(args.out, system, recipe, progress=not args.no_progress,
                                workers=args.workers)
    seconds = data.manifest["seconds"]
    print(f"{data}: simulation took {seconds:.1f} s in all "
          f"({seconds / max(1, len(data)):.2f} s per frame)")
    return 0
