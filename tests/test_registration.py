"""Chief-ray self-registration: offsets found from a frame of a drifted instrument."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from svcode_core.config import load_system
from svcode_core.methods.baselines import reconstruct_with_baseline
from svcode_core.methods.baselines.self_registration import register_recording, self_register
from svcode_core.phantoms import make_object
from svcode_core.physics.cm2 import CM2Operator
from svcode_core.physics.departures import Departures
from svcode_core.physics.instrument import departed_system
from svcode_core.physics.registration import register_views, registered_system
from svcode_core.physics.simulate import Simulator

#: an array moved by about a pixel (the tiny system's lenses are 18 px apart)
DRIFT = Departures(name="drift", mla_shift_px=(0.8, -0.5), mla_rotation_deg=1.0,
                   lens_jitter_px=0.4, seed=5)


def _relative(offsets: np.ndarray) -> np.ndarray:
    return offsets - offsets[4]


@pytest.fixture
def drifted(tiny_system):
    obj = make_object("cells", tiny_system.sub_view_size, 1)
    frame = Simulator(tiny_system, departures=DRIFT).simulate(obj, seed=2).measurement
    return tiny_system, frame


def test_nominal_frame_registers_to_zero(tiny_system):
    obj = make_object("cells", tiny_system.sub_view_size, 1)
    frame = Simulator(tiny_system).simulate(obj, noise=False).measurement
    registration = register_views(frame, tiny_system, obj)  # the true object: exact
    np.testing.assert_array_equal(registration.offsets[4], 0.0)
    assert np.abs(registration.offsets).max() < 0.05
    assert set(registration.to_dict()) == {"reference_lens", "lens_offsets_px",
                                           "array_shift_px", "array_rotation_deg"}
    with pytest.raises(ValueError, match="frame is 60×79 px"):
        register_views(frame[:, :79], tiny_system, obj)
    with pytest.raises(ValueError, match="estimate must be 48×48"):
        register_views(frame, tiny_system, obj[:40])


def test_self_registration_finds_the_drift(drifted):
    system, frame = drifted
    truth = _relative(DRIFT.lens_offsets(system))
    registration, moved, psfs = self_register(frame, system)
    error = np.linalg.norm(registration.offsets - truth, axis=1)
    assert error.max() < 0.3, error  # measured 0.24 px (3 rounds); no drift: 0.81 px
    assert np.linalg.norm(truth, axis=1).max() > 0.5
    truth_system, _ = departed_system(system, DRIFT)
    moves = np.asarray(moved.chief_rays) - np.asarray(system.chief_rays)
    true_moves = np.asarray(truth_system.chief_rays) - np.asarray(system.chief_rays)
    assert np.abs(moves - moves[4] - (true_moves - true_moves[4])).max() <= 1
    assert psfs.shape[:2] == (9, system.optics.psf_grid ** 2)


def test_register_recording_writes_a_system_every_method_loads(drifted, tmp_path):
    system, frame = drifted
    moved, registration = register_recording(frame[None], system, tmp_path / "reg")
    loaded = load_system(tmp_path / "reg" / "system.json")
    assert loaded.chief_rays == moved.chief_rays and loaded.psf_model is not None
    record = json.loads((tmp_path / "reg" / "registration.json").read_text())
    assert record == json.loads(json.dumps(registration.to_dict()))
    recon = reconstruct_with_baseline("admm", frame, loaded, iterations=5)
    assert recon.shape == (48, 48) and np.isfinite(recon).all()


def test_registered_system_moves_whole_pixels_into_chief_rays(tiny_system):
    offsets = np.zeros((9, 2))
    offsets[0] = (1.4, -0.6)
    moved, psfs = registered_system(tiny_system, offsets)
    assert moved.chief_rays[0] == (tiny_system.chief_rays[0][0] + 1,
                                   tiny_system.chief_rays[0][1] - 1)
    assert moved.chief_rays[1:] == tiny_system.chief_rays[1:]
    # the same forward model as the pupil model computed at the moved image points
    x = torch.rand(48, 48, dtype=torch.float64)
    from svcode_core.physics.optics import system_psfs

    reference = system_psfs(moved, offsets=offsets - np.rint(offsets))
    np.testing.assert_allclose(psfs, reference)
    frame = CM2Operator.from_psfs(moved, psfs, dtype=torch.float64).forward(x)
    assert torch.isfinite(frame).all()
    with pytest.raises(ValueError, match="offsets must be finite"):
        registered_system(tiny_system, np.full((9, 2), np.nan))


def test_reconstruct_register_option_records_the_moved_system(drifted, tmp_path, capsys):
    import tifffile

    from svcode_core.cli import main

    system, frame = drifted
    system.save(tmp_path / "system.json")
    tifffile.imwrite(tmp_path / "meas.tif", np.stack([frame, frame]))
    out = tmp_path / "out.tif"
    assert main(["reconstruct", str(tmp_path / "meas.tif"), "--method", "admm",
                 "--iterations", "3", "--register", "--out", str(out), "--quiet"]) == 0
    assert "registered: lens offsets up to" in capsys.readouterr().out
    moved = load_system(tmp_path / "out.registered" / "system.json")
    assert moved.chief_rays != system.chief_rays
    from svcode_core.io import read_tiff

    _, recorded, meta = read_tiff(out)
    assert recorded == moved
    assert json.dumps(meta).count("lens_offsets_px") == 1


def test_a_registration_no_rigid_array_explains_is_not_applied(drifted, tmp_path, monkeypatch,
                                                               capsys):
    import tifffile

    import svcode_core.methods.baselines.self_registration as module
    from svcode_core.cli import main
    from svcode_core.physics.registration import Registration

    system, frame = drifted
    residuals = np.zeros((9, 2))
    residuals[3] = (0.0, 1.8)
    found = Registration(residuals.copy(), np.zeros(2), 0.0, residuals, 4)
    monkeypatch.setattr(module, "self_register", lambda *a, **k: (found, system, None))
    with pytest.raises(module.RegistrationRejected, match="lens 3 would move 1.8 px"):
        register_recording(frame[None], system, tmp_path / "reg")
    assert not (tmp_path / "reg").exists()
    system.save(tmp_path / "system.json")
    tifffile.imwrite(tmp_path / "meas.tif", frame)
    assert main(["reconstruct", str(tmp_path / "meas.tif"), "--method", "wiener", "--register",
                 "--out", str(tmp_path / "out.tif"), "--quiet"]) == 0
    assert "warning: self-registration not applied: lens 3" in capsys.readouterr().out


def test_a_model_applies_to_its_system_with_moved_chief_rays(tiny_system, tiny_weights):
    from svcode_core.methods.svcode import Reconstructor

    rays = list(tiny_system.chief_rays)
    rays[0] = (rays[0][0] + 1, rays[0][1] - 1)
    moved = tiny_system.replace(chief_rays=tuple(rays))
    reconstructor = Reconstructor.from_weights(tiny_weights, moved)
    assert reconstructor.system == moved  # sub-views cut at the moved rays
    with pytest.raises(ValueError, match="patch_size"):
        Reconstructor.from_weights(tiny_weights, moved.replace(patch_size=24, patch_stride=12))
