"""The joint SV-CoDe loss and the validation metrics.

``L = L_demix + L_recon`` with ``L_stage = α (1 − SSIM) + β MSE`` (α = β = 1 in the paper;
the learned baselines have the reconstruction stage alone, :func:`joint_loss`). The MSE may
weigh some pixels more than others (:func:`field_weights`: the sub-view's edge strips, which
a patch-trained model sees least, the outer ring, which it reconstructs worst, and the
pixels that some lens loses off the sensor). SSIM is pytorch-msssim's Gaussian-window SSIM
(window 11, σ 1.5, ``data_range = 1``), averaged over channels and batch. Everything is
computed in float32, also when the network ran under bf16 autocast.

Training SSIM and report SSIM
    The loss needs a differentiable SSIM on batches of tensors, hence the Gaussian-window
    one here; the reports (:func:`svcode_core.evaluation.metrics.ssim`) use scikit-image's
    7 × 7 uniform window. The two differ by a few hundredths on the same image: validation
    SSIMs in training logs are the Gaussian-window ones. The PSNR is the same in both
    (:func:`~svcode_core.evaluation.metrics.psnr_from_mse`).
"""

from __future__ import annotations

from collections.abc import Mapping

import torch
from pytorch_msssim import ssim

from ..config import SystemConfig
from ..evaluation.metrics import psnr_from_mse
from ..evaluation.zones import EDGE_STRIP, RING_RADIUS
from ..physics.geometry import normalized_coordinates, sensor_coverage

__all__ = ["EDGE_STRIP", "field_weights", "in_field", "joint_loss", "psnr_per_sample",
           "seen_by_every_lens", "ssim_per_sample", "stage_loss", "svcode_loss"]

#: Smallest MSE used by :func:`psnr_per_sample` (caps the PSNR of a perfect patch at 100 dB).
MIN_MSE = 1e-10


def _check(prediction: torch.Tensor, target: torch.Tensor) -> None:
    if prediction.shape != target.shape:
        raise ValueError(f"prediction {tuple(prediction.shape)} and target "
                         f"{tuple(target.shape)} differ in shape")
    if prediction.ndim != 4:
        raise ValueError(f"expected (B, C, H, W) tensors, got {tuple(prediction.shape)}")
    if min(prediction.shape[-2:]) < 11:
        raise ValueError(f"patches must be at least 11 × 11 for the SSIM window, "
                         f"got {tuple(prediction.shape[-2:])}")


def stage_loss(
    prediction: torch.Tensor,
    target: torch.Tensor,
    alpha: float = 1.0,
    beta: float = 1.0,
    weights: torch.Tensor | None = None,
) -> torch.Tensor:
    """``α (1 − SSIM) + β MSE`` of one stage, a float32 scalar.

    Parameters
    ----------
    prediction, target : torch.Tensor
        ``(B, C, H, W)`` with values in ``[0, 1]``; ``H, W >= 11``.
    alpha, beta : float
        Weights of the SSIM and MSE terms.
    weights : torch.Tensor, optional
        Per-pixel weights of the squared error, broadcastable to ``(B, C, H, W)``
        (e.g. :func:`field_weights`); the MSE is then the mean of the weighted squares.

    Examples
    --------
    >>> target = torch.zeros(1, 1, 16, 16)
    >>> prediction = target + 0.1
    >>> round(float(stage_loss(prediction, target, alpha=0.0)), 6)
    0.01
    >>> thrice = torch.full((1, 1, 16, 16), 3.0)
    >>> round(float(stage_loss(prediction, target, alpha=0.0, weights=thrice)), 6)
    0.03
    """
    _check(prediction, target)
    prediction, target = prediction.float(), target.float()
    structural = 1.0 - ssim(prediction, target, data_range=1.0, size_average=True)
    squares = (prediction - target) ** 2
    if weights is not None:
        squares = squares * weights.float()
    return alpha * structural + beta * torch.mean(squares)


def joint_loss(
    stages: Mapping[str, tuple[torch.Tensor, torch.Tensor]],
    alpha: float = 1.0,
    beta: float = 1.0,
    weights: torch.Tensor | None = None,
) -> tuple[torch.Tensor, dict[str, float]]:
    """Sum of :func:`stage_loss` over named ``(prediction, target)`` pairs, every stage's
    squared error weighted by the same ``weights`` (their pixels are the same).

    Returns
    -------
    (loss, parts)
        The differentiable total and each stage's loss as a float, by name.
    """
    losses = {name: stage_loss(pred, target, alpha, beta, weights) for name, (pred, target) in
              stages.items()}
    parts = {name: float(loss.detach()) for name, loss in losses.items()}
    return sum(losses.values()), parts


def field_weights(
    origins: torch.Tensor, size: int, sub_view_size: int, edge: float = 1.0,
    ring: float = 1.0, strip: int = EDGE_STRIP, partial: float = 1.0,
    seen_by_all: torch.Tensor | None = None,
) -> torch.Tensor:
    """Loss weights of square crops of a sub-view: ``edge`` on the pixels within ``strip``
    pixels of the sub-view's edge, ``ring`` on the outer ring (normalised field radius
    above :data:`~svcode_core.evaluation.zones.RING_RADIUS`, the benchmark's zone),
    ``partial`` on the pixels that not every lens sees (``seen_by_all`` false), their
    product where several hold, 1 elsewhere, and 1 on the pixels of a crop that lie past
    the sub-view (a model with a view margin).

    Parameters
    ----------
    origins : torch.Tensor
        ``(B, 2)`` integer ``(row, col)`` of each crop's first pixel in the sub-view.
    size : int
        Side of the crops.
    sub_view_size : int
        Side of the sub-view.
    edge, ring : float
        Weights of the edge strips and of the outer ring.
    strip : int
        Width of the edge strips in pixels.
    partial : float
        Weight of the pixels that some lens's image loses off the sensor.
    seen_by_all : torch.Tensor or None
        ``(S, S)`` bool, true where every lens sees the pixel
        (:func:`seen_by_every_lens`); needed when ``partial`` is not 1.

    Returns
    -------
    torch.Tensor
        ``(B, 1, size, size)`` float32.

    Examples
    --------
    >>> w = field_weights(torch.tensor([[0, 8]]), size=4, sub_view_size=12, edge=5.0, strip=2)
    >>> w[0, 0].tolist()  # the top two rows and, at columns 10-11, the right edge
    [[5.0, 5.0, 5.0, 5.0], [5.0, 5.0, 5.0, 5.0], [1.0, 1.0, 5.0, 5.0], [1.0, 1.0, 5.0, 5.0]]
    >>> w = field_weights(torch.tensor([[0, 0]]), size=6, sub_view_size=6, ring=2.0)
    >>> w[0, 0, :3].tolist()  # the top half of a whole 6-px sub-view: its corners are ring
    [[2.0, 2.0, 2.0, 2.0, 2.0, 2.0], [2.0, 2.0, 1.0, 1.0, 2.0, 2.0], [2.0, 1.0, 1.0, 1.0, 1.0, 2.0]]
    >>> seen = torch.ones(6, 6, dtype=torch.bool)
    >>> seen[:2] = False  # the top two rows: some lens loses them off the sensor
    >>> w = field_weights(torch.tensor([[1, 0]]), size=3, sub_view_size=6, partial=3.0,
    ...                   seen_by_all=seen)
    >>> w[0, 0, :, 0].tolist()  # rows 1-3 of the sub-view
    [3.0, 1.0, 1.0]
    >>> w = field_weights(torch.tensor([[2, -1]]), size=3, sub_view_size=6, edge=5.0, strip=2)
    >>> w[0, 0, 0].tolist()  # row 2: column -1 lies past the sub-view
    [1.0, 5.0, 5.0]
    """
    pixels = origins.to(torch.int64)[:, :, None] + torch.arange(size)  # (B, 2, size)
    near = (pixels < strip) | (pixels >= sub_view_size - strip)
    at_edge = (near[:, 0, :, None] | near[:, 1, None, :]).float()
    first = int(pixels.min())
    axis = normalized_coordinates(sub_view_size, first, int(pixels.max()) - first + 1,
                                  dtype=torch.float64)
    u = axis[pixels - first]  # (B, 2, size)
    in_ring = (torch.hypot(u[:, 0, :, None], u[:, 1, None, :]) > RING_RADIUS).float()
    weights = (1.0 + (edge - 1.0) * at_edge) * (1.0 + (ring - 1.0) * in_ring)
    if partial != 1.0:
        if seen_by_all is None:
            raise ValueError("field_weights: a partial weight needs seen_by_all")
        rows, cols = pixels.clamp(0, sub_view_size - 1).unbind(1)
        weights = weights * (1.0 + (partial - 1.0) * (~seen_by_all[rows[:, :, None],
                                                                   cols[:, None, :]]).float())
    return torch.where(in_field(origins, size, sub_view_size), weights[:, None], 1.0)


def in_field(origins: torch.Tensor, size: int, sub_view_size: int) -> torch.Tensor:
    """``(B, 1, size, size)`` bool: which pixels of the square crops at ``origins``
    ``(B, 2)`` lie inside the ``sub_view_size`` field.

    Examples
    --------
    >>> in_field(torch.tensor([[-1, 0]]), 2, 4)[0, 0].tolist()
    [[False, False], [True, True]]
    """
    pixels = origins.to(torch.int64)[:, :, None] + torch.arange(size)
    within = (pixels >= 0) & (pixels < sub_view_size)
    return (within[:, 0, :, None] & within[:, 1, None, :])[:, None]


def seen_by_every_lens(system: SystemConfig) -> torch.Tensor:
    """``(S, S)`` bool: true where every lens's image of the sub-view pixel falls on the
    sensor.

    Examples
    --------
    >>> seen = seen_by_every_lens(SystemConfig.preset("cm2-mini"))
    >>> seen[:96].any().item(), seen[96:288, 16:368].all().item(), seen[:, :16].any().item()
    (False, True, False)
    """
    return sensor_coverage(system).bool().all(0)


def svcode_loss(
    demixed: torch.Tensor,
    recon: torch.Tensor,
    demixed_target: torch.Tensor,
    object_target: torch.Tensor,
    alpha: float = 1.0,
    beta: float = 1.0,
) -> tuple[torch.Tensor, dict[str, float]]:
    """Joint loss of both stages.

    Parameters
    ----------
    demixed, demixed_target : torch.Tensor
        ``(B, 9, P, P)`` network output and per-lens targets.
    recon, object_target : torch.Tensor
        ``(B, 1, P, P)`` reconstruction and ground truth.
    alpha, beta : float

    Returns
    -------
    (loss, parts)
        The differentiable total and the floats ``demix`` and ``recon``.
    """
    return joint_loss({"demix": (demixed, demixed_target), "recon": (recon, object_target)},
                      alpha, beta)


@torch.no_grad()
def psnr_per_sample(prediction: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """PSNR in dB of each sample for data in ``[0, 1]``, shape ``(B,)`` (MSE floored at
    :data:`MIN_MSE`)."""
    _check(prediction, target)
    mse = ((prediction.float() - target.float()) ** 2).flatten(1).mean(1)
    return psnr_from_mse(mse.clamp(min=MIN_MSE))


@torch.no_grad()
def ssim_per_sample(prediction: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """SSIM of each sample (mean over its channels), shape ``(B,)``."""
    _check(prediction, target)
    return ssim(prediction.float(), target.float(), data_range=1.0, size_average=False)
