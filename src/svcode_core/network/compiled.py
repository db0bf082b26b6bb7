"""``torch.compile`` for the SV-CoDe network, with the coordinate masks left out of the graph.

A tile's masks depend on its origin: the lattice nodes it spans and the crop of each
mask's field change from tile to tile, so a graph that held them would be compiled again
for every origin (and torch gives up after eight and runs eagerly). :func:`compile_model`
marks the mask provider of a call (``masks_for``) and each block's masks
(``FoldedMasks.tile_masks``) to run eagerly, beside a graph that sees only tensors of
the tile's shape. The marks are set on first use, so importing the network does not load
torch's compiler (about 2 s)."""

from __future__ import annotations

import torch
from torch import nn

from .base import TiledModel
from .fast import FoldedMasks

__all__ = ["compile_model"]


def compile_model(model: nn.Module, bf16_on_cpu: bool = False) -> nn.Module:
    """``torch.compile(model, dynamic=False)`` with the coordinate masks computed eagerly.

    ``model`` is an SV-CoDe model (or a wrapper of one, e.g. DistributedDataParallel) or
    any other module; every call should bring inputs of one shape (one graph).
    ``bf16_on_cpu``: the graph will run under bf16 autocast on a CPU. Code is then
    generated with 256-bit vectors (torch's inductor setting, for the whole process):
    torch 2.13's 512-bit (AVX-512) code for SV-CoDe's bf16 training step computes the
    forward pass right but returns non-finite gradients."""
    if bf16_on_cpu:
        from torch._inductor import config

        config.cpp.simdlen = 256
    for cls, name in ((TiledModel, "masks_for"), (FoldedMasks, "tile_masks")):
        method = getattr(cls, name)
        if not getattr(method, "_eager_beside_graph", False):
            eager = torch.compiler.disable(method)
            eager._eager_beside_graph = True
            setattr(cls, name, eager)
    return torch.compile(model, dynamic=False)
