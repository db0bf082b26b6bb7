"""The DistributedDataParallel path: two CPU processes with the gloo backend."""

from __future__ import annotations

import os
import socket

import torch
import torch.multiprocessing as mp
from test_training import TINY_MODEL, tiny_data  # noqa: F401  (module-scoped fixture)

from svcode_core.training import TrainConfig, Trainer, TrainingData
from svcode_core.training.distributed import init_distributed, shutdown_distributed


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def _worker(rank: int, world_size: int, port: int, data_path: str, out: str) -> None:
    os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port), RANK=str(rank),
                      WORLD_SIZE=str(world_size), LOCAL_RANK=str(rank))
    torch.set_num_threads(1)
    info = init_distributed("cpu")
    try:
        config = TrainConfig(epochs=1, batch_size=1, patches_per_epoch=4, val_patches=3)
        trainer = Trainer(TrainingData(data_path), out, TINY_MODEL, config, dist=info,
                          progress=False)
        trainer.fit()
        flat = torch.cat([p.detach().flatten() for p in trainer.model.parameters()])
        torch.save({"params": flat, "history": trainer.history,
                    "val": len(trainer.val_indices)}, f"{out}/rank{rank}.pt")
    finally:
        shutdown_distributed(info)


def test_ddp_two_cpu_processes(tiny_data, tmp_path):  # noqa: F811
    mp.spawn(_worker, args=(2, _free_port(), str(tiny_data.path), str(tmp_path)), nprocs=2,
             join=True)
    ranks = [torch.load(tmp_path / f"rank{k}.pt", weights_only=True) for k in range(2)]
    # gradients are averaged, so both replicas hold the same weights after the steps
    assert torch.equal(ranks[0]["params"], ranks[1]["params"])
    # metrics are reduced over both processes: every rank logs the same numbers (times aside)
    timing = {"seconds", "cpu_seconds"}
    assert [{k: v for k, v in r.items() if k not in timing} for r in ranks[0]["history"]] == [
        {k: v for k, v in r.items() if k not in timing} for r in ranks[1]["history"]]
    assert ranks[0]["val"] + ranks[1]["val"] == 3  # validation patches are sharded
    assert ranks[0]["history"][0]["step"] == 2  # 4 patches / 2 processes / batch 1
    assert (tmp_path / "best.safetensors").is_file()
    assert (tmp_path / "checkpoints" / "latest.json").is_file()
