"""Training data, patch sampler, loss, trainer, checkpoints and the train/dataset commands."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest
import torch
from test_cm2 import gaussian_psfs

from svcode_core.config import ConfigError, SystemConfig
from svcode_core.evaluation.metrics import field_zones
from svcode_core.methods.learned.config import MultiWienerConfig
from svcode_core.methods.model_file import load_model
from svcode_core.network import ModelConfig
from svcode_core.physics.cm2 import CM2Operator
from svcode_core.physics.geometry import context_views, extract_sub_views
from svcode_core.physics.simulate import Simulator
from svcode_core.training import (
    DataRecipe,
    EpochSampler,
    PatchDataset,
    TrainConfig,
    Trainer,
    TrainingData,
    check_disjoint_view_patches,
    field_weights,
    generate_dataset,
    joint_loss,
    seen_by_every_lens,
    split_frames,
    stage_loss,
    svcode_loss,
)

TINY_MODEL = ModelConfig(
    width=4, view_width=1, demix_enc_blocks=(1,), demix_middle_blocks=1,
    demix_dec_blocks=(1,), recon_enc_blocks=(1,), recon_middle_blocks=1,
    recon_dec_blocks=(1,), mlp_hidden=8, pe_bands=2,
).validate()


RECIPE = DataRecipe(frames=4, seed=3, val_fraction=0.25, object_kind="beads")


def tiny_simulator(system: SystemConfig) -> Simulator:
    return Simulator(system, CM2Operator.from_psfs(system, gaussian_psfs(system), rank=2))


@pytest.fixture(scope="module")
def tiny_data(tmp_path_factory) -> TrainingData:
    from conftest import tiny_system

    system = tiny_system.__wrapped__()
    out = tmp_path_factory.mktemp("data")
    return generate_dataset(out, system, RECIPE, tiny_simulator(system), progress=False)


# ----------------------------------------------------------------------------- dataset
def test_split_is_a_seeded_partition():
    train, val = split_frames(20, 0.2, seed=1)
    assert len(val) == 4 and sorted(train + val) == list(range(20))
    assert split_frames(20, 0.2, seed=1) == (train, val)
    assert split_frames(20, 0.2, seed=2) != (train, val)
    assert len(split_frames(2, 0.01, seed=0)[1]) == 1  # never an empty side


def test_recipe_names_a_phantom_kind():
    with pytest.raises(ValueError, match="object_kind: must be one of beads, cells"):
        DataRecipe(frames=4, object_kind="galaxies").validate()


def test_dataset_contents_and_manifest(tiny_data):
    system = tiny_data.system
    size = system.sub_view_size
    assert tiny_data.views.shape == (4, 9, size, size)
    assert tiny_data.objects.shape == (4, size, size)
    manifest = json.loads((tiny_data.path / "manifest.json").read_text())
    assert manifest["count"] == 4 and manifest["recipe"]["seed"] == 3
    assert sorted(tiny_data.train_frames + tiny_data.val_frames) == [0, 1, 2, 3]
    # stored views are the noiseless sub-views of the stored object
    sim = tiny_simulator(system)
    scene = sim.simulate(np.array(tiny_data.objects[2]), noise=False)
    np.testing.assert_allclose(tiny_data.views[2], scene.views, atol=1e-6)
    np.testing.assert_allclose(tiny_data.demixed[2], scene.demixed, atol=1e-6)
    low, high = manifest["recipe"]["brightness"]
    peaks = tiny_data.objects.reshape(4, -1).max(1)
    assert np.all((peaks >= low - 1e-6) & (peaks <= high + 1e-6))


def test_interrupted_generation_resumes_to_the_same_data(tiny_data, tmp_path):
    system = tiny_data.system
    recipe = RECIPE
    sim = tiny_simulator(system)
    calls = {"n": 0}
    original = sim.simulate

    def failing(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 3:
            raise KeyboardInterrupt
        return original(*args, **kwargs)

    sim.simulate = failing
    with pytest.raises(KeyboardInterrupt):
        generate_dataset(tmp_path, system, recipe, sim, progress=False)
    assert json.loads((tmp_path / "manifest.json").read_text())["count"] == 2
    with pytest.raises(ValueError, match="only 2 of 4"):
        TrainingData(tmp_path)
    assert len(TrainingData(tmp_path, allow_partial=True)) == 2
    sim.simulate = original
    resumed = generate_dataset(tmp_path, system, recipe, sim, progress=False)
    for name in ("views", "demixed", "objects"):
        np.testing.assert_array_equal(getattr(resumed, name), getattr(tiny_data, name))
    with pytest.raises(ValueError, match="another system or recipe"):
        generate_dataset(tmp_path, system, DataRecipe(frames=5, seed=3), sim, progress=False)


# ----------------------------------------------------------------------------- sampler
def test_a_float16_store_gives_the_same_samples_to_its_rounding(tiny_data, tmp_path):
    """--dtype float16: the same frames on half the disk; every sample is read as float32
    and equals the float32 store's to float16 rounding (relative 2^-11, and 2^-24 absolute
    below float16's normal range); a float32 dataset keeps the recipe it was made with."""
    recipe = dataclasses.replace(RECIPE, dtype="float16")
    half = generate_dataset(tmp_path / "half", tiny_data.system, recipe,
                            tiny_simulator(tiny_data.system), progress=False)
    assert half.views.dtype == np.float16 and half.manifest["dtype"] == "float16"
    assert (tmp_path / "half" / "views.npy").stat().st_size < 0.51 * (
        tiny_data.path / "views.npy").stat().st_size
    assert "dtype" not in RECIPE.to_dict() and half.recipe == recipe
    full = PatchDataset(tiny_data, tiny_data.train_frames, noise=False)
    short = PatchDataset(half, half.train_frames, noise=False)
    for index in (0, len(full) - 1):
        a, b = full[index], short[index]
        for key in ("views", "demixed", "object"):
            assert b[key].dtype == torch.float32
            np.testing.assert_allclose(b[key], a[key], rtol=2.0**-11, atol=2.0**-24)
    with pytest.raises(ConfigError, match="dtype: must be one of float32, float16"):
        dataclasses.replace(RECIPE, dtype="float64").validate()


def test_view_patches_of_the_presets_are_disjoint(tiny_system):
    for name in ("cm2-mini", "cm2-v2"):
        system = SystemConfig.preset(name)
        check_disjoint_view_patches(system, system.patch_size)
    pitch = tiny_system.chief_rays[1][1] - tiny_system.chief_rays[0][1]
    check_disjoint_view_patches(tiny_system, pitch)
    with pytest.raises(ValueError, match="lenses 0 and 1"):
        check_disjoint_view_patches(tiny_system, pitch + 1)


def test_patches_line_up_with_the_stored_frames(tiny_data):
    system = tiny_data.system
    data = PatchDataset(tiny_data, tiny_data.train_frames, noise=False)
    p = system.patch_size
    per_frame = len(data.origins)
    assert len(data) == per_frame * len(tiny_data.train_frames)
    starts = sorted({int(r) for r, _ in data.origins})
    assert starts[1] - starts[0] == p // 2 and starts[-1] == system.sub_view_size - p
    for index in (0, per_frame + 7, len(data) - 1):
        item = data[index]
        frame = tiny_data.train_frames[index // per_frame]
        r, c = item["origin"].tolist()
        np.testing.assert_array_equal(item["views"], tiny_data.views[frame, :, r:r + p, c:c + p])
        np.testing.assert_array_equal(item["demixed"],
                                      tiny_data.demixed[frame, :, r:r + p, c:c + p])
        np.testing.assert_array_equal(item["object"][0], tiny_data.objects[frame, r:r + p, c:c + p])


def _edge_patch(data: PatchDataset) -> int:
    """Index of a patch whose views straddle the sensor edge."""
    for index in range(len(data.origins)):
        r, c = data.origins[index]
        inside = data.sensor_mask[:, r:r + data.patch, c:c + data.patch]
        if inside.any() and not inside.all():
            return index
    raise AssertionError("no patch straddles the sensor edge")


def test_noise_is_fresh_and_only_on_the_sensor(tiny_data):
    system = tiny_data.system
    train = PatchDataset(tiny_data, tiny_data.train_frames, fixed_noise=False, seed=1)
    clean = PatchDataset(tiny_data, tiny_data.train_frames, noise=False)
    index = _edge_patch(train)
    r, c = train.origins[index]
    window = torch.zeros(system.padded_shape)
    window[system.sensor_window] = 1
    inside = extract_sub_views(window, system)[:, r:r + train.patch, c:c + train.patch] > 0
    first, second = train[index]["views"], train[index]["views"]
    assert not torch.equal(first, second)  # a fresh draw on every access
    for draw in (first, second):
        assert torch.all(draw[~inside] == 0)  # zero padding stays noiseless
        residual = (draw - clean[index]["views"])[inside]
        assert residual.abs().max() > 0
        assert residual.std() < 0.05  # sensor noise, not garbage
    # an explicit noise seed reproduces a draw; fixed-noise (validation) patches repeat
    assert torch.equal(train[(index, 7)]["views"], train[(index, 7)]["views"])
    val = PatchDataset(tiny_data, tiny_data.val_frames, fixed_noise=True, seed=1)
    assert torch.equal(val[3]["views"], val[3]["views"])
    assert not torch.equal(val[3]["views"], val[4]["views"])


def test_lens_context_patches_share_one_noise_draw(tiny_data):
    clean = PatchDataset(tiny_data, tiny_data.train_frames, noise=False)
    context = PatchDataset(tiny_data, tiny_data.train_frames, noise=False, lens_context=True)
    noisy = PatchDataset(tiny_data, tiny_data.train_frames, seed=1, lens_context=True)
    system = tiny_data.system
    p = system.patch_size
    window = torch.zeros(system.padded_shape)
    window[system.sensor_window] = 1
    for index in (0, len(clean) // 2, len(clean) - 1):
        off_sensor = context_views(window, system, tuple(clean.locate(index)[1]), p) == 0
        views = context[index]["views"]
        assert views.shape == (81, p, p)
        torch.testing.assert_close(views[::9], clean[index]["views"])  # each lens's own crop
        draw = noisy[(index, 7)]["views"]
        assert torch.equal(draw, noisy[(index, 7)]["views"])
        assert not torch.equal(draw, views)
        # lens 0 moved one pitch right reads lens 1's sensor pixels (chief rays a pitch
        # apart): the noise is drawn on the sensor, so both crops carry the same draw
        assert torch.equal(draw[9 * 0 + 5], draw[9 * 1 + 0])
        assert off_sensor.any() and torch.all(draw[off_sensor] == 0)  # padding: no noise


def test_window_crops_are_the_whole_frames_crops(tiny_data):
    # the crops a patch needs are cut from windows of the frame, each read and drawn on
    # its own: noiseless they are the whole frame's crops bit for bit (the same sums in
    # the same order), also where crops overlap (one window) or leave the frame
    clean = PatchDataset(tiny_data, tiny_data.train_frames, noise=False, lens_context=True)
    noisy = PatchDataset(tiny_data, tiny_data.train_frames, seed=1, lens_context=True)
    system, p = tiny_data.system, tiny_data.system.patch_size
    frame = tiny_data.train_frames[0]
    whole = clean.padded_frame(frame, torch.Generator())
    rows, cols = system.padded_shape
    corners = np.array([[0, 0], [3, 5], [-7, 2], [rows - 4, cols - p // 2], [rows + 1, 0],
                        [rows // 2, cols // 2]])  # fmt: skip
    crops = clean.window_crops(frame, corners, p, torch.Generator())
    assert torch.equal(crops, _crops_of(whole, corners, p))
    draw = noisy.window_crops(frame, corners, p, torch.Generator().manual_seed(3))
    # crops 0 and 1 overlap by (p - 3) x (p - 5) pixels: one draw there
    assert torch.equal(draw[0, 3:, 5:], draw[1, : p - 3, : p - 5])
    window = torch.zeros(system.padded_shape)
    window[system.sensor_window] = 1
    off_sensor = _crops_of(window, corners, p) == 0
    assert off_sensor.any() and torch.all(draw[off_sensor] == 0)  # padding and beyond: 0
    assert torch.all(draw[4] == 0)  # wholly below the frame
    # one window over the whole frame is the whole frame's draw, bit for bit: the same
    # pixels read by the same camera from the same random stream
    side = max(rows, cols)
    whole_window = noisy.window_crops(frame, np.zeros((1, 2), int), side,
                                      torch.Generator().manual_seed(4))[0]  # fmt: skip
    drawn = noisy.padded_frame(frame, torch.Generator().manual_seed(4))
    assert torch.equal(whole_window[:rows, :cols], drawn)


def _crops_of(frame, corners, size):
    """Crops of a padded frame at ``corners``, zero outside it: the reference."""
    out = torch.zeros(len(corners), size, size)
    for k, (r, c) in enumerate(corners):
        r0, c0 = max(r, 0), max(c, 0)
        r1, c1 = min(r + size, frame.shape[0]), min(c + size, frame.shape[1])
        if r0 < r1 and c0 < c1:
            out[k, r0 - r : r1 - r, c0 - c : c1 - c] = frame[r0:r1, c0:c1]
    return out


def test_epoch_sampler_is_seeded_and_splits_ranks():
    sampler = EpochSampler(30, 20, seed=4)
    sampler.set_epoch(2)
    draws = list(sampler)
    assert draws == list(sampler) and len({i for i, _ in draws}) == 20
    sampler.set_epoch(3)
    assert list(sampler) != draws
    ranks = [EpochSampler(30, 20, seed=4, rank=k, world_size=2) for k in range(2)]
    for rank in ranks:
        rank.set_epoch(2)
    assert sorted(list(ranks[0]) + list(ranks[1])) == sorted(draws)
    long = EpochSampler(5, 12, seed=0)
    assert len(list(long)) == 12 and len({i for i, _ in long}) == 5


def test_epoch_sampler_runs_share_their_origin():
    frames, origins, group = 10, 6, 4
    size = frames * origins
    sampler = EpochSampler(size, 72, seed=1, group=group, origins=origins)
    draws = [i for i, _ in sampler]
    assert set(draws) == set(range(size))  # 10 frames fill 3 runs of 4: two come twice
    runs = [draws[k : k + group] for k in range(0, len(draws), group)]
    assert all(len({i % origins for i in run}) == 1 for run in runs)
    assert all(len({i // origins for i in run}) == group for run in runs)
    ranks = [EpochSampler(size, 40, seed=1, rank=k, world_size=2, group=group, origins=origins)
             for k in range(2)]
    seen = [list(rank) for rank in ranks]
    single = EpochSampler(size, 40, seed=1, group=group, origins=origins)
    assert len(seen[0]) == len(seen[1]) == 20  # whole runs, alternating between the ranks
    assert sorted(seen[0] + seen[1]) == sorted(single)
    with pytest.raises(ValueError, match="origins"):
        EpochSampler(size, 8, group=2, origins=7)


# -------------------------------------------------------------------------------- loss
@pytest.mark.parametrize("value", [0.0, 1.0])
def test_loss_is_finite_on_flat_patches(value):
    target = torch.full((2, 9, 16, 16), value)
    prediction = torch.full((2, 9, 16, 16), value, requires_grad=True)
    loss = stage_loss(prediction, target)
    loss.backward()
    assert torch.isfinite(loss) and abs(float(loss.detach())) < 1e-6
    assert torch.isfinite(prediction.grad).all()
    opposite = stage_loss(torch.full_like(target, 1 - value), target)
    assert torch.isfinite(opposite) and float(opposite) > 0.9  # MSE 1 plus 1 - SSIM


def test_joint_loss_sums_both_stages():
    gen = torch.Generator().manual_seed(0)
    d, dt = torch.rand(2, 9, 16, 16, generator=gen), torch.rand(2, 9, 16, 16, generator=gen)
    r, rt = torch.rand(2, 1, 16, 16, generator=gen), torch.rand(2, 1, 16, 16, generator=gen)
    total, parts = svcode_loss(d, r, dt, rt)
    assert float(total) == pytest.approx(parts["demix"] + parts["recon"], rel=1e-6)
    assert parts["demix"] == pytest.approx(float(stage_loss(d, dt)))
    with pytest.raises(ValueError, match="at least 11"):
        stage_loss(torch.rand(1, 1, 8, 8), torch.rand(1, 1, 8, 8))


def test_field_weights_mark_the_sub_view_edge_strips():
    size, sub_view, strip = 24, 64, 5
    rows, cols = np.indices((sub_view, sub_view))
    distance = np.minimum.reduce([rows, cols, sub_view - 1 - rows, sub_view - 1 - cols])
    whole = np.where(distance < strip, 4.0, 1.0)  # the sub-view's weights, built directly
    origins = torch.tensor([[0, 0], [20, 40], [40, 17], [20, 20]])
    weights = field_weights(origins, size, sub_view, 4.0, strip=strip)
    assert weights.shape == (4, 1, size, size) and weights.dtype == torch.float32
    for (r, c), crop in zip(origins.tolist(), weights[:, 0].numpy(), strict=True):
        np.testing.assert_array_equal(crop, whole[r : r + size, c : c + size])
    assert (weights[3] == 1).all()  # a crop clear of the edges


def test_field_weights_mark_the_benchmark_ring():
    size, sub_view = 40, 96
    ring = field_zones(sub_view)["ring"]  # the benchmark's own zone
    origins = torch.tensor([[0, 0], [30, 50], [56, 0]])
    weights = field_weights(origins, size, sub_view, edge=3.0, ring=2.0, strip=4)
    rows, cols = np.indices((sub_view, sub_view))
    edge = np.minimum.reduce([rows, cols, sub_view - 1 - rows, sub_view - 1 - cols]) < 4
    whole = np.where(edge, 3.0, 1.0) * np.where(ring, 2.0, 1.0)
    for (r, c), crop in zip(origins.tolist(), weights[:, 0].numpy(), strict=True):
        np.testing.assert_array_equal(crop, whole[r : r + size, c : c + size])
    assert set(np.unique(weights.numpy())) == {1.0, 2.0, 6.0}  # no edge pixel outside the ring


def test_seen_by_every_lens_follows_the_sensor_padding():
    """cm2-mini, checked from its geometry: a sub-view of 384 px at chief rays 144 px
    apart on a 480 x 640 sensor padded by 96 px in rows and 16 in columns. The top lens
    row's sub-view starts 96 px above the sensor, so object rows 0-95 of that lens fall
    off it (and rows 288-383 of the bottom row's); likewise 16 px of columns."""
    system = SystemConfig.preset("cm2-mini")
    seen = seen_by_every_lens(system).numpy()
    size = system.sub_view_size
    pad_r, pad_c = system.padding
    rows, cols = np.indices((size, size))
    expected = ((rows >= pad_r) & (rows < size - pad_r)
                & (cols >= pad_c) & (cols < size - pad_c))  # fmt: skip
    np.testing.assert_array_equal(seen, expected)


def test_partial_weight_multiplies_the_other_weights():
    seen = torch.ones(64, 64, dtype=torch.bool)
    seen[:10] = False
    seen[:, 60:] = False
    origins = torch.tensor([[0, 0], [5, 40], [30, 20]])
    plain = field_weights(origins, 24, 64, edge=3.0, ring=2.0, strip=4)
    weights = field_weights(origins, 24, 64, edge=3.0, ring=2.0, strip=4, partial=5.0,
                            seen_by_all=seen)
    for (r, c), crop, base in zip(origins.tolist(), weights[:, 0], plain[:, 0], strict=True):
        lost = ~seen[r : r + 24, c : c + 24]
        torch.testing.assert_close(crop, base * torch.where(lost, 5.0, 1.0), rtol=0, atol=0)
    assert (weights[2] == plain[2]).all()  # a crop every lens sees
    with pytest.raises(ValueError, match="seen_by_all"):
        field_weights(origins, 24, 64, partial=2.0)


def test_edge_weight_scales_the_squared_error_of_the_edge_only():
    target = torch.zeros(1, 1, 32, 32)
    weights = field_weights(torch.tensor([[0, 0]]), 32, 96, 5.0)
    at_edge, inside = target.clone(), target.clone()
    at_edge[..., :4, 20:24] = 0.5
    inside[..., 20:24, 20:24] = 0.5
    for error, factor in ((at_edge, 5.0), (inside, 1.0)):
        plain = float(stage_loss(error, target, alpha=0.0))
        assert float(stage_loss(error, target, alpha=0.0, weights=weights)) == pytest.approx(
            factor * plain, rel=1e-6)


# ------------------------------------------------------------------------------ trainer
def _trainer(data, out, **changes) -> Trainer:
    config = TrainConfig(**{"epochs": 2, "batch_size": 2, "lr": 1e-3, "patches_per_epoch": 4,
                            "val_patches": 4, **changes})
    return Trainer(data, out, TINY_MODEL, config, progress=False)


def test_one_step_lowers_the_loss_on_a_fixed_batch(tiny_data, tmp_path):
    trainer = _trainer(tiny_data, tmp_path, lr=1e-3)
    items = [trainer.val_set[i] for i in range(2)]  # fixed noise
    batch = {k: torch.stack([it[k] for it in items]) for k in ("views", "demixed", "object",
                                                              "origin")}

    def loss() -> float:
        with torch.no_grad():
            d, r = trainer.model(batch["views"], batch["origin"], tiny_data.system.sub_view_size)
            return float(svcode_loss(d, r, batch["demixed"], batch["object"])[0])

    before = loss()
    step = trainer.train_step(batch)
    assert step["loss"] == pytest.approx(before, rel=1e-5)
    assert loss() < before


def test_non_finite_gradients_stop_training_before_the_update(tiny_data, tmp_path):
    """A step whose gradients are not finite (the loss itself finite) raises and leaves
    the weights as they were: nothing diverged is written over a sound model."""
    trainer = _trainer(tiny_data, tmp_path, compile=False)
    batch = trainer.task.collate([trainer.val_set[i] for i in range(2)])
    before = {k: v.clone() for k, v in trainer.model.state_dict().items()}
    trainer.model.demix.intro.weight.register_hook(lambda grad: grad * math.nan)
    with pytest.raises(FloatingPointError, match="gradients became non-finite at step 0"):
        trainer.train_step(batch)
    after = trainer.model.state_dict()
    assert all(torch.equal(before[k], after[k]) for k in before)


def test_bf16_training_step_runs_the_forward_in_bf16(tiny_data, tmp_path):
    """``precision="bf16"`` on the CPU: the stages come out in bf16 and the step's loss
    (computed in float32) is the float32 loss to bf16's rounding: 8 significant bits,
    2⁻⁸ relative per operation, a few percent through the network."""
    fp32, bf16 = (_trainer(tiny_data, tmp_path / p, precision=p) for p in ("fp32", "bf16"))
    bf16.model.load_state_dict(fp32.model.state_dict())
    batch = fp32.task.collate([fp32.val_set[i] for i in range(2)])
    with torch.no_grad():
        assert bf16._forward(bf16.net, batch, bf16.autocast)["recon"][0].dtype == torch.bfloat16
        assert fp32._forward(fp32.net, batch, fp32.autocast)["recon"][0].dtype == torch.float32
    assert bf16.train_step(batch)["loss"] == pytest.approx(fp32.train_step(batch)["loss"],
                                                           rel=0.05)
    with pytest.raises(ValueError, match="precision: must be one of auto, fp32, bf16"):
        TrainConfig(precision="fp16").validate()


@pytest.mark.parametrize("native", [True, False])
def test_the_best_model_file_records_its_bf16_check(tiny_data, tmp_path, monkeypatch, native):
    """With bf16 units the best epoch is validated again in bf16 and the PSNR it loses is
    written into best.safetensors, which precision="auto" reads; without them, nothing."""
    from svcode_core.methods import svcode
    from svcode_core.methods.model_file import read_model_metadata
    from svcode_core.training import trainer as module

    copies = []  # on the CPU the check runs the network as reconstructions do: features_in
    features_in = svcode.features_in
    monkeypatch.setattr(svcode, "features_in", lambda *a: copies.append(a) or features_in(*a))
    monkeypatch.setattr(module, "native_bf16", lambda device: native)
    trainer = _trainer(tiny_data, tmp_path, epochs=1)
    trainer.fit()
    assert len(copies) == int(native)
    extra = read_model_metadata(tmp_path / "best.safetensors")["extra"]
    if not native:
        assert "precision_check" not in extra
        return
    fp32 = trainer.best["val_recon_psnr"]
    bf16 = trainer.validate(bf16=True)["val_recon_psnr"]
    assert extra["precision_check"]["bf16"]["loss_db"] == pytest.approx(fp32 - bf16, abs=1e-4)
    assert "4 validation patches" in extra["precision_check"]["bf16"]["measured_on"]


def test_resume_may_change_compile_but_not_precision(tiny_data, tmp_path, monkeypatch):
    # nothing is compiled (resuming a finished run runs no step): no compiler needed
    monkeypatch.setattr("svcode_core.training.trainer._cxx_compiler", lambda: "c++")
    _trainer(tiny_data, tmp_path).fit()
    assert _trainer(tiny_data, tmp_path, compile=True).fit(resume=True)[-1]["epoch"] == 2
    with pytest.raises(ValueError, match=r"differs in \['precision'\]"):
        _trainer(tiny_data, tmp_path, precision="bf16").fit(resume=True)


def test_bf16_compiled_on_a_cpu_is_warned_about(tiny_data, tmp_path, monkeypatch):
    monkeypatch.setattr("svcode_core.training.trainer._cxx_compiler", lambda: "c++")
    with pytest.warns(UserWarning, match="256-bit code"):
        _trainer(tiny_data, tmp_path, compile=True, precision="bf16")


def test_compile_without_a_cxx_compiler_is_refused_at_once(tiny_data, tmp_path, monkeypatch):
    from torch._inductor import config

    monkeypatch.setattr(config.cpp, "cxx", ("no-such-c++-compiler",))
    with pytest.raises(RuntimeError, match="needs a C.. compiler"):
        _trainer(tiny_data, tmp_path, compile=True)


def test_edge_and_ring_weights_enter_the_training_loss(tiny_data, tmp_path):
    trainer = _trainer(tiny_data, tmp_path, edge_weight=3.0, ring_weight=2.0)
    items = [trainer.val_set[i] for i in range(2)]
    batch = trainer.task.collate(items)
    with torch.no_grad():
        d, r = trainer.model(batch["views"], batch["origin"], tiny_data.system.sub_view_size)
    weights = field_weights(batch["origin"], r.shape[-1], tiny_data.system.sub_view_size, 3.0,
                            ring=2.0)
    expected = float(joint_loss({"demix": (d, batch["demixed"]), "recon": (r, batch["object"])},
                                weights=weights)[0])
    assert trainer.train_step(batch)["loss"] == pytest.approx(expected, rel=1e-5)
    assert _trainer(tiny_data, tmp_path / "plain")._loss_weights(batch) is None
    partial = _trainer(tiny_data, tmp_path / "partial", partial_weight=4.0)
    seen = seen_by_every_lens(tiny_data.system)
    expected = field_weights(batch["origin"], r.shape[-1], tiny_data.system.sub_view_size,
                             partial=4.0, seen_by_all=seen)
    torch.testing.assert_close(partial._loss_weights(batch), expected, rtol=0, atol=0)
    assert (~seen).any()  # the tiny system's sub-view does lose pixels off the sensor


def test_resume_continues_exactly(tiny_data, tmp_path, monkeypatch):
    reference = _trainer(tiny_data, tmp_path / "a")
    history = reference.fit()
    assert [r["epoch"] for r in history] == [1, 2]
    run = tmp_path / "b"
    interrupted = _trainer(tiny_data, run)
    original = Trainer.train_epoch

    def stop_in_second_epoch(self, epoch):
        if epoch == 1:
            raise KeyboardInterrupt
        return original(self, epoch)

    monkeypatch.setattr(Trainer, "train_epoch", stop_in_second_epoch)
    with pytest.raises(KeyboardInterrupt):
        interrupted.fit()
    monkeypatch.setattr(Trainer, "train_epoch", original)
    torch.manual_seed(123)  # the global RNG state is restored from the checkpoint
    resumed = _trainer(tiny_data, run)
    assert resumed.fit(resume=True)[-1]["epoch"] == 2
    assert resumed.step_losses == reference.step_losses  # identical next steps
    for name, value in reference.model.state_dict().items():
        assert torch.equal(value, resumed.model.state_dict()[name]), name
    assert resumed.optimizer.state_dict()["state"].keys() == \
        reference.optimizer.state_dict()["state"].keys()
    assert sorted(p.name for p in (run / "checkpoints").iterdir()) == [
        "epoch-0002.pt", "epoch-0002.safetensors", "latest.json"]
    for name in ("log.csv", "log.json", "loss.png", "best.safetensors"):
        assert (run / name).stat().st_size > 0
    model, system = load_model(run / "best.safetensors", tiny_data.system)
    assert model.model_config == TINY_MODEL
    with pytest.raises(ValueError, match="differs in"):
        _trainer(tiny_data, run, lr=5e-4).fit(resume=True)
    with pytest.raises(FileNotFoundError, match="no checkpoint"):
        _trainer(tiny_data, tmp_path / "c").fit(resume=True)


def test_a_resume_writes_back_best_weights_left_out_of_a_kept_state(tiny_data, tmp_path):
    """A resume state kept without best.safetensors (its best epoch is the checkpoint's:
    ``snapshot.sh RUN DEST running``) gets it back on resuming, the same weights and
    metadata; nothing else is written when no epoch is left to train."""
    from safetensors import safe_open

    run = tmp_path / "run"
    _trainer(tiny_data, run, epochs=1).fit()
    best = run / "best.safetensors"
    with safe_open(str(best), "pt") as kept:
        tensors = {name: kept.get_tensor(name) for name in kept.keys()}
        metadata = kept.metadata()
    best.unlink()
    assert _trainer(tiny_data, run, epochs=1).fit(resume=True)[-1]["epoch"] == 1
    with safe_open(str(best), "pt") as again:
        assert again.metadata() == metadata
        for name, value in tensors.items():
            assert torch.equal(again.get_tensor(name), value), name


def test_resume_from_a_checkpoint_older_than_a_config_field(tiny_data, tmp_path):
    """A field added after a checkpoint was written compares at its default."""
    run = tmp_path / "run"
    _trainer(tiny_data, run).fit()
    state_file = run / "checkpoints" / "epoch-0002.pt"
    state = torch.load(state_file, weights_only=True)
    for key in ("model_config", "train_config"):  # as written before pool_window, warmup_steps
        stored = json.loads(state[key])
        stored.pop("pool_window" if key == "model_config" else "warmup_steps")
        state[key] = json.dumps(stored)
    torch.save(state, state_file)
    assert _trainer(tiny_data, run).fit(resume=True)[-1]["epoch"] == 2
    pooled = dataclasses.replace(TINY_MODEL, pool_window=16)
    with pytest.raises(ValueError, match=r"differs in \['pool_window'\]"):
        Trainer(tiny_data, run, pooled, TrainConfig(epochs=2, batch_size=2, lr=1e-3,
                                                   patches_per_epoch=4, val_patches=4),
                progress=False).fit(resume=True)


def test_too_few_patches_for_a_batch(tiny_data, tmp_path):
    with pytest.raises(ValueError, match="make no batch"):
        _trainer(tiny_data, tmp_path, patches_per_epoch=1, batch_size=2)


def test_patch_size_sets_the_training_patches(tiny_data, tmp_path):
    p = tiny_data.system.patch_size - 4
    trainer = _trainer(tiny_data, tmp_path, patch_size=p, batch_size=2)
    for samples in (trainer.train_set, trainer.val_set):
        starts = sorted({int(r) for r, _ in samples.origins})
        assert starts[1] - starts[0] == p // 2 and samples[0]["views"].shape[-1] == p
    trainer.train_step(trainer.task.collate([trainer.train_set[i] for i in (0, 1)]))
    with pytest.raises(ValueError, match="patch_size: MultiWienerNet trains on whole frames"):
        Trainer(tiny_data, tmp_path / "mwn", MultiWienerConfig(),
                TrainConfig(patch_size=p), progress=False)  # fmt: skip


def test_learning_rate_warms_up_then_anneals(tiny_data, tmp_path):
    trainer = _trainer(tiny_data, tmp_path, lr=1e-3, warmup_steps=2, min_lr_ratio=0.1)
    schedule = trainer.scheduler.lr_lambdas[0]
    factors = [schedule(t) for t in range(trainer.config.epochs * trainer.steps_per_epoch)]
    assert factors[:2] == [0.5, 1.0]  # linear warm-up to the peak
    assert all(a >= b for a, b in zip(factors[1:], factors[2:], strict=False))
    assert schedule(10**6) == pytest.approx(0.1)  # the floor
    assert trainer.optimizer.param_groups[0]["lr"] == pytest.approx(5e-4)
