"""What the trainer trains: the model, its samples and its ``(prediction, target)`` stages.

:class:`~.trainer.Trainer` is method-agnostic; a task supplies the method-specific parts:

* :class:`PatchTask`: SV-CoDe on aligned sub-view patches with their origins, two stages
  (``demix``, ``recon``);
* :class:`FrameTask`: the learned baselines (:mod:`svcode_core.methods.learned`) on whole
  padded frames (they filter the whole field of view), one stage (``recon``), initialised
  from the system's pupil-model operator.

:func:`training_task` picks the task from the type of the model configuration.
"""

from __future__ import annotations

import contextlib
from collections.abc import Sequence
from contextlib import AbstractContextManager
from typing import Any

import torch
from torch import nn

from ..config import SystemConfig
from ..methods.learned import LEARNED_MODELS, FourierNetConfig, MultiWienerConfig
from ..network import ModelConfig, SVCoDe
from ..physics.cm2 import CM2Operator
from .dataset import TrainingData
from .loss import in_field
from .sampler import FrameDataset, PatchDataset

__all__ = ["FrameTask", "PatchTask", "Stages", "training_task"]

Stages = dict[str, tuple[torch.Tensor, torch.Tensor]]
"""Named ``(prediction, target)`` pairs of one batch, reconstruction under ``"recon"``."""

_EVAL_MASK_BYTES = 2**28


def _stack(items: list[dict[str, Any]], keys: Sequence[str]) -> dict[str, torch.Tensor]:
    return {key: torch.stack([item[key] for item in items]) for key in keys}


class PatchTask:
    """SV-CoDe (Demixing-Net and Recon-Net) trained on patches.

    Parameters
    ----------
    config : ModelConfig
    """

    label = "SV-CoDe"
    unit = "patches"
    stages = ("demix", "recon")

    def __init__(self, config: ModelConfig) -> None:
        self.config = config

    def build(self, system: SystemConfig) -> nn.Module:
        """A freshly initialised model."""
        return SVCoDe(self.config)

    def dataset(
        self, data: TrainingData, frames: Sequence[int], fixed_noise: bool, seed: int,
        **sampling: Any,
    ) -> PatchDataset:
        """The samples of ``frames`` (``sampling``: photon range and exposure options of
        :class:`PatchDataset`)."""
        return PatchDataset(data, frames, fixed_noise=fixed_noise, seed=seed,
                            lens_context=self.config.lens_context,
                            context_reach=self.config.context_reach,
                            view_margin=self.config.view_margin, **sampling)

    def origins(self, dataset: PatchDataset) -> int:
        """Distinct sample origins per frame (patches at one origin share their masks)."""
        return len(dataset.origins)

    def collate(self, items: list[dict[str, Any]]) -> dict[str, torch.Tensor]:
        """Stack samples into a batch."""
        return _stack(items, ("views", "demixed", "object", "origin", "gain"))

    def outputs(
        self, net: nn.Module, batch: dict[str, torch.Tensor], system: SystemConfig
    ) -> Stages:
        """Run ``net`` on a batch; the pairs of both stages. A patch's reconstruction past
        the field (a model with a view margin) is not scored: it is replaced there by its
        target."""
        demixed, recon = net(batch["views"], batch["origin"], system.sub_view_size)
        target = batch["object"]
        if self.config.view_margin:
            inside = in_field(batch["origin"], target.shape[-1], system.sub_view_size)
            recon = torch.where(inside.to(recon.device), recon, target.to(recon.dtype))
        return {"demix": (demixed, batch["demixed"]), "recon": (recon, target)}

    def evaluating(self, model: nn.Module) -> AbstractContextManager:
        """Context for validation passes: the coordinate-mask cache."""
        return model.cache_masks(max_bytes=_EVAL_MASK_BYTES)

    def field_part(self, batch: dict[str, torch.Tensor], system: SystemConfig
                   ) -> list[tuple[slice, slice]] | None:  # fmt: skip
        """Per sample, the rows and columns of its patch that lie inside the field, where
        its reconstruction is scored; ``None`` when that is every patch whole (no view
        margin)."""
        if not self.config.view_margin:
            return None
        size, p = system.sub_view_size, batch["object"].shape[-1]
        return [tuple(slice(max(-o, 0), min(size - o, p)) for o in origin.tolist())
                for origin in batch["origin"]]  # fmt: skip


class FrameTask:
    """A learned baseline (MultiWienerNet or SV-FourierNet) trained on whole frames.

    Parameters
    ----------
    config : MultiWienerConfig or FourierNetConfig
    """

    unit = "frames"
    stages = ("recon",)
    _MODELS = {cls.config_class: cls for cls in LEARNED_MODELS.values()}

    def __init__(self, config: MultiWienerConfig | FourierNetConfig) -> None:
        self.config = config
        self.model_class = self._MODELS[type(config)]
        self.label = self.model_class.__name__

    def build(self, system: SystemConfig) -> nn.Module:
        """The model with its filters initialised from the pupil-model operator of ``system``."""
        return self.model_class.from_operator(CM2Operator.from_system(system), self.config)

    def dataset(
        self, data: TrainingData, frames: Sequence[int], fixed_noise: bool, seed: int,
        **sampling: Any,
    ) -> FrameDataset:
        """The padded frames of ``frames`` (``sampling`` as for :class:`PatchTask`)."""
        return FrameDataset(data, frames, fixed_noise=fixed_noise, seed=seed, **sampling)

    def origins(self, dataset: FrameDataset) -> int:
        """One: a sample is the whole frame."""
        return 1

    def collate(self, items: list[dict[str, Any]]) -> dict[str, torch.Tensor]:
        """Stack samples into a batch."""
        return _stack(items, ("frame", "object", "gain"))

    def outputs(
        self, net: nn.Module, batch: dict[str, torch.Tensor], system: SystemConfig
    ) -> Stages:
        """Run ``net`` on a batch; the reconstruction pair."""
        return {"recon": (net(batch["frame"]), batch["object"])}

    def evaluating(self, model: nn.Module) -> AbstractContextManager:
        """No state to set up for validation passes."""
        return contextlib.nullcontext()

    def field_part(self, batch: dict[str, torch.Tensor], system: SystemConfig) -> None:
        """``None``: a whole frame's reconstruction is the field."""
        return None


def training_task(
    config: ModelConfig | MultiWienerConfig | FourierNetConfig,
) -> PatchTask | FrameTask:
    """The task that trains the model ``config`` describes."""
    if isinstance(config, ModelConfig):
        return PatchTask(config)
    if type(config) in FrameTask._MODELS:
        return FrameTask(config)
    raise TypeError(f"no training task for a {type(config).__name__}")
