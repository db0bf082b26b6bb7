"""Training SV-CoDe and the learned baselines from physics simulations: data, samplers,
loss, tasks and trainer."""

from .dataset import DataRecipe, TrainingData, generate_dataset, split_frames, training_object
from .distributed import DistInfo, init_distributed, shutdown_distributed
from .loss import (
    field_weights,
    joint_loss,
    psnr_per_sample,
    ssim_per_sample,
    stage_loss,
    svcode_loss,
)
from .sampler import EpochSampler, FrameDataset, PatchDataset, check_disjoint_view_patches
from .tasks import FrameTask, PatchTask, training_task
from .trainer import TrainConfig, Trainer

__all__ = [
    "DataRecipe",
    "DistInfo",
    "EpochSampler",
    "FrameDataset",
    "FrameTask",
    "PatchDataset",
    "PatchTask",
    "TrainConfig",
    "Trainer",
    "TrainingData",
    "check_disjoint_view_patches",
    "field_weights",
    "generate_dataset",
    "init_distributed",
    "joint_loss",
    "psnr_per_sample",
    "shutdown_distributed",
    "split_frames",
    "ssim_per_sample",
    "stage_loss",
    "svcode_loss",
    "training_object",
    "training_task",
]
