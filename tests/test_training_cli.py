"""``svcode dataset`` and ``svcode train`` end to end on a tiny system."""

from __future__ import annotations

import json

import pytest
import torch

from svcode_core.cli import main
from svcode_core.methods.model_file import load_model
from svcode_core.training import TrainingData


def test_settings_and_zones_keep_their_old_homes():
    """The constants and defaults moved to torch-free modules are the same objects where
    they were, and the lazy ``svcode_core.training`` exports every name it lists."""
    import svcode_core.training as training
    from svcode_core.evaluation import metrics, zones
    from svcode_core.training import configs, loss, settings, trainer

    assert trainer.TrainConfig is settings.TrainConfig is training.TrainConfig
    assert configs.ABLATIONS is settings.ABLATIONS
    assert (metrics.RING_RADIUS, metrics.CENTRE_RADIUS) == (zones.RING_RADIUS,
                                                            zones.CENTRE_RADIUS)
    assert loss.EDGE_STRIP == zones.EDGE_STRIP and loss.RING_RADIUS == zones.RING_RADIUS
    assert set(training.__all__) <= set(dir(training))
    for name in training.__all__:
        assert getattr(training, name).__name__ == name
    with pytest.raises(AttributeError, match="no attribute 'nothing'"):
        training.nothing  # noqa: B018


def test_dataset_then_train(tiny_system, tiny_model_config, tmp_path, capsys):
    system_file = tiny_system.save(tmp_path / "tiny.json")
    data = tmp_path / "data"
    assert main(["dataset", "--system", str(system_file), "--frames", "3", "--out", str(data),
                 "--seed", "5", "--val-fraction", "0.3", "--no-progress"]) == 0
    assert "3 frames of tiny" in capsys.readouterr().out
    assert len(TrainingData(data).val_frames) == 1
    model_file = tmp_path / "model.json"
    model_file.write_text(tiny_model_config.to_json())
    run = tmp_path / "run"
    args = ["train", "--data", str(data), "--out", str(run), "--epochs", "1",
            "--model-config", str(model_file), "--ablation", "no-pe", "--batch-size", "2",
            "--patches-per-epoch", "2", "--val-patches", "2", "--device", "cpu",
            "--mse-weight", "30", "--partial-weight", "3", "--no-progress"]
    assert main(args) == 0
    assert "validation reconstruction PSNR" in capsys.readouterr().out
    state = torch.load(run / "checkpoints" / "epoch-0001.pt", weights_only=True)
    assert json.loads(state["train_config"])["beta"] == 30.0
    assert json.loads(state["train_config"])["partial_weight"] == 3.0
    assert main([*args, "--ssim-weight", "-1"]) == 2
    err = capsys.readouterr().err  # the option's name, not the field's (alpha)
    assert "error: --ssim-weight: must be >= 0, got -1.0" in err and "alpha" not in err
    assert main([*args, "--partial-weight", "-2"]) == 2
    assert "error: --partial-weight: must be >= 0" in capsys.readouterr().err
    model, system = load_model(run / "best.safetensors", tiny_system)
    assert model.model_config.positional_encoding is False
    assert main([*args, "--resume"]) == 0  # nothing left to do, but it loads
    # a preset that is not the dataset's system is refused
    assert main([*args, "--preset", "cm2-mini"]) == 2
    assert "differs from 'cm2-mini'" in capsys.readouterr().err


def test_dataset_objects_choose_the_phantom_kind(tiny_system, tmp_path, capsys):
    system_file = tiny_system.save(tmp_path / "tiny.json")
    args = ["dataset", "--system", str(system_file), "--frames", "2", "--no-progress"]
    assert main([*args, "--out", str(tmp_path / "cells"), "--objects", "isolated-cells"]) == 0
    assert TrainingData(tmp_path / "cells").recipe.object_kind == "isolated-cells"
    with pytest.raises(SystemExit):
        main([*args, "--out", str(tmp_path / "bad"), "--objects", "galaxies"])
    assert "invalid choice: 'galaxies'" in capsys.readouterr().err


def test_train_from_initial_weights(tiny_system, tiny_model_config, tmp_path, capsys):
    from safetensors.torch import load_file

    from svcode_core.methods.model_file import record_extra, save_model
    from svcode_core.network import SVCoDe
    from svcode_core.training import TrainConfig, Trainer

    system_file = tiny_system.save(tmp_path / "tiny.json")
    data = tmp_path / "data"
    assert main(["dataset", "--system", str(system_file), "--frames", "2", "--out", str(data),
                 "--seed", "1", "--val-fraction", "0.5", "--no-progress"]) == 0
    config = tiny_model_config
    torch.manual_seed(3)
    weights = save_model(tmp_path / "start.safetensors", SVCoDe(config), tiny_system)
    record_extra(weights, overlap_check={"overlap": 8})  # as bench/tile_overlap.py --record
    trainer = Trainer(TrainingData(data), tmp_path / "run", config, TrainConfig(epochs=1),
                      init_weights=weights, progress=False)
    stored = load_file(str(weights))
    assert all(torch.equal(stored[k], v) for k, v in trainer.model.state_dict().items())
    with pytest.raises(ValueError, match="another network configuration"):
        Trainer(TrainingData(data), tmp_path / "run", config.replace(mlp_hidden=4),
                TrainConfig(epochs=1), init_weights=weights)

    args = ["train", "--data", str(data), "--out", str(tmp_path / "tuned"), "--epochs", "1",
            "--init", str(weights), "--batch-size", "2", "--patches-per-epoch", "2",
            "--val-patches", "2", "--device", "cpu", "--no-progress"]
    assert main(args) == 0
    tuned, _ = load_model(tmp_path / "tuned" / "best.safetensors", tiny_system)
    assert tuned.model_config == config
    # the measured tile overlap travels with the weights, marked as inherited
    inherited = {"overlap": 8, "inherited_from": "start.safetensors"}
    assert tuned.overlap_check == inherited
    checkpoint, _ = load_model(tmp_path / "tuned" / "checkpoints" / "epoch-0001.safetensors")
    assert checkpoint.overlap_check == inherited
    # fine-tuning that adds the lens context starts from the same function
    wide = Trainer(TrainingData(data), tmp_path / "wide", config.replace(lens_context=True),
                   TrainConfig(epochs=1), init_weights=weights, progress=False).model.eval()
    start, _ = load_model(weights, tiny_system)
    views = torch.rand(2, 81, 16, 16)
    with torch.no_grad():
        torch.testing.assert_close(wide(views, [[0, 0], [8, 16]], 48)[1],
                                   start.eval()(views[:, ::9], [[0, 0], [8, 16]], 48)[1])
    assert main([*args[:4], str(tmp_path / "widened"), *args[5:], "--lens-context"]) == 0
    widened, _ = load_model(tmp_path / "widened" / "best.safetensors", tiny_system)
    assert widened.model_config == config.replace(lens_context=True)
    # and one that lengthens its reach (from that file, whose context crops keep their weights)
    farther = [*args[:4], str(tmp_path / "farther"), *args[5:7], "--init",
               str(tmp_path / "widened" / "best.safetensors"), *args[9:], "--lens-context", "2"]
    assert main(farther) == 0
    far, _ = load_model(tmp_path / "farther" / "best.safetensors", tiny_system)
    assert far.model_config == config.replace(lens_context=True, context_reach=2)
    # a fine-tuning keeps the model file's reach; a shorter one is refused before training
    shorter = [*args[:4], str(tmp_path / "shorter"), *args[5:7], "--init",
               str(tmp_path / "farther" / "best.safetensors"), *args[9:], "--lens-context"]
    assert main(shorter) == 2
    assert "already has the lens context of reach 2" in capsys.readouterr().err
    assert not (tmp_path / "shorter").exists()
    # mirrored padding changes no weights: the file's start under the run's padding
    mirrored = [*args[:4], str(tmp_path / "mirrored"), *args[5:], "--padding", "reflect"]
    assert main(mirrored) == 0
    tuned, _ = load_model(tmp_path / "mirrored" / "best.safetensors", tiny_system)
    assert tuned.model_config == config.replace(padding="reflect")
    assert main([*mirrored[:-1], "mirror"]) == 2
    assert "padding: must be one of ('zeros', 'reflect'), got 'mirror'" in capsys.readouterr().err
    assert main([*args[:7], *args[9:], "--method", "fouriernet", "--padding", "reflect"]) == 2
    assert "--padding applies to SV-CoDe" in capsys.readouterr().err
    assert main([*args, "--method", "fouriernet", "--lens-context"]) == 2
    assert main([*args, "--ablation", "no-pe"]) == 2
    assert "leave out --model-config and --ablation" in capsys.readouterr().err
    assert main([*args, "--method", "fouriernet"]) == 2
    assert "not one for --method fouriernet" in capsys.readouterr().err
    # no model is bundled for this system: the way on, for training
    assert main([*args[:7], "--init", "pretrained", *args[9:]]) == 2
    err = capsys.readouterr().err
    assert "no bundled SV-CoDe model for system 'tiny'" in err and "--init FILE" in err


def test_resume_names_a_damaged_file_and_what_to_do(tiny_system, tiny_model_config, tmp_path,
                                                    capsys):
    import os
    import shutil

    system_file = tiny_system.save(tmp_path / "tiny.json")
    data = tmp_path / "data"
    assert main(["dataset", "--system", str(system_file), "--frames", "2", "--out", str(data),
                 "--seed", "1", "--val-fraction", "0.5", "--no-progress"]) == 0
    model_file = tmp_path / "model.json"
    model_file.write_text(tiny_model_config.to_json())
    run = tmp_path / "run"
    args = ["train", "--data", str(data), "--out", str(run), "--epochs", "1",
            "--model-config", str(model_file), "--batch-size", "2", "--patches-per-epoch", "2",
            "--val-patches", "2", "--device", "cpu", "--no-progress"]
    assert main(args) == 0
    capsys.readouterr()
    shutil.copytree(data, tmp_path / "data.copy")
    shutil.copytree(run, tmp_path / "run.copy")
    checkpoints = run / "checkpoints"

    def halve(path):
        os.truncate(path, path.stat().st_size // 2)

    damages = [
        (checkpoints / "epoch-0001.pt", halve, "is damaged or truncated", "without --resume"),
        (checkpoints / "epoch-0001.safetensors", halve, "is damaged or truncated",
         "without --resume"),
        (checkpoints / "latest.json", lambda p: p.write_text('{"epoch": '),
         "is damaged (Expecting value", "without --resume"),
        (checkpoints / "latest.json", lambda p: p.write_text('{"epoch": 1}'),
         "is damaged (it does not name the checkpoint's weights", "without --resume"),
        (data / "views.npy", halve, "is damaged or truncated", "svcode dataset"),
        (data / "views.npy", lambda p: os.truncate(p, 50), "is damaged or truncated",
         "svcode dataset"),
        (data / "manifest.json", lambda p: p.write_text('{"fo'), "is damaged",
         "svcode dataset"),
    ]  # fmt: skip
    for path, damage, fragment, advice in damages:
        damage(path)
        assert main([*args, "--resume"]) == 2, path
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and "Traceback" not in err, err
        assert f"svcode train: error: {path} {fragment}" in err and advice in err, err
        for folder in (data, run):
            shutil.rmtree(folder)
            shutil.copytree(folder.with_name(folder.name + ".copy"), folder)
    assert main([*args, "--resume"]) == 0  # restored: it resumes


def test_a_dataset_with_a_view_margin_trains_a_model_with_it(tiny_system, tiny_model_config,
                                                             tmp_path, capsys):
    system_file = tiny_system.save(tmp_path / "tiny.json")
    data = tmp_path / "data"
    make = ["dataset", "--system", str(system_file), "--frames", "3", "--out", str(data),
            "--val-fraction", "0.3", "--no-progress", "--view-margin"]
    assert main([*make, "-1"]) == 2
    assert "error: --view-margin: must be >= 0" in capsys.readouterr().err
    assert main([*make, "5"]) == 2  # the tiny system's kernel reaches 4 px
    assert "error: --view-margin: 5 px is beyond the kernel radius of tiny (4 px)" in \
        capsys.readouterr().err
    assert not data.exists()  # refused before anything is written
    assert main([*make, "4"]) == 0
    model_file = tmp_path / "model.json"
    model_file.write_text(tiny_model_config.to_json())
    train = ["train", "--data", str(data), "--epochs", "1", "--model-config", str(model_file),
             "--batch-size", "2", "--patches-per-epoch", "2", "--val-patches", "2",
             "--no-progress", "--out"]
    assert main([*train, str(tmp_path / "a")]) == 0  # the dataset's margin by default
    assert main([*train, str(tmp_path / "b"), "--view-margin", "0"]) == 0
    assert main([*train, str(tmp_path / "c"), "--view-margin", "8"]) == 2
    assert "svcode dataset --view-margin 8" in capsys.readouterr().err
    margins = [load_model(tmp_path / run / "best.safetensors")[0].model_config.view_margin
               for run in "ab"]
    assert margins == [4, 0]
