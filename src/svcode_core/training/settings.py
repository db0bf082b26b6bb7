"""The settings of a training run that need no torch: the optimisation settings
(:class:`TrainConfig`) and the SV-CoDe ablations (:data:`ABLATIONS`).

They live apart from :mod:`.trainer` and :mod:`.configs` (which import torch) so that
``svcode train --help`` can quote their defaults without importing torch; both modules
re-export them.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

from ..config import ConfigError, check_int, check_number

__all__ = ["ABLATIONS", "STORE_DTYPES", "TRAIN_PRECISIONS", "TrainConfig"]

#: training precisions: ``auto`` is bf16 autocast on CUDA and float32 elsewhere
TRAIN_PRECISIONS = ("auto", "fp32", "bf16")

#: how a dataset may store its arrays (``svcode dataset --dtype``; read as float32)
STORE_DTYPES = ("float32", "float16")

#: SV-CoDe ablations: name → the :class:`~svcode_core.network.ModelConfig` fields they change
ABLATIONS = {
    "none": {},
    "no-coordgate": {"coord_gate": False},
    "no-pe": {"positional_encoding": False},
}


@dataclass(frozen=True)
class TrainConfig:
    """Optimisation settings of one run.

    Attributes
    ----------
    epochs : int
    batch_size : int
        Patches (whole frames for the learned baselines) per step and process.
    lr : float
        Peak Adam learning rate: reached linearly over ``warmup_steps`` steps, then
        cosine-annealed per step to ``lr · min_lr_ratio`` at the last step.
    min_lr_ratio : float
    warmup_steps : int
        Length of the linear warm-up. Without it, Adam's first full-size steps can push
        the sigmoid outputs of both stages into saturation on the mostly dark patches,
        where their gradient vanishes and training stalls at an all-zero prediction.
    grad_clip : float
        Maximum global gradient norm.
    patches_per_epoch : int or None
        Training samples (patches, or frames) drawn per epoch over all processes;
        ``None``: all of them.
    val_patches : int or None
        Size of the fixed validation subset; ``None``: every validation sample.
    alpha, beta : float
        Weights of ``1 − SSIM`` and MSE in the loss.
    edge_weight : float
        Weight of the squared error on the pixels within
        :data:`~svcode_core.evaluation.zones.EDGE_STRIP` pixels of the sub-view's edge (1: the
        same as elsewhere). A pixel of the edge strip lies in fewer training patches than one
        further in, and has neighbours on one side only.
    ring_weight : float
        Weight of the squared error in the outer ring (normalised field radius above
        :data:`~svcode_core.evaluation.zones.RING_RADIUS`; 1: the same as elsewhere). The
        ring is seen by fewer lenses through dimmer, more aberrated PSFs, so noise costs it
        more than the centre.
    partial_weight : float
        Weight of the squared error on the pixels that some lens's image loses off the
        sensor (:func:`~svcode_core.training.loss.seen_by_every_lens`; at ``cm2-mini`` the
        rows within 96 px of the top and bottom and the 16-px column strips; 1: the same as
        elsewhere). Fewer readings determine them.
    seed : int
        Seeds the initialisation, the patch draws and the noise.
    workers : int
        DataLoader worker processes.
    same_origin : int
        Training patches come in runs of this many that share their origin
        (:class:`EpochSampler` ``group``); the network computes the coordinate masks once
        per distinct origin in a batch, so ``same_origin = batch_size`` makes a CPU step
        several times cheaper. 1: independent draws. Ignored for whole frames.
    photon_range : (float, float)
        Each training sample's photon level is the frame's times a factor drawn
        log-uniformly from this range (validation keeps the frame's own): the network
        learns dimmer samples than the dataset holds.
    normalise_exposure : bool
        Bring every frame to the reference level before the network, targets alike, as
        the reconstructors do at inference (:mod:`~svcode_core.methods.exposure`).
    precision : {"auto", "fp32", "bf16"}
        The forward pass's precision (:data:`TRAIN_PRECISIONS`): ``bf16`` runs it under
        bf16 autocast on any device (faster on CPUs with AVX-512 bf16 or AMX units, slower
        on others); the loss, the weights and validation stay float32.
    compile : bool
        Run the training steps through :func:`torch.compile` (needs a C++ compiler on the
        CPU; the first step compiles for minutes, validation runs uncompiled). A bf16
        step is compiled with 256-bit vectors on a CPU
        (:func:`~svcode_core.network.compiled.compile_model`): it pays only on networks
        whose convolutions dominate the step.
    patch_size : int or None
        SV-CoDe's training and validation patch side, on a grid of half that stride;
        ``None``: the system's ``patch_size`` and ``patch_stride``. Not for the learned
        baselines, which train on whole frames.

    Examples
    --------
    >>> TrainConfig(epochs=2, photon_range=(0.25, 1.0)).validate().to_dict()["epochs"]
    2
    """

    epochs: int = 10
    batch_size: int = 4
    lr: float = 1e-3
    min_lr_ratio: float = 0.01
    warmup_steps: int = 100
    grad_clip: float = 1.0
    patches_per_epoch: int | None = None
    val_patches: int | None = None
    alpha: float = 1.0
    beta: float = 1.0
    edge_weight: float = 1.0
    ring_weight: float = 1.0
    partial_weight: float = 1.0
    seed: int = 0
    workers: int = 0
    same_origin: int = 1
    photon_range: tuple[float, float] = (1.0, 1.0)
    normalise_exposure: bool = False
    precision: str = "auto"
    compile: bool = False
    patch_size: int | None = None

    def validate(self) -> TrainConfig:
        """Raise ``ValueError`` (:class:`~svcode_core.config.ConfigError`) naming the first
        bad field; return ``self``."""
        for name in ("epochs", "batch_size", "same_origin"):
            check_int(name, getattr(self, name), 1)
        for name in ("patches_per_epoch", "val_patches"):
            if getattr(self, name) is not None:
                check_int(name, getattr(self, name), 1)
        if self.patch_size is not None:
            check_int("patch_size", self.patch_size, 11)  # the SSIM window
        for name in ("lr", "grad_clip"):
            check_number(name, getattr(self, name), 0, strict=True)
        for name in ("warmup_steps", "seed", "workers"):
            check_int(name, getattr(self, name), 0)
        if not 0 <= check_number("min_lr_ratio", self.min_lr_ratio) <= 1:
            raise ConfigError(f"min_lr_ratio: must lie in [0, 1], got {self.min_lr_ratio!r}")
        for name in ("alpha", "beta", "edge_weight", "ring_weight", "partial_weight"):
            check_number(name, getattr(self, name), 0)
        if self.precision not in TRAIN_PRECISIONS:
            raise ConfigError(f"precision: must be one of {', '.join(TRAIN_PRECISIONS)}, "
                              f"got {self.precision!r}")
        low, high = (check_number("photon_range", v, 0, strict=True) for v in self.photon_range)
        if low > high:
            raise ConfigError(f"photon_range: low must not exceed high, got {self.photon_range!r}")
        return self

    def to_dict(self) -> dict[str, Any]:
        """Plain-JSON dictionary."""
        return dataclasses.asdict(self)
