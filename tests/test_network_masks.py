"""Mask cache and mask inspection of the SV-CoDe network."""

from __future__ import annotations

import pytest
import torch

from svcode_core.network import DemixNet, SVCoDe
from svcode_core.network.encoding import level_coordinates, positional_encoding
from svcode_core.network.fast import fold


@pytest.fixture
def model(two_level_model_config) -> SVCoDe:
    torch.manual_seed(0)
    model = SVCoDe(two_level_model_config)
    with torch.no_grad():
        for name, param in model.named_parameters():
            if name.endswith(("beta", "gamma")):
                param.fill_(0.5)
    return model.eval()


def _close(a: torch.Tensor, b: torch.Tensor) -> bool:
    return bool(((a - b).abs() <= 1e-5 * b.abs() + 1e-7).all())


def _entries(model: SVCoDe) -> dict:
    return dict(model._mask_cache._entries)


def test_cached_and_uncached_outputs_agree(model):
    # (0, 0) and (24, 8) are aligned to the model stride 4 and crop every level from the
    # cached fields; (24, -8) lies partly outside the field (its masks are computed at
    # every level) and (5, 6) is unaligned (computed beyond level 0)
    origins = [[0, 0], [24, -8], [0, 0], [24, 8], [5, 6]]
    views = torch.rand(5, 9, 19, 21)
    with torch.no_grad():
        reference = model(views, origins, 48)
        with model.cache_masks():
            first = model(views, origins, 48)
            info = model.mask_cache_info()
            second = model(views, origins, 48)
            after = model.mask_cache_info()
    for ref, a, b in zip(reference, first, second, strict=True):
        assert _close(a, ref) and _close(b, ref)
    # one whole-field entry per CoDe block, whatever the number of tiles; then only hits
    blocks = {(m.stage, m.block) for m in model.mask_layers()}
    assert info["entries"] == len(blocks) and info["bytes"] > 0
    assert after["entries"] == info["entries"] and after["hits"] == info["misses"]
    assert after["misses"] == info["misses"]
    assert not model.mask_cache_info()["enabled"]  # the context restored "off"


def test_tile_cropped_from_the_field_equals_the_tile_masks(model, two_level_model_config):
    """A cached field entry, cropped at a tile, equals the block's folded masks computed
    for that tile alone, and the folding equals the products of the layer masks."""
    encoding = (two_level_model_config.pe_bands, two_level_model_config.pe_scheme)
    origin, size, tile = (8, 12), 48, 16
    with torch.no_grad(), model.cache_masks():
        model(torch.rand(1, 9, tile, tile), [origin], size)
        entries = _entries(model)
        for stage in (model.demix, model.recon):
            for name, block, level in stage.named_blocks():
                key = (f"{stage.stage}/{name}", (size, level, 52 // 2**level), torch.float32)
                field = entries[key][0]
                step, n = 2**level, tile // 2**level
                rows = level_coordinates(torch.tensor([origin[0]]), tile, size, level)[level]
                cols = level_coordinates(torch.tensor([origin[1]]), tile, size, level)[level]
                enc = [positional_encoding(t, *encoding) for t in (rows, cols)]
                expected = [m[0] for m in fold(block, *enc)]
                r, c = origin[0] // step, origin[1] // step
                for part, want in zip(field, expected, strict=True):
                    assert _close(part[..., r : r + n, c : c + n], want), (name, level)
                # the fold itself: conv2 pair and β·conv3 from the unfolded layer masks
                k = block.beta.shape[1]
                m2 = block.conv2.masks(*enc)[0]
                m3 = block.conv3.masks(*enc)[0] * block.beta.view(k, 1, 1)
                assert _close(expected[1], m2[:, :k] * m2[:, k:])
                assert _close(expected[2], m3)


def test_cache_memory_does_not_grow_with_the_tiles(model):
    with torch.no_grad(), model.cache_masks():
        model(torch.rand(1, 9, 16, 16), [[0, 0]], 48)
        one = model.mask_cache_info()
        grid = [[r, c] for r in (0, 16, 32) for c in (0, 16, 32)]
        model(torch.rand(9, 9, 16, 16), grid, 48)
        nine = model.mask_cache_info()
    assert nine["bytes"] == one["bytes"] and nine["misses"] == one["misses"]


def test_full_field_bytes_and_stale_entries(model):
    """A tile grid over the whole sub-view fills exactly mask_field_bytes(S); after a
    switch to another S, old fields make room for the new ones within the budget."""
    size, tile = 48, 16
    starts = [0, 16, 32]
    grid = [[r, c] for r in starts for c in starts]
    budget = model.mask_field_bytes(size) + model.mask_field_bytes(40) // 2
    with torch.no_grad(), model.cache_masks(max_bytes=budget):
        model(torch.rand(9, 9, tile, tile), grid, size)
        assert model.mask_cache_info()["bytes"] == model.mask_field_bytes(size)
        assert model.mask_field_bytes(size, torch.bfloat16) * 2 == model.mask_field_bytes(size)
        for _ in range(3):
            model(torch.rand(1, 9, tile, tile), [[0, 0]], 40)
        info = model.mask_cache_info()
        model(torch.rand(1, 9, tile, tile), [[0, 0]], 40)
        after = model.mask_cache_info()
    assert after["misses"] == info["misses"]  # every S = 40 field is cached by now
    assert model.mask_field_bytes(40) < info["bytes"] <= budget


def test_cache_is_dropped_when_weights_change(model):
    views = torch.rand(1, 9, 16, 16)
    model.cache_masks()
    with torch.no_grad():
        before = model(views, [[0, 0]], 48)
        entries = model.mask_cache_info()["entries"]
        assert entries > 0
        model.recon.unet.decoders[0][0].conv5.mlp.b_out.add_(3.0)  # an in-place update
        model.demix.unet.encoders[0][0].beta.mul_(-1.0)  # folded into the cached masks
        cached = model(views, [[0, 0]], 48)
    info = model.mask_cache_info()
    model.cache_masks(False)
    with torch.no_grad():
        fresh = model(views, [[0, 0]], 48)
    assert info["entries"] == entries  # rebuilt once, not doubled
    assert (before[1] - fresh[1]).abs().max() > 1e-4  # the update matters ...
    assert (before[0] - fresh[0]).abs().max() > 1e-4
    assert _close(cached[0], fresh[0]) and _close(cached[1], fresh[1])  # ... and the cache saw it


def test_cache_is_dropped_on_load_state_dict(model, two_level_model_config):
    views = torch.rand(1, 9, 16, 16)
    torch.manual_seed(5)
    other = SVCoDe(two_level_model_config).state_dict()
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


def test_cache_is_bounded_and_does_not_thrash(model):
    """With a budget below one call's masks, the first entries stay and the rest are
    computed every call (an LRU cycling through more than it holds would never hit)."""
    views = torch.rand(2, 9, 16, 16)
    origins = [[0, 0], [16, 32]]
    with torch.no_grad():
        reference = model(views, origins, 48)
        with model.cache_masks(max_bytes=200_000):
            first = model(views, origins, 48)
            info = model.mask_cache_info()
            second = model(views, origins, 48)
            after = model.mask_cache_info()
    assert 0 < info["bytes"] <= 200_000 and 0 < info["entries"] < info["misses"]
    assert after["bytes"] == info["bytes"]
    assert after["hits"] - info["hits"] == info["entries"]  # every stored entry hit
    for ref, a, b in zip(reference, first, second, strict=True):
        assert _close(a, ref) and _close(b, ref)


def test_cached_masks_use_the_autocast_dtype(model):
    views = torch.rand(2, 9, 16, 16)
    with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16):
        reference = model(views, [[0, 0], [8, 8]], 48)
        with model.cache_masks():
            cached = model(views, [[0, 0], [8, 8]], 48)
            dtypes = {m.dtype for masks, _ in _entries(model).values() for m in masks}
    assert dtypes == {torch.bfloat16}
    for ref, out in zip(reference, cached, strict=True):  # bf16 epsilon 2^-8, a few units
        assert (ref.float() - out.float()).abs().max() < 1e-2


def test_cache_is_bypassed_when_gradients_are_needed(model):
    views = torch.rand(1, 9, 16, 16)
    with model.cache_masks():
        _, recon = model(views, [[0, 0]], 48)
        recon.mean().backward()
        assert model.mask_cache_info()["entries"] == 0
    assert model.demix.view_block.conv1.mlp.w_out.grad.abs().max() > 0


def test_coordinate_mask_matches_the_forward_masks(model, two_level_model_config):
    encoding = (two_level_model_config.pe_bands, two_level_model_config.pe_scheme)
    size = 48
    layers = {(m.stage, m.block, m.layer): m for m in model.mask_layers()}
    assert ("demix", "view", "conv1") in layers and ("recon", "middle.0", "conv5") in layers
    info = layers[("demix", "view", "conv2")]
    assert info.lenses == 9 and info.channels == 2 * two_level_model_config.view_width
    full = model.coordinate_mask("demix", "view", "conv2", size, lens=4, max_chunk_bytes=4096)
    assert full.shape == (info.channels, size, size)
    # the same layer evaluated for a 16 × 16 tile at (8, 20): a crop of the full field
    gate = model.demix.view_block.conv2
    rows = torch.linspace(-1, 1, size, dtype=torch.float64)
    enc_r = positional_encoding(rows[8:24], *encoding)[None]
    enc_c = positional_encoding(rows[20:36], *encoding)[None]
    with torch.no_grad():
        tile = gate.masks(enc_r, enc_c)[0, 4]
    torch.testing.assert_close(full[:, 8:24, 20:36], tile, rtol=1e-6, atol=1e-6)
    one = model.coordinate_mask("demix", "view", "conv2", size, lens=0, channels=1)
    assert one.shape == (1, size, size)
    assert (one[0] - full[1]).abs().max() > 1e-4  # lens-specific masks differ
    with pytest.raises(ValueError, match="no gated layer"):
        model.coordinate_mask("demix", "view", "conv9", size)


def test_demix_net_alone_has_its_own_cache(two_level_model_config):
    torch.manual_seed(0)
    net = DemixNet(two_level_model_config).eval()
    views = torch.rand(2, 9, 12, 12)
    with torch.no_grad():
        reference = net(views, [[0, 0], [4, 4]], 48)
        with net.cache_masks():
            cached = net(views, [[0, 0], [4, 4]], 48)
            blocks = {m.block for m in net.mask_layers()}
            assert net.mask_cache_info()["entries"] == len(blocks)
    assert _close(cached, reference)


def test_tiles_at_one_origin_share_their_masks_exactly(model):
    torch.manual_seed(2)
    views = torch.rand(4, 9, 24, 24)
    origins = torch.tensor([[8, 16], [0, 0], [8, 16], [0, 0]])
    demixed, recon = model(views, origins, 64)
    for b in range(4):
        alone = model(views[b : b + 1], origins[b : b + 1], 64)
        assert torch.equal(alone[1], recon[b : b + 1]) or _close(alone[1], recon[b : b + 1])
        assert _close(alone[0], demixed[b : b + 1])
