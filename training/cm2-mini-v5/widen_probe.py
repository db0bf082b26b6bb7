"""The view blocks, or the whole network, twice as wide: does the border stop costing the inside?

Every way of training the border so far traded along one line against the realistic
mean (README), which points at the network's size rather than its training. The
narrowest place is the view-dependent first block of each stage: four channels per lens
(`view_width`), the only block whose masks are the lens's own. This probe widens it to
eight in both stages (with --unet also every U-Net level, 16 to 32 channels at the first)
without changing what the model computes (Net2Net): every channel of a block's stream,
and every channel of its doubled convolutions, is copied; each layer reading copies
splits the original weight between them at random proportions (r and 1 - r, r uniform in
0.3 ... 0.7), so the copies compute the same values but receive different gradients and
can part. Then four epochs of `m16-edge32-ring8`'s recipe.

A probe, not a product option. Usage (from the repository root; the v2 data with the
16-px margin, `MARGIN=16` in ../resume.sh):
    python training/cm2-mini-v5/widen_probe.py RUN [--unet] [--threads 1]
"""

from __future__ import annotations

import torch
from recipe import border_recipe, probe_parser, start_weights

from svcode_core.config import N_LENSES
from svcode_core.methods.model_file import load_model, save_model
from svcode_core.network import SVCoDe
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
    ``cols``; the two copies of a column share the original weight at r and 1 - r, a
    column not copied keeps it."""
    new = weight[rows][:, cols].clone()
    r = 0.3 + 0.4 * torch.rand(new.shape[0], weight.shape[1], *new.shape[2:], generator=gen)
    first = torch.zeros(len(cols), dtype=torch.bool)  # the first copy of each column
    first[[cols.tolist().index(old) for old in set(cols.tolist())]] = True
    copied = torch.bincount(cols, minlength=weight.shape[1])[cols] > 1
    shape = (1, -1, *[1] * (new.dim() - 2))  # per input column
    share = torch.where(first.view(shape), r[:, cols], 1 - r[:, cols])
    return torch.where(copied.view(shape), new * share, new)


def _widen_block(state: dict, b: str, c: int, gen) -> None:
    """The CoDe block at prefix ``b`` of ``c`` channels, every channel copied."""
    stream, doubled = _copies(c), _copies(c, doubled=True)
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


def widen(model: SVCoDe, views: bool = True, unet: bool = False, seed: int = 0) -> SVCoDe:
    """``model`` with twice the view width (``views``) and twice the U-Net width at every
    level (``unet``) in both stages, computing the same."""
    config = model.model_config
    if unet and config.max_width:
        raise ValueError("a capped U-Net (max_width) is not widened here")
    c, width = config.view_width, config.width
    wide = SVCoDe(config.replace(view_width=2 * c if views else c,
                                 width=2 * width if unet else width))  # fmt: skip
    state, gen = model.state_dict(), torch.Generator().manual_seed(seed)
    lenses = _copies(c, groups=N_LENSES) if views else torch.arange(N_LENSES * c)
    for stage in ("demix", "recon"):
        p = f"{stage}."
        if views:
            shared = state[p + "intro.weight"].shape[0] == c  # one intro for the nine views
            rows = _copies(c) if shared else lenses
            state[p + "intro.weight"] = state[p + "intro.weight"][rows]
            state[p + "intro.bias"] = state[p + "intro.bias"][rows]
            _widen_block(state, p + "view_block.", c, gen)
            f = p + "fusion.attention."
            state[f + "weight"] = _split(state[f + "weight"], lenses, lenses, gen)
            state[f + "bias"] = state[f + "bias"][lenses]
        merge = _copies(width) if unet else torch.arange(width)
        state[p + "fusion.merge.weight"] = _split(state[p + "fusion.merge.weight"], merge,
                                                  lenses, gen)  # fmt: skip
        state[p + "fusion.merge.bias"] = state[p + "fusion.merge.bias"][merge]
        if unet:
            _widen_unet(state, p, getattr(model, stage), width, gen)
    wide.load_state_dict(state)
    return wide


def _widen_unet(state: dict, p: str, stage, width: int, gen) -> None:
    """Every level of the U-Net of ``stage`` (prefix ``p``), ``width · 2^k`` channels at
    level ``k``, and the layers around it, every channel copied."""
    unet = stage.unet
    widths = [width * 2**k for k in range(unet.levels + 1)]
    for group in ("encoders", "decoders"):
        for k, blocks in enumerate(getattr(unet, group)):
            for i in range(len(blocks)):
                _widen_block(state, f"{p}unet.{group}.{k}.{i}.", widths[k], gen)
    for i in range(len(unet.middle)):
        _widen_block(state, f"{p}unet.middle.{i}.", widths[-1], gen)
    for k in range(unet.levels):
        low, high = widths[k], widths[k + 1]
        d = f"{p}unet.downs.{k}."
        state[d + "weight"] = _split(state[d + "weight"], _copies(high), _copies(low), gen)
        state[d + "bias"] = state[d + "bias"][_copies(high)]
        u = f"{p}unet.ups.{k}.0.weight"  # 4 channels per output channel, pixel-shuffled
        new = torch.arange(8 * low)
        state[u] = _split(state[u], (new // 4 % low) * 4 + new % 4, _copies(high), gen)
    e = f"{p}ending.weight"
    state[e] = _split(state[e], torch.arange(state[e].shape[0]), _copies(width), gen)


def main() -> None:
    parser = probe_parser(__doc__)
    parser.add_argument("--unet", action="store_true", help="widen the U-Nets as well")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    model, system = load_model(start_weights(args.init))
    args.run.mkdir(parents=True, exist_ok=True)
    wide = widen(model, unet=args.unet)
    start = save_model(args.run / "start.safetensors", wide, system)
    trainer = Trainer(TrainingData(args.data), args.run, wide.model_config,
                      border_recipe(args.epochs), progress=False, init_weights=start)
    trainer.fit(resume=(args.run / "checkpoints" / "latest.json").is_file())
    print(f"best epoch {trainer.best.get('epoch')}: {args.run / 'best.safetensors'}")


if __name__ == "__main__":
    main()
