"""One prepared GPU check: the CUDA tests, paper-scale timings and one report.

With CUDA, in this order, each section on its own (a failure is reported and the next
section runs) within a global time budget (a section that no longer fits is skipped):

* the CUDA-marked tests (``pytest -m cuda tests/test_cuda.py``);
* a simulated ``cm2-v2`` frame (paper scale) and a ``cm2-mini`` frame (``svcode simulate``);
* SV-CoDe on the whole ``cm2-v2`` frame: ``svcode reconstruct --device cuda`` in fp32 and
  bf16, then in-process per-frame timings, with the reference-width network at random
  weights saved to a model file (no ``cm2-v2`` model is bundled; the weights do not change
  the work);
* SV-CoDe with the bundled ``cm2-mini`` model on the ``cm2-mini`` frame, and how far the
  CUDA results (fp32, bf16) lie from the CPU's;
* SV-CoDe training throughput at the paper's patch size under bf16 autocast (patches per
  second and ``torch.cuda.max_memory_allocated`` per batch size);
* MultiWienerNet and SV-FourierNet per ``cm2-v2`` frame (random filters and weights);
* LSV-ADMM iterations on the ``cm2-v2`` frame.

Without CUDA it says so, checks that every CUDA code path refuses cleanly (a
``ValueError`` naming CUDA from the Python API, exit status 2 with a one-line message from
the command line), runs the refusal tests of ``tests/test_cuda.py`` and writes a report that
says no GPU ran it. ``--smoke-cpu`` instead runs the GPU sections on the CPU at small scale
(the ``tiny`` system for the paper-scale ones), to check this script where no GPU is at hand;
its figures are not GPU figures.

Exit status: 0 when every section that ran passed, 1 otherwise.

Run: ``bash bench/gpu_check.sh`` (installs what the GPU machine lacks, then runs this), or
``python bench/gpu_check.py [--budget SECONDS] [--out FILE] [--work DIR] [--smoke-cpu]``.
"""

from __future__ import annotations

import argparse
import contextlib
import datetime
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
SRC = ROOT / "src"
sys.path.insert(0, str(SRC))  # the checked-out code, installed or not
os.environ["PYTHONPATH"] = os.pathsep.join(filter(None, [str(SRC), os.environ.get("PYTHONPATH")]))

import numpy as np  # noqa: E402
import tifffile  # noqa: E402
import torch  # noqa: E402

from svcode_core.config import SystemConfig  # noqa: E402
from svcode_core.network import ModelConfig, SVCoDe  # noqa: E402

REPORT = ROOT / "bench" / "results" / "gpu.md"
MIB = 2**20


# --------------------------------------------------------------------------- the run
@dataclass
class Section:
    """One guarded part of the check and what it found."""

    title: str
    run: Callable[[Check], list[str]]
    needs_s: float  # the least time left at which it is started
    status: str = "not run"
    seconds: float = 0.0
    lines: list[str] = field(default_factory=list)


class Check:
    """What the sections share: options, clock, scratch folder, device and scenes."""

    def __init__(self, args: argparse.Namespace, work: Path) -> None:
        self.args = args
        self.work = work
        self.start = time.perf_counter()
        self.cuda = torch.cuda.is_available() and not args.smoke_cpu
        self.device = "cuda" if self.cuda else "cpu"
        self.smoke = args.smoke_cpu
        self.frames: dict[str, Path] = {}
        if self.smoke:  # the tiny system stands in for cm2-v2
            self.big = SystemConfig.tiny()
            self.big_spec = str(self.big.save(work / "tiny.json"))
        else:
            self.big = SystemConfig.preset("cm2-v2")
            self.big_spec = "cm2-v2"

    def remaining(self) -> float:
        return self.args.budget - (time.perf_counter() - self.start)

    def sync(self) -> None:
        if self.cuda:
            torch.cuda.synchronize()

    def reset_peak(self) -> None:
        if self.cuda:
            torch.cuda.empty_cache()
            torch.cuda.reset_peak_memory_stats()

    def peak(self) -> str:
        return f"{torch.cuda.max_memory_allocated() / MIB:.0f}" if self.cuda else "n/a"

    def cli(self, *argv: str, timeout: float | None = None) -> tuple[int, float, str, str]:
        """``python -m svcode_core.cli ARGV`` → (status, seconds, stdout, stderr)."""
        timeout = max(1.0, self.remaining()) if timeout is None else timeout
        start = time.perf_counter()
        done = subprocess.run([sys.executable, "-m", "svcode_core.cli", *argv], cwd=ROOT,
                              capture_output=True, text=True, timeout=timeout)
        return done.returncode, time.perf_counter() - start, done.stdout, done.stderr


def _lines(text: str) -> list[str]:
    return [line for line in text.strip().splitlines() if line.strip()]


def _cli_summary(stdout: str) -> str:
    """The ``reconstructed ...`` line of ``svcode reconstruct``, without the output path."""
    found = [line for line in _lines(stdout) if line.startswith("reconstructed")]
    return found[-1].split(" -> ")[0] if found else ""


def _relative(a: np.ndarray, b: np.ndarray) -> float:
    """max |a - b| / max |b|."""
    scale = float(np.abs(b).max())
    return float(np.abs(a.astype(np.float64) - b).max()) / scale if scale else 0.0


# ------------------------------------------------------------------------ sections
def environment(check: Check) -> list[str]:
    lines = [f"- torch {torch.__version__}, Python {platform.python_version()}, "
             f"{os.cpu_count()} CPU cores"]
    if check.cuda:
        props = torch.cuda.get_device_properties(0)
        lines += [
            f"- device: **{torch.cuda.get_device_name(0)}**, {props.total_memory / 2**30:.0f} "
            f"GiB, compute capability {props.major}.{props.minor}, "
            f"{torch.cuda.device_count()} visible",
            f"- CUDA {torch.version.cuda}, cuDNN {torch.backends.cudnn.version()}",
            f"- float32 convolutions: {_conv_precision()} (PyTorch's default, left as is: "
            "the fp32 timings are what a user gets)",
        ]
    else:
        lines.append("- device: CPU (" + ("--smoke-cpu" if check.smoke else
                                          "CUDA is not available") + ")")
    return lines


def _conv_precision() -> str:
    conv = getattr(torch.backends.cudnn, "conv", None)
    if conv is not None and hasattr(conv, "fp32_precision"):
        return f"cudnn.conv.fp32_precision = {conv.fp32_precision!r}"
    return f"cudnn.allow_tf32 = {torch.backends.cudnn.allow_tf32}"


def cuda_tests(check: Check) -> list[str]:
    """The CUDA-marked tests with CUDA, the refusal tests without."""
    marker = "cuda" if check.cuda or check.smoke else "not cuda"
    # the ini's warning filters name an optional package (pydantic) that a bare machine
    # lacks, which older pytest refuses (newer warns); one filter that needs no import
    # stands in for them (the ones they silence are DeprecationWarnings)
    command = [sys.executable, "-m", "pytest", "-m", marker, "-q", "tests/test_cuda.py",
               "-o", "filterwarnings=ignore::DeprecationWarning", "-p", "no:cacheprovider"]
    start = time.perf_counter()
    done = subprocess.run(command, cwd=ROOT, capture_output=True, text=True,
                          timeout=max(1.0, check.remaining()))
    seconds = time.perf_counter() - start
    output = _lines(done.stdout + done.stderr)
    lines = [f"`pytest -m \"{marker}\" -q tests/test_cuda.py`: exit {done.returncode} in "
             f"{seconds:.0f} s: {output[-1] if output else '(no output)'}"]
    if done.returncode != 0:
        print("\n".join(output[-40:]))
        failed = [line for line in output if line.startswith(("FAILED", "ERROR"))]
        lines += [f"- {line}" for line in failed[:20]]
        raise RuntimeError("; ".join(lines))
    return lines


def scenes(check: Check) -> list[str]:
    """One simulated frame per system, as a user makes it."""
    lines = ["| system | object | seconds | frame |", "|---|---|---|---|"]
    for name, spec in (("big", check.big_spec), ("mini", "cm2-mini")):
        out = check.work / f"scene-{name}"
        source = ["--system", spec] if spec.endswith(".json") else ["--preset", spec]
        status, seconds, _, err = check.cli("simulate", *source, "--object", "cells",
                                            "--seed", "0", "--out", str(out))
        if status != 0:
            raise RuntimeError(f"svcode simulate {spec}: exit {status}: {err.strip()[-500:]}")
        check.frames[name] = out / "measurement.tif"
        shape = tifffile.imread(check.frames[name]).shape
        lines.append(f"| {Path(spec).stem} | cells | {seconds:.1f} | {shape[0]}×{shape[1]} |")
    return lines


def _frame(check: Check, name: str) -> np.ndarray:
    if name not in check.frames:
        raise RuntimeError("no simulated frame (the scenes section did not run)")
    return tifffile.imread(check.frames[name])


def _timed_frames(rec, frame: np.ndarray, sync: Callable[[], None], repeats: int = 1):
    """A warm-up frame (kernels chosen, masks cached), then ``repeats`` timed ones:
    (seconds per frame, the last result)."""
    rec.reconstruct(frame)
    sync()
    start = time.perf_counter()
    for _ in range(repeats):
        result = rec.reconstruct(frame)
    sync()
    return (time.perf_counter() - start) / repeats, result


def svcode_paper(check: Check) -> list[str]:
    """SV-CoDe, reference width, on the whole paper-scale frame."""
    from svcode_core.methods.model_file import save_model
    from svcode_core.methods.svcode import Reconstructor

    frame = _frame(check, "big")
    torch.manual_seed(0)
    model = SVCoDe(ModelConfig.reference())
    count = sum(p.numel() for p in model.parameters())
    weights = save_model(check.work / "reference.safetensors", model, check.big,
                         extra={"note": "random weights, for timing"})
    del model
    lines = [f"Reference-width network ({ModelConfig.reference().width} channels, "
             f"{count / 1e6:.2f} M parameters) at random weights; one "
             f"{check.big.sensor_shape[0]}×{check.big.sensor_shape[1]} frame.", "",
             "`svcode reconstruct` (a fresh process: start-up, model and frame loading, "
             "default tiling planned within 1 GiB):", "",
             "| precision | exit | wall (s) | its summary |", "|---|---|---|---|"]
    failures = []
    for precision in ("fp32", "bf16"):
        out = check.work / f"svcode-big-{precision}.tif"
        status, seconds, stdout, err = check.cli(
            "reconstruct", str(check.frames["big"]), "--weights", str(weights), "--device",
            check.device, "--precision", precision, "--quiet", "--out", str(out))
        summary = _cli_summary(stdout) if status == 0 else " ".join(err.split())[-300:]
        lines.append(f"| {precision} | {status} | {seconds:.1f} | {summary} |")
        if status != 0:
            failures.append(f"svcode reconstruct {precision}: exit {status}")
        elif not np.isfinite(tifffile.imread(out)).all():
            failures.append(f"svcode reconstruct {precision}: non-finite output")
    lines += ["", "In-process (`Reconstructor.from_weights`): a warm-up frame, then one timed; "
              "stages summed over the frame:", "",
              "| precision | tile budget | tile / stride × batch | tiles run / skipped | "
              "s per frame | model | prepare | blend | peak GPU MiB |",
              "|---|---|---|---|---|---|---|---|---|"]
    for precision, budget in (("fp32", 1), ("bf16", 1), ("fp32", 16), ("bf16", 16)):
        if check.remaining() < 30:
            lines.append(f"| {precision} | {budget} GiB | skipped: time budget | | | | | | |")
            continue
        check.reset_peak()
        rec = Reconstructor.from_weights(weights, device=check.device, precision=precision,
                                         tile_memory_bytes=budget * 2**30)
        seconds, result = _timed_frames(rec, frame, check.sync)
        t = result.timings
        grid = rec.grid
        lines.append(f"| {precision} | {budget} GiB | {grid.patch} / {grid.stride} × "
                     f"{rec.batch_size} | {result.tiles_run} / {result.tiles_skipped} | "
                     f"{seconds:.2f} | {t['model']:.2f} | {t['prepare']:.2f} | "
                     f"{t['blend']:.2f} | {check.peak()} |")
        del rec, result
    if failures:
        raise RuntimeError("; ".join(failures) + "\n" + "\n".join(lines))
    return lines


def svcode_mini(check: Check) -> list[str]:
    """The bundled cm2-mini model: command line, per-frame times, CUDA against the CPU."""
    from svcode_core.methods.svcode import Reconstructor

    frame = _frame(check, "mini")
    lines = ["| run | exit | wall (s) | its summary |", "|---|---|---|---|"]
    failures = []
    for precision in ("fp32", "bf16"):
        out = check.work / f"svcode-mini-{precision}.tif"
        status, seconds, stdout, err = check.cli(
            "reconstruct", str(check.frames["mini"]), "--device", check.device, "--precision",
            precision, "--quiet", "--out", str(out))
        summary = _cli_summary(stdout) if status == 0 else " ".join(err.split())[-300:]
        lines.append(f"| `svcode reconstruct` {precision} | {status} | {seconds:.1f} | "
                     f"{summary} |")
        if status != 0:
            failures.append(f"svcode reconstruct {precision}: exit {status}")
    lines += ["", "In-process, a warm-up frame then three timed; difference: max |x - x_cpu| / "
              "max |x_cpu| against the CPU's fp32 reconstruction:", "",
              "| device | precision | s per frame | tiles run | difference | peak GPU MiB |",
              "|---|---|---|---|---|---|"]
    cpu = Reconstructor.pretrained(device="cpu", precision="fp32")
    cpu_seconds, reference = _timed_frames(cpu, frame, lambda: None)
    lines.append(f"| cpu | fp32 | {cpu_seconds:.2f} | {reference.tiles_run} | 0 | n/a |")
    for precision in ("fp32", "bf16") if check.cuda else ():
        check.reset_peak()
        rec = Reconstructor.pretrained(device=check.device, precision=precision)
        seconds, result = _timed_frames(rec, frame, check.sync, repeats=3)
        difference = _relative(result.reconstruction, reference.reconstruction)
        lines.append(f"| {check.device} | {precision} | {seconds:.3f} | {result.tiles_run} | "
                     f"{difference:.1e} | {check.peak()} |")
        del rec
    if failures:
        raise RuntimeError("; ".join(failures) + "\n" + "\n".join(lines))
    return lines


def training(check: Check) -> list[str]:
    """SV-CoDe training steps at the paper's patch size, as ``Trainer.train_step`` runs
    them (bf16 autocast on CUDA, loss in float32, Adam, gradient clipping), on random
    patches at random origins of the patch grid."""
    system = check.big
    size, patch, stride = system.sub_view_size, system.patch_size, system.patch_stride
    config = ModelConfig.reference()
    torch.manual_seed(0)
    model = SVCoDe(config).to(check.device)
    optimizer = torch.optim.Adam(model.parameters(), lr=1e-4)
    rng = np.random.default_rng(0)
    lines = [f"Reference-width network, {patch}-pixel patches (`{system.name}`), "
             f"bf16 autocast: {check.cuda}; 2 warm-up steps, then timed steps:", "",
             "| batch | steps | s per step | patches / s | peak GPU MiB |", "|---|---|---|---|---|"]
    batches = (1, 2) if check.smoke else (1, 2, 4, 8, 16)
    for batch in batches:
        if check.remaining() < 20:
            lines.append(f"| {batch} | skipped: time budget | | | |")
            break
        check.reset_peak()
        tensors = (torch.rand(batch, 9 * config.views_per_lens, patch, patch,
                              device=check.device) * 0.3,  # views
                   torch.rand(batch, 9, patch, patch, device=check.device) * 0.3,  # demixed
                   torch.rand(batch, 1, patch, patch, device=check.device) * 0.5)  # object
        places = (size - patch) // stride + 1
        draw = [torch.as_tensor(rng.integers(0, places, (batch, 2)) * stride)
                for _ in range(12)]
        try:
            for origins in draw[:2]:
                _train_step(model, optimizer, tensors, origins, size, check.cuda)
            check.sync()
            steps, start = 0, time.perf_counter()
            for origins in draw[2:]:
                _train_step(model, optimizer, tensors, origins, size, check.cuda)
                steps += 1
                if steps >= 3 and time.perf_counter() - start > 5:
                    break
            check.sync()
        except torch.cuda.OutOfMemoryError:
            lines.append(f"| {batch} | out of memory | | | {check.peak()} |")
            break
        finally:
            del tensors
        seconds = (time.perf_counter() - start) / steps
        lines.append(f"| {batch} | {steps} | {seconds:.3f} | {batch / seconds:.1f} | "
                     f"{check.peak()} |")
    return lines


def _train_step(model: torch.nn.Module, optimizer: torch.optim.Optimizer,
                tensors: tuple[torch.Tensor, ...], origins: torch.Tensor, size: int,
                bf16: bool) -> None:
    from svcode_core.training.loss import joint_loss

    views, demixed, obj = tensors
    model.train()
    with torch.autocast(views.device.type, dtype=torch.bfloat16, enabled=bf16):
        out_demixed, out_recon = model(views, origins, size)
    loss, _ = joint_loss({"demix": (out_demixed, demixed), "recon": (out_recon, obj)})
    optimizer.zero_grad(set_to_none=True)
    loss.backward()
    torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
    optimizer.step()


def learned(check: Check) -> list[str]:
    """MultiWienerNet and SV-FourierNet per paper-scale frame (random filters)."""
    from svcode_core.methods.learned import (
        FourierNetConfig,
        MultiWienerConfig,
        MultiWienerNet,
        SVFourierNet,
    )
    from svcode_core.methods.learned.reconstruct import LearnedReconstructor

    system = check.big
    frame = _frame(check, "big")
    rows, cols = system.padded_shape
    generator = torch.Generator().manual_seed(0)
    config = MultiWienerConfig()
    builders = {
        "MultiWienerNet": lambda: MultiWienerNet(
            config, system, torch.rand(config.rank, rows, cols, generator=generator) / rows),
        "SV-FourierNet": lambda: SVFourierNet(
            FourierNetConfig(), system,
            torch.randn(9, rows, cols // 2 + 1, dtype=torch.complex64, generator=generator)),
    }
    lines = ["A warm-up frame, then three timed:", "",
             "| model | precision | s per frame | peak GPU MiB |", "|---|---|---|---|"]
    for name, build in builders.items():
        torch.manual_seed(0)
        model = build()
        for precision in ("fp32", "bf16"):
            check.reset_peak()
            rec = LearnedReconstructor(model, system, device=check.device, precision=precision)
            seconds, result = _timed_frames(rec, frame, check.sync, repeats=3)
            if not np.isfinite(result.reconstruction).all():
                raise RuntimeError(f"{name} {precision}: non-finite reconstruction")
            lines.append(f"| {name} | {precision} | {seconds:.3f} | {check.peak()} |")
            del rec
        del model
    return lines


def admm(check: Check) -> list[str]:
    """LSV-ADMM iterations on the paper-scale frame."""
    from svcode_core.methods.baselines.admm import LsvAdmm, settings_for
    from svcode_core.physics.cm2 import CM2Operator
    from svcode_core.physics.geometry import pad_sensor_frame
    from svcode_core.physics.psf_io import model_psfs

    system = check.big
    frame = _frame(check, "big")
    budget = check.args.admm_budget_gib
    start = time.perf_counter()
    psfs = model_psfs(system)
    psf_seconds = time.perf_counter() - start
    check.reset_peak()
    start = time.perf_counter()
    operator = CM2Operator.from_psfs(system, psfs, device=check.device,
                                     memory_budget=int(budget * 2**30))
    check.sync()
    build_seconds = time.perf_counter() - start
    settings = settings_for(system)
    start = time.perf_counter()
    solver = LsvAdmm(operator, tv_weight=settings.tv_weight, rho=settings.rho,
                     cg_iterations=settings.cg_iterations)
    check.sync()
    norm_seconds = time.perf_counter() - start
    padded = pad_sensor_frame(torch.from_numpy(frame).to(check.device), system)
    stamps = [time.perf_counter()]

    def tick(iteration: int, estimate: torch.Tensor) -> None:
        check.sync()
        stamps.append(time.perf_counter())

    iterations = check.args.admm_iterations
    result = solver.solve(padded, iterations=iterations, tolerance=0.0, callback=tick)
    steps = np.diff(stamps)
    later = steps[1:] if len(steps) > 1 else steps
    median = statistics.median(later)
    finite = bool(torch.isfinite(result.x).all())
    falling = result.objective[-1] < result.objective[0]
    lines = [
        f"Operator rank K = {operator.rank}, memory budget {budget:g} GiB, float32.", "",
        "| PSF model (CPU) | operator build | ‖A‖ (10 power steps) | iterations | first | "
        "median of the rest | 200 iterations at that rate | peak GPU MiB |",
        "|---|---|---|---|---|---|---|---|",
        f"| {psf_seconds:.1f} s | {build_seconds:.1f} s | {norm_seconds:.2f} s | "
        f"{len(steps)} | {steps[0]:.3f} s | {median:.3f} s | {200 * median:.0f} s | "
        f"{check.peak()} |", "",
        f"Objective {result.objective[0]:.4g} → {result.objective[-1]:.4g}; estimate finite: "
        f"{finite}.",
    ]
    if not (finite and falling):
        raise RuntimeError("LSV-ADMM: non-finite estimate or a rising objective\n"
                           + "\n".join(lines))
    return lines


# --------------------------------------------------------------- without CUDA
@dataclass(frozen=True)
class Refusal:
    """A CUDA code path and how it must refuse on a machine without CUDA."""

    name: str
    attempt: Callable[[], object]


def _refusals(work: Path) -> list[Refusal]:
    from svcode_core.methods.base import resolve_device
    from svcode_core.methods.baselines.reconstructor import (
        BaselineReconstructor,
        build_operator,
        reconstruct_with_baseline,
    )
    from svcode_core.methods.learned import MultiWienerConfig, MultiWienerNet
    from svcode_core.methods.learned.reconstruct import LearnedReconstructor
    from svcode_core.methods.model_file import save_model
    from svcode_core.methods.svcode import Reconstructor

    tiny = SystemConfig.tiny()
    config = ModelConfig.mini()
    frame = np.full(tiny.sensor_shape, 0.1, dtype=np.float32)
    wiener = MultiWienerNet(MultiWienerConfig(), tiny)
    svcode_file = save_model(work / "tiny-svcode.safetensors", SVCoDe(config), tiny)
    wiener_file = save_model(work / "tiny-wiener.safetensors", wiener, tiny)
    return [
        Refusal("resolve_device('cuda')", lambda: resolve_device("cuda")),
        Refusal("resolve_device('cuda:0')", lambda: resolve_device("cuda:0")),
        Refusal("Reconstructor(model, device='cuda')",
                lambda: Reconstructor(SVCoDe(config), tiny, device="cuda")),
        Refusal("Reconstructor(..., refine_periphery=10, device='cuda')",
                lambda: Reconstructor(SVCoDe(config), tiny, device="cuda", refine_periphery=10)),
        Refusal("Reconstructor.from_weights(file, device='cuda')",
                lambda: Reconstructor.from_weights(svcode_file, device="cuda")),
        Refusal("Reconstructor.pretrained(device='cuda')",
                lambda: Reconstructor.pretrained(device="cuda")),
        Refusal("LSV-ADMM: BaselineReconstructor('admm', device='cuda')",
                lambda: BaselineReconstructor("admm", tiny, device="cuda")),
        Refusal("LSV-ADMM: reconstruct_with_baseline('admm', device='cuda')",
                lambda: reconstruct_with_baseline("admm", frame, tiny, device="cuda")),
        Refusal("build_operator(device='cuda')", lambda: build_operator(tiny, device="cuda")),
        Refusal("LearnedReconstructor(model, device='cuda')",
                lambda: LearnedReconstructor(wiener, tiny, device="cuda")),
        Refusal("LearnedReconstructor.from_weights(file, device='cuda')",
                lambda: LearnedReconstructor.from_weights(wiener_file, device="cuda")),
    ]


def api_refusals(check: Check) -> list[str]:
    lines = ["| call | outcome |", "|---|---|"]
    failures = []
    for refusal in _refusals(check.work):
        try:
            refusal.attempt()
        except ValueError as err:
            clean = "CUDA" in str(err)
            outcome = f"ValueError: {err}" if clean else f"**ValueError without CUDA**: {err}"
            if not clean:
                failures.append(refusal.name)
        except Exception as err:  # noqa: BLE001 - the point is to see which one
            outcome = f"**not clean**: {type(err).__name__}: {err}"
            failures.append(refusal.name)
        else:
            outcome = "**accepted** (no error)"
            failures.append(refusal.name)
        lines.append(f"| `{refusal.name}` | {outcome} |")
    if failures:
        raise RuntimeError("not refused cleanly: " + ", ".join(failures) + "\n" + "\n".join(lines))
    return lines


def cli_refusals(check: Check) -> list[str]:
    """Every command with ``--device``: exit status 2 and one line naming CUDA."""
    missing = str(check.work / "missing.tif")
    out = str(check.work / "out")
    commands = [
        ("reconstruct", missing, "--out", out + ".tif", "--device", "cuda"),
        ("reconstruct", missing, "--out", out + ".tif", "--device", "cuda:0",
         "--method", "admm"),
        ("reconstruct", missing, "--out", out + ".tif", "--device", "cuda",
         "--method", "multiwiener"),
        ("demo", "--device", "cuda", "--out", out),
        ("train", "--data", str(check.work / "missing"), "--out", out, "--device", "cuda"),
    ]
    lines = ["| command | exit | stderr |", "|---|---|---|"]
    failures = []
    for argv in commands:
        status, _, _, err = check.cli(*argv, timeout=120)
        text = _lines(err)
        ok = status == 2 and len(text) == 1 and "CUDA is not available" in text[0]
        shown = " ".join(argv).replace(str(check.work) + "/", "")
        lines.append(f"| `svcode {shown}` | {status} | {' / '.join(text)[:300]} |")
        if not ok:
            failures.append(f"svcode {shown}")
    if failures:
        raise RuntimeError("not refused cleanly: " + ", ".join(failures) + "\n" + "\n".join(lines))
    return lines


# ------------------------------------------------------------------- the report
def sections_for(check: Check) -> list[Section]:
    if not check.cuda and not check.smoke:
        return [Section("Environment", environment, 0),
                Section("Refusals: Python API", api_refusals, 10),
                Section("Refusals: command line", cli_refusals, 20),
                Section("Refusal tests (tests/test_cuda.py)", cuda_tests, 20)]
    return [
        Section("Environment", environment, 0),
        Section("CUDA tests", cuda_tests, 60),
        Section("Simulated frames", scenes, 60),
        Section("SV-CoDe on a paper-scale frame", svcode_paper, 60),
        Section("SV-CoDe, bundled cm2-mini model", svcode_mini, 20),
        Section("SV-CoDe training throughput", training, 30),
        Section("Learned baselines per paper-scale frame", learned, 30),
        Section("LSV-ADMM at paper scale", admm, 60),
    ]


def run_section(check: Check, section: Section) -> None:
    if check.remaining() < section.needs_s:
        section.status = "skipped"
        section.lines = [f"Skipped: {check.remaining():.0f} s of the time budget left, it "
                         f"needs {section.needs_s:.0f} s."]
        print(f"== {section.title}: skipped (time budget)", flush=True)
        return
    print(f"== {section.title}", flush=True)
    start = time.perf_counter()
    try:
        section.lines = section.run(check)
        section.status = "ok"
    except KeyboardInterrupt:  # the wrapper's time limit (SIGINT): keep what was found
        section.status = "interrupted"
        section.lines = ["Interrupted (the time limit of bench/gpu_check.sh, or Ctrl-C)."]
    except Exception as err:  # noqa: BLE001 - report it, run the next section
        traceback.print_exc()
        section.status = "FAILED"
        detail = str(err).splitlines() or [type(err).__name__]
        section.lines = [f"**Failed**: {type(err).__name__}: {detail[0]}", *detail[1:]]
        if "\n" not in str(err):
            section.lines.append(
                "```\n" + "".join(traceback.format_exception_only(type(err), err)).strip()
                + "\n```")
    finally:
        section.seconds = time.perf_counter() - start
        if check.cuda:
            torch.cuda.empty_cache()
    print("\n".join(section.lines), flush=True)
    print(f"-- {section.status} in {section.seconds:.1f} s", flush=True)


def report(check: Check, sections: list[Section], total: float) -> str:
    stamp = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    if check.cuda:
        device = torch.cuda.get_device_name(0)
        lead = [f"Measured on **{device}** by `bench/gpu_check.sh` ({stamp}, "
                f"{total:.0f} s of a {check.args.budget:.0f} s budget)."]
    elif check.smoke:
        lead = [f"**No GPU ran this report.** `python bench/gpu_check.py --smoke-cpu` ran the "
                f"GPU sections on the CPU at small scale ({check.big.name} for the paper-scale "
                f"ones) to check the script itself ({stamp}, {total:.0f} s): these are not GPU "
                "figures."]
    else:
        lead = ["**No GPU ran this report.** CUDA is not available on the machine that "
                f"produced it (torch {torch.__version__}), so `bench/gpu_check.sh` checked "
                f"instead that every CUDA code path refuses cleanly ({stamp}, {total:.0f} s). "
                "Run `bash bench/gpu_check.sh` on a machine with an NVIDIA GPU for the CUDA "
                "tests and the paper-scale timings."]
    lines = ["# GPU check", "", *lead, "", "| section | status | seconds |", "|---|---|---|"]
    lines += [f"| {s.title} | {s.status} | {s.seconds:.1f} |" for s in sections]
    for section in sections:
        lines += ["", f"## {section.title}", "", *section.lines]
    return "\n".join(lines) + "\n"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--budget", type=float, default=400.0,
                        help="seconds for the whole check; sections that no longer fit are "
                        "skipped (default 400)")
    parser.add_argument("--out", type=Path, default=REPORT, help=f"report (default {REPORT})")
    parser.add_argument("--work", type=Path,
                        help="scratch folder, kept (default: a temporary one, removed)")
    parser.add_argument("--admm-iterations", type=int, default=20)
    parser.add_argument("--admm-budget-gib", type=float, default=8.0,
                        help="memory budget of the LSV-ADMM operator (default 8 GiB)")
    parser.add_argument("--smoke-cpu", action="store_true",
                        help="run the GPU sections on the CPU at small scale (checks this "
                        "script; not GPU figures)")
    args = parser.parse_args()

    with contextlib.ExitStack() as stack:
        if args.work is None:
            work = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="gpu-check-")))
        else:
            work = args.work
            work.mkdir(parents=True, exist_ok=True)
        check = Check(args, work)
        if check.cuda:
            print(f"device: {torch.cuda.get_device_name(0)}; torch {torch.__version__}, "
                  f"CUDA {torch.version.cuda}", flush=True)
        else:
            print(f"torch {torch.__version__}: "
                  + ("--smoke-cpu: the GPU sections on the CPU, at small scale"
                     if check.smoke else "CUDA is not available; checking that every CUDA "
                     "code path refuses cleanly"), flush=True)
        sections = sections_for(check)
        args.out.parent.mkdir(parents=True, exist_ok=True)
        for section in sections:  # the report is rewritten after every section
            run_section(check, section)
            total = time.perf_counter() - check.start
            args.out.write_text(report(check, sections, total), encoding="utf-8")
            if section.status == "interrupted":
                break
    failed = [s.title for s in sections if s.status in ("FAILED", "interrupted")]
    print(f"report: {args.out} ({total:.0f} s); "
          + (f"not passed: {', '.join(failed)}" if failed else "every section that ran passed"),
          flush=True)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
