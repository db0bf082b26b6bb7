"""Lens context added to a trained model, as the start of its fine-tuning."""

from __future__ import annotations

from ..config import N_LENSES
from .models import SVCoDe

__all__ = ["with_lens_context"]


def with_lens_context(model: SVCoDe, reach: int = 1) -> SVCoDe:
    """A copy of ``model`` whose demixing stage also takes the crops up to ``reach``
    lens pitches away (:attr:`ModelConfig.lens_context`, :attr:`ModelConfig.context_reach`),
    computing exactly what ``model`` computes until it is trained further: the new inputs
    enter with zero weights. The starting point for fine-tuning a model without lens
    context, or with a shorter reach.

    Examples
    --------
    >>> import torch
    >>> from svcode_core.network import ModelConfig
    >>> plain = SVCoDe(ModelConfig.mini()).eval()
    >>> wide = with_lens_context(plain).eval()
    >>> views = torch.rand(1, 81, 16, 16)
    >>> with torch.no_grad():
    ...     before = plain(views[:, ::9], [[0, 0]], 384)[1]
    ...     after = wide(views, [[0, 0]], 384)[1]
    >>> torch.allclose(before, after, rtol=1e-5, atol=1e-6)  # float32 sums in another order
    True
    """
    config = model.model_config
    if config.lens_context and reach <= config.context_reach:
        raise ValueError(f"the model already has lens context of reach {config.context_reach}")
    wide = SVCoDe(config.replace(lens_context=True, context_reach=reach))
    state = model.state_dict()
    narrow, bias = state["demix.intro.weight"], state["demix.intro.bias"]
    if not config.lens_context:  # one first convolution shared by the nine lenses
        narrow, bias = narrow.repeat(N_LENSES, 1, 1, 1), bias.repeat(N_LENSES)
    narrow = narrow.unflatten(0, (N_LENSES, -1))  # (lens, out, crops, k, k)
    weight = narrow.new_zeros(*narrow.shape[:2], wide.demix.intro.in_channels // N_LENSES,
                              *narrow.shape[3:])  # fmt: skip
    weight[:, :, : narrow.shape[2]] = narrow  # a shorter reach's crops come first
    state["demix.intro.weight"] = weight.flatten(0, 1)
    state["demix.intro.bias"] = bias
    wide.load_state_dict(state)
    return wide.to(next(model.parameters()).device)
