"""``svcode simulate``: simulate a raw CM² frame (or stack) of a phantom or an image."""

from __future__ import annotations

import argparse
import time
import warnings
from pathlib import Path

import numpy as np

from ..physics.departures import NAMED_SETS
from . import (
    SUMMARIES,
    add_object_argument,
    add_progress_argument,
    add_system_arguments,
    chosen_system,
    system_file,
)


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    """Register ``svcode simulate``."""
    parser = subparsers.add_parser(
        "simulate",
        help=SUMMARIES["simulate"],
        description=(
            "Simulate a raw sensor frame of an object through the chosen system and write "
            "measurement.tif, views.tif, demixed.tif, object.tif and system.json to OUT."
        ),
    )
    add_system_arguments(parser)
    add_object_argument(parser, "mixed", image=True)
    parser.add_argument("--seed", type=int, default=0, help="seed of the phantom and the noise")
    parser.add_argument("--out", type=Path, required=True, help="output folder")
    parser.add_argument("--no-noise", action="store_true", help="write the noiseless frame")
    parser.add_argument("--frames", type=int, default=1,
                        help="number of frames T (independent noise draws); T > 1 writes T×H×W")
    parser.add_argument("--departures", metavar="{" + ",".join(NAMED_SETS) + ",FILE}",
                        help="simulate the true instrument: a named set of departures from "
                        "the system, or a departures JSON file; system.json stays nominal "
                        "and departures.json records them")  # fmt: skip
    parser.add_argument("--memory-budget", type=float, metavar="GIB",
                        help="memory of the forward model's kept spectra and working chunks "
                             "(default 1 GiB; the nominal instrument only)")
    add_progress_argument(parser, "progress bar of a stack")
    parser.set_defaults(func=run)


def _read_image(path: Path) -> np.ndarray:
    """The pixels of ``--object PATH``; a colour image is taken as its luminance, with a
    warning."""
    import tifffile

    if path.suffix.lower() in (".tif", ".tiff"):
        image = tifffile.imread(path)
    else:
        import skimage.io

        image = skimage.io.imread(path)
    if image.ndim == 3 and image.shape[-1] in (3, 4):
        warnings.warn(f"--object {path.name} is a colour image ({image.shape[-1]} channels): "
                      "it is simulated as grey, from its luminance", UserWarning, stacklevel=2)
    return image


def run(args: argparse.Namespace) -> int:
    """Simulate and write the files; print a one-line summary."""
    from ..outputs import check_outputs, require_space
    from ..phantoms import KINDS, from_image, make_object
    from ..physics.cm2 import CM2Operator
    from ..physics.departures import load_departures
    from ..physics.scene_checks import check_object, check_system_geometry
    from ..physics.simulate import Simulator, scene_bytes, scene_files

    if args.frames < 1:
        raise ValueError(f"--frames must be >= 1, got {args.frames}")
    if args.memory_budget is not None and not 0 < args.memory_budget < float("inf"):
        raise ValueError(f"--memory-budget must be a positive number of GiB, "
                         f"got {args.memory_budget:g}")  # fmt: skip
    system = chosen_system(args)
    check_system_geometry(system)
    size = system.sub_view_size
    image = Path(args.object) if args.object not in KINDS else None
    outputs = [("--out", path) for path in scene_files(args.out).values()]
    check_outputs(outputs, {"--object": image, "--system": system_file(args)})
    require_space({args.out: scene_bytes(system.sensor_shape, size, args.frames)})
    if image is None:
        obj = make_object(args.object, size, args.seed)
    elif image.is_file():
        obj = from_image(_read_image(image), size)
        check_object(obj, str(image))
    else:
        raise ValueError(
            f"--object {args.object!r} is neither a phantom kind ({', '.join(KINDS)}) "
            "nor an existing image file"
        )
    departures = None if args.departures is None else load_departures(args.departures, system)
    start = time.perf_counter()
    budget = None if args.memory_budget is None else int(args.memory_budget * 2**30)
    nominal = departures is None or departures.is_nominal
    operator = CM2Operator.from_system(system, memory_budget=budget) if nominal else None
    simulator = Simulator(system, operator, departures=departures)
    built = time.perf_counter()
    scene = simulator.simulate(obj, seed=args.seed, noise=not args.no_noise,
                               frames=args.frames,
                               progress=args.frames > 1 and not args.no_progress)
    done = time.perf_counter()
    scene.save(args.out, system, extra={"object": str(args.object), "seed": args.seed,
                                        "noise": not args.no_noise}, departures=departures)
    print(
        f"simulated {args.frames} frame(s) of {args.object!r} with {system.name}"
        + ("" if departures is None else f" (departures: {departures.name})") + " "
        f"(K = {simulator.operator.rank}): operator {built - start:.2f} s, "
        f"simulation {done - built:.2f} s -> {args.out}"
    )
    return 0
