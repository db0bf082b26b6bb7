"""Benchmark of tiled reconstruction: memory and time vs field size, skipping, dask workers.

Measures
  1. peak working memory (resident memory above the level before the call; each size in a
     fresh process) and seconds per frame at sub-view sizes S, 2S, 4S, same tile and batch,
     with the coordinate-mask cache off (the tiling's own memory: flat), under glibc's
     default allocator and with a fixed mmap threshold (resident memory then follows the
     bytes in use), and at the cache's default budget (the cache holds masks of the whole
     field, so it grows with S up to the budget); plus S run for as many batches as 4S,
     which separates the allocator's retained blocks from any growth with S;
  2. the speed-up from skipping signal-free tiles on a sparse bead scene (nine Gaussian-blurred
     lens images with crosstalk and sensor noise), and the change in PSNR it causes;
  3. frames per second on a local dask cluster of 1 and 2 workers (cluster start-up and
     model loading excluded).

The model is a randomly initialised ``SVCoDe(ModelConfig.mini())`` when the network package
is available, else a small convolutional stand-in with the same call signature; the output
says which. Random weights do not reconstruct anything, so the PSNR change is also reported
for a proxy model (the mean of the nine views) whose background output is zero, as a trained
model's is. Results go to bench/results/tiling.json and tiling.md.

Run: ``OMP_NUM_THREADS=1 python bench/tiling.py [--base 64] [--frames 8]``
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch
from scipy.ndimage import gaussian_filter

from svcode_bench.footprint import PeakMemory
from svcode_core.config import OpticsConfig, SystemConfig, system_from_scale
from svcode_core.evaluation.metrics import psnr
from svcode_core.methods.svcode import DEFAULT_MASK_CACHE_BYTES, Reconstructor
from svcode_core.methods.tiling import exhaust, iter_tiled
from svcode_core.physics.geometry import (
    crop_to_sensor,
    extract_sub_views,
    pad_sensor_frame,
    place_sub_views,
)
from svcode_core.physics.noise import apply_sensor_noise
from svcode_core.run.parallel import dask_client, dask_frames

RESULTS = Path(__file__).parent / "results"
PATCH = 32
BATCH = 8


def make_system(size: int) -> SystemConfig:
    """A small CM² system of sub-view size ``size``, tile 32 / stride 16."""
    pitch = 3 * size // 8
    side = size + 2 * pitch
    optics = OpticsConfig(psf_grid=3, kernel_size=9, airy_radius=1.0, pupil_samples=32)
    system = system_from_scale(
        f"bench-{size}", (3 * side // 4, side), size, pitch, PATCH, optics, 1e-2
    )
    return system.validate()


class StandIn(torch.nn.Module):
    """Two small convolutional stages with sigmoid outputs, SV-CoDe's call signature."""

    def __init__(self, width: int = 32) -> None:
        super().__init__()
        self.demix = torch.nn.Sequential(
            torch.nn.Conv2d(9, width, 3, padding=1), torch.nn.GELU(),
            torch.nn.Conv2d(width, width, 3, padding=1), torch.nn.GELU(),
            torch.nn.Conv2d(width, 9, 3, padding=1),
        )  # fmt: skip
        self.recon = torch.nn.Sequential(
            torch.nn.Conv2d(9, width, 3, padding=1), torch.nn.GELU(),
            torch.nn.Conv2d(width, 1, 3, padding=1),
        )  # fmt: skip

    def forward(self, views, origins, sub_view_size):
        demixed = torch.sigmoid(self.demix(views))
        return demixed, torch.sigmoid(self.recon(demixed))


class MeanOfViews(torch.nn.Module):
    """Proxy with a zero background: the reconstruction is the mean of the nine views."""

    def forward(self, views, origins, sub_view_size):
        return views, views.mean(1, keepdim=True)


def make_model() -> tuple[torch.nn.Module, str]:
    """Random-weight SVCoDe mini model if the network package exists, else the stand-in."""
    torch.manual_seed(0)
    try:
        from svcode_core.network import ModelConfig, SVCoDe
    except ImportError:
        return StandIn(), "stand-in conv net (svcode_core.network not available), random weights"
    return SVCoDe(ModelConfig.mini()), "SVCoDe(ModelConfig.mini()), random weights"


def build(
    size: int, skip: bool = True, cache_bytes: int = DEFAULT_MASK_CACHE_BYTES
) -> Reconstructor:
    """The benchmark's reconstructor for sub-view size ``size``."""
    model, _ = make_model()
    return Reconstructor(model, make_system(size), batch_size=BATCH, skip_empty=skip,
                         mask_cache_bytes=cache_bytes)  # fmt: skip


#: glibc's allocator setting that makes every allocation above 64 KiB its own mapping,
#: returned to the system when freed: resident memory then follows the bytes in use
FIXED_MMAP = {"MALLOC_MMAP_THRESHOLD_": "65536"}
#: the groups of rows of :func:`memory_scaling`, in the order of the report's table
MEMORY_GROUPS = ("default", "fixed_mmap", "cached", "long_run")


def child_memory(size: int, cache_bytes: int, min_batches: int = 0) -> dict:
    """In a fresh process: memory and time of one frame at sub-view size ``size``.

    ``tiling_memory_mib`` is the resident memory added while the tiles run (model, batch,
    blending), measured after the sub-views exist and less the two ``S × S`` output
    accumulators; the frame's tiles are run again until at least ``min_batches`` batches
    ran. ``call_memory_mib`` is that of a whole :meth:`Reconstructor.reconstruct` call,
    which also holds the frame's own ``O(S²)`` arrays (listed as ``frame_arrays_mib``).
    """
    torch.set_num_threads(1)
    rec = build(size, skip=False, cache_bytes=cache_bytes)
    frame = np.random.default_rng(0).random(rec.system.sensor_shape, dtype=np.float32)
    views = rec.prepare(frame)

    def run(tiles, origins):
        return rec._run_batch(tiles, origins, want_views=False)

    batches = -(-len(rec.grid) // rec.batch_size)
    repeats = max(1, -(-min_batches // batches))
    with PeakMemory() as tiling:
        for _ in range(repeats):
            exhaust(iter_tiled(run, views, rec.grid, rec.batch_size))
    accumulators = 2 * size * size * 4 / 2**20
    del views
    with PeakMemory() as call:
        result = rec(frame)
    start = time.perf_counter()
    rec(frame)
    seconds = time.perf_counter() - start
    padded = np.prod(rec.system.padded_shape)
    return {
        "sub_view_size": size,
        "mask_cache_mib": cache_bytes / 2**20,
        "fixed_mmap": os.environ.get("MALLOC_MMAP_THRESHOLD_") is not None,
        "tiles": result.tiles_total,
        "batches": batches * repeats,
        "tiling_memory_mib": tiling.mib - accumulators,
        "call_memory_mib": call.mib,
        "frame_arrays_mib": (3 * frame.size + padded + 12 * size * size) * 4 / 2**20,
        "seconds_per_frame": seconds,
    }


def _child(size: int, cache: int, fixed_mmap: bool = False, min_batches: int = 0) -> dict:
    args = ["--child-memory", str(size), "--child-cache", str(cache),
            "--child-batches", str(min_batches)]  # fmt: skip
    env = {**os.environ, **(FIXED_MMAP if fixed_mmap else {})}
    out = subprocess.run([sys.executable, __file__, *args], check=True, capture_output=True,
                         text=True, env=env)  # fmt: skip
    return json.loads(out.stdout.strip().splitlines()[-1])


def memory_scaling(base: int) -> dict:
    """Rows at S, 2S, 4S without the mask cache under the default allocator (``default``)
    and with a fixed mmap threshold (``fixed_mmap``), with the cache at its default budget
    (``cached``), and the row of S run for as many batches as 4S (``long_run``)."""
    sizes = (base, 2 * base, 4 * base)
    default = [_child(size, 0) for size in sizes]
    return {
        "default": default,
        "fixed_mmap": [_child(size, 0, fixed_mmap=True) for size in sizes],
        "cached": [_child(size, DEFAULT_MASK_CACHE_BYTES) for size in sizes],
        "long_run": _child(base, 0, min_batches=default[-1]["batches"]),
    }


def _psnr(x: np.ndarray, ref: np.ndarray) -> float:
    return psnr(ref, x, float(ref.max()))


def sparse_scene(size: int, beads: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A raw frame of ``beads`` bright beads and the noiseless mean of its nine views.

    Each lens images the object with a Gaussian blur (a shift-invariant stand-in for the
    low-rank forward model); the nine images are placed at their chief rays, cropped to the
    sensor and given the system's sensor noise.
    """
    system = make_system(size)
    rng = np.random.default_rng(seed)
    obj = np.zeros((size, size), np.float32)
    for r, c in rng.integers(size // 8, size - size // 8, (beads, 2)):
        obj[r - 1 : r + 2, c - 1 : c + 2] = 1.0
    lens_image = torch.from_numpy(gaussian_filter(obj, 1.5))
    padded = place_sub_views(lens_image.expand(9, size, size), system)
    clean = crop_to_sensor(padded, system)
    noisy = apply_sensor_noise(clean, system.noise, torch.Generator().manual_seed(seed))
    views = extract_sub_views(pad_sensor_frame(clean, system), system)
    return noisy.numpy(), views.mean(0).numpy()


def skipping(size: int, beads: int) -> dict:
    frame, target = sparse_scene(size, beads)
    timings = {}
    for skip in (False, True):
        rec = build(size, skip)
        rec(frame)  # warm-up
        start = time.perf_counter()
        result = rec(frame)
        timings[skip] = (time.perf_counter() - start, result)
    (dense_s, dense), (sparse_s, sparse) = timings[False], timings[True]
    system = make_system(size)
    proxy = {
        skip: Reconstructor(MeanOfViews(), system, skip_empty=skip)(frame).reconstruction
        for skip in (False, True)
    }
    return {
        "sub_view_size": size,
        "beads": beads,
        "tiles": dense.tiles_total,
        "tiles_skipped": sparse.tiles_skipped,
        "dense_seconds": dense_s,
        "skip_seconds": sparse_s,
        "speedup": dense_s / sparse_s,
        "max_change_random_model": float(
            np.abs(dense.reconstruction - sparse.reconstruction).max()
        ),
        "proxy_psnr_dense_db": _psnr(proxy[False], target),
        "proxy_psnr_skip_db": _psnr(proxy[True], target),
    }


def dask_throughput(size: int, frames: int) -> list[dict]:
    stack = np.random.default_rng(1).random((frames, *make_system(size).sensor_shape), "float32")
    factory = functools.partial(build, size, False)
    rows = []
    for workers in (1, 2):
        with dask_client(workers) as client:
            list(dask_frames(factory, stack, range(2 * workers), False, client))  # warm-up
            start = time.perf_counter()
            done = list(dask_frames(factory, stack, range(frames), False, client))
            seconds = time.perf_counter() - start
        rows.append({"workers": workers, "frames": len(done), "fps": len(done) / seconds})
    return rows


def to_markdown(report: dict) -> str:
    lines = [
        "# Tiled reconstruction benchmark",
        "",
        f"Model: {report['model']}. Tile {PATCH}, stride {PATCH // 2}, batch {BATCH}, CPU, "
        f"{report['threads']} thread(s).",
        "",
        "Peak resident memory added (MiB): while the tiles run (model, batch, blending; "
        "outputs excluded), and for a whole call (which also holds the frame's O(S²) arrays). "
        "Allocator: glibc's default, or with a fixed mmap threshold "
        "(`MALLOC_MMAP_THRESHOLD_=65536`), under which freed blocks go back to the system "
        "at once and resident memory follows the bytes in use.",
        "",
        "| S | allocator | mask cache budget (MiB) | tiles | batches | tiling (MiB) "
        "| whole call (MiB) | frame arrays (MiB) | s / frame |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    memory = report["memory"]
    default, fixed, cached, long_run = (memory[key] for key in MEMORY_GROUPS)
    for row in [*default, *fixed, *cached, long_run]:
        allocator = "fixed mmap" if row["fixed_mmap"] else "default"
        lines.append(
            f"| {row['sub_view_size']} | {allocator} | {row['mask_cache_mib']:.0f} | "
            f"{row['tiles']} | {row['batches']} | {row['tiling_memory_mib']:.1f} | "
            f"{row['call_memory_mib']:.1f} | {row['frame_arrays_mib']:.1f} | "
            f"{row['seconds_per_frame']:.3f} |"
        )

    def spread(rows: list[dict]) -> str:
        mib = [row["tiling_memory_mib"] for row in rows]
        return f"{max(mib) / min(mib) - 1:.1%}"

    lines += [
        "",
        f"Tiling memory spread over S, 2S, 4S without the mask cache (max/min - 1): "
        f"{spread(fixed)} with the fixed mmap threshold, {spread(default)} with glibc's "
        f"default. The default allocator keeps freed blocks for reuse, and its peak rises "
        f"with the number of batches run, not with S: S = {long_run['sub_view_size']} run "
        f"for {long_run['batches']} batches (as many as one 4S frame) peaks at "
        f"{long_run['tiling_memory_mib']:.1f} MiB against "
        f"{default[2]['tiling_memory_mib']:.1f} MiB at 4S. The fixed threshold costs "
        f"{fixed[1]['seconds_per_frame'] / default[1]['seconds_per_frame']:.1f}× the time "
        f"at 2S (a page fault for every large allocation), so it is not the default.",
        "",
        "With the cache, the masks of the whole field are kept (up to the budget, "
        f"`--mask-cache`), trading memory that grows with S for speed: at 4S the cache added "
        f"{cached[2]['tiling_memory_mib'] - default[2]['tiling_memory_mib']:.0f} MiB with a "
        f"{cached[2]['mask_cache_mib']:.0f} MiB budget. The budget bounds the bytes of the "
        "cached masks, not the process: computing whole-field masks and the allocator's "
        "retained blocks come on top.",
        "",
    ]
    lines += [
        f"Skipping on sparse bead scenes (S = {report['skipping'][0]['sub_view_size']}); "
        "PSNR of the zero-background proxy model against the noiseless target:",
        "",
        "| beads | tiles skipped | dense s | skipping s | speed-up | proxy PSNR dense → skip |",
        "|---|---|---|---|---|---|",
    ]
    for s in report["skipping"]:
        lines.append(
            f"| {s['beads']} | {s['tiles_skipped']} / {s['tiles']} | {s['dense_seconds']:.3f} | "
            f"{s['skip_seconds']:.3f} | {s['speedup']:.1f}× | "
            f"{s['proxy_psnr_dense_db']:.2f} → {s['proxy_psnr_skip_db']:.2f} dB |"
        )
    lines += [
        "",
        "| dask workers | frames | frames / s |",
        "|---|---|---|",
    ]
    lines += [f"| {r['workers']} | {r['frames']} | {r['fps']:.2f} |" for r in report["dask"]]
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--base", type=int, default=64, help="smallest sub-view size S")
    parser.add_argument("--sparse-size", type=int, default=256)
    parser.add_argument("--beads", type=int, nargs="+", default=[1, 3, 10])
    parser.add_argument("--frames", type=int, default=8, help="frames for the dask test")
    parser.add_argument("--child-memory", type=int, help=argparse.SUPPRESS)
    parser.add_argument("--child-cache", type=int, default=0, help=argparse.SUPPRESS)
    parser.add_argument("--child-batches", type=int, default=0, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child_memory:
        print(json.dumps(child_memory(args.child_memory, args.child_cache, args.child_batches)))
        return
    torch.set_num_threads(1)
    report = {
        "model": make_model()[1],
        "threads": torch.get_num_threads(),
        "memory": memory_scaling(args.base),
        "skipping": [skipping(args.sparse_size, beads) for beads in args.beads],
        "dask": dask_throughput(args.base * 2, args.frames),
    }
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "tiling.json").write_text(json.dumps(report, indent=2) + "\n")
    markdown = to_markdown(report)
    (RESULTS / "tiling.md").write_text(markdown)
    print(markdown)


if __name__ == "__main__":
    main()
