"""The SV-CoDe network: configuration, shapes, coordinates, equivariance, gradients, precision."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from svcode_core.config import ConfigError
from svcode_core.network import (
    DemixNet,
    ModelConfig,
    ReconNet,
    SVCoDe,
    level_coordinates,
    positional_encoding,
)
from svcode_core.physics.geometry import normalized_coordinates


def _randomise_scales(model: torch.nn.Module, value: float = 0.5) -> None:
    """Give the zero-initialised residual scales a value so every branch matters."""
    with torch.no_grad():
        for name, param in model.named_parameters():
            if name.endswith(("beta", "gamma")):
                param.fill_(value)


def _model(config: ModelConfig, seed: int = 0) -> SVCoDe:
    torch.manual_seed(seed)
    model = SVCoDe(config)
    _randomise_scales(model)
    return model


# ------------------------------------------------------------------ configuration
def test_reference_parameter_count():
    model = SVCoDe(ModelConfig.reference())
    total = sum(p.numel() for p in model.parameters())
    mlp = sum(p.numel() for n, p in model.named_parameters() if ".mlp." in n)
    assert abs(total - 5.9e6) <= 0.15 * 5.9e6, total
    assert 0.7e6 < mlp < 1.5e6, mlp  # the paper quotes about 1.3 M in the mask MLPs
    assert sum(p.numel() for p in SVCoDe(ModelConfig.mini()).parameters()) < total / 5


def test_max_width_caps_the_levels_and_leaves_uncapped_models_as_they_were():
    deep = ModelConfig.mini().replace(demix_enc_blocks=(1,) * 5, demix_dec_blocks=(1,) * 5)
    widths = [d.out_channels for d in SVCoDe(deep).demix.unet.downs]
    assert widths == [32, 64, 128, 256, 512]  # 16 · 2^k
    capped = SVCoDe(deep.replace(max_width=64).validate())
    assert [d.out_channels for d in capped.demix.unet.downs] == [32, 64, 64, 64, 64]
    # each up-sampling gives the level below its own width back (4 w channels, shuffled)
    assert [u[0].out_channels for u in capped.demix.unet.ups] == [64, 128, 256, 256, 256]
    assert sum(p.numel() for p in capped.parameters()) < sum(
        p.numel() for p in SVCoDe(deep).parameters()) / 4  # fmt: skip
    demixed, recon = capped.eval()(torch.rand(1, 9, 40, 40), [[0, 0]], 384)
    assert demixed.shape == (1, 9, 40, 40) and recon.shape == (1, 1, 40, 40)
    # uncapped, 4 w_k = 2 w_(k+1): every weight keeps the shape it had before the option
    assert [u[0].out_channels for u in SVCoDe(deep).demix.unet.ups] == [2 * w for w in widths]
    with pytest.raises(ConfigError, match="max_width: 8 is below width 16"):
        ModelConfig.mini().replace(max_width=8).validate()


def test_pixel_unshuffle_runs_each_stage_on_a_coarser_grid():
    """``pixel_unshuffle = f``: each stage's first convolution takes ``f²`` channels per
    crop and its last gives ``f²`` per output, the stride and receptive radius grow by
    ``f``, and the masks are those of the sub-view's level ``log2 f`` (coordinates of the
    pooled grid, so a coarse model's level k is a fine one's level k + 1)."""
    from svcode_core.network.masks import coordinate_grids

    fine = ModelConfig.mini().replace(lens_context=True)
    coarse = fine.replace(pixel_unshuffle=2)
    assert ModelConfig.from_json(coarse.to_json()) == coarse
    model, plain = _model(coarse), _model(fine)
    assert model.demix.intro.in_channels == 4 * plain.demix.intro.in_channels == 4 * 81
    assert model.recon.intro.in_channels == 4 and model.demix.ending.out_channels == 4 * 9
    assert model.stride == 2 * plain.stride
    assert model.receptive_radius() == 2 * plain.receptive_radius() + 2  # + (f - 1) a stage
    demixed, recon = model(torch.rand(2, 81, 40, 37), [[0, 0], [100, 48]], 384)
    assert demixed.shape == (2, 9, 40, 37) and recon.shape == (2, 1, 40, 37)

    def encode(t):
        return positional_encoding(t, 4, "code")

    origins = torch.tensor([[0, 0], [96, 40]])
    shifted = coordinate_grids(encode, origins, 384, (64, 64), 3, first=1)
    pooled = coordinate_grids(encode, origins, 384, (64, 64), 4)[1:]
    for a, b in zip(shifted, pooled, strict=True):
        assert torch.equal(a.enc_row, b.enc_row) and torch.equal(a.enc_col, b.enc_col)
    for bad in (3, 0, True):
        with pytest.raises(ConfigError, match="pixel_unshuffle"):
            fine.replace(pixel_unshuffle=bad)


def test_config_json_round_trip_and_errors():
    config = ModelConfig.mini().replace(pe_scheme="paper", positional_encoding=False)
    assert ModelConfig.from_json(config.to_json()) == config
    with pytest.raises(ConfigError, match="width"):
        ModelConfig(width=0).validate()
    with pytest.raises(ConfigError, match="demix_dec_blocks"):
        ModelConfig(demix_dec_blocks=(1, 1)).validate()
    with pytest.raises(ConfigError, match="pe_scheme"):
        ModelConfig.from_dict({"pe_scheme": "fourier"})
    with pytest.raises(ConfigError, match="model.depth"):
        ModelConfig.from_dict({"depth": 3})
    with pytest.raises(ConfigError, match="coord_gate"):
        ModelConfig.from_dict({"coord_gate": "yes"})
    with pytest.raises(ConfigError, match="padding: must be one of"):
        ModelConfig.from_dict({"padding": "mirror"})
    assert ModelConfig.from_dict({}).padding == "zeros"  # files from before the option


def test_reflect_padding_mirrors_every_padded_convolution(two_level_model_config):
    """The option sets every padded convolution of both stages and changes no weight: the
    same weights give the same interior and another border; the smallest tiles (one pixel
    at the coarsest level before padding) still run."""
    config = two_level_model_config.replace(pool_window=8)  # the interior stays local
    zeros = _model(config)
    mirrored = SVCoDe(config.replace(padding="reflect"))
    mirrored.load_state_dict(zeros.state_dict())
    padded = [m for m in mirrored.modules() if isinstance(m, torch.nn.Conv2d) and any(m.padding)]
    assert len(padded) > 4 and {m.padding_mode for m in padded} == {"reflect"}
    torch.manual_seed(2)
    views = torch.rand(1, 9, 64, 64)
    with torch.no_grad():
        a, b = (model.eval()(views, [[0, 0]], 64)[1][0, 0] for model in (zeros, mirrored))
        border = (a - b).abs()
        assert border[:, 0].max() > 1e-3 and border[0, :].max() > 1e-3
        small = mirrored(torch.rand(2, 9, 3, 5), [[0, 0], [40, 7]], 48)
    centre = slice(24, 40)  # farther from the edges than the receptive radius
    # equal up to rounding (a mirrored convolution pads first, then sums in its own order)
    assert border[centre, centre].max() <= 4 * torch.finfo(torch.float32).eps
    assert small[1].shape == (2, 1, 3, 5) and torch.isfinite(small[1]).all()


# ------------------------------------------------------------ positional encoding
@pytest.mark.parametrize("scheme", ["paper", "code"])
def test_largest_band_is_exact_at_the_field_edge(scheme):
    edge = torch.tensor([-1.0, 1.0])
    enc = positional_encoding(edge, 4, scheme)
    # last band: 2^3 π (paper) or 2 π (code): sin = 0 and cos = 1 exactly at ±1
    assert enc[:, -2].abs().max().item() <= 1e-15
    assert torch.equal(enc[:, -1], torch.ones(2))


def test_encoding_matches_float64_reference():
    t = torch.linspace(-1.3, 1.3, 301, dtype=torch.float64)
    enc = positional_encoding(t, 5, "paper")
    for k in range(5):
        angle = 2.0**k * np.pi * t.numpy()
        np.testing.assert_allclose(enc[:, 2 * k].numpy(), np.sin(angle), atol=2e-7)
        np.testing.assert_allclose(enc[:, 2 * k + 1].numpy(), np.cos(angle), atol=2e-7)
    code = positional_encoding(t, 4, "code")
    np.testing.assert_allclose(code[:, 4].numpy(), np.sin(1.5 * np.pi * t.numpy()), atol=2e-7)
    raw = positional_encoding(t, 4, "code", enabled=False)
    assert raw.shape == (301, 1)


def test_level_coordinates_are_those_of_the_pooled_grid():
    size = 50
    levels = level_coordinates(torch.tensor([-3, 20]), 16, size, 2)
    assert torch.equal(levels[0][1], normalized_coordinates(size, 20, 16, dtype=torch.float64))
    # level-k pixel j covers level-0 pixels 2^k j .. 2^k (j+1) - 1: its centre
    for k in (1, 2):
        centre = -3 + 2**k * torch.arange(16 // 2**k, dtype=torch.float64) + (2**k - 1) / 2
        torch.testing.assert_close(levels[k][0], 2 * centre / (size - 1) - 1, rtol=0, atol=1e-15)


# ------------------------------------------------------------------------- shapes
@pytest.mark.parametrize("shape", [(13, 13), (21, 35), (16, 9)])
def test_output_shapes_for_any_size(shape, two_level_model_config):
    model = _model(two_level_model_config)
    views = torch.rand(2, 9, *shape)
    demixed, recon = model(views, torch.tensor([[0, 0], [-5, 30]]), 48)
    assert demixed.shape == (2, 9, *shape) and recon.shape == (2, 1, *shape)
    assert 0 < demixed.min() and demixed.max() < 1 and 0 < recon.min() and recon.max() < 1
    assert DemixNet(two_level_model_config)(views, [[0, 0], [1, 1]], 48).shape == (2, 9, *shape)
    assert ReconNet(two_level_model_config)(views, [[0, 0], [1, 1]], 48).shape == (2, 1, *shape)


def test_bad_inputs_raise(two_level_model_config):
    model = _model(two_level_model_config)
    with pytest.raises(ValueError, match="views must have shape"):
        model(torch.rand(1, 8, 16, 16), [[0, 0]], 48)
    for bad in (float("nan"), float("inf"), -float("inf")):  # one value among finite ones
        for dtype in (torch.float32, torch.bfloat16):
            views = torch.rand(1, 9, 16, 16)
            views[0, 4, 7, 3] = bad
            with pytest.raises(ValueError, match="NaN or Inf"):
                model(views.to(dtype), [[0, 0]], 48)
    with pytest.raises(ValueError, match="origins"):
        model(torch.rand(1, 9, 16, 16), [[0.5, 0.0]], 48)
    with pytest.raises(ValueError, match="origins"):
        model(torch.rand(2, 9, 16, 16), [[0, 0]], 48)


def test_global_coordinates_change_the_output(two_level_model_config):
    model = _model(two_level_model_config)
    views = torch.rand(1, 9, 16, 16)
    with torch.no_grad():
        a = model(views, [[0, 0]], 48)[1]
        b = model(views, [[16, 0]], 48)[1]
        c = model(views, [[16, 0]], 96)[1]
    assert (a - b).abs().max() > 1e-4 and (b - c).abs().max() > 1e-4


# ---------------------------------------------------------------- equivariance
def _circular(model: torch.nn.Module) -> None:
    for module in model.modules():
        if isinstance(module, torch.nn.Conv2d) and module.padding != (0, 0):
            module.padding_mode = "circular"


def _shift_error(model: SVCoDe) -> float:
    """Largest output change (interior) between rolling the input and rolling the output.

    Convolutions are made circular, so the only non-equivariant part left is the mask.
    The shift (8) is a multiple of the total stride (4) and the size (32) needs no padding.
    """
    _circular(model)
    torch.manual_seed(1)
    views = torch.rand(1, 9, 32, 32)
    with torch.no_grad():
        _, recon = model(views, [[0, 0]], 48)
        _, shifted = model(torch.roll(views, (8, 8), (2, 3)), [[0, 0]], 48)
    interior = (slice(None), slice(None), slice(12, 28), slice(12, 28))
    return (torch.roll(recon, (8, 8), (2, 3)) - shifted)[interior].abs().max().item()


def test_plain_nafnet_is_translation_equivariant(two_level_model_config):
    assert _shift_error(_model(two_level_model_config.replace(coord_gate=False))) < 1e-5


def test_coordinate_gated_model_is_not_translation_equivariant(two_level_model_config):
    assert _shift_error(_model(two_level_model_config)) > 1e-3


def test_coord_gate_off_builds_no_mlp(two_level_model_config):
    model = SVCoDe(two_level_model_config.replace(coord_gate=False))
    assert not any(".mlp." in n for n, _ in model.named_parameters())
    assert model.mask_layers() == []


# ------------------------------------------------------------------- gradients
@pytest.mark.parametrize("switches", [{}, {"positional_encoding": False},
                                      {"lens_specific_first_block": False}])
def test_gradient_reaches_every_parameter(switches, two_level_model_config):
    model = _model(two_level_model_config.replace(**switches))
    demixed, recon = model(torch.rand(2, 9, 12, 12), [[0, 0], [30, 4]], 48)
    (demixed.square().mean() + recon.square().mean()).backward()
    for name, param in model.named_parameters():
        assert param.grad is not None, name
        assert torch.isfinite(param.grad).all(), name
        assert param.grad.abs().max() > 0, name


# ------------------------------------------------------------------- precision
@pytest.mark.parametrize("dtype, tolerance", [(torch.bfloat16, 1e-2), (torch.float16, 2e-3)])
def test_autocast_is_finite_and_close_to_float32(dtype, tolerance, two_level_model_config):
    """Absolute tolerance on the (0, 1) outputs: about 2.5 units of the format's epsilon
    (2^-8 for bf16, 2^-11 for fp16); measured 2.2e-3 and 2.9e-4."""
    model = _model(two_level_model_config)
    views = torch.rand(2, 9, 16, 16)
    with torch.no_grad():
        reference = model(views, [[0, 0], [8, 8]], 48)
        with torch.autocast("cpu", dtype=dtype):
            low = model(views, [[0, 0], [8, 8]], 48)
    for ref, out in zip(reference, low, strict=True):
        assert torch.isfinite(out).all()
        assert (ref - out.float()).abs().max().item() < tolerance


def test_half_model_runs(two_level_model_config):
    model = _model(two_level_model_config)
    views = torch.rand(1, 9, 16, 16)
    with torch.no_grad():
        reference = model(views, [[0, 0]], 48)[1]
        half = model.half()(views.half(), [[0, 0]], 48)[1]
    assert half.dtype == torch.float16 and torch.isfinite(half).all()
    assert (reference - half.float()).abs().max() < 1e-2
    assert math.isfinite(float(half.sum()))


# ------------------------------------------------------------------ layer norm
@pytest.mark.parametrize("layout", [torch.contiguous_format, torch.channels_last])
def test_layer_norm_matches_the_per_pixel_formula_in_float64(layout):
    from svcode_core.network.blocks import LayerNorm2d

    torch.manual_seed(0)
    norm = LayerNorm2d(6)
    with torch.no_grad():
        norm.weight.uniform_(0.5, 1.5)
        norm.bias.normal_()
    x = (3 * torch.randn(2, 6, 5, 7) + 1).contiguous(memory_format=layout).requires_grad_()
    out = norm(x)
    a = x.detach().double().numpy()
    mean = a.mean(1, keepdims=True)
    var = ((a - mean) ** 2).mean(1, keepdims=True)  # biased, as in NAFNet
    expected = (a - mean) / np.sqrt(var + norm.eps) * norm.weight.detach().double().numpy()[
        None, :, None, None] + norm.bias.detach().double().numpy()[None, :, None, None]
    # normalised values are O(1): a few float32 roundings of each
    atol = 16 * np.finfo(np.float32).eps * np.abs(expected).max()
    np.testing.assert_allclose(out.detach().double().numpy(), expected, rtol=0, atol=atol)
    with torch.no_grad():  # inference computes the channel means as matrix products
        np.testing.assert_allclose(norm(x).double().numpy(), expected, rtol=0, atol=atol)
    out.square().sum().backward()
    assert x.grad is not None and torch.isfinite(x.grad).all()


@pytest.mark.parametrize("layout", [torch.contiguous_format, torch.channels_last])
def test_bf16_means_are_float32_means_rounded(layout):
    """The matrix-product means accumulate bf16 features in float32: the channel mean is
    the float32 mean rounded once to bf16 (unit roundoff 2⁻⁸), the spatial mean twice (the
    sum, then the quotient), each up to the float32 sum's own error (n roundings at worst)."""
    from svcode_core.network.blocks import channel_mean, spatial_mean

    torch.manual_seed(0)
    x = torch.rand(2, 8, 16, 24).bfloat16()
    with torch.no_grad():  # inference: the matrix products
        pairs = [(spatial_mean(x.contiguous(memory_format=layout)), x.float().mean((2, 3), True),
                  2)]  # fmt: skip
        if layout == torch.contiguous_format:
            pairs.append((channel_mean(x), x.float().mean(1, keepdim=True), 1))
    for got, mean, roundings in pairs:
        n = x[0].numel() // mean[0].numel()  # terms per mean
        bound = (roundings * 2.0**-8 + n * torch.finfo(torch.float32).eps) * mean.abs()
        assert got.dtype == torch.bfloat16 and got.shape == mean.shape
        assert ((got.float() - mean).abs() <= bound).all()


def test_view_block_runs_channels_first_and_the_u_net_channels_last():
    """The layouts each part is fast in (see LayerNorm2d); the output does not depend on
    them: the same model on a channels-last copy of the input gives the same result."""
    model = _model(ModelConfig.mini()).eval()
    seen = {}
    model.demix.view_block.register_forward_hook(
        lambda m, args, out: seen.setdefault("view", args[0]))
    model.demix.unet.register_forward_hook(lambda m, args, out: seen.setdefault("unet", args[0]))
    views = torch.rand(1, 9, 48, 48)
    with torch.no_grad():
        first = model(views, [[0, 0]], 96)
        second = model(views.contiguous(memory_format=torch.channels_last), [[0, 0]], 96)
    assert seen["view"].is_contiguous()
    assert seen["unet"].is_contiguous(memory_format=torch.channels_last)
    for a, b in zip(first, second, strict=True):
        torch.testing.assert_close(a, b, rtol=0, atol=0)
