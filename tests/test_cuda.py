"""CUDA against the CPU, and clean refusals where CUDA is absent.

The ``cuda``-marked tests run each computation on both devices from the same inputs and
weights and compare the results; they are skipped without CUDA (``pytest -m cuda`` selects
them; ``bench/gpu_check.sh`` runs them on a GPU machine). The others run only without CUDA
and check that asking for ``device="cuda"`` fails before any work with a message that says
why.

Tolerances
----------
float32 rounds every operation to a relative ``u = 2**-24 ≈ 6e-8``. The two devices sum in
different orders (oneDNN and pocketfft on the CPU; cuDNN, cuBLAS and cuFFT on the GPU), so
each result carries its own rounding error and their difference is at most the sum of the
two. Measured on the CPU against float64 with the inputs used here, relative to the
result's largest magnitude: network forward 6e-7, forward operator and adjoint 3e-7, 20
LSV-ADMM iterations 8e-7, gradients of a training step 3e-6 (of the largest gradient). Each
tolerance below allows 30–50× that (other summation orders, cuDNN's Winograd and FFT
convolutions) and stays below TF32's rounding of the inputs (``2**-11 ≈ 5e-4``), so a
silent fall to a lower precision fails; the tests ask for full float32 (no TF32) in cuDNN
and cuBLAS, which PyTorch otherwise allows for convolutions on Ampere and later GPUs.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from svcode_core.config import SystemConfig
from svcode_core.methods.base import resolve_device
from svcode_core.methods.baselines.reconstructor import BaselineReconstructor
from svcode_core.methods.learned import MultiWienerConfig, MultiWienerNet
from svcode_core.methods.learned.reconstruct import LearnedReconstructor
from svcode_core.methods.model_file import save_model
from svcode_core.methods.svcode import Reconstructor
from svcode_core.network import ModelConfig, SVCoDe
from svcode_core.physics.cm2 import CM2Operator
from svcode_core.physics.psf_io import model_psfs

CUDA = torch.cuda.is_available()
needs_cuda = pytest.mark.skipif(not CUDA, reason="CUDA is not available")
without_cuda = pytest.mark.skipif(CUDA, reason="CUDA is available: nothing to refuse")

#: max |cuda - cpu| / max |cpu| (module docstring)
NETWORK_TOL = 3e-5
OPERATOR_TOL = 1e-5
ADMM_TOL = 3e-5
GRADIENT_TOL = 1e-4


def relative(got: torch.Tensor | np.ndarray, reference: torch.Tensor | np.ndarray) -> float:
    """max |got - reference| / max |reference|, in float64 on the CPU."""
    got = torch.as_tensor(got).detach().cpu().double()
    reference = torch.as_tensor(reference).detach().cpu().double()
    return float((got - reference).abs().max() / reference.abs().max())


@pytest.fixture
def full_float32():
    """Full float32 in cuDNN and cuBLAS for the test (no TF32), restored afterwards."""
    cudnn, matmul = torch.backends.cudnn, torch.backends.cuda.matmul
    if hasattr(getattr(cudnn, "conv", None), "fp32_precision"):
        # the per-backend API; every cuDNN flag is set so that PyTorch's legacy reads agree
        knobs = (cudnn.conv, cudnn.rnn, matmul)
        saved = [knob.fp32_precision for knob in knobs]
        for knob in knobs:
            knob.fp32_precision = "ieee"
        yield
        for knob, value in zip(knobs, saved, strict=True):
            knob.fp32_precision = value
    else:
        saved = cudnn.allow_tf32, matmul.allow_tf32
        cudnn.allow_tf32 = matmul.allow_tf32 = False
        yield
        cudnn.allow_tf32, matmul.allow_tf32 = saved


def _mini_model() -> SVCoDe:
    torch.manual_seed(0)
    return SVCoDe(ModelConfig.mini())


def _patches(generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """Two 96-pixel patches of nine views at two origins of a 384-pixel sub-view."""
    views = torch.rand(2, 9, 96, 96, generator=generator) * 0.5
    return views, torch.tensor([[0, 0], [144, 96]])


# ------------------------------------------------------------------------ CUDA = CPU
@pytest.mark.cuda
@needs_cuda
def test_network_forward_matches_the_cpu(full_float32):
    model = _mini_model().eval()
    views, origins = _patches(torch.Generator().manual_seed(1))
    with torch.inference_mode():
        cpu = model(views, origins, 384)
        model.to("cuda")
        gpu = model(views.cuda(), origins, 384)
    for got, reference in zip(gpu, cpu, strict=True):
        assert got.device.type == "cuda"
        assert relative(got, reference) < NETWORK_TOL


@pytest.mark.cuda
@needs_cuda
def test_tiled_reconstruction_matches_the_cpu(full_float32):
    """The bundled model over 16 overlapping tiles (batched, blended) on a cm2-mini frame:
    4 × 4 over its 416-px sub-views (384 px and the model's 16-px view margin)."""
    frame = np.random.default_rng(0).uniform(0.0, 0.3, (480, 640)).astype(np.float32)
    options = {"tile_size": 192, "stride": 96, "batch_size": 4, "precision": "fp32"}
    cpu = Reconstructor.pretrained(device="cpu", **options).reconstruct(frame, return_views=True)
    gpu = Reconstructor.pretrained(device="cuda", **options).reconstruct(frame, return_views=True)
    assert gpu.tiles_run == cpu.tiles_run == 16
    assert relative(gpu.reconstruction, cpu.reconstruction) < NETWORK_TOL
    assert relative(gpu.views, cpu.views) < NETWORK_TOL


@pytest.mark.cuda
@needs_cuda
def test_forward_operator_and_adjoint_match_the_cpu():
    system = SystemConfig.preset("cm2-mini")
    psfs = model_psfs(system)
    cpu = CM2Operator.from_psfs(system, psfs, device="cpu")
    gpu = CM2Operator.from_psfs(system, psfs, device="cuda")
    generator = torch.Generator().manual_seed(2)
    x = torch.rand(system.sub_view_size, system.sub_view_size, generator=generator)
    y = torch.rand(*system.padded_shape, generator=generator)
    forward, adjoint = gpu.forward(x.cuda()), gpu.adjoint(y.cuda())
    assert relative(forward, cpu.forward(x)) < OPERATOR_TOL
    assert relative(adjoint, cpu.adjoint(y)) < OPERATOR_TOL
    # the adjoint identity <A x, y> = <x, Aᵀ y> on the GPU itself
    left = float((forward.double() * y.cuda().double()).sum())
    right = float((x.cuda().double() * adjoint.double()).sum())
    assert abs(left - right) <= OPERATOR_TOL * abs(left)


@pytest.mark.cuda
@needs_cuda
def test_lsv_admm_matches_the_cpu():
    """20 iterations, two residual checks (adaptive ρ), from the same noiseless frame."""
    system = SystemConfig.tiny()
    psfs = model_psfs(system)
    generator = torch.Generator().manual_seed(3)
    obj = torch.rand(system.sub_view_size, system.sub_view_size, generator=generator) * 0.5
    frame = CM2Operator.from_psfs(system, psfs).measure(obj).numpy()
    results = {}
    for device in ("cpu", "cuda"):
        operator = CM2Operator.from_psfs(system, psfs, device=device)
        solver = BaselineReconstructor("admm", system, operator=operator, iterations=20,
                                       tolerance=0.0)  # fmt: skip
        estimate = solver.reconstruct_tensor(frame)
        assert estimate.device.type == device
        results[device] = estimate
    assert relative(results["cuda"], results["cpu"]) < ADMM_TOL


@pytest.mark.cuda
@needs_cuda
def test_training_step_matches_the_cpu(full_float32):
    """One step as ``Trainer.train_step`` takes it, in float32 on both devices (the trainer
    adds bf16 autocast on CUDA, which this comparison leaves out): loss, gradients, and the
    weights after a plain gradient step."""
    from svcode_core.training.loss import joint_loss

    generator = torch.Generator().manual_seed(4)
    views, origins = _patches(generator)
    demixed = torch.rand(2, 9, 96, 96, generator=generator) * 0.3
    obj = torch.rand(2, 1, 96, 96, generator=generator) * 0.5
    outcome = {}
    for device in ("cpu", "cuda"):
        model = _mini_model().to(device).train()
        predicted = model(views.to(device), origins, 384)
        loss, _ = joint_loss({"demix": (predicted[0], demixed.to(device)),
                              "recon": (predicted[1], obj.to(device))})  # fmt: skip
        loss.backward()
        grads = torch.cat([p.grad.flatten() for p in model.parameters()])
        torch.optim.SGD(model.parameters(), lr=0.1).step()
        weights = torch.cat([p.detach().flatten() for p in model.parameters()])
        outcome[device] = (loss.detach(), grads, weights)
    (loss_gpu, grads_gpu, weights_gpu), (loss_cpu, grads_cpu, weights_cpu) = (
        outcome["cuda"], outcome["cpu"])
    assert relative(loss_gpu, loss_cpu) < NETWORK_TOL
    assert relative(grads_gpu, grads_cpu) < GRADIENT_TOL
    step = 0.1 * float(grads_cpu.abs().max())  # the largest change the step made
    assert float((weights_gpu.cpu() - weights_cpu).abs().max()) <= GRADIENT_TOL * step + 1e-6


@pytest.mark.cuda
@needs_cuda
def test_a_missing_cuda_device_is_a_clear_error():
    with pytest.raises(ValueError, match="does not exist"):
        resolve_device(f"cuda:{torch.cuda.device_count()}")


# ----------------------------------------------------------------- without CUDA
@pytest.fixture(scope="module")
def tiny() -> SystemConfig:
    return SystemConfig.tiny()


@without_cuda
@pytest.mark.parametrize("name", ["cuda", "cuda:0"])
def test_resolve_device_refuses_cuda(name):
    with pytest.raises(ValueError, match="CUDA is not available"):
        resolve_device(name)


@without_cuda
def test_svcode_refuses_cuda(tiny):
    with pytest.raises(ValueError, match="CUDA is not available"):
        Reconstructor(SVCoDe(ModelConfig.mini()), tiny, device="cuda")


@without_cuda
def test_lsv_admm_refuses_cuda_before_building_the_operator(tiny):
    with pytest.raises(ValueError, match="CUDA is not available"):
        BaselineReconstructor("admm", tiny, device="cuda")


@without_cuda
def test_learned_baselines_refuse_cuda(tiny):
    with pytest.raises(ValueError, match="CUDA is not available"):
        LearnedReconstructor(MultiWienerNet(MultiWienerConfig(), tiny), tiny, device="cuda")


@without_cuda
def test_a_model_file_refuses_cuda(tiny, tmp_path):
    path = save_model(tmp_path / "m.safetensors", SVCoDe(ModelConfig.mini()), tiny)
    with pytest.raises(ValueError, match="CUDA is not available"):
        Reconstructor.from_weights(path, device="cuda")


@without_cuda
def test_the_command_line_refuses_cuda_in_one_line(tmp_path, capsys):
    from svcode_core.cli import main

    status = main(["reconstruct", str(tmp_path / "missing.tif"), "--out",
                   str(tmp_path / "out.tif"), "--device", "cuda"])  # fmt: skip
    err = capsys.readouterr().err.strip().splitlines()
    assert status == 2
    assert len(err) == 1 and "CUDA is not available" in err[0]
