"""Training SV-CoDe from physics simulations: data, patch sampler, loss and trainer."""

from .dataset import DataRecipe, TrainingData, generate_dataset, split_frames, training_object
from .distributed import DistInfo, init_distributed, shutdown_distributed
from .loss import psnr, ssim_per_sample, stage_loss, svcode_loss
from .sampler import EpochSampler, PatchDataset, check_disjoint_view_patches
from .trainer import TrainConfig, Trainer

__all__ = [
    "DataRecipe",
    "DistInfo",
    "EpochSampler",
    "PatchDataset",
    "TrainConfig",
    "Trainer",
    "TrainingData",
    "check_disjoint_view_patches",
    "generate_dataset",
    "init_distributed",
    "psnr",
    "shutdown_distributed",
    "split_frames",
    "ssim_per_sample",
    "stage_loss",
    "svcode_loss",
    "training_object",
]
