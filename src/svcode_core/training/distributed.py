"""Multi-process training with ``torchrun``: process group set-up and small collectives.

``torchrun --nproc-per-node N -m svcode_core.cli train ...`` sets ``RANK``,
``WORLD_SIZE`` and ``LOCAL_RANK``; :func:`init_distributed` reads them and joins the
process group (NCCL on CUDA, gloo on the CPU). A single process needs no set-up and every
helper here is then a no-op.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import torch
import torch.distributed as dist

__all__ = ["DistInfo", "all_reduce_sum", "barrier", "init_distributed", "shutdown_distributed"]


@dataclass(frozen=True)
class DistInfo:
    """Where this process sits in the job.

    Attributes
    ----------
    rank, world_size, local_rank : int
    """

    rank: int = 0
    world_size: int = 1
    local_rank: int = 0

    @property
    def is_main(self) -> bool:
        """Rank 0 writes the checkpoints, logs and progress bars."""
        return self.rank == 0

    @property
    def active(self) -> bool:
        """More than one process."""
        return self.world_size > 1


def init_distributed(device_type: str = "cpu") -> DistInfo:
    """Join the process group described by the ``torchrun`` environment, if any.

    Parameters
    ----------
    device_type : str
        ``"cuda"`` selects the NCCL backend (and the local GPU), anything else gloo.

    Returns
    -------
    DistInfo
    """
    world_size = int(os.environ.get("WORLD_SIZE", "1"))
    if world_size <= 1:
        return DistInfo()
    info = DistInfo(int(os.environ["RANK"]), world_size, int(os.environ.get("LOCAL_RANK", "0")))
    if not dist.is_initialized():
        backend = "nccl" if device_type == "cuda" else "gloo"
        if device_type == "cuda":
            torch.cuda.set_device(info.local_rank)
        dist.init_process_group(backend, rank=info.rank, world_size=world_size)
    return info


def shutdown_distributed(info: DistInfo) -> None:
    """Leave the process group (after a final barrier)."""
    if info.active and dist.is_initialized():
        dist.barrier()
        dist.destroy_process_group()


def barrier(info: DistInfo) -> None:
    """Wait for every process."""
    if info.active:
        dist.barrier()


def all_reduce_sum(values: torch.Tensor, info: DistInfo) -> torch.Tensor:
    """Sum ``values`` over processes (in place, returned)."""
    if info.active:
        dist.all_reduce(values, op=dist.ReduceOp.SUM)
    return values
