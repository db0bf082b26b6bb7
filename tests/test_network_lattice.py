"""Coordinate masks on a lattice: bound, exactness limits, tiling invariance, gradients."""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F

from svcode_core.network import ModelConfig, SVCoDe, lattice
from svcode_core.network.encoding import positional_encoding
from svcode_core.network.fast import fold
from svcode_core.network.lattice import (
    LatticeAxis,
    encoding_error_bound,
    interpolate,
    interpolate_once,
    lattice_axis,
    mask_spacing_for,
    row_interpolants,
)

S = 96
TINY = ModelConfig(
    width=4, view_width=2, demix_enc_blocks=(1, 1), demix_dec_blocks=(1, 1),
    demix_middle_blocks=1, recon_enc_blocks=(1,), recon_dec_blocks=(1,),
    recon_middle_blocks=0, mlp_hidden=8, output="linear", mask_spacing=8,
)  # fmt: skip
#: Masks interpolated in one piece and band by band (:class:`RowInterpolant`) differ by a
#: few float32 ulp (a lerp instead of a weighted sum); through a dozen gated layers the
#: outputs may then differ by some tens of ulp.
ROUTES_RTOL = 64 * torch.finfo(torch.float32).eps


def visible_model(config: ModelConfig, seed: int = 0) -> SVCoDe:
    """A random model whose masks all act (β and γ drawn instead of zero)."""
    torch.manual_seed(seed)
    model = SVCoDe(config).eval()
    with torch.no_grad():  # β and γ start at zero: give every mask a visible effect
        for name, param in model.named_parameters():
            if name.endswith(("beta", "gamma")):
                param.normal_(0.0, 0.5)
    return model


def _same_weights(model: SVCoDe, config: ModelConfig) -> SVCoDe:
    other = SVCoDe(config).eval()
    other.load_state_dict(model.state_dict())
    return other


def test_encoding_interpolates_within_the_bound():
    """Linear interpolation of every encoding feature between lattice nodes errs by at
    most ω²Δ²/8, and the bound is not loose by more than a few times."""
    for spacing in (4, 8, 16):
        nodes, axis = lattice_axis(torch.tensor([0]), S, 0, spacing, S)
        enc_nodes = positional_encoding(nodes, 4, "code", dtype=torch.float64)
        pixels = torch.arange(S, dtype=torch.float64) * 2 / (S - 1) - 1
        exact = positional_encoding(pixels, 4, "code", dtype=torch.float64)
        weights = torch.zeros(S, axis.nodes, dtype=torch.float64)
        below = axis.position[0].floor().clamp(max=axis.nodes - 2).long()
        frac = axis.position[0] - below
        weights[torch.arange(S), below] = 1 - frac
        weights[torch.arange(S), below + 1] = frac
        error = (weights @ enc_nodes[0] - exact).abs().max().item()
        bound = encoding_error_bound(spacing, S, 4, "code")
        assert error <= bound * (1 + 1e-9)
        assert error >= bound / 4


def test_mask_spacing_for_respects_the_tolerance():
    for size, levels in ((384, 3), (2400, 4), (96, 2)):
        for tolerance in (1e-3, 1e-2):
            spacing = mask_spacing_for(size, 4, "code", levels, tolerance)
            assert encoding_error_bound(spacing, size, 4, "code") <= tolerance
    # the presets' spacings are within 1 % at the sub-view size they are meant for
    assert encoding_error_bound(ModelConfig.mini().mask_spacing, 384, 4, "code") <= 1e-2
    assert encoding_error_bound(ModelConfig.reference().mask_spacing, 2400, 4, "code") <= 1e-2


@pytest.mark.parametrize("lenses", [1, 9])
def test_both_interpolation_routes_match_bilinear_upsampling(lenses):
    """Either route (up-sampling for one aligned lens, interpolation matrices otherwise,
    in either layout) gives each tile's crop of torch's bilinear up-sampling of its node
    masks."""
    torch.manual_seed(0)
    origins = torch.tensor([0, 16, 40])
    for level in (0, 1, 2):
        length = 32 // 2**level
        _, rows = lattice_axis(origins, length, level, 8, S)
        _, cols = lattice_axis(origins.flip(0), length, level, 8, S)
        assert rows.upsample is not None
        masks = torch.rand(3, lenses, 5, rows.nodes, cols.nodes)
        general = (LatticeAxis(rows.position, rows.nodes, None, ()),
                   LatticeAxis(cols.position, cols.nodes, None, ()))  # fmt: skip
        size = [(axis.nodes - 1) * axis.upsample + 1 for axis in (rows, cols)]
        routes = (interpolate(masks, rows, cols), interpolate(masks, *general),
                  interpolate(masks, rows, cols, channels_last=False))  # fmt: skip
        for route in routes:
            for t, tile in enumerate(route):
                up = F.interpolate(masks[t], size=size, mode="bilinear", align_corners=True)
                r, c = rows.crops[t], cols.crops[t]
                expected = up[:, :, r : r + length, c : c + length]
                torch.testing.assert_close(tile, expected, rtol=0,
                                           atol=4 * torch.finfo(torch.float32).eps)


def test_the_training_route_interpolates_alike_and_its_gradient_is_exact():
    """With gradients (training) all tiles are interpolated in one gather per tap: the
    same values as the route without, and autograd's gradient passes gradcheck."""
    torch.manual_seed(0)
    origins = torch.tensor([0, 16, 40])
    _, rows = lattice_axis(origins, 32, 0, 8, S)
    _, cols = lattice_axis(origins.flip(0), 32, 0, 8, S)
    general = (LatticeAxis(rows.position, rows.nodes, None, ()),
               LatticeAxis(cols.position, cols.nodes, None, ()))  # fmt: skip
    masks = torch.rand(3, 9, 5, rows.nodes, cols.nodes, dtype=torch.float64)
    for channels_last in (True, False):
        plain = interpolate(masks, *general, channels_last=channels_last)
        tracked = interpolate(masks.clone().requires_grad_(), *general,
                              channels_last=channels_last)  # fmt: skip
        for without, with_grad in zip(plain, tracked, strict=True):
            torch.testing.assert_close(with_grad.detach(), without, rtol=0, atol=0)
    small = torch.rand(3, 1, 2, rows.nodes, cols.nodes, dtype=torch.float64,
                       requires_grad=True)  # fmt: skip
    assert torch.autograd.gradcheck(
        lambda m: torch.stack(interpolate(m, *general, channels_last=False)), (small,))


def test_nodes_are_reproduced_exactly_and_spacing_one_is_exact():
    model = visible_model(TINY)
    exact = _same_weights(model, TINY.replace(mask_spacing=0))
    unit = _same_weights(model, TINY.replace(mask_spacing=1))
    views = torch.rand(2, 9, 32, 32)
    origins = [[0, 0], [24, 40]]
    with torch.no_grad():
        for a, b in zip(unit(views, origins, S), exact(views, origins, S), strict=True):
            torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6)
    # at the nodes (every 8th pixel of level 0) the interpolated mask is the MLP's value
    lattice = model.coordinate_mask("demix", "enc0.0", "conv1", S)
    pixels = exact.coordinate_mask("demix", "enc0.0", "conv1", S)
    torch.testing.assert_close(lattice[:, ::8, ::8], pixels[:, ::8, ::8], rtol=0, atol=1e-6)
    # between the nodes it differs, by less than a smooth function's interpolation error
    difference = (lattice - pixels).abs().max().item()
    assert 0 < difference < 0.05


def test_lattice_masks_depend_only_on_the_global_position():
    """A tile's masks are the crop of a whole-sub-view tile's masks (the lattice does
    not move with the tile), on both interpolation routes."""
    model = visible_model(TINY)
    block = model.demix.unet.encoders[1][0]
    whole = model.masks_for(torch.tensor([[0, 0]]), S, (S, S)).grids[1]
    (reference,) = whole.tile_masks(fold(block, whole.enc_row, whole.enc_col))
    for origin in ([16, 32], [18, 6], [3, 5]):
        grid = model.masks_for(torch.tensor([origin]), S, (32, 32)).grids[1]
        (masks,) = grid.tile_masks(fold(block, grid.enc_row, grid.enc_col))
        r, c = origin[0] // 2, origin[1] // 2
        for tile, full in zip(masks, reference, strict=True):
            if origin[0] % 2 == 0 and origin[1] % 2 == 0:  # on the level-1 pixel grid
                torch.testing.assert_close(tile, full[..., r : r + 16, c : c + 16],
                                           rtol=0, atol=1e-6)  # fmt: skip
            else:
                assert torch.isfinite(tile).all()


def test_tiled_output_equals_whole_sub_view_output_inside():
    """Pixels far from every tile border agree between a tile and the whole sub-view."""
    model = visible_model(TINY)
    views = torch.rand(1, 9, S, S)
    with torch.no_grad():
        _, whole = model(views, [[0, 0]], S)
        _, tile = model(views[..., 32:80, 16:64].contiguous(), [[32, 16]], S)
    # the receptive field of TINY is far smaller than 16 px: compare the tile's centre
    torch.testing.assert_close(tile[..., 16:32, 16:32], whole[..., 48:64, 32:48],
                               rtol=1e-5, atol=1e-6)  # fmt: skip


@pytest.mark.parametrize("channels_last", [True, False])
@pytest.mark.parametrize("band_bytes", [1, 1 << 22])  # a row per band / whole node gaps
@pytest.mark.parametrize(("lenses", "views"), [(3, 3), (1, 4)])  # own masks / shared
def test_row_interpolants_apply_the_interpolated_masks(channels_last, band_bytes, lenses,
                                                       views, monkeypatch):
    monkeypatch.setattr(lattice, "BAND_BYTES", band_bytes)
    origins = torch.tensor([0, 20])  # the second tile starts between two nodes
    _, rows = lattice_axis(origins, 24, 1, 8, S)
    _, cols = lattice_axis(origins.flip(0), 28, 1, 8, S)
    torch.manual_seed(0)
    masks = torch.rand(2, lenses, 5, rows.nodes, cols.nodes, dtype=torch.float64)
    full = interpolate(masks, rows, cols, channels_last)
    lazy = row_interpolants(masks, rows, cols, channels_last)
    layout = torch.channels_last if channels_last else torch.contiguous_format
    for whole, bands in zip(full, lazy, strict=True):
        assert len(bands.bands) >= (24 if band_bytes == 1 else 3)
        torch.testing.assert_close(bands.materialize(), whole, rtol=1e-14, atol=0)
        x, z = (torch.rand(views, 5, 24, 28, dtype=torch.float64).contiguous(
            memory_format=layout) for _ in range(2))
        out = torch.empty_like(x)
        bands.add_product(x, z, out)
        torch.testing.assert_close(out, x + whole * z, rtol=1e-14, atol=0)
        expected = z * whole
        bands.multiply_(z)
        torch.testing.assert_close(z, expected, rtol=1e-14, atol=0)


@pytest.mark.parametrize("route", [interpolate, row_interpolants])
def test_interpolation_stays_on_the_masks_device(route):
    """The interpolation weights (built on the CPU) follow the masks to their device: the
    meta device stands in for a GPU (a mix would fail there, and gives CPU tensors here)."""
    _, axis = lattice_axis(torch.tensor([0, 20]), 24, 0, 8, S)
    masks = torch.empty(2, 9, 4, axis.nodes, axis.nodes, device="meta")
    for tile in route(masks, axis, axis, channels_last=False):
        assert (tile.columns if isinstance(tile, lattice.RowInterpolant) else tile).is_meta


def test_masks_used_once_are_written_out_only_when_they_fit_in_one_band():
    _, small = lattice_axis(torch.tensor([0]), 32, 0, 8, S)
    _, large = lattice_axis(torch.tensor([0]), 512, 0, 8, 1024)
    for axis, kind in ((small, torch.Tensor), (large, lattice.RowInterpolant)):
        masks = torch.rand(1, 9, 8, axis.nodes, axis.nodes)  # 9·8·512² floats: 75 MiB
        assert isinstance(interpolate_once(masks, axis, axis)[0], kind)


def test_gradients_reach_the_mask_mlps_through_the_interpolation():
    model = visible_model(TINY).train()
    views = torch.rand(2, 9, 32, 32)
    demixed, recon = model(views, [[0, 0], [8, 16]], S)
    (demixed.square().mean() + recon.square().mean()).backward()
    grads = [p.grad for n, p in model.named_parameters() if ".mlp." in n]
    assert grads and all(g is not None and torch.isfinite(g).all() for g in grads)
    assert sum(g.abs().sum().item() for g in grads) > 0


def test_old_model_files_load_exact(tmp_path, tiny_system):
    """A configuration without ``mask_spacing`` (written before the lattice) is exact."""
    data = TINY.to_dict()
    del data["mask_spacing"]
    assert ModelConfig.from_dict(data).mask_spacing == 0
    with pytest.raises(Exception, match="mask_spacing"):
        TINY.replace(mask_spacing=-1)
    assert math.isclose(encoding_error_bound(0, 384, 4, "code"), 0.0)


@pytest.mark.parametrize("band_bytes", [lattice.BAND_BYTES, 1])  # masks written out / not
def test_cached_lattice_masks_give_the_same_output_and_are_read_on_the_next_frame(
        band_bytes, monkeypatch):
    monkeypatch.setattr(lattice, "BAND_BYTES", band_bytes)
    model = visible_model(TINY)
    views = torch.rand(3, 9, 32, 32)
    origins = [[0, 0], [24, 40], [0, 0]]  # two tiles share a place
    with torch.inference_mode():
        plain = model(views, origins, S)
        for budget in (2**30, 1):  # all kept / nothing fits: the masks are computed
            with model.cache_masks(max_bytes=budget):
                first = model(views, origins, S)
                second = model(views, origins, S)
                info = model.mask_cache_info()
            for a, b, c in zip(plain, first, second, strict=True):
                # kept masks are interpolated in one piece, the others (with bands of one
                # row) band by band where they are applied
                exact = budget == 1 or band_bytes > 1
                torch.testing.assert_close(b, a, rtol=0 if exact else ROUTES_RTOL,
                                           atol=0 if exact else ROUTES_RTOL)
                torch.testing.assert_close(c, b, rtol=0, atol=0)
            if budget == 1:
                assert info["entries"] == 0 and info["bytes"] == 0
            else:  # every block and level of both tile places, read on the second call
                assert info["entries"] > 0 and info["hits"] == info["entries"]
                assert info["bytes"] <= budget
