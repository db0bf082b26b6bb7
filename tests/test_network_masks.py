"""Mask cache and mask inspection of the SV-CoDe network."""

from __future__ import annotations

import pytest
import torch

from svcode_core.network import DemixNet, ModelConfig, SVCoDe
from svcode_core.network.encoding import positional_encoding

TINY = ModelConfig(
    width=4,
    view_width=2,
    demix_enc_blocks=(1, 1),
    demix_dec_blocks=(1, 1),
    recon_enc_blocks=(1,),
    recon_dec_blocks=(1,),
    mlp_hidden=8,
)
ORIGINS = [[0, 0], [24, -8], [0, 0]]


@pytest.fixture
def model() -> SVCoDe:
    torch.manual_seed(0)
    model = SVCoDe(TINY)
    with torch.no_grad():
        for name, param in model.named_parameters():
            if name.endswith(("beta", "gamma")):
                param.fill_(0.5)
    return model.eval()


def _close(a: torch.Tensor, b: torch.Tensor) -> bool:
    return bool(((a - b).abs() <= 1e-5 * b.abs() + 1e-7).all())


def test_cached_and_uncached_outputs_agree(model):
    views = torch.rand(3, 9, 19, 21)
    with torch.no_grad():
        reference = model(views, ORIGINS, 48)
        with model.cache_masks():
            first = model(views, ORIGINS, 48)
            info = model.mask_cache_info()
            second = model(views, ORIGINS, 48)
            after = model.mask_cache_info()
    for ref, a, b in zip(reference, first, second, strict=True):
        assert _close(a, ref) and _close(b, ref)
    # two distinct tiles × every gated layer, then only hits
    assert info["entries"] == 2 * len(model.mask_layers()) and info["bytes"] > 0
    assert after["entries"] == info["entries"] and after["hits"] > info["hits"]
    assert after["misses"] == info["misses"]
    assert not model.mask_cache_info()["enabled"]  # the context restored "off"


def test_cache_is_dropped_when_weights_change(model):
    views = torch.rand(1, 9, 16, 16)
    model.cache_masks()
    with torch.no_grad():
        before = model(views, [[0, 0]], 48)
        assert model.mask_cache_info()["entries"] > 0
        model.recon.unet.decoders[0][0].conv5.mlp.b_out.add_(3.0)  # an in-place update
        cached = model(views, [[0, 0]], 48)
    info = model.mask_cache_info()
    model.cache_masks(False)
    with torch.no_grad():
        fresh = model(views, [[0, 0]], 48)
    assert info["entries"] == len(model.mask_layers())  # rebuilt once, not doubled
    assert (before[1] - fresh[1]).abs().max() > 1e-4  # the update matters ...
    assert _close(cached[1], fresh[1])  # ... and the cache saw it


def test_cache_is_dropped_on_load_state_dict(model):
    views = torch.rand(1, 9, 16, 16)
    torch.manual_seed(5)
    other = SVCoDe(TINY).state_dict()
    model.cache_masks()
    with torch.no_grad():
        model(views, [[0, 0]], 48)
        model.load_state_dict(other)
        for name, param in model.named_parameters():
            if name.endswith(("beta", "gamma")):
                param.copy_(0.5)
        cached = model(views, [[0, 0]], 48)
        model.cache_masks(False)
        fresh = model(views, [[0, 0]], 48)
    assert _close(cached[0], fresh[0]) and _close(cached[1], fresh[1])


def test_cache_is_bounded_in_bytes(model):
    views = torch.rand(1, 9, 16, 16)
    with torch.no_grad(), model.cache_masks(max_bytes=20_000):
        for row in range(4):
            model(views, [[row * 16, 0]], 48)
        info = model.mask_cache_info()
    assert 0 < info["bytes"] <= 20_000


def test_cache_is_bypassed_when_gradients_are_needed(model):
    views = torch.rand(1, 9, 16, 16)
    with model.cache_masks():
        _, recon = model(views, [[0, 0]], 48)
        recon.mean().backward()
        assert model.mask_cache_info()["entries"] == 0
    assert model.demix.view_block.conv1.mlp.w_out.grad.abs().max() > 0


def test_coordinate_mask_matches_the_forward_masks(model):
    size = 48
    layers = {(m.stage, m.block, m.layer): m for m in model.mask_layers()}
    assert ("demix", "view", "conv1") in layers and ("recon", "middle.0", "conv5") in layers
    info = layers[("demix", "view", "conv2")]
    assert info.lenses == 9 and info.channels == 2 * TINY.view_width
    full = model.coordinate_mask("demix", "view", "conv2", size, lens=4, max_chunk_bytes=4096)
    assert full.shape == (info.channels, size, size)
    # the same layer evaluated for a 16 × 16 tile at (8, 20): a crop of the full field
    gate = model.demix.view_block.conv2
    rows = torch.linspace(-1, 1, size, dtype=torch.float64)
    enc_r = positional_encoding(rows[8:24], TINY.pe_bands, TINY.pe_scheme)[None]
    enc_c = positional_encoding(rows[20:36], TINY.pe_bands, TINY.pe_scheme)[None]
    with torch.no_grad():
        tile = gate.masks(enc_r, enc_c)[0, 4]
    torch.testing.assert_close(full[:, 8:24, 20:36], tile, rtol=1e-6, atol=1e-6)
    one = model.coordinate_mask("demix", "view", "conv2", size, lens=0, channels=1)
    assert one.shape == (1, size, size)
    assert (one[0] - full[1]).abs().max() > 1e-4  # lens-specific masks differ
    with pytest.raises(ValueError, match="no gated layer"):
        model.coordinate_mask("demix", "view", "conv9", size)


def test_demix_net_alone_has_its_own_cache():
    torch.manual_seed(0)
    net = DemixNet(TINY).eval()
    views = torch.rand(2, 9, 12, 12)
    with torch.no_grad():
        reference = net(views, [[0, 0], [4, 4]], 48)
        with net.cache_masks():
            cached = net(views, [[0, 0], [4, 4]], 48)
            assert net.mask_cache_info()["entries"] == 2 * len(net.mask_layers())
    assert _close(cached, reference)
