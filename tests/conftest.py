"""Shared fixtures: small systems and models that keep the suite fast on a 2-core CPU."""

from __future__ import annotations

import os

# Idle OpenMP threads sleep instead of spinning (read when torch loads, so before the
# import): with one of the two cores busy with other work, spinning threads made the
# suite several times slower (tests/test_tile_plan.py: 94 s, 47 s with this).
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import pytest  # noqa: E402
import torch  # noqa: E402

from svcode_core.config import SystemConfig
from svcode_core.network import ModelConfig

torch.set_num_threads(min(2, torch.get_num_threads()))


@pytest.fixture(scope="session")
def drain():
    """Run a progress generator to its end: ``drain(generator) -> (yielded, returned)``."""

    def run(generator):
        yielded = []
        while True:
            try:
                yielded.append(next(generator))
            except StopIteration as stop:
                return yielded, stop.value

    return run


@pytest.fixture(scope="session")
def mini_system() -> SystemConfig:
    """The ``cm2-mini`` preset."""
    return SystemConfig.preset("cm2-mini")


@pytest.fixture(scope="session")
def tiny_system() -> SystemConfig:
    """A 48-pixel sub-view system with a 9-pixel kernel, for fast end-to-end tests."""
    return SystemConfig.tiny()


@pytest.fixture(scope="session")
def tiny_model_config() -> ModelConfig:
    """The smallest SV-CoDe: one U-Net level of one block per stage, 4 channels."""
    return ModelConfig(width=4, view_width=2, demix_enc_blocks=(1,), demix_dec_blocks=(1,),
                       recon_enc_blocks=(1,), recon_dec_blocks=(1,), mlp_hidden=8,
                       pe_bands=2).validate()  # fmt: skip


@pytest.fixture(scope="session")
def two_level_model_config(tiny_model_config) -> ModelConfig:
    """``tiny_model_config`` with a second Demixing-Net level and the default encoding
    bands: masks at two U-Net levels."""
    return tiny_model_config.replace(demix_enc_blocks=(1, 1), demix_dec_blocks=(1, 1),
                                     pe_bands=ModelConfig().pe_bands)  # fmt: skip


@pytest.fixture
def tiny_weights(tiny_system, tiny_model_config, tmp_path):
    """A small random SV-CoDe model of ``tiny_system``, saved as ``tiny.safetensors``."""
    from svcode_core.methods.model_file import save_model
    from svcode_core.network import SVCoDe

    torch.manual_seed(0)
    return save_model(tmp_path / "tiny.safetensors", SVCoDe(tiny_model_config), tiny_system)
