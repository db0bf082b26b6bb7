"""Models that see each sub-view past its window (``ModelConfig.view_margin``): the data,
the patches, the loss, the trainer and the reconstructor."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
from test_dataset_departures import recipe as departures_recipe
from test_training import RECIPE, TINY_MODEL, tiny_simulator

from svcode_core.config import ConfigError
from svcode_core.methods.model_file import load_model
from svcode_core.methods.svcode import Reconstructor
from svcode_core.network import SVCoDe
from svcode_core.physics.geometry import (
    assemble_frame,
    context_views,
    crop_to_sensor,
    extract_sub_views,
    pad_sensor_frame,
)
from svcode_core.training import PatchDataset, TrainConfig, Trainer, generate_dataset
from svcode_core.training.loss import in_field
from svcode_core.training.tasks import PatchTask

M = 4  # within the tiny system's kernel margin


@pytest.fixture(scope="module")
def both(tmp_path_factory):
    """The same recipe stored without and with a view margin."""
    from conftest import tiny_system

    system = tiny_system.__wrapped__()
    out = tmp_path_factory.mktemp("margin")
    plain = generate_dataset(out / "plain", system, RECIPE, tiny_simulator(system),
                             progress=False)  # fmt: skip
    wide = generate_dataset(out / "wide", system, dataclasses.replace(RECIPE, view_margin=M),
                            tiny_simulator(system), progress=False)  # fmt: skip
    return plain, wide


def test_the_stored_margin_surrounds_the_ordinary_data(both):
    plain, wide = both
    size = plain.system.sub_view_size
    middle = (slice(None), slice(None), slice(M, M + size), slice(M, M + size))
    assert wide.views.shape[-1] == wide.demixed.shape[-1] == size + 2 * M
    np.testing.assert_array_equal(wide.views[middle], plain.views)
    np.testing.assert_array_equal(wide.demixed[middle], plain.demixed)
    np.testing.assert_array_equal(wide.objects, plain.objects)
    np.testing.assert_array_equal(wide.sub_views(1), plain.views[1])
    assert wide.demixed[:, 4, :, :M].sum() > 0  # the centre lens's light past its window
    assert "view_margin" not in plain.manifest["recipe"]  # older manifests still match


def test_registered_targets_run_past_the_window_alike(tiny_system, tmp_path):
    """With departures the targets are moved into the nominal sub-views: enlarged, their
    middle is the ordinary targets wherever neither shift brought in zeros."""
    plan = departures_recipe(tiny_system)
    plain = generate_dataset(tmp_path / "plain", tiny_system, plan, progress=False)
    wide = generate_dataset(tmp_path / "wide", tiny_system,
                            dataclasses.replace(plan, view_margin=M), progress=False)
    size, k = tiny_system.sub_view_size, 3  # k: beyond the lenses' moves (about 1 px)
    inner = slice(M + k, M + size - k)
    np.testing.assert_array_equal(wide.demixed[:, :, inner, inner], plain.demixed[:, :, k:-k, k:-k])
    np.testing.assert_array_equal(wide.views[:, :, M:M + size, M:M + size], plain.views)


def test_patches_tile_the_enlarged_sub_view(both):
    plain, wide = both
    size, p = plain.system.sub_view_size, plain.system.patch_size
    data = PatchDataset(wide, wide.train_frames, noise=False, view_margin=M)
    rows = sorted({int(r) for r, _ in data.origins})
    assert rows[0] == -M and rows[-1] == size + M - p
    for index in range(len(data.origins)):
        item = data[index]
        r, c = item["origin"].tolist()
        frame = wide.train_frames[0]
        np.testing.assert_array_equal(item["views"], wide.views[frame, :, M + r:M + r + p,
                                                                M + c:M + c + p])
        obj = np.pad(wide.objects[frame], M)[M + r:M + r + p, M + c:M + c + p]
        np.testing.assert_array_equal(item["object"][0], obj)  # zero beyond the field


def test_a_model_without_margin_reads_the_same_patches_from_either_store(both):
    plain, wide = both
    ordinary = PatchDataset(plain, plain.train_frames)
    cut = PatchDataset(wide, wide.train_frames)
    for index in (0, 5, len(ordinary) - 1):
        a, b = ordinary[(index, 7)], cut[(index, 7)]  # the same noise seed
        for key in ("views", "demixed", "object", "origin"):
            torch.testing.assert_close(a[key], b[key], rtol=0, atol=0)


def test_a_margin_beyond_the_stored_one_is_refused(both):
    plain, _ = both
    with pytest.raises(ValueError, match="--view-margin 4"):
        PatchDataset(plain, plain.train_frames, view_margin=M)
    with pytest.raises(ConfigError, match="view_margin"):
        TINY_MODEL.replace(view_margin=-1)


def test_lens_context_crops_run_past_the_window_from_the_frame(both):
    """The lens-context crops come from the padded frame that the sub-views tile: past a
    window they hold what the sensor read there."""
    _, wide = both
    system, p = wide.system, wide.system.patch_size
    data = PatchDataset(wide, wide.train_frames, noise=False, lens_context=True,
                        view_margin=M)  # fmt: skip
    frame = wide.read(wide.views[wide.train_frames[0]])
    padded = pad_sensor_frame(crop_to_sensor(assemble_frame(
        frame[:, M:-M, M:-M], system), system), system)
    for index in (0, len(data.origins) - 1):
        item = data[index]
        origin = tuple(item["origin"].tolist())
        assert min(origin) < 0 or max(origin) > system.sub_view_size - p
        torch.testing.assert_close(item["views"], context_views(padded, system, origin, p))
        own = item["views"][::9]  # each lens's own crop: the stored enlarged views
        r, c = (o + M for o in origin)
        torch.testing.assert_close(own, wide.read(wide.views[wide.train_frames[0], :, r:r + p,
                                                             c:c + p]))


def test_the_reconstruction_past_the_field_is_not_scored(both):
    _, wide = both
    task = PatchTask(TINY_MODEL.replace(view_margin=M))
    data = task.dataset(wide, wide.train_frames, True, 0)
    size, p = wide.system.sub_view_size, wide.system.patch_size
    inner = next(i for i, (r, c) in enumerate(data.origins) if 0 <= min(r, c)
                 and max(r, c) <= size - p)  # fmt: skip
    batch = task.collate([data[0], data[inner]])  # the top-left corner, a patch inside

    def ones(views, origins, size):
        return views, torch.ones(len(views), 1, *views.shape[-2:])

    recon, target = task.outputs(ones, batch, wide.system)["recon"]
    assert torch.equal(recon[0, 0, :M], target[0, 0, :M])  # above the field: the target
    assert torch.equal(recon[0, 0, M:, M:], torch.ones_like(recon[0, 0, M:, M:]))
    assert torch.equal(recon[1], torch.ones_like(recon[1]))


def test_fine_tuning_adds_the_margin_to_a_model_without(both, tmp_path):
    _, wide = both
    config = TrainConfig(epochs=1, batch_size=2, patches_per_epoch=4, val_patches=4,
                         edge_weight=4.0, partial_weight=2.0)  # fmt: skip
    first = Trainer(wide, tmp_path / "a", TINY_MODEL, config, progress=False)
    first.fit()
    tuned = Trainer(wide, tmp_path / "b", TINY_MODEL.replace(view_margin=M), config,
                    progress=False, init_weights=tmp_path / "a" / "best.safetensors")
    for mine, theirs in zip(tuned.model.parameters(), first.model.parameters(), strict=True):
        assert torch.equal(mine, theirs)
    tuned.fit()
    model, _ = load_model(tmp_path / "b" / "best.safetensors")
    assert model.model_config.view_margin == M


@pytest.mark.parametrize("lens_context", [False, True])
def test_the_reconstructor_runs_the_enlarged_sub_views(tiny_system, lens_context):
    """The reconstruction is the model's output on the sub-views (with the lens context,
    each lens's crops) cut ``m`` past their windows at origin ``-m``, its middle kept."""
    torch.manual_seed(0)
    model = SVCoDe(TINY_MODEL.replace(view_margin=M, lens_context=lens_context)).eval()
    frame = np.random.default_rng(0).random(tiny_system.sensor_shape, dtype=np.float32)
    rec = Reconstructor(model, tiny_system, precision="fp32", skip_empty=False,
                        normalise_exposure=False, mask_cache_bytes=0)  # fmt: skip
    assert rec.grid.size == tiny_system.sub_view_size + 2 * M
    result = rec(frame, return_views=True)
    padded = pad_sensor_frame(torch.from_numpy(frame), tiny_system)
    size = tiny_system.sub_view_size
    views = (context_views(padded, tiny_system, (-M, -M), size + 2 * M) if lens_context
             else extract_sub_views(padded, tiny_system, M))  # fmt: skip
    with torch.no_grad():
        demixed, recon = model(views[None], torch.tensor([[-M, -M]]), size)
    middle = (slice(M, M + size),) * 2
    torch.testing.assert_close(torch.from_numpy(result.reconstruction), recon[0, 0][middle])
    torch.testing.assert_close(torch.from_numpy(result.views), demixed[0][(slice(None), *middle)])


def test_validation_scores_each_patch_on_its_part_in_the_field(both, tmp_path):
    """A model that reconstructs the object exactly inside the field and anything past it
    has a perfect validation score."""
    _, wide = both
    config = TrainConfig(epochs=1, batch_size=3, patches_per_epoch=4, val_patches=None)
    trainer = Trainer(wide, tmp_path, TINY_MODEL.replace(view_margin=M), config,
                      progress=False)  # fmt: skip
    outputs = trainer.task.outputs

    def exact(net, batch, system):
        stages = outputs(net, batch, system)
        recon, target = stages["recon"]
        return {**stages, "recon": (target + 0.5 * ~in_field(batch["origin"], target.shape[-1],
                                                              system.sub_view_size), target)}

    trainer.task.outputs = exact
    scores = trainer.validate()
    assert scores["val_recon_psnr"] == pytest.approx(100.0)  # the floor of psnr_per_sample
    assert scores["val_recon_ssim"] == pytest.approx(1.0)
