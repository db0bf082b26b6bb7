"""Where the SV-CoDe network's time goes, per precision, against the processor's peak.

Two workloads on one thread, each in float32 and in bf16:
  * ``frame``: the bundled cm2-mini model reconstructing one sensor frame with the
    :class:`~svcode_core.Reconstructor`'s defaults (masks kept after the first frame; bf16
    as the reconstructor runs it on the CPU, a bf16 copy of the network);
  * ``train``: one training step of the same network (batch 8 × 96², one shared origin,
    forward, loss, backward, Adam), eager, bf16 under autocast.

The time of each torch operator (self CPU time, :mod:`torch.profiler`) is summed into
parts: convolutions, matrix products (the coordinate MLPs), layer norms, copies (layout
and dtype conversions) and the remaining element-wise work (masks, gates, attention,
checks). Convolutions and matrix products get GFLOP/s from their FLOPs
(:mod:`torch.utils.flop_counter`) over their own time; the peak is what this processor
reaches on one thread in a large matrix product (2048², the best of three), per precision.

Results go to bench/results/network_parts.json and network_parts.md (``--out`` names
another stem, e.g. for a second kind of processor). Run: ``python bench/network_parts.py``;
the ratios between precisions hold on a busy machine, the absolute times need a quiet one.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch
from torch.profiler import ProfilerActivity, profile
from torch.utils.flop_counter import FlopCounterMode

from svcode_bench import processor
from svcode_core import SystemConfig
from svcode_core.config import N_LENSES
from svcode_core.methods.build import build_reconstructor
from svcode_core.methods.model_file import load_model
from svcode_core.network.compiled import compile_model
from svcode_core.pretrained import bundled_weights
from svcode_core.run.allocator import reuse_freed_memory

RESULTS = Path(__file__).parent / "results"
PARTS = ("convolution", "matrix product", "layer norm", "copy", "element-wise")
DTYPES = {"fp32": torch.float32, "bf16": torch.bfloat16}
ROUNDS = 5


def part_of(op: str) -> str:
    """The part an aten operator's time is counted in."""
    if "conv" in op:
        return "convolution"
    if "::baddbmm" in op:  # the view block's 1×1 convolutions (fast.pointwise)
        return "convolution"
    if any(k in op for k in ("::mm", "::bmm", "::addmm", "::matmul")):
        return "matrix product"
    if "layer_norm" in op:
        return "layer norm"
    if op in ("aten::copy_", "aten::_to_copy", "aten::clone", "aten::contiguous"):
        return "copy"
    return "element-wise"


def flop_part(op) -> str | None:
    """The part of an operator the FLOP counter names (``aten.convolution``...): only
    convolutions and products have FLOPs counted."""
    part = part_of(str(op).replace(".", "::", 1))
    return part if part in ("convolution", "matrix product") else None


def gemm_peak(dtype: torch.dtype, n: int = 2048) -> float:
    """GFLOP/s of an ``n × n`` matrix product on one thread, the best of three."""
    a, b = torch.rand(n, n).to(dtype), torch.rand(n, n).to(dtype)
    torch.mm(a, b)
    best = min(_timed(lambda: torch.mm(a, b)) for _ in range(3))
    return 2 * n**3 / best / 1e9


def _timed(call) -> float:
    start = time.perf_counter()
    call()
    return time.perf_counter() - start


def alternating_walls(runs: dict, rounds: int = ROUNDS) -> dict:
    """Wall seconds of each of ``runs`` (name → callable) over ``rounds`` rounds, the runs
    taking turns within each round after one warm-up call each, so that a machine whose
    speed drifts slows them alike and their ratios hold."""
    for run in runs.values():
        run()
    walls = {name: [] for name in runs}
    for _ in range(rounds):
        for name, run in runs.items():
            walls[name].append(_timed(run))
    return walls


def profile_parts(run) -> dict:
    """``run``'s operator time per part in one profiled call and its convolution and
    product FLOPs (``run`` warm: :func:`alternating_walls` has run it)."""
    with FlopCounterMode(display=False) as counter:
        run()
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        run()
    seconds = dict.fromkeys(PARTS, 0.0)
    for event in prof.key_averages():
        if event.key.startswith("aten::"):
            seconds[part_of(event.key)] += event.self_cpu_time_total / 1e6
    flops = dict.fromkeys(PARTS, 0.0)
    for op, count in counter.get_flop_counts()["Global"].items():
        part = flop_part(op)
        if part:
            flops[part] += count
    return {"seconds": seconds, "gflop": {k: v / 1e9 for k, v in flops.items()}}


def frame_workload(precision: str):
    """One frame through the bundled model with the reconstructor's defaults."""
    system = SystemConfig.preset("cm2-mini")
    rec = build_reconstructor("svcode", system, precision=precision)
    frame = np.random.default_rng(0).random(system.sensor_shape, dtype=np.float32)
    rec(frame)  # the masks of the tile grid, computed once per recording
    return lambda: rec(frame)


def training_batch(weights: str | None = None, patch: int = 96, batch: int = 8):
    """A model file's network (the bundled cm2-mini one by default) in training mode and
    a fixed batch of ``batch`` patches of ``patch`` px at one origin; returns
    ``(model, loss)`` where ``loss(net, precision)`` is the batch's loss through ``net``
    (the model or a compiled copy), its forward under bf16 autocast for ``bf16``."""
    model, system = load_model(weights or bundled_weights("cm2-mini"))
    model.train()
    channels = N_LENSES * model.demix.views_per_lens  # the views, with their lens context
    views = torch.rand(batch, channels, patch, patch,
                       generator=torch.Generator().manual_seed(0))
    origins = torch.tensor([[48, 96]] * batch)

    def loss(net: torch.nn.Module, precision: str) -> torch.Tensor:
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=precision == "bf16"):
            demixed, recon = net(views, origins, system.sub_view_size)
        return demixed.float().square().mean() + recon.float().square().mean()

    return model, loss


def train_workload(precision: str, compiled: bool = False, weights: str | None = None,
                   patch: int = 96, batch: int = 8):
    """One training step on :func:`training_batch`, Adam, compiled as ``svcode train
    --compile`` does when ``compiled``."""
    model, loss = training_batch(weights, patch, batch)
    net = compile_model(model, precision == "bf16") if compiled else model
    optimizer = torch.optim.Adam(model.parameters(), 1e-4)

    def step():
        optimizer.zero_grad()
        loss(net, precision).backward()
        optimizer.step()

    return step


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", default="network_parts", help="stem of the results' files")
    args = parser.parse_args()
    torch.set_num_threads(1)
    reuse_freed_memory()  # as the svcode command does
    peak = {name: gemm_peak(dtype) for name, dtype in DTYPES.items()}
    runs = {(workload, precision): make(precision)
            for workload, make in (("frame", frame_workload), ("train", train_workload))
            for precision in DTYPES}
    walls = alternating_walls(runs)
    rows = []
    for (workload, precision), run in runs.items():
        own, fp32 = np.array(walls[workload, precision]), np.array(walls[workload, "fp32"])
        row = {"workload": workload, "precision": precision,
               "wall_s": float(np.median(own)), "walls_s": own.tolist(),
               "speed_vs_fp32": float(np.median(fp32 / own)), **profile_parts(run)}
        rows.append(row)
        print(workload, precision, f"{row['wall_s']:.3f} s", flush=True)
    name, bf16 = processor()
    report = {"processor": f"{name} ({', '.join(bf16) or 'no bf16 units'})",
              "capability": torch.backends.cpu.get_cpu_capability(),
              "gemm_peak_gflops": peak, "rows": rows}
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / f"{args.out}.json").write_text(json.dumps(report, indent=2) + "\n")
    (RESULTS / f"{args.out}.md").write_text(markdown(report))
    print((RESULTS / f"{args.out}.md").read_text())


def markdown(report: dict) -> str:
    peak = report["gemm_peak_gflops"]
    lines = [
        "# Where the network's time goes",
        "",
        "Generated by `bench/network_parts.py`: one thread, the bundled cm2-mini model; "
        "`frame` is one sensor frame through the reconstructor's defaults (masks kept), "
        "`train` one eager training step (8 × 96², forward, backward, Adam). The wall time is "
        f"the median of {ROUNDS} rounds in which the four runs take turns; *× fp32* the "
        "median over rounds of the float32 run's time over this one's in the same round "
        "(a ratio that holds on a machine whose speed drifts); *× fp32, products free* the "
        "speed-up over float32 if this run's convolutions and matrix products took no time "
        "(their share of the parts' time removed from its wall time), the most that faster "
        "products alone can give. Seconds per part are each "
        "part's own operator time in one profiled run; GFLOP/s of a part is its FLOPs over "
        "its time, and *of peak* compares it with a 2048² matrix product on the same thread "
        f"(fp32 {peak['fp32']:.0f}, bf16 {peak['bf16']:.0f} GFLOP/s; {report['processor']}, "
        f"torch's CPU capability {report['capability']}).",
        "",
        "| workload | precision | wall s | × fp32 | " + " | ".join(f"{p} s" for p in PARTS)
        + " | conv GFLOP/s | conv of peak | MLP GFLOP/s | × fp32, products free |",
        "|---|---|---|---|" + "---|" * len(PARTS) + "---|---|---|---|",
    ]
    fp32_wall = {r["workload"]: r["wall_s"] for r in report["rows"] if r["precision"] == "fp32"}
    for r in report["rows"]:
        sec, gf = r["seconds"], r["gflop"]
        products = (sec["convolution"] + sec["matrix product"]) / sum(sec.values())
        bound = fp32_wall[r["workload"]] / (r["wall_s"] * (1 - products))
        conv = gf["convolution"] / max(sec["convolution"], 1e-9)
        mlp = gf["matrix product"] / max(sec["matrix product"], 1e-9)
        lines.append(
            f"| {r['workload']} | {r['precision']} | {r['wall_s']:.3f} | "
            f"{r['speed_vs_fp32']:.2f} | "
            + " | ".join(f"{sec[p]:.3f}" for p in PARTS)
            + f" | {conv:.0f} | {conv / peak[r['precision']]:.0%} | {mlp:.0f} | {bound:.2f} |"
        )
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
