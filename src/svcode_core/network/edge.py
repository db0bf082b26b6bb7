"""Edge features added to a trained model, as the start of its fine-tuning."""

from __future__ import annotations

import torch

from .models import CoordMLP, SVCoDe

__all__ = ["with_edge_features"]


def with_edge_features(model: SVCoDe, width: int) -> SVCoDe:
    """A copy of ``model`` whose coordinate MLPs also take the edge features of ``width``
    pixels (:attr:`ModelConfig.edge_width`), computing exactly what ``model`` computes
    until it is trained further: the new features enter with zero weights. The starting
    point for fine-tuning a model without them.

    Examples
    --------
    >>> from svcode_core.network import ModelConfig
    >>> plain = SVCoDe(ModelConfig.mini()).eval()
    >>> edged = with_edge_features(plain, 8).eval()
    >>> views = torch.rand(1, 9, 16, 16)
    >>> with torch.no_grad():
    ...     before = plain(views, [[0, 0]], 384)[1]
    ...     after = edged(views, [[0, 0]], 384)[1]
    >>> torch.equal(before, after)
    True
    """
    config = model.model_config
    if config.edge_width:
        raise ValueError(f"the model already has edge features of width {config.edge_width}")
    edged = SVCoDe(config.replace(edge_width=width))
    state = model.state_dict()
    for name, module in model.named_modules():
        if isinstance(module, CoordMLP):
            for key in ("w_row", "w_col"):
                weight = state[f"{name}.{key}"]  # (lenses, hidden, features)
                zeros = weight.new_zeros(*weight.shape[:2], 2)
                state[f"{name}.{key}"] = torch.cat((weight, zeros), -1)
    edged.load_state_dict(state)
    return edged.to(next(model.parameters()).device)
