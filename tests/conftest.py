"""Shared fixtures: small systems and models that keep the suite fast on a 2-core CPU."""

from __future__ import annotations

import pytest
import torch

from svcode_core.config import OpticsConfig, SystemConfig, system_from_scale
from svcode_core.network import ModelConfig

torch.set_num_threads(min(2, torch.get_num_threads()))

#: optics of the tiny system: a 3 × 3 PSF grid of 9-pixel kernels
TINY_OPTICS = OpticsConfig(psf_grid=3, kernel_size=9, airy_radius=1.0, pupil_samples=32,
                           distortion=0.5)  # fmt: skip


@pytest.fixture(scope="session")
def mini_system() -> SystemConfig:
    """The ``cm2-mini`` preset."""
    return SystemConfig.preset("cm2-mini")


@pytest.fixture(scope="session")
def tiny_system() -> SystemConfig:
    """A 48-pixel sub-view system with a 9-pixel kernel, for fast end-to-end tests."""
    return system_from_scale("tiny", sensor_shape=(60, 80), sub_view_size=48, pitch=18,
                             patch_size=16, optics=TINY_OPTICS,
                             rank_tolerance=1e-2).validate()  # fmt: skip


@pytest.fixture(scope="session")
def tiny_model_config() -> ModelConfig:
    """The smallest SV-CoDe: one U-Net level of one block per stage, 4 channels."""
    return ModelConfig(width=4, view_width=2, demix_enc_blocks=(1,), demix_dec_blocks=(1,),
                       recon_enc_blocks=(1,), recon_dec_blocks=(1,), mlp_hidden=8,
                       pe_bands=2).validate()  # fmt: skip


@pytest.fixture
def tiny_weights(tiny_system, tiny_model_config, tmp_path):
    """A small random SV-CoDe model of ``tiny_system``, saved as ``tiny.safetensors``."""
    from svcode_core.methods.model_file import save_model
    from svcode_core.network import SVCoDe

    torch.manual_seed(0)
    return save_model(tmp_path / "tiny.safetensors", SVCoDe(tiny_model_config), tiny_system)
