"""``svcode reconstruct``: reconstruct a raw CM² frame or stack into a TIFF.

The methods' own flags, their help and their checks are made from the tables of options in
:mod:`~svcode_core.methods.registry` (:class:`~svcode_core.methods.registry.Option`).
"""

from __future__ import annotations

import argparse
import math
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from ..config import SystemConfig, load_system
from ..methods.registry import (
    LEARNED,
    METHODS,
    MODEL_BASED,
    MODEL_BASED_METHODS,
    SVCODE,
    Option,
    method,
)
from . import SUMMARIES, add_progress_argument, add_system_arguments


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
        "--register",
        action="store_true",
        help="first estimate the microlens array's drift from the recording itself "
        "(chief-ray self-registration on the mean of its first 8 frames, about 3 LSV-ADMM "
        "solves) and reconstruct with the moved system; it is written to OUT's folder as "
        "OUT-stem.registered/system.json (with its PSFs and registration.json)",
    )
    parser.add_argument(
        "--weights",
        type=Path,
        help="trained model (svcode default: the bundled model; required for the learned "
        "baselines)",
    )
    parser.add_argument(
        "--views", type=Path, metavar="VIEWS.tif", help="also write the nine demixed views"
    )
    parser.add_argument("--device", default="cpu", help="cpu, cuda, cuda:N or mps")
    parser.add_argument(
        "--input-scale",
        type=float,
        metavar="COUNTS",
        help="divide every frame by COUNTS, the sensor's full-scale value (e.g. 4095 for a "
        "12-bit sensor); default: 8- and 16-bit integer frames are divided by their type's "
        "maximum (255, 65535), float frames are taken as normalised (full scale 1.0)",
    )
    parser.add_argument(
        "--precision",
        choices=sorted({p for name in METHODS for p in method(name).precisions}),
        help="; ".join(f"{name}: {', '.join(method(name).precisions)}" for name in METHODS)
        + " (default: each method's first; svcode's auto is bf16 on processors and GPUs with "
        "bf16 units when the model's file records bf16 within 0.05 dB of fp32, else fp32)",
    )
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


def _number_or_auto(text: str) -> float | str:
    """The value of a flag that takes a number or ``auto``."""
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
    print(
        f"registered: lens offsets up to {abs(registration.offsets).max():.2f} px, array "
        f"shift {registration.shift.round(2).tolist()} px, rotation "
        f"{registration.rotation_deg:.3f}°; moved system in {folder}"
    )
    return moved, {"registration": {**registration.to_dict(), "system": str(folder)}}


def _flags(family: str | None = None) -> dict[str, dict[str, Option]]:
    """Each method option's flag → ``{method: its option}``, in the tables' order (of the
    methods of ``family``)."""
    flags: dict[str, dict[str, Option]] = {}
    for name in METHODS:
        if family is None or method(name).family == family:
            for option in method(name).options:
                flags.setdefault(option.flag, {})[name] = option
    return flags


def _given(args: argparse.Namespace, flag: str) -> Any:
    """The value of ``flag`` in ``args``; ``None`` when not given (``0`` is given)."""
    value = getattr(args, flag.removeprefix("--").replace("-", "_"), None)
    return None if value is False else value


def add_method_arguments(parser: argparse.ArgumentParser) -> None:
    """Register every method's options on ``parser``, from the tables of
    :mod:`~svcode_core.methods.registry`, a group per family (all default to ``None``, or
    ``False``: the method's default)."""
    for family in (SVCODE, MODEL_BASED):
        names = [name for name in METHODS if method(name).family == family]
        group = parser.add_argument_group(f"options of --method {', '.join(names)}")
        for flag, takers in _flags(family).items():
            option = next(iter(takers.values()))
            if len(set(takers.values())) == 1:  # one option: its help, for whom it is
                text = option.describe()
                text = text if len(takers) == len(names) else f"{', '.join(takers)}: {text}"
            else:
                text = "; ".join(f"{name}: {o.describe()}" for name, o in takers.items())
            if option.kind is bool:
                group.add_argument(flag, action="store_true", help=text)
                continue
            kind = _number_or_auto if option.auto else option.flag_kind or option.kind
            group.add_argument(flag, type=kind, choices=option.choices or None,
                               metavar=option.metavar, help=text)  # fmt: skip


def method_options(args: argparse.Namespace) -> dict[str, Any]:
    """The options of ``args.method`` given on the command line, as keyword arguments.

    Raises
    ------
    ValueError
        If a value is out of bounds or an option of another method was given.
    """
    options = {}
    for flag, takers in _flags().items():
        value = _given(args, flag)
        if value is None:
            continue
        if args.method not in takers:
            raise ValueError(f"{flag} does not apply to --method {args.method}")
        option = takers[args.method]
        option.check(value, flag=True)
        options[option.name] = option.from_flag(value)
    return options


#: the name of :func:`method_options` when it took only the model-based baselines'
baseline_options = method_options


def _refuse(args: argparse.Namespace, family: str, why: str = "") -> None:
    """Refuse the flags of the methods of ``family`` given with ``--method`` of another
    family (``why``: what that method does differently)."""
    given = [flag for flag in _flags(family) if _given(args, flag) is not None]
    if given:
        names = [name for name in METHODS if method(name).family == family]
        whom = f"--method {names[0]}" if len(names) == 1 else f"the {family} baselines"
        verb = "applies" if len(given) == 1 else "apply"
        reason = f" ({why})" if why else ""
        raise ValueError(f"{' and '.join(given)} {verb} to {whom}, not to --method "
                         f"{args.method}{reason}")  # fmt: skip


def _check_precision(args: argparse.Namespace) -> None:
    accepted = method(args.method).precisions
    if args.precision is None:
        args.precision = accepted[0]
    if args.precision not in accepted:
        raise ValueError(f"--precision {args.precision} does not apply to --method "
                         f"{args.method}; it takes {', '.join(accepted)}")  # fmt: skip


def _finite(value: float) -> bool:
    return math.isfinite(value)


#: the rules of the options of the command itself (the methods' are in their tables):
#: ``args`` attribute → (accepts the value, what it must be)
_VALUE_RULES: dict[str, tuple[Callable[[Any], bool], str]] = {
    "workers": (lambda v: v >= 0, ">= 0 (processes; 0 runs in this process)"),
    "input_scale": (lambda v: _finite(v) and v > 0, "a finite number > 0 (counts)"),
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
    for flag, takers in _flags().items():  # the bounds first, whichever method takes it
        value = _given(args, flag)
        if value is not None:
            takers.get(args.method, next(iter(takers.values()))).check(value, flag=True)
    _check_precision(args)
    family = method(args.method).family
    if family == MODEL_BASED:
        _refuse(args, SVCODE, "it inverts the forward model, without tiles")
        if args.weights is not None:
            raise ValueError(
                f"--weights does not apply to --method {args.method}: it inverts "
                "the system's forward model, without a trained network"
            )
        method_options(args)
        return
    _refuse(args, MODEL_BASED)
    if args.weights is not None and not args.weights.is_file():
        raise FileNotFoundError(f"weights not found: {args.weights}")
    if family == LEARNED:
        if args.weights is None:
            raise ValueError(f"--method {args.method} needs --weights: no learned baseline is "
                             "bundled; train one with `svcode train --method "
                             f"{args.method}` (see the README)")  # fmt: skip
        _refuse(args, SVCODE, "it reconstructs the whole frame at once")


def _spec(args: argparse.Namespace, system: SystemConfig):
    """The picklable reconstructor recipe of ``args.method``, a
    :class:`~svcode_core.methods.build.MethodSpec` (options checked by
    :func:`check_options`)."""
    from ..methods.build import MethodSpec
    from ..methods.model_file import read_model_metadata
    from ..methods.svcode import auto_precision
    from ..pretrained import require_bundled_weights

    options = {"device": args.device, "precision": args.precision}
    weights = args.weights
    if args.method == SVCODE:  # recorded in full, defaults too
        options.update({option.name: option.default for option in method(SVCODE).options})
        weights = require_bundled_weights(system) if weights is None else weights
        if args.precision == "auto":  # recorded as chosen
            checks = read_model_metadata(weights)["extra"].get("precision_check", {})
            options["precision"] = auto_precision(checks, args.device)
    options.update(method_options(args))
    return MethodSpec(args.method, system, None if weights is None else str(weights), options)


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
        system = (
            moved
            if args.method in MODEL_BASED_METHODS
            else system.replace(chief_rays=moved.chief_rays)
        )
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
        + f" in {seconds:.2f} s ({spec.options['precision']})"
        + (
            f"; tiles run {summary.tiles_run}, skipped {summary.tiles_skipped}"
            if summary.tiles_run + summary.tiles_skipped
            else ""
        )
        + f" -> {args.out}"
    )
    return 0
