"""Does the bundled model lose the sub-view's border because its convolutions pad with 0?

Inside the field the network sees context on every side; at the sub-view's border its
convolutions run into zero padding, at every U-Net level, where the features of a dark
object would not be 0. Without any training, this probe runs the Recon-Net (and with
``--demix`` the Demixing-Net too) on its input surrounded by ``--margin`` px of zeros,
with the coordinate masks of those pixels (the MLP evaluated past the sub-view), and
crops the margin off: every pixel of the border then sees what a pixel next to a dark
region inside the field sees. Measured as ``bench/ring_gap.py`` does (its options).

Usage (from the repository root)::

    OMP_NUM_THREADS=1 python training/cm2-mini-v5/margin_probe.py --margin 32 \\
        --regimes realistic --no-admm --out runs/margin-probe/ring_gap
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch
import torch.nn.functional as F

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "bench"))

import ring_gap  # noqa: E402

from svcode_core.network.models import SVCoDe  # noqa: E402


def in_margin(model: SVCoDe, stage, views, origins: torch.Tensor, size: int, margin: int):
    """``stage`` run on ``views`` ``(B, C, h, w)`` at ``origins`` inside a zero margin."""
    h, w = views.shape[-2:]
    bottom = margin + (-(h + 2 * margin)) % model.stride  # the padded size a multiple of it
    right = margin + (-(w + 2 * margin)) % model.stride
    big = F.pad(views, (margin, right, margin, bottom))
    masks = model.masks_for(origins - margin, size, tuple(big.shape[-2:]))
    return stage.run(big, masks)[..., margin : margin + h, margin : margin + w]


def patched(margin: int, demix: bool):
    """:meth:`SVCoDe.forward` with the Recon-Net (and with ``demix`` the Demixing-Net) in
    the margin."""

    def forward(self: SVCoDe, views, origins, sub_view_size):
        padded, masks = self._prepare(views, origins, sub_view_size)
        origins = torch.as_tensor(origins, dtype=torch.long)
        h, w = views.shape[-2:]
        if demix:
            demixed = in_margin(self, self.demix, views, origins, sub_view_size, margin)
        else:
            demixed = self.demix.run(padded, masks)[..., :h, :w]
        return demixed, in_margin(self, self.recon, demixed, origins, sub_view_size, margin)

    return forward


if __name__ == "__main__":
    parser = argparse.ArgumentParser(add_help=False)
    parser.add_argument("--margin", type=int, default=32)
    parser.add_argument("--demix", action="store_true")
    args, rest = parser.parse_known_args()
    SVCoDe.forward = patched(args.margin, args.demix)
    sys.argv = [sys.argv[0], *rest]
    ring_gap.main()
