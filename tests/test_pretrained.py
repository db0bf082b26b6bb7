"""The bundled model: found by system, refused clearly when missing, runs the demo."""

from __future__ import annotations

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


@pytest.mark.slow
def test_demo_reconstructs_and_scores(tmp_path, capsys):
    out = tmp_path / "demo"
    assert main(["demo", "--object", "beads", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "SV-CoDe: PSNR" in printed and "s per frame" in printed
    for name in ("demo.png", "measurement.tif", "reconstruction.tif", "system.json"):
        assert (out / name).is_file()
