"""Work–precision benchmark of every method and knob in every regime (``svcode bench``).

A *regime* is the instrument the test frames come from (:mod:`svcode_core.physics.departures`):
``matched`` is the nominal system itself, i.e. the data are simulated with the very
forward model the model-based solvers invert (the inverse crime); ``calibration``,
``model``, ``background``, ``low-light`` and ``realistic`` are the named sets of
departures, scaled to the system. The reconstructors are always given the nominal system.

Fixed test scenes: synthetic phantoms (cells, vessels, sparse and dense beads, neurons;
fixed object seeds) and the held-out real images of
:data:`svcode_core.phantoms.HELD_OUT_IMAGES` (never used for training), each imaged with a
fixed noise seed. Every method and knob reconstructs every scene of every regime; each
row reports the scene-mean PSNR, SSIM, centre and outer-ring PSNR
(:mod:`svcode_core.evaluation.metrics`, ``data_range = 1``), seconds per frame and peak memory.

Rows (per regime)
    * **LSV-ADMM**, ``K`` = 3: one run per scene, read out at 10, 20 and 50 iterations
      (time = solver time up to that iteration), with the system's TV weight and (not with
      ``--quick``) with each frame's own (``λ auto``,
      :func:`~svcode_core.methods.baselines.admm.auto_tv_weight`); with ``--rank-sweep``,
      in the matched regime, also at 50 iterations with ``K`` = 1 and 6;
    * **Wiener** per view with balance 1e-3, 1e-2, 1e-1; **Richardson–Lucy** per view with
      10 and 30 iterations;
    * **SV-CoDe** (only with ``--weights`` or a bundled model): the planned tiling
      (:func:`~svcode_core.methods.svcode.plan_tiles`) without and with the periphery
      refinement (:mod:`~svcode_core.methods.periphery`, ``refine_periphery`` 10) in every
      regime and, in the matched one, the system's patch ``P`` at stride ``P/2`` and
      ``P/4`` and the planned tiling with its channel attention pooled over ``P`` pixels
      (``--pool-window``); with ``--all-knobs``, in the matched regime, also batches of
      one, mask cache off, bf16 and empty-tile skipping off (knobs that change the time,
      not the estimate);
    * learned baselines (``--learned``) and ablations (``--ablations``), one row each;
    * **LSV-ADMM at the system's K** (family ``admm-system-k``, only when asked for:
      minutes per frame): the slow end of LSV-ADMM, the system's ``K``, up to 200
      iterations with the stopping tolerance and the fixed ``λ``, against which the
      defaults (``K`` = 3, 50 iterations, ``λ`` auto: the rows above) are chosen.

Timing and memory
    Seconds per frame are wall-clock time of the reconstruction call on one CPU thread
    (``torch.set_num_threads``), excluding one-off set-up (building the operator and
    estimating its norm, loading the model), which is reported separately. Peak memory is
    the rise of the process's peak resident set size (``VmHWM`` in ``/proc/self/status``,
    reset before each row through ``/proc/self/clear_refs``) above the resident size before
    the row; it includes torch's allocations, which ``tracemalloc`` would not see, but not
    memory the allocator reuses from earlier rows (small rows after large ones
    under-report). Where the peak cannot be reset (not Linux) the column is empty.

Plans (:func:`plan_for`)
    The rows above are the full plan. ``--quick`` runs two scenes (one synthetic, one
    held-out), ADMM (``K`` = 3) to 30 iterations, one Wiener and one RL setting and
    SV-CoDe's planned tiling without and with the periphery refinement (no footprint
    measurement), in every regime: a few minutes on one core. On paper-scale systems
    (``cm2-v2``), where 10 LSV-ADMM iterations take minutes a frame, the plan is three scenes
    (cells, neurons, the held-out ``ihc``; one with ``--quick``) in the matched and realistic
    regimes: LSV-ADMM at 10 iterations and again read out, frame by frame, at SV-CoDe's own
    time, Wiener at balance 1e-2 and SV-CoDe's planned tiling. ``--regimes`` runs a subset,
    ``--methods`` a subset of the method families.
"""

from __future__ import annotations

import json
import platform
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from svcode_core.config import SystemConfig
from svcode_core.evaluation.metrics import CENTRE_RADIUS, RING_RADIUS, image_quality
from svcode_core.methods import registry
from svcode_core.methods.baselines import LsvAdmm
from svcode_core.methods.baselines.admm import settings_for
from svcode_core.methods.build import build_reconstructor
from svcode_core.methods.model_file import read_model_metadata
from svcode_core.methods.periphery import REFINE_ITERATIONS
from svcode_core.phantoms import HELD_OUT_IMAGES, held_out_image, make_object
from svcode_core.physics.cm2 import CM2Operator
from svcode_core.physics.departures import Departures
from svcode_core.physics.geometry import pad_sensor_frame
from svcode_core.physics.psf_io import model_psfs
from svcode_core.physics.simulate import Simulator
from svcode_core.pretrained import bundled_weights

from . import REGIMES
from .footprint import PeakMemory, model_footprint

SCENES = (
    ("cells", "cells", {}),
    ("vessels", "vessels", {}),
    ("beads-sparse", "beads", {"density": 1.0}),
    ("beads-dense", "beads", {"density": 40.0}),
    ("neurons", "neurons", {}),
    *((name.removesuffix(".png"), "held-out", {"name": name}) for name in HELD_OUT_IMAGES),
)
#: what the matched regime is
INVERSE_CRIME = "inverse crime: data simulated with the reconstructors' own forward model"
ADMM_RANK = 3
RANK_SWEEP = (1, 6)
RANK_SWEEP_ITERATIONS = 50
METRICS = ("psnr", "ssim", "psnr_centre", "psnr_ring")
METHOD_FAMILIES = ("admm", "deconvolution", "svcode", "learned", "admm-system-k")
#: the iterations of the ``admm-system-k`` row (at most: it stops at the tolerance)
SYSTEM_K_ITERATIONS = 200
#: the families ``svcode bench`` runs unless ``--methods`` says otherwise
DEFAULT_FAMILIES = METHOD_FAMILIES[:4]


@dataclass(frozen=True)
class Plan:
    """What one run measures: its scenes, its regimes unless told, and its rows."""

    name: str
    scenes: tuple[str, ...]
    regimes: tuple[str, ...]
    #: LSV-ADMM (K = 3) read out at these iterations
    admm_checkpoints: tuple[int, ...]
    #: the LSV-ADMM rows again with each frame's own TV weight
    admm_auto: bool
    wiener_balances: tuple[float, ...]
    rl_iterations: tuple[int, ...]
    #: SV-CoDe's first knobs (:func:`svcode_rows`): in the matched regime, elsewhere
    svcode_knobs: tuple[int, int]
    #: the models' size and memory at S and 2S (a subprocess each)
    footprint: bool
    #: LSV-ADMM also read out, frame by frame, at SV-CoDe's own time (:func:`equal_time_row`)
    equal_time: bool
    #: SV-CoDe's precision in its first row: float32 (alike on every machine) or ``auto``
    #: (what the command runs by default here)
    svcode_precision: str = "fp32"


FULL = Plan("full", tuple(s[0] for s in SCENES), tuple(REGIMES), (10, 20, 50), True,
            (1e-3, 1e-2, 1e-1), (10, 30), (5, 2), True, False)  # fmt: skip
QUICK = Plan("quick", ("cells", "ihc"), tuple(REGIMES), (10, 30), False, (1e-2,), (30,),
             (2, 2), False, False)  # fmt: skip
#: paper-scale systems: LSV-ADMM's 10 iterations take minutes a frame there
PAPER = Plan("paper-scale", ("cells", "neurons", "ihc"), ("matched", "realistic"), (10,), False,
             (1e-2,), (), (1, 1), False, True, "auto")  # fmt: skip
#: sub-views from this size on are paper-scale (cm2-v2: 2400 px; cm2-mini: 384)
PAPER_SCALE_SUB_VIEW = 1024


def plan_for(system: SystemConfig, quick: bool = False) -> Plan:
    """The plan of a run on ``system``: :data:`FULL` or :data:`QUICK`, and :data:`PAPER`
    (one scene with ``quick``) for sub-views of :data:`PAPER_SCALE_SUB_VIEW` px and more.

    >>> plan_for(SystemConfig.preset("cm2-v2")).name, plan_for(SystemConfig.tiny(), True).name
    ('paper-scale', 'quick')
    """
    if system.sub_view_size >= PAPER_SCALE_SUB_VIEW:
        return replace(PAPER, name="paper-scale quick", scenes=PAPER.scenes[:1]) if quick else PAPER
    return QUICK if quick else FULL


@dataclass
class Scene:
    """One test scene: name, ground truth and its raw frame."""

    name: str
    truth: np.ndarray
    raw: np.ndarray


@dataclass
class Row:
    """One method/knob: per-scene metrics and times, and the peak memory of the row."""

    method: str
    knob: str
    settings: dict[str, Any]
    per_scene: dict[str, dict[str, float]] = field(default_factory=dict)
    setup_seconds: float = 0.0
    peak_memory_mib: float | None = None
    footprint: dict[str, Any] | None = None
    regime: str = "matched"

    def summary(self) -> dict[str, Any]:
        """Scene means of every metric and of the seconds per frame."""
        values = list(self.per_scene.values())
        mean = {key: float(np.mean([v[key] for v in values])) for key in (*METRICS, "seconds")}
        return {
            "regime": self.regime,
            "method": self.method,
            "knob": self.knob,
            "settings": self.settings,
            **mean,
            "setup_seconds": self.setup_seconds,
            "peak_memory_mib": self.peak_memory_mib,
            "footprint": self.footprint,
            "per_scene": self.per_scene,
        }


def scene_object(kind: str, size: int, index: int, params: dict[str, Any]) -> np.ndarray:
    """Ground truth of a scene: a phantom (object seed ``index``) or a held-out image."""
    if kind == "held-out":
        return held_out_image(params["name"], size)
    return make_object(kind, size, index, **params)


def make_scenes(system: SystemConfig, names: tuple[str, ...], simulator: Simulator) -> list[Scene]:
    """The fixed test scenes (object seed = index in :data:`SCENES`, noise seed 100 + index)."""
    scenes = []
    for index, (name, kind, params) in enumerate(SCENES):
        if name not in names:
            continue
        truth = scene_object(kind, system.sub_view_size, index, params)
        raw = simulator.simulate(truth, seed=100 + index).measurement
        scenes.append(Scene(name, truth, raw))
    return scenes


def _padded(scene: Scene, operator: CM2Operator) -> torch.Tensor:
    raw = torch.as_tensor(scene.raw, dtype=operator.lenses.dtype)
    return pad_sensor_frame(raw, operator.system)


def _score(row: Row, scene: Scene, estimate: np.ndarray, seconds: float) -> None:
    quality = image_quality(scene.truth, np.asarray(estimate, dtype=np.float64), data_range=1.0)
    row.per_scene[scene.name] = {**quality, "seconds": seconds}


# ------------------------------------------------------------------ methods
class CheckpointRecorder:
    """ADMM callback keeping the estimate and the solver time at chosen iterations and,
    given the ``truth``, the time and scores after every iteration (``scores``).

    The time spent copying and scoring is excluded from the reported times.
    """

    def __init__(self, wanted: set[int], truth: np.ndarray | None = None) -> None:
        self.wanted, self.truth = wanted, truth
        self.snapshots: dict[int, tuple[float, np.ndarray]] = {}
        self.scores: dict[int, tuple[float, dict[str, float]]] = {}
        self.start = time.perf_counter()
        self.paused = 0.0

    def __call__(self, iteration: int, x: torch.Tensor) -> None:
        if iteration not in self.wanted and self.truth is None:
            return
        now = time.perf_counter()
        seconds, estimate = now - self.start - self.paused, x.cpu().numpy()
        if iteration in self.wanted:
            self.snapshots[iteration] = (seconds, estimate.copy())
        if self.truth is not None:
            quality = image_quality(self.truth, estimate.astype(np.float64), data_range=1.0)
            self.scores[iteration] = (seconds, quality)
        self.paused += time.perf_counter() - now


def admm_rows(
    operator: CM2Operator,
    scenes: list[Scene],
    checkpoints: tuple[int, ...],
    label: str,
    setup_seconds: float,
    tv_weight: float | str | None = None,
    trace: dict[str, list[tuple[float, dict[str, float]]]] | None = None,
) -> list[Row]:
    """LSV-ADMM rows: one run per scene, read out at every checkpoint; ``tv_weight`` the
    system's setting by default, ``"auto"`` for each scene's own
    (:func:`~svcode_core.methods.baselines.admm.auto_tv_weight`). A ``trace`` dict receives,
    per scene, the solver time and the scores after every iteration up to the last
    checkpoint (for :func:`equal_time_row`)."""
    settings = settings_for(operator.system)
    tv_weight = settings.tv_weight if tv_weight is None else tv_weight
    auto = tv_weight == "auto"
    start = time.perf_counter()
    solver = LsvAdmm(
        operator, tv_weight, settings.rho, settings.cg_iterations, settings.adaptive_rho
    )
    setup_seconds += time.perf_counter() - start
    rows = {
        n: Row(
            registry.method("admm").label,
            f"{label}, {n} it" + (", λ auto" if auto else ""),
            {"rank": operator.rank, "iterations": n, "tv_weight": tv_weight},
            setup_seconds=setup_seconds,
        )
        for n in checkpoints
    }
    with PeakMemory() as memory:
        for scene in scenes:
            frame = _padded(scene, operator)
            record = CheckpointRecorder(set(rows), None if trace is None else scene.truth)
            solver.solve(frame, iterations=max(checkpoints), tolerance=0.0, callback=record)
            for n, (seconds, estimate) in record.snapshots.items():
                _score(rows[n], scene, estimate, seconds)
            if trace is not None:
                trace[scene.name] = [record.scores[n] for n in sorted(record.scores)]
    for row in rows.values():
        row.peak_memory_mib = memory.mib
    return list(rows.values())


def equal_time_row(admm: Row, trace: dict[str, list[tuple[float, dict[str, float]]]],
                   reference: Row) -> Row:
    """LSV-ADMM read out, frame by frame, after the last iteration it completed within
    ``reference``'s seconds on that frame (at least one; at most the traced ones).

    ``admm`` is one of the traced run's rows (:func:`admm_rows` with ``trace``), whose
    set-up and memory the new row shares. The row keeps the reference's method and the
    trace in its settings, so that :func:`merge_reports` reads it out again when the
    reference alone is run anew.
    """
    row = Row(admm.method, f"K={admm.settings['rank']}, at {reference.method}'s time",
              {"rank": admm.settings["rank"], "tv_weight": admm.settings["tv_weight"],
               "reference": reference.method, "trace": trace},
              setup_seconds=admm.setup_seconds, peak_memory_mib=admm.peak_memory_mib)  # fmt: skip
    for name, steps in trace.items():
        budget = reference.per_scene[name]["seconds"]
        done = max(1, sum(seconds <= budget for seconds, _ in steps))
        seconds, quality = steps[done - 1]
        row.per_scene[name] = {**quality, "seconds": seconds, "iterations": done}
    counts = sorted({scores["iterations"] for scores in row.per_scene.values()})
    row.settings["iterations"] = counts
    row.knob += f" ({'–'.join(str(n) for n in dict.fromkeys((counts[0], counts[-1])))} it)"
    return row


def deconvolution_rows(operator: CM2Operator, scenes: list[Scene], plan: Plan) -> list[Row]:
    """Wiener and Richardson–Lucy rows at the plan's settings."""
    rows = []
    knobs = [("wiener", "balance", b) for b in plan.wiener_balances]
    knobs += [("rl", "iterations", n) for n in plan.rl_iterations]
    for method, name, value in knobs:
        start = time.perf_counter()
        rec = build_reconstructor(method, operator.system, operator=operator, **{name: value})
        setup = time.perf_counter() - start
        row = Row(registry.method(method).label, f"{name} {value:g}", {name: value},
                  setup_seconds=setup)  # fmt: skip
        rows.append(_score_reconstructor(row, rec, scenes))
    return rows


def admm_default_row(operator: CM2Operator, scenes: list[Scene]) -> Row:
    """LSV-ADMM at the system's ``K``: up to :data:`SYSTEM_K_ITERATIONS` iterations with
    the stopping tolerance and the fixed ``λ`` (minutes per frame).

    ``operator`` is the system's operator at its own rank (the nominal simulator's).
    """
    start = time.perf_counter()
    settings = settings_for(operator.system)
    reconstructor = build_reconstructor(
        "admm", operator.system, operator=operator, iterations=SYSTEM_K_ITERATIONS,
        tolerance=settings.tolerance, tv_weight=settings.tv_weight,
    )  # fmt: skip
    label = (f"K={reconstructor.operator.rank}, ≤{reconstructor.iterations} it, "
             f"tolerance {reconstructor.tolerance:g}")
    row = Row(f"{registry.method('admm').label} at the system's K", label,
              {"rank": reconstructor.operator.rank, "iterations": reconstructor.iterations,
               "tolerance": reconstructor.tolerance, "tv_weight": settings.tv_weight},
              setup_seconds=time.perf_counter() - start)
    return _score_reconstructor(row, reconstructor, scenes)


def model_label(weights: Path) -> str:
    """``SV-CoDe``, or e.g. ``SV-CoDe (no CoordGate, no PE)`` for a model with ablations,
    ``SV-CoDe (lens context)`` for one with
    :attr:`~svcode_core.network.ModelConfig.lens_context`, ``SV-CoDe (mirrored padding)``
    for one with :attr:`~svcode_core.network.ModelConfig.padding` ``"reflect"``,
    ``SV-CoDe (view margin 16)`` for one with
    :attr:`~svcode_core.network.ModelConfig.view_margin` 16."""
    config = read_model_metadata(weights)["model_config"]
    notes = [f"no {name}" for name, on in (("CoordGate", config.coord_gate),
                                           ("PE", config.positional_encoding)) if not on]
    reach = f", reach {config.context_reach}" if config.context_reach > 1 else ""
    notes += [f"lens context{reach}"] if config.lens_context else []
    notes += ["mirrored padding"] if config.padding == "reflect" else []
    notes += [f"view margin {config.view_margin}"] if config.view_margin else []
    return "SV-CoDe" + (f" ({', '.join(notes)})" if notes else "")


def _score_reconstructor(row: Row, reconstructor: Any, scenes: list[Scene]) -> Row:
    """Reconstruct every scene with ``reconstructor``; scores, times and peak into ``row``."""
    with PeakMemory() as memory:
        for scene in scenes:
            start = time.perf_counter()
            estimate = reconstructor.reconstruct(scene.raw).reconstruction
            _score(row, scene, estimate, time.perf_counter() - start)
    row.peak_memory_mib = memory.mib
    return row


def _cached(cache: dict | None, key: tuple, build: Callable[[], Any]) -> tuple[Any, float, bool]:
    """``build()`` once per key when a cache is given: (object, set-up seconds, fresh)."""
    if cache is not None and key in cache:
        return (*cache[key], False)
    start = time.perf_counter()
    made = build()
    entry = (made, time.perf_counter() - start)
    if cache is not None:
        cache[key] = entry
    return (*entry, True)


def svcode_rows(
    weights: Path,
    system: SystemConfig,
    scenes: list[Scene],
    all_knobs: bool | int = True,
    cache: dict | None = None,
    footprint: bool = True,
    precision: str = "fp32",
) -> list[Row]:
    """SV-CoDe rows over tiling, mask cache, precision and skipping (or the default only).

    ``all_knobs``: ``True`` every knob, ``False`` the default only, an integer ``n`` the
    first ``n`` (default: the planned tiling; the same with the periphery refinement
    (``refine_periphery``); then the system's patch ``P`` at stride
    ``P/2`` and ``P/4`` with batches of 8, channel attention pooled over ``P`` pixels
    (``pool_window``), ``P`` at ``P/2`` with batches of 1, cache off, bf16, skipping off).

    With ``cache`` (a dict kept across calls) each knob's reconstructor is built and warmed
    up once and reused for the scenes of later regimes. ``footprint`` measures the model's
    size and memory at S and 2S (in a subprocess: slow) on the first row. ``precision`` is
    the planned row's; a row's label names the precision that ran.
    """
    from svcode_core.methods.svcode import DEFAULT_MASK_CACHE_BYTES

    patch = system.patch_size
    planned = {"tile": None, "stride": None, "batch": None, "cache": True,
               "precision": precision, "skip": True}  # fmt: skip
    knobs = [
        planned,
        {**planned, "refine": REFINE_ITERATIONS},  # the only knob with "refine"
        {**planned, "tile": patch, "stride": patch // 2, "batch": 8},
        {**planned, "tile": patch, "stride": patch // 4, "batch": 8},
        {**planned, "pool": patch},  # the only knob with "pool": other rows keep their labels
        {**planned, "tile": patch, "stride": patch // 2, "batch": 1},
        {**planned, "cache": False},
        {**planned, "precision": "bf16"},
        {**planned, "skip": False},
    ]
    method = model_label(weights)
    rows = []
    chosen = knobs[: len(knobs) if all_knobs is True else max(1, int(all_knobs))]
    for knob in chosen:
        def build(knob: dict = knob) -> Any:
            rec = build_reconstructor(
                "svcode", system, weights, precision=knob["precision"], tile_size=knob["tile"],
                stride=knob["stride"], batch_size=knob["batch"], skip_empty=knob["skip"],
                mask_cache_bytes=DEFAULT_MASK_CACHE_BYTES if knob["cache"] else 0,
                pool_window=knob.get("pool"), refine_periphery=knob.get("refine", 0),
            )  # fmt: skip
            rec.reconstruct(scenes[0].raw)  # warm-up: fills the mask cache, as in a recording
            return rec

        key = ("svcode", str(weights), tuple(knob.items()))
        rec, setup, fresh = _cached(cache, key, build)
        ran = {**knob, "precision": rec.precision}  # "auto" resolved
        label = ", ".join(f"{k} {'planned' if v is None else v}" for k, v in ran.items())
        row = Row(method, label, ran, setup_seconds=setup)
        rows.append(_score_reconstructor(row, rec, scenes))
        if fresh and footprint and knob is knobs[0]:
            row.footprint = model_footprint(weights, system).to_dict()
    return rows


def learned_rows(
    weights: Path, system: SystemConfig, scenes: list[Scene], cache: dict | None = None
) -> list[Row]:
    """One row for a trained MultiWienerNet or SV-FourierNet, with its footprint."""
    method = registry.method_of_architecture(read_model_metadata(weights)["architecture"])

    def build() -> Any:
        rec = build_reconstructor(method, system, weights)
        rec.reconstruct(scenes[0].raw)  # warm-up
        return rec

    rec, setup, fresh = _cached(cache, ("learned", str(weights)), build)
    row = Row(registry.method(method).label, "fp32", {"precision": "fp32"}, setup_seconds=setup)
    _score_reconstructor(row, rec, scenes)
    if fresh:
        row.footprint = model_footprint(weights, system).to_dict()
    return [row]


# ------------------------------------------------------------------ driver
def regime_simulator(system: SystemConfig, regime: str, nominal: Simulator | None = None
                     ) -> Simulator:  # fmt: skip
    """The simulator of one regime: the nominal instrument for matched (``nominal`` when
    given, built once by callers that run several regimes), else the departed one."""
    if regime not in REGIMES:
        raise ValueError(f"unknown regime {regime!r}; choose from {', '.join(REGIMES)}")
    if regime == "matched":
        return Simulator(system) if nominal is None else nominal
    return Simulator(system, departures=Departures.named(REGIMES[regime], system))


def run_benchmark(
    system: SystemConfig,
    quick: bool = False,
    weights: Path | None = None,
    progress: Callable[[str], None] = print,
    methods: tuple[str, ...] = DEFAULT_FAMILIES,
    ablations: tuple[Path, ...] = (),
    learned: tuple[Path, ...] = (),
    regimes: tuple[str, ...] | None = None,
    all_knobs: bool = False,
    rank_sweep: bool = False,
) -> dict[str, Any]:
    """Run the rows of ``methods`` on the fixed scenes of ``regimes`` (default: the plan's,
    :func:`plan_for`); return the report.

    ``ablations`` are further SV-CoDe model files, benchmarked at the default knob only;
    ``learned`` are trained learned-baseline model files (the ``learned`` family). Every
    reconstructor is built once, for the nominal system, and used in every regime.
    ``all_knobs`` adds SV-CoDe's time-only knobs and ``rank_sweep`` ADMM at other ``K``,
    both in the matched regime only.
    """
    plan = plan_for(system, quick)
    regimes = plan.regimes if regimes is None else tuple(regimes)
    unknown = set(methods) - set(METHOD_FAMILIES)
    if unknown:
        raise ValueError(f"unknown method families {sorted(unknown)}; choose from "
                         f"{', '.join(METHOD_FAMILIES)}")  # fmt: skip
    for regime in regimes:
        if regime not in REGIMES:
            raise ValueError(f"unknown regime {regime!r}; choose from {', '.join(REGIMES)}")
    names = plan.scenes
    start = time.perf_counter()
    psfs = model_psfs(system)
    nominal = Simulator(system, CM2Operator.from_psfs(system, psfs))

    def operator(rank: int) -> tuple[CM2Operator, float]:
        begin = time.perf_counter()
        op = CM2Operator.from_psfs(system, psfs, rank=rank)
        return op, time.perf_counter() - begin

    if {"admm", "deconvolution"} & set(methods):
        op, setup = operator(ADMM_RANK)  # shared by both families and every regime
    notes = []
    if "svcode" in methods:
        weights = weights or bundled_weights(system)
        if weights is None:
            notes.append("SV-CoDe rows skipped: no --weights given and no bundled model")
    if "learned" in methods and not learned:
        notes.append("learned-baseline rows skipped: no --learned model files given")
    labels = [model_label(path) for path in [*ablations, *([weights] if weights else [])]]
    # ablations of the same network as other rows: told apart by file
    by_file = {path for path, label in zip(ablations, labels[: len(ablations)], strict=True)
               if labels.count(label) > 1}  # fmt: skip
    rows: list[Row] = []
    cache: dict = {}
    departures: dict[str, Any] = {}
    for regime in regimes:
        begin = time.perf_counter()
        simulator = regime_simulator(system, regime, nominal)
        departures[regime] = simulator.departures.to_dict() if simulator.departures else None
        scenes = make_scenes(system, names, simulator)
        progress(f"[{regime}] {len(scenes)} scenes simulated (true K = "
                 f"{simulator.operator.rank}) in {time.perf_counter() - begin:.1f} s")  # fmt: skip
        new: list[Row] = []
        trace: dict | None = {} if plan.equal_time else None
        # a family takes many minutes at paper scale: a line after each
        tick = "[{}] {}: {} rows ({:.0f} s)".format
        if "admm" in methods:
            checkpoints = plan.admm_checkpoints
            traced = admm_rows(op, scenes, checkpoints, f"K={ADMM_RANK}", setup, trace=trace)
            new += traced
            if plan.admm_auto:
                new += admm_rows(op, scenes, checkpoints, f"K={ADMM_RANK}", setup, "auto")
            if regime == "matched" and rank_sweep:
                for rank in RANK_SWEEP:
                    sweep, sweep_setup = operator(rank)
                    new += admm_rows(sweep, scenes, (RANK_SWEEP_ITERATIONS,), f"K={sweep.rank}",
                                     sweep_setup)  # fmt: skip
            progress(tick(regime, "LSV-ADMM", len(new), time.perf_counter() - start))
        if "deconvolution" in methods:
            new += deconvolution_rows(op, scenes, plan)
            progress(tick(regime, "Wiener and RL", len(new), time.perf_counter() - start))
        if "svcode" in methods and weights is not None:
            matched, other = plan.svcode_knobs
            knobs = (all_knobs or matched) if regime == "matched" else other
            main = svcode_rows(weights, system, scenes, all_knobs=knobs, cache=cache,
                               footprint=plan.footprint,
                               precision=plan.svcode_precision)  # fmt: skip
            new += main
            if trace:  # LSV-ADMM given SV-CoDe's time on each frame
                new.append(equal_time_row(traced[0], trace, main[0]))
            progress(tick(regime, "SV-CoDe", len(new), time.perf_counter() - start))
        for path in ablations:
            extra = svcode_rows(path, system, scenes, all_knobs=False, cache=cache,
                                footprint=plan.footprint)  # fmt: skip
            if path in by_file:
                for row in extra:
                    row.method += f" ({path.parent.name}/{path.name})"
            new += extra
        if "learned" in methods:
            for path in learned:
                new += learned_rows(path, system, scenes, cache=cache)
        if "admm-system-k" in methods:
            new.append(admm_default_row(nominal.operator, scenes))
        for row in new:
            row.regime = regime
        rows += new
        progress(f"[{regime}] {len(new)} rows done ({time.perf_counter() - start:.0f} s)")
    return {
        "system": system.name,
        "quick": quick,
        "plan": plan.name,
        "regimes": list(regimes),
        "departures": departures,
        "scenes": list(names),
        "simulator_rank": nominal.operator.rank,
        "zones": {"centre": f"r < {CENTRE_RADIUS}", "ring": f"r > {RING_RADIUS}"},
        "threads": torch.get_num_threads(),
        "machine": f"{platform.machine()} {platform.processor() or ''}".strip(),
        "torch": torch.__version__,
        "total_seconds": time.perf_counter() - start,
        "note": "; ".join(notes) or None,
        "rows": [row.summary() for row in rows],
    }


def _regimes(report: dict[str, Any]) -> list[str]:
    """Regimes of the report's rows in order (rows without one are matched)."""
    return list(dict.fromkeys(row.get("regime", "matched") for row in report["rows"]))


def _regime_title(regime: str) -> str:
    return f"{regime} ({INVERSE_CRIME})" if regime == "matched" else regime


def regime_table(report: dict[str, Any]) -> list[str]:
    """Markdown lines: PSNR (dB) of every method and knob (rows) in every regime (columns)."""
    regimes = _regimes(report)
    psnr: dict[tuple[str, str], dict[str, float]] = {}
    for row in report["rows"]:
        key = (row["method"], row["knob"])
        psnr.setdefault(key, {})[row.get("regime", "matched")] = row["psnr"]
    lines = [
        "| method | knob | " + " | ".join(regimes) + " |",
        "|---|---|" + "---|" * len(regimes),
    ]
    for (method, knob), values in psnr.items():
        cells = [f"{values[r]:.2f}" if r in values else "" for r in regimes]
        lines.append(f"| {method} | {knob} | " + " | ".join(cells) + " |")
    return lines


def write_markdown(report: dict[str, Any], path: Path) -> None:
    """The report as Markdown: PSNR per regime, then one full table per regime."""
    departures = report.get("departures") or {}
    lines = [
        "# Work–precision benchmark in every regime",
        "",
        f"System {report['system']}; scenes {', '.join(report['scenes'])}. The reconstructors "
        f"are given the nominal system (its forward model, K = {report['simulator_rank']} for "
        "the simulator, K = 3 for LSV-ADMM, Wiener and RL); the frames come from the regime's "
        "instrument (departures below, docs/regimes.md). The **matched** regime is the "
        f"{INVERSE_CRIME}, at the default sensor noise. Means over scenes; PSNR in dB "
        f"against the ground truth (data range 1); centre {report['zones']['centre']}, ring "
        f"{report['zones']['ring']} (normalised field radius). CPU, {report['threads']} "
        "thread(s), on a 2-core machine shared with other jobs: times are indicative to "
        "about ±30%. Set-up (operator build, norm estimate, model load) is excluded from "
        "s/frame. Peak MiB is the rise of the peak resident memory above the resident memory "
        "before the row: memory the allocator already holds from earlier rows is reused "
        "without being counted, so small rows after large ones under-report (down to 0). "
        f"Total run {report['total_seconds'] / 60:.1f} min.",
    ]
    if len(_regimes(report)) > 1:
        lines += ["", "## PSNR (dB) per regime", "", *regime_table(report)]
    for regime in _regimes(report):
        lines += ["", f"## {_regime_title(regime)}", ""]
        changed = departures.get(regime)
        if changed:
            nominal = Departures().to_dict()
            diff = {k: v for k, v in changed.items() if v != nominal[k] and k != "name"}
            lines += ["Departures: " + ", ".join(f"`{k}` = {v}" for k, v in diff.items()), ""]
        lines += [
            "| method | knob | PSNR | SSIM | PSNR centre | PSNR ring | s / frame | set-up s "
            "| peak MiB |",
            "|---|---|---|---|---|---|---|---|---|",
        ]
        for row in report["rows"]:
            if row.get("regime", "matched") != regime:
                continue
            memory = "" if row["peak_memory_mib"] is None else f"{row['peak_memory_mib']:.0f}"
            lines.append(
                f"| {row['method']} | {row['knob']} | {row['psnr']:.2f} | {row['ssim']:.3f} | "
                f"{row['psnr_centre']:.2f} | {row['psnr_ring']:.2f} | {row['seconds']:.3g} | "
                f"{row['setup_seconds']:.2f} | {memory} |"
            )
    sized = [row for row in report["rows"] if row.get("footprint")]
    if sized:
        lines += [
            "",
            "## Model size and memory at the field size S and 2S",
            "",
            "Parameters in millions; peak MiB: rise of the peak resident memory over building "
            "the model and reconstructing one frame of uniform noise (no tile skipped), at the "
            "system's sub-view size S and with every sensor length doubled (2S).",
            "",
            "| method | parameters (M), S | parameters (M), 2S | peak MiB, S | peak MiB, 2S |",
            "|---|---|---|---|---|",
        ]
        for row in sized:
            size = row["footprint"]
            peaks = [("" if v is None else f"{v:.0f}") for v in
                     (size["peak_mib"], size["peak_mib_2s"])]  # fmt: skip
            lines.append(f"| {row['method']} | {size['parameters_m']:.2f} | "
                         f"{size['parameters_m_2s']:.2f} | {peaks[0]} | {peaks[1]} |")  # fmt: skip
    if report["note"]:
        lines += ["", report["note"] + "."]
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")


def plot_pareto(report: dict[str, Any], path: Path) -> None:
    """Work–precision per regime: seconds per frame (log) against PSNR, Pareto fronts marked."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    regimes = _regimes(report)
    columns = min(3, len(regimes))
    count = -(-len(regimes) // columns)
    fig, axes = plt.subplots(count, columns, figsize=(5.2 * columns, 4.0 * count),
                             squeeze=False, sharey=True)  # fmt: skip
    methods = list(dict.fromkeys(row["method"] for row in report["rows"]))
    colours = {m: f"C{i % 10}" for i, m in enumerate(methods)}
    for ax, regime in zip(axes.flat, regimes, strict=False):
        rows = [r for r in report["rows"] if r.get("regime", "matched") == regime]
        for method in methods:
            mine = [r for r in rows if r["method"] == method]
            if mine:
                ax.scatter([r["seconds"] for r in mine], [r["psnr"] for r in mine],
                           color=colours[method], label=method, s=14)  # fmt: skip
        front = pareto_front([(r["seconds"], r["psnr"]) for r in rows])
        if front:
            ax.plot(*zip(*front, strict=True), "k--", lw=0.8, label="Pareto front")
        ax.set_xscale("log")
        ax.set_title(regime + (" (inverse crime)" if regime == "matched" else ""), fontsize=9)
        ax.set_xlabel("seconds per frame (CPU, log)", fontsize=8)
        ax.grid(alpha=0.3)
    for ax in axes.flat[len(regimes):]:
        ax.axis("off")
    for ax in axes[:, 0]:
        ax.set_ylabel("PSNR (dB), mean over scenes", fontsize=8)
    axes.flat[0].legend(fontsize=6)
    fig.suptitle(f"Work–precision per regime, {report['system']}")
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)


def pareto_front(points: list[tuple[float, float]]) -> list[tuple[float, float]]:
    """Points not beaten in both time (lower) and PSNR (higher), sorted by time."""
    front, best = [], -np.inf
    for seconds, quality in sorted(points, key=lambda p: (p[0], -p[1])):
        if quality > best:
            front.append((seconds, quality))
            best = quality
    return front


def merge_reports(earlier: dict[str, Any], report: dict[str, Any]) -> dict[str, Any]:
    """``report`` with the rows of ``earlier`` whose (regime, method) it did not run.

    An earlier row measured at another method's time (:func:`equal_time_row`) whose
    reference ``report`` ran anew is read out again from its trace at the new seconds, or
    left out, with a note, when the earlier report kept no trace: an old time budget
    never stands beside a new model.

    Raises
    ------
    ValueError
        If the two reports are of different systems, scenes or ``--quick`` settings.
    """
    for key in ("system", "scenes", "quick", "simulator_rank"):
        if earlier.get(key) != report[key]:
            raise ValueError(f"cannot merge into the earlier report: its {key} is "
                             f"{earlier.get(key)!r}, now {report[key]!r}")  # fmt: skip

    def key(row: dict[str, Any]) -> tuple[str, str]:
        return row.get("regime", "matched"), row["method"]

    ran = {key(row) for row in report["rows"]}
    references = {}
    for row in report["rows"]:  # a method's first row in a regime is its reference
        references.setdefault(key(row), row)
    kept, notes = [], [n for n in (earlier.get("note"), report["note"]) if n]
    for row in earlier["rows"]:
        if key(row) in ran:
            continue
        regime, reference = row.get("regime", "matched"), row.get("settings", {}).get("reference")
        if (regime, reference) in references:
            if "trace" not in row["settings"]:
                notes.append(f"{row['method']} {row['knob']} ({regime}) left out: "
                             f"{reference} was run anew and the earlier report kept no trace")
                continue
            row = _read_out_again(row, references[regime, reference])
        kept.append(row)
    return {
        **report,
        "total_seconds": earlier["total_seconds"] + report["total_seconds"],
        "note": "; ".join(dict.fromkeys(notes)) or None,
        "regimes": list(dict.fromkeys([*earlier.get("regimes", []),
                                       *report.get("regimes", [])])),
        "departures": {**earlier.get("departures", {}), **report.get("departures", {})},
        "rows": kept + report["rows"],
    }


def _read_out_again(row: dict[str, Any], reference: dict[str, Any]) -> dict[str, Any]:
    """The equal-time ``row`` of a report read out from its trace at ``reference``'s
    seconds on each frame."""
    settings = row["settings"]
    kept = {"rank": settings["rank"], "tv_weight": settings["tv_weight"]}
    admm = Row(row["method"], "", kept, setup_seconds=row["setup_seconds"],
               peak_memory_mib=row["peak_memory_mib"])  # fmt: skip
    trace = {name: [tuple(step) for step in steps] for name, steps in settings["trace"].items()}
    reference_row = Row(reference["method"], "", {}, per_scene=reference["per_scene"])
    again = equal_time_row(admm, trace, reference_row)
    again.regime, again.footprint = row.get("regime", "matched"), row.get("footprint")
    return again.summary()


def write_report(report: dict[str, Any], out: Path, merge: bool = False) -> Path:
    """Write ``regimes.{json,md,png}`` to ``out`` (one work–precision panel per regime).

    With ``merge``, the rows of other methods in an earlier ``regimes.json`` there are kept
    (:func:`merge_reports`). Returns the common stem ``out / "regimes"``.
    """
    out.mkdir(parents=True, exist_ok=True)
    stem = out / "regimes"
    if merge and Path(f"{stem}.json").is_file():
        report = merge_reports(json.loads(Path(f"{stem}.json").read_text()), report)
    Path(f"{stem}.json").write_text(json.dumps(report, indent=2) + "\n", encoding="utf-8")
    write_markdown(report, Path(f"{stem}.md"))
    plot_pareto(report, Path(f"{stem}.png"))
    return stem
