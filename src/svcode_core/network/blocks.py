"""Building blocks: LayerNorm2d, SimpleGate, channel attention, the CoDe block, view fusion."""

from __future__ import annotations

import torch
from torch import nn

from .coordgate import CoordGate, CoordGrid

__all__ = ["CoDeBlock", "LayerNorm2d", "SimpleChannelAttention", "SimpleGate", "ViewFusion"]


class LayerNorm2d(nn.Module):
    """Layer normalisation over the channels of each pixel, with a per-channel affine."""

    def __init__(self, channels: int, eps: float = 1e-6) -> None:
        super().__init__()
        self.weight = nn.Parameter(torch.ones(channels))
        self.bias = nn.Parameter(torch.zeros(channels))
        self.eps = eps

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        mean = x.mean(1, keepdim=True)
        centred = x - mean
        var = centred.pow(2).mean(1, keepdim=True)
        scale = self.weight.view(1, -1, 1, 1) * torch.rsqrt(var + self.eps)
        return centred * scale + self.bias.view(1, -1, 1, 1)


class SimpleGate(nn.Module):
    """Split the channels in two halves and multiply them."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        first, second = x.chunk(2, dim=1)
        return first * second


class SimpleChannelAttention(nn.Module):
    """NAFNet's simplified channel attention: ``x · conv1×1(mean_space(x))``."""

    def __init__(self, channels: int) -> None:
        super().__init__()
        self.conv = nn.Conv2d(channels, channels, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x * self.conv(x.mean((2, 3), keepdim=True))


class CoDeBlock(nn.Module):
    """A NAFNet block in which every convolution is a :class:`CoordGate`.

    ``x + β·conv3(SCA(SimpleGate(conv2(conv1(LN(x))))))``, then
    ``y + γ·conv5(SimpleGate(conv4(LN(y))))``; β and γ start at zero.

    Parameters
    ----------
    channels : int
        Feature channels ``c`` (the block widens to ``2c`` inside).
    axis_features : int
        Positional-encoding features per axis.
    mlp_hidden : int or None
        Hidden units of the mask MLPs; ``None`` builds a plain NAFBlock.
    lenses : int
        1 for masks shared across lenses, 9 for lens-specific masks.
    """

    def __init__(
        self, channels: int, axis_features: int, mlp_hidden: int | None, lenses: int = 1
    ) -> None:
        super().__init__()
        c = channels

        def gate(cin: int, cout: int, kernel: int = 1, groups: int = 1) -> CoordGate:
            return CoordGate(cin, cout, kernel, groups, axis_features, mlp_hidden, lenses)

        self.norm1 = LayerNorm2d(c)
        self.conv1 = gate(c, 2 * c)
        self.conv2 = gate(2 * c, 2 * c, 3, groups=2 * c)
        self.gate = SimpleGate()
        self.sca = SimpleChannelAttention(c)
        self.conv3 = gate(c, c)
        self.beta = nn.Parameter(torch.zeros(1, c, 1, 1))
        self.norm2 = LayerNorm2d(c)
        self.conv4 = gate(c, 2 * c)
        self.conv5 = gate(c, c)
        self.gamma = nn.Parameter(torch.zeros(1, c, 1, 1))

    def forward(self, x: torch.Tensor, grid: CoordGrid | None) -> torch.Tensor:
        z = self.conv2(self.conv1(self.norm1(x), grid), grid)
        z = self.conv3(self.sca(self.gate(z)), grid)
        y = x + self.beta * z
        z = self.conv5(self.gate(self.conv4(self.norm2(y), grid)), grid)
        return y + self.gamma * z


class ViewFusion(nn.Module):
    """Channel attention with view-wise pooling, then a 1×1 merge of the views.

    Every (view, channel) feature map is average-pooled over space; a 1×1 layer and a
    sigmoid turn the pooled ``V·c`` vector into one weight per view and channel
    (squeeze-and-excitation), and a 1×1 convolution merges the weighted views into
    ``out_channels``.
    """

    def __init__(self, views: int, channels: int, out_channels: int) -> None:
        super().__init__()
        self.attention = nn.Conv2d(views * channels, views * channels, 1)
        self.merge = nn.Conv2d(views * channels, out_channels, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """``x``: ``(B, V·c, h, w)`` (views major) → ``(B, out_channels, h, w)``."""
        weights = torch.sigmoid(self.attention(x.mean((2, 3), keepdim=True)))
        return self.merge(x * weights)
