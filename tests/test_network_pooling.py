"""Windowed pooling of the channel attention (``ModelConfig.pool_window``): the local means
against a direct float64 computation, training untouched (tiles that agree with it:
test_tile_plan.py)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from svcode_core import Reconstructor, SystemConfig
from svcode_core.network import ModelConfig, SVCoDe
from svcode_core.network.blocks import pooled_mean, spread

#: float32 sums of a few hundred O(1) numbers, divided: a few ulps of the mean
RTOL = 64 * torch.finfo(torch.float32).eps


def window_runs(index: int, size: int, cells: int, window: int, cell: int) -> list[slice]:
    """Pixels of the runs of ``size`` cells centred on cell ``index`` (one for an odd size,
    the two half a cell either side for an even one), each kept inside ``cells`` cells;
    the whole axis when the window covers it."""
    if size >= cells:
        return [slice(None)]
    firsts = {index - size // 2, index - size // 2 + 1 - size % 2}
    starts = (min(max(f, 0), cells - size) * cell for f in sorted(firsts))
    return [slice(start, start + window) for start in starts]


def direct_window_means(x: np.ndarray, window: int, cell: int) -> np.ndarray:
    """Per grid cell, the float64 mean of ``x`` over its centred ``window``-pixel square,
    averaged over the squares either side of the centre where the window has an even
    number of cells (whole axes where the window covers them: then that axis has one
    cell)."""
    rows, cols = (n // cell for n in x.shape[-2:])
    size = window // cell
    out = np.empty((*x.shape[:-2], 1 if size >= rows else rows, 1 if size >= cols else cols))
    for i, j in np.ndindex(out.shape[-2:]):
        means = [x[..., rs, cs].astype(np.float64).mean((-2, -1))
                 for rs in window_runs(i, size, rows, window, cell)
                 for cs in window_runs(j, size, cols, window, cell)]
        out[..., i, j] = np.mean(means, axis=0)
    return out


@pytest.mark.parametrize(("shape", "window", "cell"), [
    ((2, 3, 24, 32), 8, 1), ((1, 4, 32, 48), 16, 4), ((1, 2, 16, 64), 32, 2),
])
def test_window_means_match_a_direct_float64_computation(shape, window, cell):
    x = torch.rand(shape, generator=torch.Generator().manual_seed(0))
    x = x.contiguous(memory_format=torch.channels_last)
    got = pooled_mean(x, window, cell).numpy()
    reference = direct_window_means(x.numpy(), window, cell)
    np.testing.assert_allclose(got, reference, rtol=RTOL, atol=0)


@pytest.mark.parametrize("window", [12, 16])  # 3 and 4 cells: odd and even
def test_a_linear_ramp_is_its_own_local_mean_away_from_the_edges(window):
    """A centred mean of a linear function is its value at the centre: the cell's mean,
    wherever the square lies inside the map."""
    x = torch.arange(64.0).view(1, 1, 1, 64).expand(1, 1, 8, 64)
    cells = x.view(1, 1, 8, 16, 4).mean(-1)[:, :, :2]  # the cells' own means, 4-px cells
    got = pooled_mean(x, window, 4)[0, 0, 0]
    inside = slice(window // 8, 16 - window // 8)
    torch.testing.assert_close(got[inside], cells[0, 0, 0, inside])


def test_a_window_covering_the_map_is_the_plain_mean():
    x = torch.rand(2, 3, 16, 24)
    plain = x.mean((2, 3), keepdim=True)
    # the same sum in another order: at worst n float32 roundings of n positive terms
    bound = x[0, 0].numel() * torch.finfo(torch.float32).eps * plain
    for window in (0, 24, 100):
        for layout in (torch.contiguous_format, torch.channels_last):
            for grad in (False, True):  # a matrix product in inference, torch's mean else
                with torch.set_grad_enabled(grad):
                    got = pooled_mean(x.contiguous(memory_format=layout), window, 4)
                assert got.shape == plain.shape and ((got - plain).abs() <= bound).all()
    assert spread(x.mean((2, 3), keepdim=True), x).shape == (2, 3, 1, 1)  # broadcasts


def test_spread_interpolates_the_cell_grid_to_the_pixels():
    x = torch.zeros(1, 1, 8, 8)
    constant = torch.full((1, 1, 2, 2), 0.25)
    assert torch.allclose(spread(constant, x), torch.full((1, 1, 8, 8), 0.25))
    ramp = torch.tensor([[[[0.0, 1.0], [0.0, 1.0]]]])
    row = spread(ramp, x)[0, 0, 0]  # cell centres at 1.5 and 5.5: linear between them
    assert row[1].item() == 0.0 and row[6].item() == 1.0
    assert torch.allclose(row[2:6], torch.tensor([0.125, 0.375, 0.625, 0.875]))


def test_patches_no_larger_than_the_window_see_the_training_model():
    """``pool_window`` changes nothing on patches of at most its size, so a model trained
    without it is the same model with it, bit for bit, there; its gradients too."""
    torch.manual_seed(0)
    config = ModelConfig.mini()
    plain, windowed = SVCoDe(config), SVCoDe(config.replace(pool_window=96))
    windowed.load_state_dict(plain.state_dict())
    views = torch.rand(2, 9, 96, 96)
    origins = [[0, 96], [192, 48]]
    outputs = []
    for model in (plain, windowed):
        demixed, recon = model(views, origins, 384)
        (demixed.mean() + recon.mean()).backward()
        outputs.append((demixed, recon, model.recon.ending.weight.grad))
    for a, b in zip(*outputs, strict=True):
        assert torch.equal(a, b)


def test_old_configurations_pool_over_the_tile():
    data = ModelConfig.mini().to_dict()
    del data["pool_window"]  # a model file written before the option
    assert ModelConfig.from_dict(data).pool_window == 0


def test_a_bad_window_is_a_clear_error():
    model = SVCoDe(ModelConfig.mini())
    with pytest.raises(ValueError, match="pool_window must be a whole number >= 0"):
        Reconstructor(model, SystemConfig.tiny(), pool_window=-1)


def test_a_small_window_stays_local_at_every_level():
    model = SVCoDe(ModelConfig.mini().replace(pool_window=4))
    windows = [block.sca.window for stage in (model.demix, model.recon)
               for _, block, _ in stage.named_blocks()]
    assert min(windows) == 1  # 4 px at level 0 is 1 px at levels 2 and 3, not the whole tile
