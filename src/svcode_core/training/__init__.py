"""Training SV-CoDe and the learned baselines from physics simulations: data, samplers,
loss, tasks and trainer."""

from ..lazy import lazy_exports

#: each exported name → the module that defines it, imported on first use (PEP 562), so
#: that :mod:`.settings` (and ``svcode train --help``, which quotes it) loads no torch
_EXPORTS = {
    **dict.fromkeys(("DataRecipe", "TrainingData", "generate_dataset", "split_frames",
                     "training_object"), ".dataset"),
    **dict.fromkeys(("DistInfo", "init_distributed", "shutdown_distributed"), ".distributed"),
    **dict.fromkeys(("field_weights", "joint_loss", "psnr_per_sample", "seen_by_every_lens",
                     "ssim_per_sample", "stage_loss", "svcode_loss"), ".loss"),
    **dict.fromkeys(("EpochSampler", "FrameDataset", "PatchDataset",
                     "check_disjoint_view_patches"), ".sampler"),
    **dict.fromkeys(("FrameTask", "PatchTask", "training_task"), ".tasks"),
    "TrainConfig": ".settings",
    "Trainer": ".trainer",
}


__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS, globals())


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
    "seen_by_every_lens",
    "shutdown_distributed",
    "split_frames",
    "ssim_per_sample",
    "stage_loss",
    "svcode_loss",
    "training_object",
    "training_task",
]
