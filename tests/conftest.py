"""Shared fixtures: small systems that keep the suite fast on a 2-core CPU."""

from __future__ import annotations

import pytest
import torch

from svcode_core.config import SystemConfig

torch.set_num_threads(min(2, torch.get_num_threads()))


@pytest.fixture
def mini_system() -> SystemConfig:
    """The ``cm2-mini`` preset."""
    return SystemConfig.preset("cm2-mini")


@pytest.fixture
def tiny_system() -> SystemConfig:
    """A 48-pixel sub-view system with a 9-pixel kernel, for fast end-to-end tests."""
    from svcode_core.config import _system_from_scale

    base = SystemConfig.preset("cm2-mini")
    system = _system_from_scale(
        "tiny",
        sensor_shape=(60, 80),
        sub_view_size=48,
        pitch=18,
        patch_size=16,
        optics=base.optics.__class__(psf_grid=3, kernel_size=9, airy_radius=1.0,
                                     pupil_samples=32, distortion=0.5),
        rank_tolerance=1e-2,
    )
    return system.validate()


@pytest.fixture
def tiny_weights(tiny_system, tmp_path):
    """A small random SV-CoDe model of ``tiny_system``, saved as ``tiny.safetensors``."""
    from svcode_core.network import ModelConfig, SVCoDe, save_model

    config = ModelConfig(width=4, view_width=2, demix_enc_blocks=(1,), demix_dec_blocks=(1,),
                         recon_enc_blocks=(1,), recon_dec_blocks=(1,), mlp_hidden=8,
                         pe_bands=2)
    torch.manual_seed(0)
    return save_model(tmp_path / "tiny.safetensors", SVCoDe(config.validate()), tiny_system)
