"""``svcode demo``: simulate a scene, reconstruct it with the bundled model, score it."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from . import SUMMARIES, add_object_argument, add_system_arguments, chosen_system, system_file

#: frames estimated to take longer are not reconstructed twice (once to warm up)
WARM_UP_BELOW_SECONDS = 20.0


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    """Register ``svcode demo``."""
    parser = subparsers.add_parser(
        "demo",
        help=SUMMARIES["demo"],
        description=(
            "Simulate a scene with the chosen system, reconstruct it with the bundled "
            "SV-CoDe model (or --weights), print PSNR and SSIM against the ground truth and "
            "the seconds per frame, and write demo.png (raw frame with the sub-view boxes, "
            "demixed views, reconstruction, ground truth, error map) with the TIFFs."
        ),
    )
    add_system_arguments(parser)
    add_object_argument(parser, "cells")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--weights", type=Path, help="trained model (default: the bundled one)")
    parser.add_argument("--device", default="cpu", help="cpu, cuda, cuda:N or mps")
    parser.add_argument("--out", type=Path, default=Path("svcode-demo"),
                        help="output folder (default: ./svcode-demo)")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Simulate, reconstruct, score, save the files and the picture."""
    import numpy as np

    from ..evaluation.figures import overview_figure
    from ..evaluation.metrics import image_quality
    from ..io import write_tiff
    from ..methods.cost import duration, tile_seconds
    from ..methods.svcode import Reconstructor
    from ..outputs import check_outputs
    from ..phantoms import make_object
    from ..physics.cm2 import simulation_cost
    from ..physics.simulate import Simulator, scene_files

    files = [("--out", path) for path in scene_files(args.out).values()]
    files += [("--out", args.out / name) for name in ("reconstruction.tif", "demo.png")]
    check_outputs(files, {"--weights": args.weights, "--system": system_file(args)})
    system = chosen_system(args)
    if args.weights is not None:
        rec = Reconstructor.from_weights(args.weights, system, device=args.device)
    else:
        rec = Reconstructor.pretrained(system, device=args.device)
    estimate = tile_seconds(len(rec.grid), rec.grid.patch, rec.model.working_bytes_per_pixel(),
                            str(rec.device))
    warm_up = estimate < WARM_UP_BELOW_SECONDS  # a long frame is timed with its set-up
    runs = "twice (a warm-up, then timed)" if warm_up else "once (timed with its set-up)"
    print(f"system {system.name}: sensor {system.sensor_shape}, sub-views "
          f"{system.sub_view_size}², object {args.object} (seed {args.seed}); simulating "
          f"one frame (roughly {duration(simulation_cost(system).seconds)}), then "
          f"reconstructing it {runs} in {len(rec.grid)} "
          f"tile{'s' * (len(rec.grid) > 1)} ({rec.precision}): roughly "
          f"{duration(estimate * (1 + warm_up))} of reconstruction on this {rec.device.type}",
          flush=True)
    obj = make_object(args.object, system.sub_view_size, args.seed)
    simulator = Simulator(system)
    scene = simulator.simulate(obj, seed=args.seed)
    if warm_up:
        rec.reconstruct(scene.measurement)  # masks cached, kernels chosen
    start = time.perf_counter()
    result = rec.reconstruct(scene.measurement, return_views=True)
    seconds = time.perf_counter() - start
    quality = image_quality(scene.object, result.reconstruction, data_range=1.0)

    scene.save(args.out, system, extra={"object": args.object, "seed": args.seed})
    write_tiff(args.out / "reconstruction.tif", result.reconstruction, system,
               kind="reconstruction", extra={"method": "svcode"})
    error = np.abs(result.reconstruction - scene.object)
    picture = overview_figure(
        args.out / "demo.png",
        system,
        scene.measurement,
        {"demixed views": result.views, "SV-CoDe reconstruction": result.reconstruction,
         "ground truth": scene.object, "|error|": error},
        title=(f"{system.name}, simulated {args.object}: PSNR {quality['psnr']:.2f} dB, "
               f"SSIM {quality['ssim']:.3f}"),
    )
    print(f"SV-CoDe: PSNR {quality['psnr']:.2f} dB (centre {quality['psnr_centre']:.2f}, "
          f"outer ring {quality['psnr_ring']:.2f}), SSIM {quality['ssim']:.3f}")
    print(f"{seconds:.2f} s per frame{'' if warm_up else ' with its set-up'} on "
          f"{rec.device} ({result.tiles_run} tile{'s' * (result.tiles_run != 1)} run, "
          f"{result.tiles_skipped} skipped)")
    print(f"wrote {picture} and {args.out}/{{measurement,views,demixed,object,"
          "reconstruction}.tif, system.json")
    return 0
