"""The view blocks twice as wide: does the border stop costing the inside?

Every way of training the border so far traded along one line against the realistic
mean (README), which points at the network's size rather than its training. The
narrowest place is the view-dependent first block of each stage: four channels per lens
(`view_width`), the only block whose masks are the lens's own. This probe widens it to
eight in both stages without changing what the model computes (Net2Net): every channel
of a view block's stream, and every channel of its doubled convolutions, is copied; each
layer reading copies splits the original weight between them at random proportions
(r and 1 - r, r uniform in 0.3 ... 0.7), so the copies compute the same values but receive
different gradients and can part. Then four epochs of `m16-edge32-ring8`'s recipe.

A probe, not a product option. Usage (from the repository root; the v2 data with the
16-px margin, `MARGIN=16` in ../resume.sh):
    python training/cm2-mini-v5/widen_probe.py RUN [--threads 1]
"""

from __future__ import annotations

import torch
from recipe import border_recipe, probe_parser

from svcode_core.config import N_LENSES
from svcode_core.methods.model_file import load_model, save_model
from svcode_core.network import SVCoDe
from svcode_core.pretrained import bundled_weights
from svcode_core.training import Trainer, TrainingData


def _copies(c: int, doubled: bool = False, groups: int = 1) -> torch.Tensor:
    """Old index of each new channel: a stream of ``c`` channels per group becomes each
    group's channels twice; a doubled one (``2c``, gate halves ``a, b``) becomes
    ``a, a, b, b``."""
    if doubled:
        half = torch.arange(2 * c) % c
        return torch.cat((half, c + half))
    return torch.cat([g * c + torch.arange(2 * c) % c for g in range(groups)])


def _split(weight: torch.Tensor, rows: torch.Tensor, cols: torch.Tensor, gen) -> torch.Tensor:
    """A layer reading copied channels: rows taken by ``rows``, each input column by
    ``cols``, the two copies of a column sharing the original weight at r and 1 - r."""
    new = weight[rows][:, cols].clone()
    r = 0.3 + 0.4 * torch.rand(new.shape[0], new.shape[1] // 2, *new.shape[2:], generator=gen)
    first = torch.zeros(new.shape[1], dtype=torch.bool)
    seen: set[int] = set()
    for j, old in enumerate(cols.tolist()):
        first[j] = old not in seen
        seen.add(old)
    new[:, first] *= r
    new[:, ~first] *= 1 - r
    return new


def widen_views(model: SVCoDe, seed: int = 0) -> SVCoDe:
    """``model`` with twice the view width in both stages, computing the same."""
    c = model.model_config.view_width
    wide = SVCoDe(model.model_config.replace(view_width=2 * c))
    state, gen = model.state_dict(), torch.Generator().manual_seed(seed)
    stream, doubled, lenses = _copies(c), _copies(c, doubled=True), _copies(c, groups=N_LENSES)
    every = torch.arange(state["recon.fusion.merge.weight"].shape[0])
    for stage in ("demix", "recon"):
        p, b = f"{stage}.", f"{stage}.view_block."
        shared = state[p + "intro.weight"].shape[0] == c  # one intro for the nine views
        rows = stream if shared else lenses
        state[p + "intro.weight"] = state[p + "intro.weight"][rows]
        state[p + "intro.bias"] = state[p + "intro.bias"][rows]
        for name in ("beta", "gamma"):
            state[b + name] = state[b + name][:, stream]
        for name in ("norm1", "norm2"):
            for part in ("weight", "bias"):
                state[f"{b}{name}.{part}"] = state[f"{b}{name}.{part}"][stream]
        for gate, out in (("conv1", doubled), ("conv2", doubled), ("conv3", stream),
                          ("conv4", doubled), ("conv5", stream), ("sca", stream)):  # fmt: skip
            w = f"{b}{gate}.conv.weight"
            if gate == "conv2":  # depthwise: one filter per channel
                state[w] = state[w][out]
            else:
                state[w] = _split(state[w], out, stream, gen)
            state[f"{b}{gate}.conv.bias"] = state[f"{b}{gate}.conv.bias"][out]
            if gate != "sca":
                state[f"{b}{gate}.mlp.w_out"] = state[f"{b}{gate}.mlp.w_out"][:, out]
                state[f"{b}{gate}.mlp.b_out"] = state[f"{b}{gate}.mlp.b_out"][:, out]
        f = p + "fusion."
        state[f + "attention.weight"] = _split(state[f + "attention.weight"], lenses, lenses, gen)
        state[f + "attention.bias"] = state[f + "attention.bias"][lenses]
        state[f + "merge.weight"] = _split(state[f + "merge.weight"], every, lenses, gen)
    wide.load_state_dict(state)
    return wide


def main() -> None:
    args = probe_parser(__doc__).parse_args()
    torch.set_num_threads(args.threads)
    model, system = load_model(bundled_weights("cm2-mini"))
    args.run.mkdir(parents=True, exist_ok=True)
    start = save_model(args.run / "start.safetensors", widen_views(model), system)
    wide = load_model(start)[0]
    trainer = Trainer(TrainingData(args.data), args.run, wide.model_config,
                      border_recipe(args.epochs),
                      progress=False, init_weights=start)
    trainer.fit(resume=(args.run / "checkpoints" / "latest.json").is_file())
    print(f"best epoch {trainer.best.get('epoch')}: {args.run / 'best.safetensors'}")


if __name__ == "__main__":
    main()
