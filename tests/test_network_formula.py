"""The network's two routes against a plain transcription of the paper's formulas, and
against each other: the plain route (``PlainMasks``: each gate applies ``M ⊙ conv`` as
written in ``network/models.py``) and the fast one (``FastMasks``: folded, cached,
lattice-interpolated masks, ``network/fast.py``).

The reference here is written from the formulas and a state dict alone, in float64:

* coordinates: pixel ``i`` of a tile at level-0 origin ``o`` on U-Net level ``k`` is the
  mean of the ``2^k`` level-0 pixels it pools, ``t = 2 (o + 2^k i + (2^k - 1)/2)/(S-1) - 1``;
* encoding ``γ(t) = [sin(f_0 π t), cos(f_0 π t), ...]`` with ``f_k = 2^k`` ("paper") or
  ``0.5 (k + 1)`` ("code");
* CoordGate ``M(r) ⊙ (W ∗ F)`` with ``M(v, u) = sigmoid(W₂ relu(W₁ [γ(v), γ(u)] + b₁) + b₂)``
  evaluated per pixel (no row/column split);
* the NAFNet block ``y = x + β ⊙ M₃⊙conv3(SCA(SG(M₂⊙conv2(M₁⊙conv1(LN x)))))``,
  ``out = y + γ ⊙ M₅⊙conv5(SG(M₄⊙conv4(LN y)))``, and the two stages around their U-Nets.

With ``mask_spacing = p`` the masks are evaluated on the documented lattice (nodes at
level-0 positions ``j p + (2^k - 1)/2``) and interpolated bilinearly in ``u = (o + 2^k i)/p``;
as documented (:class:`~svcode_core.network.masks.PlainMasks`) the interpolated masks of
conv2 and conv4 are the products of their halves, applied after the SimpleGate. The
reference follows that definition rather than comparing with exact per-pixel masks: the
difference between the two is the lattice approximation (``encoding_error_bound`` times the
MLPs' gain, then through every block), far above float32 rounding, and
``test_network_lattice.py`` already bounds it; here the question is whether the fast
routes compute what they document, which only float32 rounding may blur.
"""

from __future__ import annotations

import contextlib
import math

import pytest
import torch
import torch.nn.functional as F
from test_network_lattice import visible_model

from svcode_core.methods.model_file import load_model
from svcode_core.network import ModelConfig, SVCoDe, lattice
from svcode_core.pretrained import require_bundled_weights

F64 = torch.float64
EPS = torch.finfo(torch.float32).eps  # one float32 ulp at 1 (2^-23)
UNIT = EPS / 2  # unit roundoff u
LENSES = 9

# ----------------------------------------------------------------------------- reference


def encode(t: torch.Tensor, bands: int, scheme: str) -> torch.Tensor:
    """γ of coordinates ``(n,)``: ``(n, 2 bands)``, sin and cos interleaved per band."""
    freq = (
        [2.0**k for k in range(bands)]
        if scheme == "paper"
        else [0.5 * (k + 1) for k in range(bands)]
    )
    angle = math.pi * t[:, None] * torch.tensor(freq, dtype=F64)
    return torch.stack((angle.sin(), angle.cos()), -1).flatten(1)


def pixel_coords(origin: int, n: int, level: int, size: int) -> torch.Tensor:
    """Normalised coordinates of a tile's ``n`` pixels along one axis at ``level``."""
    step = 2**level
    centre = origin + step * torch.arange(n, dtype=F64) + (step - 1) / 2
    return 2 * centre / (size - 1) - 1


def lattice_weights(origin: int, n: int, level: int, spacing: int, size: int):
    """Bilinear weights ``(n, nodes)`` of a tile's pixels on the global lattice nodes around
    it, and the nodes' normalised coordinates."""
    step = 2**level
    u = (origin + step * torch.arange(n, dtype=F64)) / spacing
    nodes = torch.arange(math.floor(u[0]), math.floor(u[-1]) + 2, dtype=F64)
    weights = (1 - (u[:, None] - nodes).abs()).clamp_min(0)  # hat functions
    return weights, 2 * (nodes * spacing + (step - 1) / 2) / (size - 1) - 1


def mlp_masks(
    P: dict,
    gate: str,
    rows: torch.Tensor,
    cols: torch.Tensor,
    config: ModelConfig,
    bound: bool = False,
):
    """``M`` ``(lenses, C, h, w)`` of one gate at every (row, col) pair; with ``bound``
    also a float32 forward-error bound of the masks (see :func:`test_gated_convolution`)."""
    enc = [encode(t, config.pe_bands, config.pe_scheme) for t in (rows, cols)]
    h, w, e = rows.numel(), cols.numel(), enc[0].shape[1]
    features = torch.cat((enc[0][:, None].expand(h, w, e), enc[1][None].expand(h, w, e)), -1)
    w1 = torch.cat((P[f"{gate}.mlp.w_row"], P[f"{gate}.mlp.w_col"]), -1)  # (L, H, 2E)
    b1 = P[f"{gate}.mlp.b_hidden"].flatten(1)[:, None, None]  # (L, 1, 1, H)
    w2, b2 = P[f"{gate}.mlp.w_out"], P[f"{gate}.mlp.b_out"][..., None]  # (L, C, H), (L, C, 1, 1)
    pre = torch.einsum("ijf,lkf->lijk", features, w1) + b1
    logits = torch.einsum("lijk,lck->lcij", pre.relu(), w2) + b2
    masks = torch.sigmoid(logits)
    if not bound:
        return masks
    # Higham: a float32 sum of n products errs by at most n·u·Σ|terms| in any order; the
    # encoding itself is rounded to float32 (u relative); relu passes errors unamplified;
    # sigmoid' <= 1/4, and its own evaluation (exp, add, divide) a few u of the mask
    span = torch.einsum("ijf,lkf->lijk", features.abs(), w1.abs())
    e_hidden = (e + 2) * UNIT * (span + b1.abs()) + UNIT * span
    e_logit = (
        (w1.shape[1] + 1) * UNIT * (torch.einsum("lijk,lck->lcij", pre.relu(), w2.abs()) + b2.abs())
    )
    e_logit = e_logit + torch.einsum("lijk,lck->lcij", e_hidden, w2.abs())
    return masks, e_logit / 4 + 4 * UNIT * masks


def block_masks(P: dict, block: str, config: ModelConfig, level: int, origin, shape, size: int):
    """The five masks of a block at one tile ``(lenses, C, h, w)``: each gate's ``M`` at the
    pixels, or on the lattice interpolated (conv2, conv4: the product of their halves)."""
    n = [shape[0] >> level, shape[1] >> level]
    gates = [f"{block}.conv{i}" for i in range(1, 6)]
    if not config.mask_spacing:
        rows, cols = (pixel_coords(origin[a], n[a], level, size) for a in (0, 1))
        return [mlp_masks(P, gate, rows, cols, config) for gate in gates]
    (wr, rows), (wc, cols) = (
        lattice_weights(origin[a], n[a], level, config.mask_spacing, size) for a in (0, 1)
    )
    out = []
    for gate in gates:
        m = mlp_masks(P, gate, rows, cols, config)
        if gate[-1] in "24":
            half = m.shape[1] // 2
            m = m[:, :half] * m[:, half:]
        out.append(torch.einsum("ia,lcab,jb->lcij", wr, m, wc))
    return out


def conv(x: torch.Tensor, P: dict, name: str, groups: int = 1, stride: int = 1) -> torch.Tensor:
    weight = P[f"{name}.weight"]
    padding = 0 if stride > 1 else weight.shape[-1] // 2
    return F.conv2d(x, weight, P.get(f"{name}.bias"), stride, padding, groups=groups)


def gated(y: torch.Tensor, masks: torch.Tensor) -> torch.Tensor:
    """``M ⊙ y`` with ``y`` ``(T·V, C, h, w)`` and per-tile masks ``(T, lenses, C, h, w)``
    (``lenses`` is ``V``, or 1 for a mask shared by the views)."""
    return (y.unflatten(0, (masks.shape[0], -1)) * masks).flatten(0, 1)


def gate_pair(z: torch.Tensor, masks: torch.Tensor) -> torch.Tensor:
    """SimpleGate of ``M ⊙ z``; a mask of half ``z``'s channels is the pair's (lattice)."""
    if masks.shape[2] == z.shape[1]:
        a, b = gated(z, masks).chunk(2, 1)
        return a * b
    a, b = z.chunk(2, 1)
    return gated(a * b, masks)


def layer_norm(x: torch.Tensor, P: dict, name: str) -> torch.Tensor:
    """Per-pixel normalisation over the channels (biased variance, ε = 1e-6), then affine."""
    mean = x.mean(1, keepdim=True)
    var = ((x - mean) ** 2).mean(1, keepdim=True)
    scale = P[f"{name}.weight"].view(1, -1, 1, 1)
    return (x - mean) / torch.sqrt(var + 1e-6) * scale + P[f"{name}.bias"].view(1, -1, 1, 1)


def code_block(P: dict, name: str, x: torch.Tensor, masks: list[torch.Tensor]) -> torch.Tensor:
    """The CoDe block; ``masks`` as from :func:`block_masks`, stacked over the tiles."""
    m1, m2, m3, m4, m5 = masks
    c = x.shape[1]
    z = gated(conv(layer_norm(x, P, f"{name}.norm1"), P, f"{name}.conv1.conv"), m1)
    z = gate_pair(conv(z, P, f"{name}.conv2.conv", groups=2 * c), m2)
    z = z * conv(z.mean((2, 3), keepdim=True), P, f"{name}.sca.conv")  # channel attention
    y = x + P[f"{name}.beta"] * gated(conv(z, P, f"{name}.conv3.conv"), m3)
    z = gate_pair(conv(layer_norm(y, P, f"{name}.norm2"), P, f"{name}.conv4.conv"), m4)
    return y + P[f"{name}.gamma"] * gated(conv(z, P, f"{name}.conv5.conv"), m5)


def stage(P: dict, name: str, config: ModelConfig, views: torch.Tensor, masks) -> torch.Tensor:
    """One stage on padded views ``(T, 9·k, H, W)``; ``masks(block, level)`` gives a block's."""
    tiles, _, h, w = views.shape
    if views.shape[1] == LENSES:  # one first convolution shared by the views
        x = conv(views.reshape(tiles * LENSES, 1, h, w), P, f"{name}.intro")
    else:  # lens context: each lens its own convolution of its k crops
        x = conv(views, P, f"{name}.intro", groups=LENSES).reshape(tiles * LENSES, -1, h, w)
    x = code_block(P, f"{name}.view_block", x, masks(f"{name}.view_block", 0))
    x = x.reshape(tiles, -1, h, w)  # views major
    x = x * torch.sigmoid(conv(x.mean((2, 3), keepdim=True), P, f"{name}.fusion.attention"))
    x = conv(x, P, f"{name}.fusion.merge")
    enc, dec = getattr(config, f"{name}_enc_blocks"), getattr(config, f"{name}_dec_blocks")
    unet, skips = f"{name}.unet", []
    for level, count in enumerate(enc):
        for i in range(count):
            x = code_block(
                P, f"{unet}.encoders.{level}.{i}", x, masks(f"{unet}.encoders.{level}.{i}", level)
            )
        skips.append(x)
        x = conv(x, P, f"{unet}.downs.{level}", stride=2)
    for i in range(getattr(config, f"{name}_middle_blocks")):
        x = code_block(P, f"{unet}.middle.{i}", x, masks(f"{unet}.middle.{i}", len(enc)))
    for level in reversed(range(len(dec))):
        x = F.pixel_shuffle(conv(x, P, f"{unet}.ups.{level}.0"), 2) + skips[level]
        for i in range(dec[level]):
            x = code_block(
                P, f"{unet}.decoders.{level}.{i}", x, masks(f"{unet}.decoders.{level}.{i}", level)
            )
    out = conv(x, P, f"{name}.ending")
    return torch.sigmoid(out) if config.output == "sigmoid" else out.clamp_min(0)  # eval mode


def svcode(P: dict, config: ModelConfig, views: torch.Tensor, origins, size: int):
    """``(demixed, reconstruction)`` of views ``(T, 9·k, H, W)`` at ``origins``."""
    levels = max(len(config.demix_enc_blocks), len(config.recon_enc_blocks))
    stride = 2**levels
    h, w = views.shape[-2:]
    padded = F.pad(views.to(F64), (0, -w % stride, 0, -h % stride))  # coordinates continue
    shape = padded.shape[-2:]

    def masks(block: str, level: int) -> list[torch.Tensor]:
        per_tile = [block_masks(P, block, config, level, o, shape, size) for o in origins]
        return [torch.stack(m) for m in zip(*per_tile, strict=True)]

    demixed = stage(P, "demix", config, padded, masks)
    recon = stage(P, "recon", config, demixed, masks)
    return demixed[..., :h, :w], recon[..., :h, :w]


def state64(model: torch.nn.Module) -> dict:
    return {k: v.detach().to(F64) for k, v in model.state_dict().items()}


# --------------------------------------------------------------------------------- tests

S = 64
SMALL = ModelConfig(
    width=4, view_width=2, demix_enc_blocks=(1, 1), demix_dec_blocks=(1, 1),
    demix_middle_blocks=1, recon_enc_blocks=(1,), recon_dec_blocks=(1,),
    recon_middle_blocks=1, mlp_hidden=8, pe_scheme="paper", output="sigmoid",
)  # fmt: skip
# sigmoid outputs: random weights with clamped linear outputs give all-zero tiles (the
# trained model covers "linear")
LATTICE = SMALL.replace(mask_spacing=8, pe_scheme="code", lens_context=True)
# aligned: multiples of the stride and the spacing (the up-sampling route of the lattice,
# tiles cropped from the cached field); unaligned: neither, one tile partly outside the
# sub-view, one origin twice (tiles sharing one mask computation)
ORIGINS = {"aligned": [[16, 8], [0, 32]], "unaligned": [[13, 21], [40, -6], [13, 21]]}
FAST_PATHS = ["uncached", "cached", "banded", "autograd"]
PATHS = ["plain", *FAST_PATHS]
#: A CoDe block: ~12 float32 stages in sequence (LN, five convolutions, gate, attention,
#: masks, two residuals), each within ~sqrt(K) u of its operands' scale for a sum of K terms
#: (rounding errors of random sign); the longest sums are the attention's tile means, K =
#: 16 * 24 here: 12 * sqrt(384) u ~ 120 ulp, x2 for the layer norms rescaling to unit spread.
BLOCK_ULPS = 256
#: The model: ~16 blocks and ~12 convolutions between input and output, tiles of up to
#: 24 * 32 pixels (~170 ulp a block as above); independent stage errors add in quadrature:
#: sqrt(28) * 170 ~ 900 ulp of the output scale.
MODEL_ULPS = 1024
#: Fast against plain route, in ulps of the plain output's scale. Both routes run the same
#: float32 operations except where a block applies its masks, in five places: M₁⊙y, the
#: conv2 and conv4 pairs ((Ma⊙a)⊙(Mb⊙b) against (a⊙b)⊙(Ma⊙Mb)) and the two residual
#: branches (x + β⊙(M⊙z) against x + (β⊙M)⊙z). There each route reaches the value from the
#: same operands (features, the MLPs' masks at the pixels or nodes, β, γ) in at most ten
#: roundings: a fold or β product, on a lattice the bilinear interpolation's two lerps
#: (three each), the products and the sum. So at each place the routes are within
#: 2 x 10 u = 10 ulp of each other, and the shared operations after it pass that on as they
#: pass on their own roundings (x2 for the layer norms, as for BLOCK_ULPS):
#: 5 places x 10 ulp x 2 = 100 ulp of a block's output scale.
ROUTES_BLOCK_ULPS = 100


@contextlib.contextmanager
def _on_path(model: SVCoDe, path: str, monkeypatch):
    """Run ``model`` on ``path``: the plain route, or the fast one for inference without or
    with the mask cache, lattice masks finished band by band where they are applied
    (``RowInterpolant``: small tiles take it only under a small band budget), or with
    autograd (training's products)."""
    calls = []
    if path == "banded":
        monkeypatch.setattr(lattice, "BAND_BYTES", 256)
        route = lattice.row_interpolants
        monkeypatch.setattr(lattice, "row_interpolants",
                            lambda *a, **k: calls.append(1) or route(*a, **k))  # fmt: skip
    with (
        monkeypatch.context() as patch,
        torch.set_grad_enabled(path == "autograd"),
        model.cache_masks(path == "cached"),
    ):
        patch.setattr(model, "fast_masks", path != "plain")
        yield
    if path == "banded" and model.model_config.mask_spacing:
        assert calls, "the banded route was not taken"


def _ulps(out: torch.Tensor, ref: torch.Tensor) -> float:
    """Largest difference in float32 ulps of the reference's scale (its largest value)."""
    return ((out.detach().to(F64) - ref).abs().max() / (EPS * ref.abs().max())).item()


@pytest.mark.parametrize("block, level", [("demix.view_block", 0),
                                          ("demix.unet.encoders.1.0", 1)])  # fmt: skip
@pytest.mark.parametrize("layer", ["conv1", "conv2"])
def test_gated_convolution(block, level, layer, monkeypatch):
    """``CoordGate.forward`` equals ``M(r) ⊙ conv`` with the MLP evaluated at each pixel's
    global coordinate, within a per-element float32 forward-error bound."""
    model = visible_model(SMALL)
    gate = model.get_submodule(f"{block}.{layer}")
    origins, shape = ORIGINS["unaligned"], (16, 12)
    monkeypatch.setattr(model, "fast_masks", False)
    masks = model.masks_for(torch.tensor(origins), S, shape)
    mask = masks(model.get_submodule(block), level)[int(layer[-1]) - 1]
    views = LENSES if "view" in block else 1
    cin, groups = gate.conv.in_channels, gate.conv.groups
    torch.manual_seed(1)
    x = torch.randn(len(origins) * views, cin, shape[0] >> level, shape[1] >> level)
    with torch.no_grad():
        out = gate(x, mask)
    P, x64, name = state64(model), x.to(F64), f"{block}.{layer}"
    y = conv(x64, P, f"{name}.conv", groups)
    # the convolution: Higham's bound over its K = cin/groups · k² products and the bias
    k = cin // groups * gate.conv.kernel_size[0] ** 2
    e_y = (k + 1) * UNIT * F.conv2d(x64.abs(), P[f"{name}.conv.weight"].abs(),
                                    P[f"{name}.conv.bias"].abs(), padding=gate.conv.padding,
                                    groups=groups)  # fmt: skip
    masks, e_masks = [], []
    for origin in origins:
        rows, cols = (pixel_coords(origin[a], x.shape[2 + a], level, S) for a in (0, 1))
        m, e = mlp_masks(P, name, rows, cols, SMALL, bound=True)
        masks.append(m)
        e_masks.append(e)
    masks, e_masks = torch.stack(masks), torch.stack(e_masks)
    ref = gated(y, masks)
    # the product M·y: each factor's error times the other, plus its own rounding
    bound = gated(e_y, masks) + gated(y.abs(), e_masks) + 2 * UNIT * ref.abs()
    error = (out.to(F64) - ref).abs()
    assert (error <= bound).all(), f"worst error / bound {(error / bound).max():.3g}"


#: the blocks the block tests run: the view block (nine lenses, channels first) and a level-1
#: U-Net block (channels last), with their levels
BLOCKS = (("demix.view_block", 0), ("demix.unet.encoders.1.0", 1))


def _block_input(model, name: str, level: int, tiles: int, shape) -> tuple:
    """Block ``name`` of ``model`` and a random input of ``tiles`` tiles of ``shape`` (at
    the block's level), in the memory layout the model runs it in."""
    block = model.get_submodule(name)
    c, views = block.beta.shape[1], LENSES if "view" in name else 1
    x = torch.randn(tiles * views, c, shape[0] >> level, shape[1] >> level)
    if views == 1:  # as the U-Net runs
        x = x.contiguous(memory_format=torch.channels_last)
    return block, x


@pytest.mark.parametrize("path", PATHS)
@pytest.mark.parametrize("origins", ORIGINS.values(), ids=ORIGINS.keys())
@pytest.mark.parametrize("config", [SMALL, LATTICE], ids=["exact", "lattice"])
def test_code_block(config, origins, path, monkeypatch):
    """A CoDe block on the model's paths (plain or folded masks; exact or lattice) equals the
    block formula, for the view block (nine lenses, channels first) and a level-1 U-Net block
    (channels last); a cached block twice (masks computed, then read)."""
    model = visible_model(config)
    P, shape = state64(model), (16, 24)
    torch.manual_seed(2)
    for name, level in BLOCKS:
        block, x = _block_input(model, name, level, len(origins), shape)
        per_tile = [block_masks(P, name, config, level, o, shape, S) for o in origins]
        ref = code_block(P, name, x.to(F64), [torch.stack(m) for m in zip(*per_tile, strict=True)])
        with _on_path(model, path, monkeypatch):
            for _ in range(2 if path == "cached" else 1):
                masks = model.masks_for(torch.tensor(origins), S, shape)
                assert _ulps(block(x, masks(block, level)), ref) <= BLOCK_ULPS, name


@pytest.mark.parametrize("path", PATHS)
@pytest.mark.parametrize("origins", ORIGINS.values(), ids=ORIGINS.keys())
@pytest.mark.parametrize("config", [SMALL, LATTICE], ids=["exact", "lattice"])
def test_svcode_random_weights(config, origins, path, monkeypatch):
    """The whole model with random weights equals the reference, on tiles padded to the
    stride."""
    model = visible_model(config)
    torch.manual_seed(3)
    views = torch.rand(len(origins), LENSES * config.views_per_lens, 13, 22)
    ref = svcode(state64(model), config, views, origins, S)
    with _on_path(model, path, monkeypatch):
        out = model(views, origins, S)
    for o, r in zip(out, ref, strict=True):
        assert _ulps(o, r) <= MODEL_ULPS


@pytest.fixture(scope="module")
def trained():
    return load_model(require_bundled_weights("cm2-mini"))


@pytest.mark.parametrize("path", PATHS)
@pytest.mark.parametrize("origins", [[[96, 200]], [[101, 43], [250, 7]]],
                         ids=["aligned", "unaligned"])  # fmt: skip
def test_svcode_trained_weights(trained, origins, path, monkeypatch):
    """The bundled cm2-mini model (lens context, 8-pixel mask lattice, clamped linear
    outputs) equals the reference on small tiles away from the sub-view's origin."""
    model, system = trained
    config, size = model.model_config, system.sub_view_size
    torch.manual_seed(4)
    views = torch.rand(len(origins), LENSES * config.views_per_lens, 20, 28)
    ref = svcode(state64(model), config, views, origins, size)
    with _on_path(model, path, monkeypatch):
        out = model(views, origins, size)
    for o, r in zip(out, ref, strict=True):
        assert (r > 0).any()  # not a tile clamped to zero
        assert _ulps(o, r) <= MODEL_ULPS


def _blocks(model: SVCoDe) -> int:
    return sum(len(stage.named_blocks()) for stage in (model.demix, model.recon))


@pytest.mark.parametrize("path", FAST_PATHS)
@pytest.mark.parametrize("origins", ORIGINS.values(), ids=ORIGINS.keys())
@pytest.mark.parametrize("config", [SMALL, LATTICE], ids=["exact", "lattice"])
def test_fast_block_equals_plain_block(config, origins, path, monkeypatch):
    """A CoDe block on each fast path equals the same block on the plain route."""
    model = visible_model(config)
    shape, tiles = (16, 24), torch.tensor(origins)
    torch.manual_seed(2)
    for name, level in BLOCKS:
        block, x = _block_input(model, name, level, len(origins), shape)
        with _on_path(model, "plain", monkeypatch):
            plain = block(x, model.masks_for(tiles, S, shape)(block, level))
        with _on_path(model, path, monkeypatch):
            for _ in range(2 if path == "cached" else 1):
                fast = block(x, model.masks_for(tiles, S, shape)(block, level))
                assert _ulps(fast, plain.to(F64)) <= ROUTES_BLOCK_ULPS, name


def _fast_and_plain(model, views, origins, size, path, monkeypatch):
    """The model's outputs on fast ``path`` paired with those on the plain route."""
    with _on_path(model, "plain", monkeypatch):
        plain = model(views, origins, size)
    with _on_path(model, path, monkeypatch):
        fast = model(views, origins, size)
    return zip(fast, plain, strict=True)


@pytest.mark.parametrize("path", FAST_PATHS)
@pytest.mark.parametrize("origins", ORIGINS.values(), ids=ORIGINS.keys())
@pytest.mark.parametrize("config", [SMALL, LATTICE], ids=["exact", "lattice"])
def test_fast_model_equals_plain_model_random_weights(config, origins, path, monkeypatch):
    """The whole model on each fast path equals it on the plain route: the blocks'
    differences, of random sign, add in quadrature (sqrt(blocks) x ROUTES_BLOCK_ULPS)."""
    model = visible_model(config)
    torch.manual_seed(3)
    views = torch.rand(len(origins), LENSES * config.views_per_lens, 13, 22)
    for f, p in _fast_and_plain(model, views, origins, S, path, monkeypatch):
        assert _ulps(f, p.to(F64)) <= math.sqrt(_blocks(model)) * ROUTES_BLOCK_ULPS


@pytest.mark.parametrize("path", FAST_PATHS)
@pytest.mark.parametrize("origins", [[[96, 200]], [[101, 43], [250, 7]]],
                         ids=["aligned", "unaligned"])  # fmt: skip
def test_fast_model_equals_plain_model_trained_weights(trained, origins, path, monkeypatch):
    """The bundled cm2-mini model on each fast path equals it on the plain route."""
    model, system = trained
    config, size = model.model_config, system.sub_view_size
    torch.manual_seed(4)
    views = torch.rand(len(origins), LENSES * config.views_per_lens, 44, 60)
    for f, p in _fast_and_plain(model, views, origins, size, path, monkeypatch):
        assert (p > 0).any()
        assert _ulps(f, p.to(F64)) <= math.sqrt(_blocks(model)) * ROUTES_BLOCK_ULPS
