"""``svcode train``: train SV-CoDe or a learned baseline on a simulated dataset (also under
``torchrun``)."""

from __future__ import annotations

import argparse
import warnings
from pathlib import Path
from typing import Any

from ..config import SystemConfig
from ..methods.registry import LEARNED_METHODS, TRAINABLE_METHODS, method
from . import (
    SUMMARIES,
    add_progress_argument,
    add_system_arguments,
    chosen_system,
    in_option_words,
)


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    """Register ``svcode train``."""
    # the torch-free homes of the training defaults and the field's zones: no torch for --help
    from ..evaluation.zones import EDGE_STRIP, RING_RADIUS
    from ..training.settings import ABLATIONS, TRAIN_PRECISIONS, TrainConfig

    defaults = TrainConfig()
    parser = subparsers.add_parser(
        "train",
        help=SUMMARIES["train"],
        description=(
            "Train the two-stage SV-CoDe network on the patches of a dataset written by "
            "`svcode dataset`, or a learned baseline (MultiWienerNet, SV-FourierNet) on its "
            "whole padded frames, with fresh sensor noise on every use. Writes checkpoints "
            "every epoch, best.safetensors (best validation PSNR), log.csv, log.json and "
            "loss.png to OUT. For several GPUs run it under `torchrun --nproc-per-node N "
            "-m svcode_core.cli train ...`."
        ),
    )
    add_system_arguments(parser, default=None, what="the system; must match the dataset's",
                         default_text="default: the dataset's")  # fmt: skip
    parser.add_argument("--data", type=Path, required=True, help="dataset folder")
    parser.add_argument("--out", type=Path, required=True, help="run folder")
    parser.add_argument("--method", default="svcode", choices=TRAINABLE_METHODS,
                        help="svcode (patch-wise), or a learned baseline trained on whole "
                        "frames: " + ", ".join(f"{name} ({method(name).label})"
                                               for name in LEARNED_METHODS))  # fmt: skip
    parser.add_argument("--model-config", metavar="{mini,reference,FILE}",
                        help="network sizes: a preset name or a JSON file of the method's "
                        "configuration (default: mini; the baselines have mini only)")
    parser.add_argument("--init", metavar="WEIGHTS",
                        help="start from the weights of a model file, or 'pretrained' for the "
                        "bundled model (fine-tuning); the network configuration and the "
                        "measured tile overlap are the file's")
    parser.add_argument("--lens-context", type=int, nargs="?", const=1, default=0,
                        metavar="REACH",
                        help="SV-CoDe: the demixing stage also sees each lens's crop moved by "
                        "one lens pitch towards its neighbours and, with REACH 2, by two "
                        "pitches left and right (for the field's edge strips; default REACH "
                        "1); with --init, the file's model gains the inputs it lacks with "
                        "zero weights")
    parser.add_argument("--padding", metavar="{zeros,reflect}",
                        help="SV-CoDe: how the convolutions extend a tile past its edge, "
                        "with zeros or mirrored (default: zeros, or the --init file's)")
    parser.add_argument("--view-margin", type=int, metavar="PX",
                        help="SV-CoDe: run both stages on each sub-view enlarged by PX on "
                        "every side, so the light past its window reaches the "
                        "reconstruction (default: the dataset's --view-margin)")
    parser.add_argument("--ablation", default="none", choices=sorted(ABLATIONS),
                        help="switch off the coordinate gate or the positional encoding")
    parser.add_argument("--epochs", type=int, default=defaults.epochs)
    parser.add_argument("--batch-size", type=int, default=defaults.batch_size,
                        help="patches (whole frames for a baseline) per step and process")
    parser.add_argument("--lr", type=float, default=defaults.lr, help="initial learning rate")
    parser.add_argument("--min-lr-ratio", type=float, default=defaults.min_lr_ratio,
                        help="final learning rate of the cosine schedule, relative to --lr")
    parser.add_argument("--warmup-steps", type=int, default=defaults.warmup_steps,
                        help="steps of linear learning-rate warm-up")
    parser.add_argument("--grad-clip", type=float, default=defaults.grad_clip,
                        help="maximum gradient norm")
    parser.add_argument("--ssim-weight", type=float, default=defaults.alpha,
                        help="weight of 1 - SSIM in each stage's loss")
    parser.add_argument("--mse-weight", type=float, default=defaults.beta,
                        help="weight of the MSE in each stage's loss (SSIM barely sees a "
                        "region's brightness; a larger weight holds dim regions to it)")
    parser.add_argument("--edge-weight", type=float, default=defaults.edge_weight,
                        help="weight of the squared error on the outer "
                        f"{EDGE_STRIP} pixels of the sub-view (its edge strips: fewer "
                        "patches see them; default 1, as elsewhere)")
    parser.add_argument("--ring-weight", type=float, default=defaults.ring_weight,
                        help="weight of the squared error in the outer ring of the field "
                        f"(normalised radius above {RING_RADIUS}, the benchmark's ring: seen by "
                        "fewer lenses, so noisier; default 1, as elsewhere)")
    parser.add_argument("--partial-weight", type=float, default=defaults.partial_weight,
                        help="weight of the squared error on the pixels that some lens's "
                        "image loses off the sensor (fewer readings determine them; "
                        "multiplies the edge and ring weights; default 1, as elsewhere)")
    parser.add_argument("--photon-range", type=float, nargs=2, metavar=("LOW", "HIGH"),
                        default=defaults.photon_range,
                        help="scale each training sample's photon level by a factor drawn "
                        "log-uniformly from LOW..HIGH (dimmer samples than the dataset; "
                        "needs a dataset with departures; default 1 1)")
    parser.add_argument("--normalise-exposure", action="store_true",
                        help="bring every frame to the reference level, as reconstruction "
                        "does (default: frames as simulated)")
    parser.add_argument("--precision", default=defaults.precision, choices=TRAIN_PRECISIONS,
                        help="the forward pass's precision: bf16 autocast on any device "
                        "(faster on CPUs with AVX-512 bf16 or AMX units); auto: bf16 on CUDA, "
                        "fp32 elsewhere (default auto)")
    parser.add_argument("--compile", action="store_true",
                        help="compile the training step with torch.compile (needs a C++ "
                        "compiler on the CPU; minutes at the first step, then faster steps)")
    parser.add_argument("--patch-size", type=int, metavar="P",
                        help="SV-CoDe: side of the training and validation patches, cut at "
                        "stride P/2 (default: the system's patch size)")
    parser.add_argument("--patches-per-epoch", type=int,
                        help="training patches drawn per epoch (default: all)")
    parser.add_argument("--val-patches", type=int,
                        help="size of the fixed validation subset (default: all)")
    parser.add_argument("--same-origin", type=int, default=defaults.same_origin, metavar="N",
                        help="draw training patches in runs of N sharing their origin, so the "
                        "coordinate masks are computed once per run (N = batch size: several "
                        "times faster on a CPU; default: 1, independent draws)")
    parser.add_argument("--seed", type=int, default=defaults.seed)
    parser.add_argument("--loader-workers", type=int, default=defaults.workers, metavar="N",
                        help="data-loading worker processes of each training process "
                        f"(default {defaults.workers})")  # fmt: skip
    parser.add_argument("--workers", type=int, dest="old_workers", metavar="N",
                        help="deprecated name of --loader-workers")
    parser.add_argument("--device",
                        help="cpu or cuda (default: cuda when available; under torchrun each "
                        "process takes cuda:LOCAL_RANK)")  # fmt: skip
    parser.add_argument("--resume", action="store_true",
                        help="continue from the latest checkpoint in OUT")
    add_progress_argument(parser)
    parser.set_defaults(func=run)


#: the command-line option of each :class:`TrainConfig` field, for the messages
_OPTION_OF_FIELD = {"alpha": "--ssim-weight", "beta": "--mse-weight"} | {
    field: "--" + field.replace("_", "-")
    for field in ("epochs", "batch_size", "lr", "min_lr_ratio", "warmup_steps", "grad_clip",
                  "edge_weight", "ring_weight", "partial_weight", "patches_per_epoch",
                  "val_patches", "seed", "same_origin", "photon_range", "patch_size")
} | {"workers": "--loader-workers"}  # fmt: skip


def initial_weights(args: argparse.Namespace, system: SystemConfig) -> tuple[Path, Any]:
    """The model file of ``--init`` (``pretrained``: the bundled model of ``system``) and
    its network configuration, checked against ``--method``; ``--model-config`` and
    ``--ablation`` must be left out."""
    from ..methods.model_file import read_model_metadata
    from ..pretrained import require_bundled_weights
    from ..training.configs import config_class

    if args.model_config is not None or args.ablation != "none":
        raise ValueError("--init takes the network configuration from the model file: "
                         "leave out --model-config and --ablation")  # fmt: skip
    if args.init == "pretrained":
        try:
            path = require_bundled_weights(system)
        except FileNotFoundError as err:  # its advice (--weights) is for reconstructing
            raise FileNotFoundError(f"--init pretrained: {str(err).split(';')[0]}; train "
                                    "from scratch (leave out --init) or give a model file "
                                    "of this system as --init FILE") from None
    else:
        path = Path(args.init)
    config = read_model_metadata(path)["model_config"]
    expected = config_class(args.method)
    if not isinstance(config, expected):
        raise ValueError(f"--init {path} holds a {type(config).__name__} model, not one for "
                         f"--method {args.method}")  # fmt: skip
    return path, config


def run(args: argparse.Namespace) -> int:
    """Train (or resume) and print where the results are."""
    import torch

    from ..training import (
        TrainConfig,
        Trainer,
        TrainingData,
        init_distributed,
        shutdown_distributed,
    )
    from ..training.configs import model_config_from, with_svcode_options

    if args.old_workers is not None:
        warnings.warn("--workers is the deprecated name of --loader-workers", FutureWarning,
                      stacklevel=1)  # fmt: skip
        args.loader_workers = args.old_workers
    config = TrainConfig(
        epochs=args.epochs, batch_size=args.batch_size, lr=args.lr,
        min_lr_ratio=args.min_lr_ratio, warmup_steps=args.warmup_steps, grad_clip=args.grad_clip,
        alpha=args.ssim_weight, beta=args.mse_weight, edge_weight=args.edge_weight,
        ring_weight=args.ring_weight, partial_weight=args.partial_weight,
        patches_per_epoch=args.patches_per_epoch, val_patches=args.val_patches,
        seed=args.seed, workers=args.loader_workers, same_origin=args.same_origin,
        photon_range=tuple(args.photon_range), normalise_exposure=args.normalise_exposure,
        precision=args.precision, compile=args.compile, patch_size=args.patch_size,
    )
    with in_option_words(_OPTION_OF_FIELD):
        config.validate()
    data = TrainingData(args.data)
    system = chosen_system(args)
    if system is not None and system != data.system:
        raise ValueError(f"the dataset {args.data} was simulated for system "
                         f"{data.system.name!r}, which differs from {system.name!r}")
    device = torch.device(args.device or ("cuda" if torch.cuda.is_available() else "cpu"))
    dist = init_distributed(device.type)
    if device.type == "cuda" and dist.active:
        device = torch.device("cuda", dist.local_rank)
    try:
        init = None
        margin = args.view_margin
        if margin is None and args.method == "svcode" and data.view_margin:
            margin = data.view_margin
        if args.init is None:
            model_config = model_config_from(args.model_config or "mini", args.ablation,
                                             args.method, args.lens_context,
                                             args.padding, margin)  # fmt: skip
        else:
            init, model_config = initial_weights(args, data.system)
            model_config = with_svcode_options(model_config, args.method,
                                               lens_context=args.lens_context,
                                               padding=args.padding, view_margin=margin)
        trainer = Trainer(data, args.out, model_config, config, device=device, dist=dist,
                          progress=not args.no_progress, init_weights=init)
        trainer.fit(resume=args.resume)
    finally:
        shutdown_distributed(dist)
    if dist.is_main and trainer.best:
        best = trainer.best
        print(f"best epoch {best['epoch']}: validation reconstruction PSNR "
              f"{best['val_recon_psnr']:.2f} dB, SSIM {best['val_recon_ssim']:.3f} -> "
              f"{args.out / 'best.safetensors'}")
    return 0
