"""``svcode reconstruct``: reconstruct a raw CM² frame or stack into a TIFF."""

from __future__ import annotations

import argparse
import math
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from ..config import SystemConfig, load_system
from ..methods.registry import (
    LEARNED_METHODS,
    METHODS,
    MODEL_BASED_METHODS,
    OPTION_FLAGS,
    method,
)
from . import SUMMARIES, add_progress_argument, add_system_arguments

#: the model-based methods' options, by their ``argparse`` destination
_BASELINE_OPTIONS = {
    OPTION_FLAGS[option].removeprefix("--").replace("-", "_"): option
    for name in MODEL_BASED_METHODS for option in method(name).options
}  # fmt: skip


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    """Register ``svcode reconstruct``."""
    parser = subparsers.add_parser(
        "reconstruct",
        help=SUMMARIES["reconstruct"],
        description=(
            "Reconstruct a raw sensor frame (H×W) into an S×S float32 TIFF, or a stack "
            "(T×H×W) into T×S×S, streamed frame by frame. An interrupted run resumes when "
            "rerun with the same arguments. Frames run in parallel on a dask cluster with "
            "--workers or --scheduler."
        ),
    )
    parser.add_argument("input", type=Path, metavar="MEAS.tif", help="raw frame or stack")
    parser.add_argument("--out", type=Path, required=True, help="output TIFF")
    parser.add_argument(
        "--method",
        default="svcode",
        choices=METHODS,
        help="; ".join(f"{name}: {method(name).title}" for name in METHODS)
        + " (the learned ones need --weights); default: svcode",
    )
    add_system_arguments(parser, default=None, default_text="default: the one stored in the "
                         "input TIFF, else system.json beside it")  # fmt: skip
    parser.add_argument(
        "--register", action="store_true",
        help="first estimate the microlens array's drift from the recording itself "
        "(chief-ray self-registration on the mean of its first 8 frames, about 3 LSV-ADMM "
        "solves) and reconstruct with the moved system; it is written to OUT's folder as "
        "OUT-stem.registered/system.json (with its PSFs and registration.json)",
    )
    parser.add_argument(
        "--weights", type=Path,
        help="trained model (svcode default: the bundled model; required for the learned "
        "baselines)",
    )
    parser.add_argument(
        "--views", type=Path, metavar="VIEWS.tif", help="also write the nine demixed views"
    )
    parser.add_argument("--device", default="cpu", help="cpu, cuda, cuda:N or mps")
    parser.add_argument(
        "--input-scale", type=float, metavar="COUNTS",
        help="divide every frame by COUNTS, the sensor's full-scale value (e.g. 4095 for a "
        "12-bit sensor); default: 8- and 16-bit integer frames are divided by their type's "
        "maximum (255, 65535), float frames are taken as normalised (full scale 1.0)",
    )
    parser.add_argument(
        "--precision",
        default="fp32",
        choices=sorted({p for name in METHODS for p in method(name).precisions}),
        help="svcode: fp32, bf16, fp16; model-based baselines: fp32, fp64; learned "
        "baselines: fp32, bf16 (default: fp32)",
    )
    parser.add_argument("--tile", type=int, help="tile size P (default: planned within 1 GiB: "
                        "the whole sub-view when it fits)")
    parser.add_argument("--stride", type=int, help="tile stride (default: planned; P/2 with "
                        "--tile)")
    parser.add_argument("--batch-size", type=int, help="tiles per model call (default: planned)")
    parser.add_argument(
        "--no-skip", action="store_true", help="run every tile, also those without signal"
    )
    parser.add_argument("--mask-cache", type=int, metavar="MIB",
                        help="memory for frozen coordinate masks, kept for the next tile "
                        "and frame; 0 to recompute them (default: 1024; the bundled cm2-mini "
                        "model needs 614 for its whole-sub-view tile)")
    parser.add_argument("--pool-window", type=int, metavar="PX",
                        help="svcode: channel attention pools over PX pixels around each "
                        "pixel (the training patch, 96 for the bundled model) instead of "
                        "the whole tile, so tiles of any size agree with the whole sub-view; "
                        "about 1.3x the time (default: as the model file says)")
    parser.add_argument("--refine-periphery", type=int, metavar="N",
                        help="svcode: refine the field's periphery (outer ring, edge strips) "
                        "with N LSV-ADMM iterations started from the network's "
                        "reconstruction, blended in from half the field radius outwards; "
                        "10 raised the bundled model's held-out scores in every regime for "
                        "2-3x the time (default: 0, none)")
    parser.add_argument(
        "--workers",
        type=int,
        default=0,
        metavar="N",
        help="reconstruct frames on a local dask cluster of N processes (default 0: in this "
        "process)",
    )
    parser.add_argument(
        "--scheduler", metavar="ADDRESS", help="use an existing dask cluster, e.g. tcp://host:8786"
    )
    add_progress_argument(parser)
    add_method_arguments(parser)
    parser.set_defaults(func=run)


def _tv_weight(text: str) -> float | str:
    """``--tv-weight``: a number, or ``auto``."""
    if text == "auto":
        return text
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"a number or 'auto', not {text!r}") from None


def _system(args: argparse.Namespace):
    from ..run.stream import FrameReader

    if args.system:
        return load_system(args.system)
    with FrameReader(args.input) as reader:
        if reader.system is None:
            raise ValueError(
                f"{args.input.name}: no system configuration in the file or in a system.json "
                "beside it; pass --system FILE.json or a preset name"
            )
        return reader.system


def _register(args: argparse.Namespace, system) -> tuple[object, dict]:
    """The system moved by self-registration of the input, written beside ``--out``."""
    from ..methods.baselines.self_registration import (
        REGISTRATION_FRAMES,
        RegistrationRejected,
        register_recording,
    )
    from ..methods.frames import finite_frame
    from ..run.stream import FrameReader

    with FrameReader(args.input) as reader:
        frames = [finite_frame(reader[i], i, scale=args.input_scale)
                  for i in range(min(len(reader), REGISTRATION_FRAMES))]  # fmt: skip
    folder = args.out.with_name(args.out.stem + ".registered")
    try:
        moved, registration = register_recording(frames, system, folder)
    except RegistrationRejected as err:
        print(f"warning: {err}; reconstructing with the given system")
        return system, {"registration": {"rejected": str(err)}}
    print(f"registered: lens offsets up to {abs(registration.offsets).max():.2f} px, array "
          f"shift {registration.shift.round(2).tolist()} px, rotation "
          f"{registration.rotation_deg:.3f}°; moved system in {folder}")
    return moved, {"registration": {**registration.to_dict(), "system": str(folder)}}


def add_method_arguments(parser: argparse.ArgumentParser) -> None:
    """Register the baselines' options on ``parser`` (all default to ``None``: the method's
    default, :mod:`~svcode_core.methods.registry`).

    The help quotes the committed benchmark (``bench/results/regimes.md``, cm2-mini, one
    CPU thread): what the slower settings buy.
    """
    admm, wiener, rl = (method(name).defaults for name in ("admm", "wiener", "rl"))
    group = parser.add_argument_group("model-based baselines (--method admm, wiener, rl)")
    group.add_argument(
        "--rank", type=int, metavar="K",
        help=f"low-rank order K of the forward model (all; default {admm['rank']}, or the "
        "system's K when smaller; LSV-ADMM at cm2-mini's K = 15 with up to 200 iterations "
        "gained 0.28 dB on the realistic benchmark for 67x the time)",
    )
    group.add_argument(
        "--memory-budget", type=float, metavar="GIB",
        help="memory of the forward model's kept spectra and working chunks (all; default 1 "
        "GiB; cm2-v2 at its K needs about 4 to run LSV-ADMM within 8 GiB)",
    )
    group.add_argument(
        "--iterations", type=int,
        help=f"admm: at most this many (default {admm['iterations']}: 0.17 dB above 20 on "
        f"the realistic benchmark, for 2.6x the time); rl: (default {rl['iterations']}: 30 "
        "scored lower in every regime, at 3x the time)",
    )
    group.add_argument(
        "--tv-weight", type=_tv_weight, metavar="LAMBDA|auto",
        help=f"admm: TV weight lambda, or auto: from each frame's noise and level (default "
        f"{admm['tv_weight']}; the fixed 1e-4 scored 1.5 dB lower at low light, 0.3 dB on "
        "the realistic benchmark, in the same time)",
    )
    group.add_argument(
        "--rho", type=float, help=f"admm: starting penalty (default {admm['rho']:g})"
    )
    group.add_argument(
        "--tolerance", type=float,
        help=f"admm: relative residual to stop at (default {admm['tolerance']:g}; 0 runs "
        "every iteration)",
    )
    group.add_argument(
        "--cg-iterations", type=int,
        help=f"admm: CG steps per x-update (default {admm['cg_iterations']})",
    )
    group.add_argument(
        "--wiener-balance", type=float,
        help=f"wiener: Laplacian regularisation weight (default {wiener['balance']:g}; 1e-2 "
        "and 1e-3 scored lower in every regime, in the same time)",
    )
    group.add_argument(
        "--wiener-boundary", choices=("reflect", "periodic"),
        help=f"wiener: view boundary handling (default {wiener['boundary']})",
    )


def baseline_options(args: argparse.Namespace) -> dict[str, Any]:
    """The options of ``args.method`` given on the command line, as keyword arguments.

    Raises
    ------
    ValueError
        If an option of another method was given.
    """
    options = {}
    for dest, name in _BASELINE_OPTIONS.items():
        value = getattr(args, dest, None)
        if value is None:
            continue
        if args.method not in MODEL_BASED_METHODS or name not in method(args.method).options:
            raise ValueError(f"{OPTION_FLAGS[name]} does not apply to --method {args.method}")
        if name == "memory_budget":
            if not value > 0:
                raise ValueError(f"--memory-budget must be positive (GiB), got {value:g}")
            value = int(value * 2**30)
        options[name] = value
    return options


def _refuse_baseline_options(args: argparse.Namespace) -> None:
    given = [dest for dest in _BASELINE_OPTIONS if getattr(args, dest, None) is not None]
    if given:
        raise ValueError(f"{OPTION_FLAGS[_BASELINE_OPTIONS[given[0]]]} applies to the "
                         f"model-based baselines, not to --method {args.method}")  # fmt: skip
    if args.weights is not None and not args.weights.is_file():
        raise FileNotFoundError(f"weights not found: {args.weights}")


#: the options only the network takes (``args`` attribute → flag)
_NETWORK_OPTIONS = {"tile": "--tile", "stride": "--stride", "batch_size": "--batch-size",
                    "no_skip": "--no-skip", "mask_cache": "--mask-cache",
                    "pool_window": "--pool-window",
                    "refine_periphery": "--refine-periphery"}  # fmt: skip


def _refuse_network_options(args: argparse.Namespace, why: str) -> None:
    """Refuse every network option given with another method (``why``: what it does)."""
    given = [flag for dest, flag in _NETWORK_OPTIONS.items()  # (0 is given, False is not)
             if getattr(args, dest) is not None and getattr(args, dest) is not False]
    if given:
        verb = "applies" if len(given) == 1 else "apply"
        raise ValueError(f"{' and '.join(given)} {verb} to --method svcode, not to --method "
                         f"{args.method} ({why})")


def _check_precision(args: argparse.Namespace) -> None:
    accepted = method(args.method).precisions
    if args.precision not in accepted:
        raise ValueError(f"--precision {args.precision} does not apply to --method "
                         f"{args.method}; it takes {', '.join(accepted)}")  # fmt: skip


def _finite(value: float) -> bool:
    return math.isfinite(value)


#: the numeric options' rules: ``args`` attribute → (accepts the value, what it must be)
_VALUE_RULES: dict[str, tuple[Callable[[Any], bool], str]] = {
    "workers": (lambda v: v >= 0, ">= 0 (processes; 0 runs in this process)"),
    "input_scale": (lambda v: _finite(v) and v > 0, "a finite number > 0 (counts)"),
    "tile": (lambda v: v >= 1, ">= 1 (pixels)"),
    "stride": (lambda v: v >= 1, ">= 1 (pixels)"),
    "batch_size": (lambda v: v >= 1, ">= 1 (tiles)"),
    "mask_cache": (lambda v: v >= 0, ">= 0 (MiB; 0 recomputes the masks)"),
    "pool_window": (lambda v: v >= 0, ">= 0 (pixels)"),
    "refine_periphery": (lambda v: v >= 0, ">= 0 (iterations)"),
    "rank": (lambda v: v >= 1, ">= 1"),
    "memory_budget": (lambda v: _finite(v) and v > 0, "positive (GiB)"),
    "iterations": (lambda v: v >= 1, ">= 1"),
    "cg_iterations": (lambda v: v >= 1, ">= 1"),
    "tv_weight": (lambda v: v == "auto" or _finite(v) and v >= 0, "a finite number >= 0 or auto"),
    "rho": (lambda v: _finite(v) and v > 0, "a finite number > 0"),
    "tolerance": (lambda v: _finite(v) and v >= 0, "a finite number >= 0"),
    "wiener_balance": (lambda v: _finite(v) and v > 0, "a finite number > 0"),
}


def check_options(args: argparse.Namespace) -> None:
    """Refuse, before any work, an option value out of range or an option that does not
    apply to ``--method``; the messages name the options as given.

    Raises
    ------
    ValueError
        For the first such option.
    """
    for dest, (accepts, what) in _VALUE_RULES.items():
        value = getattr(args, dest, None)
        if value is not None and value is not False and not accepts(value):
            flag = "--" + dest.replace("_", "-")
            shown = f"{value:g}" if isinstance(value, float) else value
            raise ValueError(f"{flag} must be {what}, got {shown}")
    _check_precision(args)
    if args.method in MODEL_BASED_METHODS:
        _refuse_network_options(args, "it inverts the forward model, without tiles")
        if args.weights is not None:
            raise ValueError(f"--weights does not apply to --method {args.method}: it inverts "
                             "the system's forward model, without a trained network")
        baseline_options(args)
        return
    _refuse_baseline_options(args)
    if args.method in LEARNED_METHODS:
        if args.weights is None:
            raise ValueError(f"--method {args.method} needs --weights: no learned baseline is "
                             "bundled; train one with `svcode train --method "
                             f"{args.method}` (see the README)")  # fmt: skip
        _refuse_network_options(args, "it reconstructs the whole frame at once")


def _spec(args: argparse.Namespace, system: SystemConfig):
    """The picklable reconstructor recipe of ``args.method``, a
    :class:`~svcode_core.methods.build.MethodSpec` (options checked by
    :func:`check_options`)."""
    from ..methods.build import MethodSpec
    from ..methods.svcode import DEFAULT_MASK_CACHE_BYTES
    from ..pretrained import require_bundled_weights

    if args.method in MODEL_BASED_METHODS:
        options = {"device": args.device, "precision": args.precision, **baseline_options(args)}
        return MethodSpec(args.method, system, options=options)
    if args.method in LEARNED_METHODS:
        options = {"device": args.device, "precision": args.precision}
        return MethodSpec(args.method, system, str(args.weights), options)
    weights = args.weights if args.weights is not None else require_bundled_weights(system)
    options = {
        "device": args.device,
        "precision": args.precision,
        "tile_size": args.tile,
        "stride": args.stride,
        "batch_size": args.batch_size,
        "skip_empty": not args.no_skip,
        "mask_cache_bytes": (DEFAULT_MASK_CACHE_BYTES if args.mask_cache is None
                             else args.mask_cache << 20),
        "pool_window": args.pool_window,
        "refine_periphery": args.refine_periphery or 0,
    }
    return MethodSpec("svcode", system, str(weights), options)


def _read_files(args: argparse.Namespace, spec) -> dict[str, Path | None]:
    """The files besides the input that the run reads (no output may overwrite them)."""
    files: dict[str, Path | None] = {"--weights": None, "--system": None}
    weights = getattr(spec, "weights", None)
    if weights is not None:
        files["--weights"] = Path(weights)
    if args.system and Path(args.system).is_file():
        files["--system"] = Path(args.system)
    return files


def run(args: argparse.Namespace) -> int:
    """Reconstruct ``args.input`` into ``args.out``; print a one-line summary."""
    from ..physics.scene_checks import check_system_geometry
    from ..run.stream import reconstruct_file

    check_options(args)
    system = _system(args)
    check_system_geometry(system)  # before --register's work too
    start = time.perf_counter()
    recorded: dict = {}
    if args.register:
        moved, recorded = _register(args, system)
        # a network sees only where the sub-views are cut: it takes the moved chief rays,
        # the model-based methods the moved PSFs as well
        system = moved if args.method in MODEL_BASED_METHODS else system.replace(
            chief_rays=moved.chief_rays)
    spec = _spec(args, system)
    summary = reconstruct_file(
        args.input,
        args.out,
        spec,
        system=system,
        views_path=args.views,
        settings={**spec.describe(), **recorded},
        workers=args.workers,
        scheduler=args.scheduler,
        progress=not args.no_progress,
        input_scale=args.input_scale,
        inputs=_read_files(args, spec),
    )
    seconds = time.perf_counter() - start
    resumed = summary.frames - summary.computed
    print(
        f"reconstructed {summary.computed} frame(s)"
        + (f" ({resumed} resumed from an earlier run)" if resumed else "")
        + f" in {seconds:.2f} s"
        + (f"; tiles run {summary.tiles_run}, skipped {summary.tiles_skipped}"
           if summary.tiles_run + summary.tiles_skipped else "")
        + f" -> {args.out}"
    )
    return 0
