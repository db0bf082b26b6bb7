"""``svcode simulate``: simulate a raw CM² frame (or stack) of a phantom or an image."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from ..cm2 import CM2Operator
from ..phantoms import KINDS, from_image, make_object
from ..simulate import Simulator
from . import add_system_arguments, chosen_system


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    """Register ``svcode simulate``."""
    parser = subparsers.add_parser(
        "simulate",
        help="simulate a raw CM² measurement with its ground truth",
        description=(
            "Simulate a raw sensor frame of an object through the chosen system and write "
            "measurement.tif, views.tif, demixed.tif, object.tif and system.json to OUT."
        ),
    )
    add_system_arguments(parser)
    parser.add_argument("--object", default="mixed", metavar="{" + ",".join(KINDS) + ",PATH}",
                        help="phantom kind, or a 2-D TIFF/PNG to use as the object")
    parser.add_argument("--seed", type=int, default=0, help="seed of the phantom and the noise")
    parser.add_argument("--out", type=Path, required=True, help="output folder")
    parser.add_argument("--no-noise", action="store_true", help="write the noiseless frame")
    parser.add_argument("--frames", type=int, default=1,
                        help="number of frames T (independent noise draws); T > 1 writes T×H×W")
    parser.add_argument("--memory-budget", type=float, metavar="GIB",
                        help="memory of the forward model's kept spectra and working chunks "
                             "(default 1 GiB)")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Simulate and write the files; print a one-line summary."""
    system = chosen_system(args)
    size = system.sub_view_size
    if args.object in KINDS:
        obj = make_object(args.object, size, args.seed)
    elif Path(args.object).is_file():
        obj = from_image(args.object, size)
    else:
        raise ValueError(
            f"--object {args.object!r} is neither a phantom kind ({', '.join(KINDS)}) "
            "nor an existing image file"
        )
    start = time.perf_counter()
    budget = None if args.memory_budget is None else int(args.memory_budget * 2**30)
    simulator = Simulator(system, CM2Operator.from_system(system, memory_budget=budget))
    built = time.perf_counter()
    scene = simulator.simulate(obj, seed=args.seed, noise=not args.no_noise,
                               frames=args.frames, progress=args.frames > 1)
    done = time.perf_counter()
    scene.save(args.out, system, extra={"object": str(args.object), "seed": args.seed,
                                        "noise": not args.no_noise})
    print(
        f"simulated {args.frames} frame(s) of {args.object!r} with {system.name} "
        f"(K = {simulator.operator.rank}): operator {built - start:.2f} s, "
        f"simulation {done - built:.2f} s -> {args.out}"
    )
    return 0
