"""The bundled model: found by system, refused clearly when missing, runs the demo."""

from __future__ import annotations

import numpy as np
import pytest

from svcode_core import Reconstructor, SystemConfig
from svcode_core.cli import main
from svcode_core.pretrained import bundled_weights, require_bundled_weights


def test_a_system_without_a_bundled_model_is_a_clear_error(tiny_system):
    assert bundled_weights(tiny_system) is None
    with pytest.raises(FileNotFoundError, match="no bundled SV-CoDe model for system 'tiny'"):
        Reconstructor.pretrained(tiny_system)


def test_the_cm2_mini_model_ships_with_its_card():
    path = require_bundled_weights("cm2-mini")
    assert path.stat().st_size <= 25 * 2**20
    assert path.with_suffix(".md").is_file()
    rec = Reconstructor.pretrained()
    assert rec.system == SystemConfig.preset("cm2-mini")


def test_the_cm2_v2_model_ships_with_its_card_and_reconstructs_a_crop():
    """Light on a 100-px corner of a paper-scale sensor: in 384-px tiles only the tiles
    that see it run (the others are skipped, 0), and they give a finite, non-negative
    image that is not all dark."""
    path = require_bundled_weights("cm2-v2")
    assert path.stat().st_size <= 25 * 2**20 and path.with_suffix(".md").is_file()
    system = SystemConfig.preset("cm2-v2")
    assert len(Reconstructor.pretrained("cm2-v2").grid) > 1  # a frame is planned in tiles
    rec = Reconstructor.pretrained("cm2-v2", tile_size=384, stride=320)
    assert rec.system == system
    assert rec.model.model_config.pool_window == 384  # tiles of any size pool alike
    frame = np.zeros(system.sensor_shape, np.float32)
    frame[40:140, 40:140] = np.random.default_rng(0).random((100, 100)) * 0.8
    result = rec.reconstruct(frame)
    out = result.reconstruction
    assert 1 <= result.tiles_run <= 4 and result.tiles_total == len(rec.grid) == 64
    assert np.isfinite(out).all() and out.min() >= 0 and out.max() > 0
    assert (out > 0).sum() <= result.tiles_run * 384**2  # only where tiles ran


@pytest.mark.slow
def test_demo_reconstructs_and_scores(tmp_path, capsys):
    out = tmp_path / "demo"
    assert main(["demo", "--object", "beads", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "SV-CoDe: PSNR" in printed and "s per frame" in printed
    for name in ("demo.png", "measurement.tif", "reconstruction.tif", "system.json"):
        assert (out / name).is_file()


@pytest.mark.parametrize("long_frame", [False, True])
def test_demo_says_what_it_will_cost_first(tmp_path, capsys, monkeypatch, tiny_system,
                                           tiny_weights, long_frame):
    """The first line names the tiles and a rough time; a frame estimated to be long is
    reconstructed once, timed with its set-up, instead of twice."""
    import svcode_core.cli.demo as demo

    calls = []
    monkeypatch.setattr(Reconstructor, "reconstruct",
                        lambda self, *a, _real=Reconstructor.reconstruct, **k:
                        calls.append(1) or _real(self, *a, **k))  # fmt: skip
    if long_frame:
        monkeypatch.setattr(demo, "WARM_UP_BELOW_SECONDS", 0.0)
    system = tiny_system.save(tmp_path / "tiny.json")
    assert main(["demo", "--system", str(system), "--weights", str(tiny_weights),
                 "--out", str(tmp_path / "demo")]) == 0
    first, *rest = capsys.readouterr().out.splitlines()
    assert "simulating one frame (roughly " in first and "in 1 tile (fp32): roughly" in first
    assert "of reconstruction on this cpu" in first
    assert len(calls) == (1 if long_frame else 2)
    assert ("with its set-up" in "".join(rest)) == long_frame
