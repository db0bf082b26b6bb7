"""Does the bundled model lose the edge strips because a view off the sensor looks dark?

In the 16-px strips three lenses' sub-views lie off the sensor, so the Demixing-Net's
outputs there are 0 and the Recon-Net sees three views of a "dark" object beside six of
the real one. Without any training, this probe fills each demixed view where its lens is
off the sensor (:func:`~svcode_core.physics.geometry.sensor_coverage`) with the mean of
the views that are on it, before the Recon-Net, and measures the field's same-content
gaps as ``bench/ring_gap.py`` does (its options, e.g. ``--regimes realistic --no-admm``).

Usage (from the repository root)::

    OMP_NUM_THREADS=1 python training/cm2-mini-v5/fill_probe.py --regimes realistic \\
        --no-admm --out runs/fill-probe/ring_gap
"""

from __future__ import annotations

import functools
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "bench"))

import ring_gap  # noqa: E402

from svcode_core.config import SystemConfig  # noqa: E402
from svcode_core.network.models import SVCoDe  # noqa: E402
from svcode_core.physics.geometry import sensor_coverage  # noqa: E402


@functools.cache
def mini_coverage(size: int) -> torch.Tensor:
    """cm2-mini's :func:`sensor_coverage` ``(9, S, S)``, computed once; refuses another size."""
    cover = sensor_coverage(SystemConfig.preset("cm2-mini"))
    if cover.shape[-1] != size:
        raise SystemExit(f"fill_probe: cm2-mini only (sub-views of {size} px given)")
    return cover


def tile_coverage(origins: torch.Tensor, height: int, width: int, size: int) -> torch.Tensor:
    """``(B, 9, height, width)``: 1 where each tile's view lies on the sensor."""
    cover = torch.nn.functional.pad(mini_coverage(size), (0, width, 0, height))  # tiles past S
    rows = [cover[:, r : r + height, c : c + width] for r, c in torch.as_tensor(origins).tolist()]
    return torch.stack(rows)


def forward_filled(self: SVCoDe, views, origins, sub_view_size):
    """:meth:`SVCoDe.forward` with the off-sensor views filled before the Recon-Net."""
    padded, masks = self._prepare(views, origins, sub_view_size)
    demixed = self.demix.run(padded, masks)
    cover = tile_coverage(origins, *demixed.shape[-2:], sub_view_size).to(demixed.dtype)
    mean = (demixed * cover).sum(1, keepdim=True) / cover.sum(1, keepdim=True).clamp(min=1)
    recon = self.recon.run(demixed * cover + mean * (1 - cover), masks)
    h, w = views.shape[-2:]
    return demixed[..., :h, :w], recon[..., :h, :w]


if __name__ == "__main__":
    SVCoDe.forward = forward_filled
    ring_gap.main()
