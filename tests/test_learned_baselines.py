"""Learned baselines: MultiWienerNet and SV-FourierNet (filters, geometry, training, files)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from skimage.restoration import wiener

from svcode_core.methods.baselines.deconv import unit_centre_psfs
from svcode_core.methods.learned import (
    FourierNetConfig,
    MultiWienerConfig,
    MultiWienerNet,
    SVFourierNet,
    lens_offsets,
)
from svcode_core.methods.model_file import load_model, read_model_metadata, save_model
from svcode_core.physics.cm2 import CM2Operator
from svcode_core.physics.geometry import assemble_frame, extract_sub_views, place_sub_views
from svcode_core.physics.simulate import Simulator
from svcode_core.training import (
    DataRecipe,
    FrameDataset,
    TrainConfig,
    Trainer,
    TrainingData,
    generate_dataset,
    stage_loss,
)

HEAD = {"width": 4, "enc_blocks": (1,), "middle_blocks": 1, "dec_blocks": (1,)}
BUILDERS = {
    "multiwiener": lambda op: MultiWienerNet.from_operator(op, MultiWienerConfig(rank=3, **HEAD)),
    "fouriernet": lambda op: SVFourierNet.from_operator(op, FourierNetConfig(**HEAD)),
}


@pytest.fixture
def operator(tiny_system) -> CM2Operator:
    return CM2Operator.from_system(tiny_system)


@pytest.fixture(scope="module")
def tiny_data(tmp_path_factory) -> TrainingData:
    from conftest import tiny_system

    recipe = DataRecipe(frames=4, seed=3, val_fraction=0.25, object_kind="beads")
    out = tmp_path_factory.mktemp("data")
    return generate_dataset(out, tiny_system.__wrapped__(), recipe, progress=False)


def _scene(operator: CM2Operator, batch: int = 2) -> tuple[torch.Tensor, torch.Tensor]:
    """Padded frames ``(B, H_pad, W_pad)`` and objects ``(B, 1, S, S)`` of a few squares."""
    size = operator.system.sub_view_size
    generator = torch.Generator().manual_seed(0)
    objects = torch.zeros(batch, 1, size, size)
    for b in range(batch):
        for r, c in torch.randint(4, size - 8, (6, 2), generator=generator).tolist():
            objects[b, 0, r : r + 4, c : c + 4] = 0.3 + 0.7 * torch.rand(1, generator=generator)
    return operator.forward(objects[:, 0]), objects


@pytest.mark.parametrize("method", sorted(BUILDERS))
def test_shapes_and_frame_check(method, operator):
    model = BUILDERS[method](operator)
    frames, objects = _scene(operator, batch=2)
    assert model(frames).shape == objects.shape
    with pytest.raises(ValueError, match="padded sensor frames"):
        model(frames[:, :-1])


def test_fouriernet_init_is_the_wiener_filter_of_each_view(operator):
    """Filter ℓ equals scikit-image's Wiener deconvolution (identity regulariser) with the
    lens's unit-sum centre PSF, shifted from the chief ray to the reference point."""
    model = BUILDERS["fouriernet"](operator).eval()
    frames, _ = _scene(operator, batch=1)
    with torch.no_grad():
        filtered = model.bank(frames)[0].double().numpy()
    balance = model.model_config.balance
    for lens, (psf, offset) in enumerate(
        zip(unit_centre_psfs(operator).double().numpy(), lens_offsets(operator.system), strict=True)
    ):
        expected = wiener(frames[0].double().numpy(), psf, balance, reg=np.ones((1, 1)), clip=False)
        expected = np.roll(expected, shift=tuple(-offset), axis=(0, 1))
        np.testing.assert_allclose(filtered[lens], expected, atol=2e-5 * np.abs(expected).max())


def test_multiwiener_bank_is_a_wiener_deconvolution(operator):
    """Each filter is scikit-image's Wiener deconvolution with its frame-sized PSF and λ."""
    model = BUILDERS["multiwiener"](operator).eval()
    frames, _ = _scene(operator, batch=1)
    bank = model.bank
    with torch.no_grad():
        filtered = bank(frames)[0].double().numpy()
        psfs = bank.psfs.double().numpy()
        lambdas = bank.log_regularisation.exp().double().numpy()
    peak = np.abs(np.fft.rfft2(psfs)).reshape(len(psfs), -1).max(1) ** 2
    np.testing.assert_allclose(lambdas, model.model_config.balance * peak, rtol=1e-5)
    shape = np.array(frames.shape[-2:])
    for k, (psf, lam) in enumerate(zip(psfs, lambdas, strict=True)):
        centred = np.roll(psf, shift=tuple(shape // 2), axis=(0, 1))  # skimage: centre at N//2
        expected = wiener(frames[0].double().numpy(), centred, lam, reg=np.ones((1, 1)), clip=False)
        np.testing.assert_allclose(filtered[k], expected, atol=1e-4 * np.abs(expected).max())


def test_initial_filters_bring_a_point_back_to_its_place(operator):
    """A point seen by one lens, deconvolved by that lens's filter, peaks at the point; the
    first MultiWiener filter does the same for the full nine-spot frame."""
    system = operator.system
    size, point = system.sub_view_size, (17, 29)
    obj = torch.zeros(size, size)
    obj[point] = 1.0
    blur = operator.lens_blur(obj)  # (9, S + 2m, S + 2m)
    fourier = BUILDERS["fouriernet"](operator)
    with torch.no_grad():
        for lens in range(9):
            alone = torch.zeros_like(blur)
            alone[lens] = blur[lens]
            frame = place_sub_views(alone, system, operator.margin)[None]
            window = fourier.filtered(frame)[0, lens]
            assert divmod(int(window.argmax()), size) == point, lens
        window = BUILDERS["multiwiener"](operator).filtered(operator.forward(obj)[None])[0, 0]
    assert divmod(int(window.argmax()), size) == point


@pytest.mark.parametrize("method", sorted(BUILDERS))
def test_one_step_lowers_the_loss(method, operator):
    torch.manual_seed(0)
    model = BUILDERS[method](operator).train()
    frames, objects = _scene(operator, batch=2)
    optimizer = torch.optim.Adam(model.parameters(), lr=1e-3)
    before = stage_loss(model(frames), objects)
    optimizer.zero_grad()
    before.backward()
    assert all(p.grad is not None for p in model.parameters())
    optimizer.step()
    with torch.no_grad():
        after = stage_loss(model(frames), objects)
    assert float(after) < float(before.detach())


@pytest.mark.parametrize("method", sorted(BUILDERS))
def test_zero_frame_gives_a_finite_non_negative_image(method, operator):
    model = BUILDERS[method](operator).eval()
    frames = torch.zeros(1, *operator.system.padded_shape)
    with torch.no_grad():
        out = model(frames)
    assert torch.isfinite(out).all() and (out >= 0).all()


@pytest.mark.parametrize("method", sorted(BUILDERS))
def test_save_load_round_trip_is_bit_exact(method, operator, tmp_path):
    model = BUILDERS[method](operator).eval()
    with torch.no_grad():  # move away from the initialisation
        for param in model.parameters():
            param.add_(0.01 * torch.randn_like(param))
    path = save_model(tmp_path / "m.safetensors", model, operator.system, {"note": method})
    meta = read_model_metadata(path)
    assert meta["architecture"] == type(model).__name__
    assert meta["model_config"] == model.model_config and meta["extra"] == {"note": method}
    loaded, system = load_model(path, operator.system)
    assert type(loaded) is type(model) and system == operator.system
    for key, value in model.state_dict().items():
        assert torch.equal(loaded.state_dict()[key], value), key
    frames, _ = _scene(operator, batch=1)
    with torch.no_grad():
        assert torch.equal(loaded(frames), model(frames))


def test_assemble_frame_inverts_the_sub_view_cut(tiny_system):
    frame = torch.rand(2, *tiny_system.padded_shape)
    views = extract_sub_views(frame, tiny_system)
    torch.testing.assert_close(assemble_frame(views, tiny_system), frame, rtol=1e-6, atol=0)


# ---------------------------------------------------------------------------- training
def test_frame_dataset_rebuilds_the_simulated_frame(tiny_data):
    system = tiny_data.system
    clean = FrameDataset(tiny_data, [1], noise=False)[0]
    scene = Simulator(system).simulate(np.array(tiny_data.objects[1]), noise=False)
    sensor = clean["frame"][system.sensor_window].numpy()
    np.testing.assert_allclose(sensor, scene.measurement, atol=1e-6)
    assert clean["object"].shape == (1, system.sub_view_size, system.sub_view_size)
    noisy = FrameDataset(tiny_data, [1], fixed_noise=True, seed=0)
    first, again = noisy[0]["frame"], noisy[0]["frame"]
    assert torch.equal(first, again)  # fixed noise: the same draw every time
    outside = torch.ones(system.padded_shape, dtype=torch.bool)
    outside[system.sensor_window] = False
    assert not first[outside].any()  # the padding stays exactly zero
    assert not torch.equal(first[~outside], clean["frame"][~outside])


@pytest.mark.parametrize(
    ("config", "architecture"),
    [
        (MultiWienerConfig(rank=2, **HEAD), "MultiWienerNet"),
        (FourierNetConfig(**HEAD), "SVFourierNet"),
    ],
)
def test_trainer_runs_whole_frame_baselines(config, architecture, tiny_data, tmp_path):
    train = TrainConfig(epochs=2, batch_size=1, lr=1e-3, warmup_steps=1)
    trainer = Trainer(tiny_data, tmp_path, config, train, progress=False)
    history = trainer.fit()
    assert len(trainer.train_set) == len(tiny_data.train_frames)
    assert [r["epoch"] for r in history] == [1, 2]
    record = history[-1]
    assert {"train_recon", "val_recon_psnr", "val_recon_ssim"} <= set(record)
    assert not any("demix" in key for key in record)
    assert all(np.isfinite(v) for v in record.values())
    model, _ = load_model(tmp_path / "best.safetensors", tiny_data.system)
    assert type(model).__name__ == architecture and model.model_config == config
    assert read_model_metadata(tmp_path / "best.safetensors")["extra"]["data"]["train_frames"] == 3
    resumed = Trainer(tiny_data, tmp_path, config, train, progress=False)
    assert resumed.load_checkpoint() == 2
    for key, value in trainer.model.state_dict().items():
        assert torch.equal(resumed.model.state_dict()[key], value), key


def test_train_command_trains_a_baseline(tiny_data, tmp_path, capsys):
    import svcode_core.cli as cli

    config = tmp_path / "fouriernet.json"
    config.write_text(FourierNetConfig(**HEAD).to_json())
    run = tmp_path / "run"
    args = [
        "train",
        "--data",
        str(tiny_data.path),
        "--out",
        str(run),
        "--method",
        "fouriernet",
        "--model-config",
        str(config),
        "--epochs",
        "1",
        "--batch-size",
        "1",
        "--device",
        "cpu",
        "--no-progress",
    ]
    assert cli.main(args) == 0
    assert "validation reconstruction PSNR" in capsys.readouterr().out
    model, _ = load_model(run / "best.safetensors", tiny_data.system)
    assert isinstance(model, SVFourierNet)
    assert cli.main([*args, "--ablation", "no-pe"]) == 2
    assert "--ablation applies to SV-CoDe" in capsys.readouterr().err
    assert cli.main([*args, "--ablation", "no-pe", "--lens-context"]) == 2
    assert "--ablation and --lens-context apply to SV-CoDe" in capsys.readouterr().err


@pytest.mark.parametrize("method", sorted(BUILDERS))
def test_reconstructor_matches_the_model_and_refuses_bad_input(method, operator, tmp_path):
    from svcode_core.methods.build import MethodSpec
    from svcode_core.methods.exposure import exposure_gain
    from svcode_core.methods.learned.reconstruct import LearnedReconstructor
    from svcode_core.physics.geometry import pad_sensor_frame

    system = operator.system
    model = BUILDERS[method](operator).eval()
    path = save_model(tmp_path / f"{method}.safetensors", model, system)
    frames, _ = _scene(operator, batch=2)
    (top, left), (rows, cols) = system.padding, system.sensor_shape
    raw = frames[:, top : top + rows, left : left + cols].numpy()
    rec = MethodSpec(method, system, str(path), {"normalise_exposure": False})()
    result = rec.reconstruct(raw)
    with torch.no_grad():
        expected = model(pad_sensor_frame(torch.from_numpy(raw), system))[:, 0].numpy()
        # by default each frame is brought to the reference level and the output scaled back
        gain = exposure_gain(raw[0])
        normalised = model(pad_sensor_frame(torch.from_numpy(raw[:1] * gain), system))[0, 0]
    normalising = MethodSpec(method, system, str(path))()
    np.testing.assert_allclose(normalising.reconstruct(raw[0]).reconstruction,
        normalised.numpy() / gain, rtol=1e-5,
        atol=64 * np.finfo(np.float32).eps * float(np.abs(normalised).max()) / gain)
    # the gain recorded is the one used, from the frame in units of the full scale, however
    # the frame is stored (16-bit counts here), and 1 for the method that does not normalise
    counts = np.round(np.clip(raw[0], 0, 1) * 65535).astype(np.uint16)
    assert normalising.reconstruct(counts).exposure_gains == pytest.approx(
        [exposure_gain(counts / 65535.0)], rel=1e-6)
    assert result.exposure_gains is None
    # frame by frame against a batch of two: float32 FFTs and convolutions sum in another
    # order, so agreement is to a few float32 ulps of the image scale, not bit for bit
    atol = 64 * np.finfo(np.float32).eps * float(np.abs(expected).max())
    np.testing.assert_allclose(result.reconstruction, expected, rtol=0, atol=atol)
    np.testing.assert_array_equal(rec.reconstruct(raw[0]).reconstruction, result.reconstruction[0])
    with pytest.raises(ValueError, match="no demixed views"):
        rec.reconstruct(raw, return_views=True)
    bad = raw[0].copy()
    bad[3, 4] = np.nan
    with pytest.raises(ValueError, match="1 NaN or Inf"):
        rec.reconstruct(bad)
    other = "fouriernet" if method == "multiwiener" else "multiwiener"
    with pytest.raises(ValueError, match=f"--method {other}"):
        LearnedReconstructor.from_weights(path, method=other)


def test_reconstruct_command_runs_a_learned_baseline(operator, tmp_path, capsys):
    import tifffile

    from svcode_core.cli import main
    from svcode_core.io import write_tiff

    system = operator.system
    path = save_model(tmp_path / "fn.safetensors", BUILDERS["fouriernet"](operator), system)
    raw = np.random.default_rng(0).random(system.sensor_shape, dtype=np.float32)
    meas = tmp_path / "meas.tif"
    write_tiff(meas, raw, system, kind="measurement")
    out = tmp_path / "recon.tif"
    args = ["reconstruct", str(meas), "--out", str(out), "--method", "fouriernet", "--quiet"]
    assert main(args) == 2
    assert "needs --weights" in capsys.readouterr().err
    assert main([*args, "--weights", str(path), "--rank", "3"]) == 2
    assert "--rank applies to the model-based baselines" in capsys.readouterr().err
    assert main([*args, "--weights", str(path)]) == 0
    assert tifffile.imread(out).shape == (system.sub_view_size,) * 2


def test_footprint_grows_with_the_field_for_the_baselines_only(operator, tmp_path):
    from svcode_bench.footprint import doubled_system, model_footprint
    from svcode_core.network import ModelConfig, SVCoDe

    system = operator.system
    big = doubled_system(system)
    assert big.sub_view_size == 2 * system.sub_view_size
    assert big.padded_shape == tuple(2 * v for v in system.padded_shape)
    blocks = {name: (1,) for name in ("demix_enc_blocks", "demix_dec_blocks",
                                      "recon_enc_blocks", "recon_dec_blocks")}  # fmt: skip
    tiny = ModelConfig(width=4, view_width=2, mlp_hidden=8, pe_bands=2, **blocks)
    svcode = model_footprint(save_model(tmp_path / "sv.safetensors", SVCoDe(tiny), system), system)
    assert svcode.parameters_m == svcode.parameters_m_2s
    fourier = model_footprint(
        save_model(tmp_path / "fn.safetensors", BUILDERS["fouriernet"](operator), system), system
    )
    # nine complex half-spectrum filters: 9 · H · (W/2 + 1) · 2 numbers, about 4× at 2S
    rows, cols = system.padded_shape
    filters = 9 * rows * (cols // 2 + 1) * 2 / 1e6
    assert fourier.parameters_m > filters
    assert fourier.parameters_m_2s - fourier.parameters_m > 2.9 * filters


def test_benchmark_rows_of_a_learned_baseline_and_merge(operator, tmp_path):
    from svcode_bench.regimes import Scene, learned_rows, merge_reports

    system = operator.system
    path = save_model(tmp_path / "mw.safetensors", BUILDERS["multiwiener"](operator), system)
    frames, objects = _scene(operator, batch=1)
    (top, left), (rows, cols) = system.padding, system.sensor_shape
    scene = Scene(
        "squares", objects[0, 0].numpy(), frames[0, top : top + rows, left : left + cols].numpy()
    )
    (row,) = learned_rows(path, system, [scene])
    summary = row.summary()
    assert summary["method"] == "MultiWienerNet" and np.isfinite(summary["psnr"])
    assert summary["footprint"]["parameters_m_2s"] > summary["footprint"]["parameters_m"]
    base = {"system": "tiny", "scenes": ["squares"], "quick": False, "simulator_rank": 3,
            "total_seconds": 1.0, "note": None}  # fmt: skip
    earlier = {**base, "rows": [{"method": "LSV-ADMM"}, {"method": "MultiWienerNet", "old": 1}]}
    merged = merge_reports(earlier, {**base, "rows": [summary]})
    assert [r["method"] for r in merged["rows"]] == ["LSV-ADMM", "MultiWienerNet"]
    assert "old" not in merged["rows"][1] and merged["total_seconds"] == 2.0
    with pytest.raises(ValueError, match="its scenes"):
        merge_reports({**earlier, "scenes": ["cells"]}, {**base, "rows": [summary]})
