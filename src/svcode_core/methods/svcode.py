"""Reconstruct raw CM² frames with a trained SV-CoDe model, tile by tile.

:class:`Reconstructor` takes a raw sensor frame ``(H, W)`` (``system.sensor_shape``) or a
stack ``(T, H, W)``, validates it, zero-pads it, cuts the nine ``S × S`` sub-views (each
enlarged by the model's :func:`view_margin`, the field kept in the output), runs
the model over overlapping tiles (see :mod:`svcode_core.methods.tiling`) and returns the
reconstruction, optionally the nine demixed views, the time spent in each stage and the
tile counters.

Input handling
    NaN or Inf, a frame of the wrong size, an empty stack or a wrong number of dimensions
    raise :class:`ValueError` naming the problem. Negative values (left by dark-frame
    subtraction) are **clipped at 0** before the model: the training measurements are
    non-negative sensor readings, so the model has never seen negative input.

Exposure
    Each frame is brought to the level the model was trained at and the reconstruction
    (and the demixed views) scaled back (:mod:`~svcode_core.methods.exposure`): a frame
    read with another gain gives the same image at its own scale. The gains are in
    :attr:`ReconstructionResult.exposure_gains`. ``normalise_exposure=False`` feeds the
    frames as they are.

Devices and precision
    ``device`` is ``"cpu"``, ``"cuda"`` / ``"cuda:N"`` or ``"mps"``; an unavailable one is a
    clear error. ``precision`` ``"fp32"`` runs as is; ``"bf16"`` on the CPU runs a copy of
    the network in bf16 (:func:`features_in`), and on GPUs ``"bf16"`` and ``"fp16"`` run
    under :func:`torch.autocast`. ``"fp16"`` on the CPU is refused (PyTorch's CPU half-precision
    kernels are slow and partly missing): use ``"bf16"`` there. ``"auto"`` (the default)
    is :func:`auto_precision`: bf16 where the device computes it in hardware and the model
    file records that bf16 costs at most :data:`AUTO_TOLERANCE_DB` on the held-out
    benchmark, else fp32. Inputs and outputs stay on the host; only one batch of tiles is
    on the device at a time.
"""

from __future__ import annotations

import contextlib
import copy
import functools
import math
import threading
import time
import warnings
from collections.abc import Generator
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import torch

from ..config import DEFAULT_MEMORY_BUDGET, SystemConfig
from ..physics.geometry import context_views, extract_sub_views, pad_sensor_frame
from ..physics.noise import noise_floor
from . import registry
from .base import (
    PRECISIONS,
    BaseReconstructor,
    FrameProgress,
    ReconstructionResult,
    native_bf16,
    precision_dtype,
    resolve_device,
)
from .exposure import exposure_gain
from .frames import finite_frame
from .periphery import PeripheryRefinement
from .tiling import (
    DEFAULT_SKIP_FACTOR,
    Cancelled,
    TileGrid,
    TileProgress,
    iter_tiled,
    tiles_with_signal,
)

__all__ = ["AUTO_TOLERANCE_DB", "Reconstructor", "TilePlan", "auto_precision", "bf16_network",
           "features_in", "plan_tiles", "tile_overlap", "tile_plan", "view_margin"]

_SVCODE = registry.method("svcode")
_DEFAULTS = _SVCODE.defaults
DEFAULT_MASK_CACHE_BYTES = _DEFAULTS["mask_cache_bytes"]
DEFAULT_TILE_MEMORY_BYTES = DEFAULT_MEMORY_BUDGET
#: the most bf16 may lose against fp32 (mean PSNR of a held-out regime, dB) for ``"auto"``
#: to choose it
AUTO_TOLERANCE_DB = 0.05


def auto_precision(checks: dict[str, Any], device: str | torch.device) -> str:
    """The precision ``"auto"`` runs a model in on ``device``: ``"bf16"`` where the device
    computes bf16 in hardware (:func:`~.base.native_bf16`) and the model's own check
    (``checks``: ``precision_check`` in its file's ``extra`` metadata, written by
    ``bench/precision.py --record``) found bf16 within :data:`AUTO_TOLERANCE_DB` of fp32 in
    every held-out regime; else ``"fp32"``.

    Examples
    --------
    >>> auto_precision({}, "cpu")  # nothing recorded
    'fp32'
    >>> auto_precision({"bf16": {"loss_db": 0.3}}, "cpu")  # bf16 costs too much
    'fp32'
    """
    check = checks.get("bf16")
    if check is not None and check["loss_db"] <= AUTO_TOLERANCE_DB:
        if native_bf16(torch.device(device)):
            return "bf16"
    return "fp32"


def _concrete(precision: str, model: torch.nn.Module | None, device: str | torch.device) -> str:
    """``precision``, with ``"auto"`` resolved for ``model`` (its file's check) on
    ``device``."""
    if precision != "auto":
        return precision
    return auto_precision(getattr(model, "precision_check", {}), device)


def bf16_network(
    model: torch.nn.Module, device: torch.device
) -> tuple[torch.nn.Module, torch.dtype | None]:
    """How ``model`` runs in bf16 on ``device``: an SV-CoDe model on the CPU as its bf16
    copy (:func:`features_in`), fed bf16 inputs (returned: the copy and ``torch.bfloat16``);
    anything else as it is, under autocast (returned: ``model`` and ``None``)."""
    if device.type == "cpu" and hasattr(model, "_gates"):
        return features_in(model, torch.bfloat16), torch.bfloat16
    return model, None


def features_in(model: torch.nn.Module, dtype: torch.dtype) -> torch.nn.Module:
    """A copy of an SV-CoDe ``model`` that computes its features in ``dtype``: every weight
    in ``dtype`` but the coordinate MLPs', which stay float32 (a coordinate needs float32's
    resolution across a 2400-px sub-view; their masks are made in float32 and stored in
    ``dtype``). Unlike autocast, no layer casts its input, so on the CPU a bf16 frame runs
    about 1.4x faster at the same accuracy. ``model`` itself is left as it is.

    Examples
    --------
    >>> from svcode_core.network import ModelConfig, SVCoDe
    >>> copy = features_in(SVCoDe(ModelConfig.mini()), torch.bfloat16)
    >>> sorted({p.dtype for p in copy.parameters()}, key=str)
    [torch.bfloat16, torch.float32]
    """
    keep = {id(p) for _, gate in model._gates.values() for p in gate.mlp.parameters()}
    cache = model._mask_cache
    copied = copy.deepcopy(model, memo={id(cache): None})  # the cache is not the copy's
    for original, param in zip(model.parameters(), copied.parameters(), strict=True):
        if id(original) not in keep:
            param.data = param.data.to(dtype)
    return copied


def plan_tiles(
    model: torch.nn.Module,
    sub_view_size: int,
    memory_bytes: int = DEFAULT_TILE_MEMORY_BYTES,
    dtype: torch.dtype = torch.float32,
) -> tuple[int, int, int]:
    """Tile side, stride and batch for a model and a sub-view size within a memory budget.

    The whole sub-view is one tile when its working memory
    (:meth:`~svcode_core.network.SVCoDe.working_bytes_per_pixel`) fits in
    ``memory_bytes``: nothing is computed twice and there are no seams. Otherwise the
    tile is the largest multiple of the model stride that fits, and tiles overlap by
    :func:`tile_overlap` (rounded up to the stride, at most half a tile), so every pixel is
    computed about ``(P / (P - overlap))²`` times instead of 4 times at stride ``P / 2``;
    as many tiles as fit run in one batch.

    Parameters
    ----------
    model : torch.nn.Module
        An SV-CoDe model (with ``stride``, ``working_bytes_per_pixel`` and
        ``receptive_radius``).
    sub_view_size : int
        ``S``.
    memory_bytes : int
        Working-memory budget of one batch.
    dtype : torch.dtype
        Compute dtype.

    Returns
    -------
    tuple of int
        ``(tile, stride, batch)``.

    Examples
    --------
    >>> from svcode_core.network import ModelConfig, SVCoDe
    >>> plan_tiles(SVCoDe(ModelConfig.mini()), 384)
    (384, 384, 1)
    >>> plan_tiles(SVCoDe(ModelConfig.reference()), 2400)
    (400, 272, 1)
    """
    step, per_pixel = model.stride, model.working_bytes_per_pixel(dtype)
    padded = math.ceil(sub_view_size / step) * step
    if padded**2 * per_pixel <= memory_bytes:
        return sub_view_size, sub_view_size, 1
    side = max(step, math.isqrt(memory_bytes // per_pixel) // step * step)
    side = min(side, sub_view_size)
    overlap = min(math.ceil(tile_overlap(model) / step) * step, side // 2)
    batch = max(1, memory_bytes // (side**2 * per_pixel))
    return side, max(side - overlap, 1), batch


def tile_overlap(model: torch.nn.Module) -> int:
    """Sub-view pixels by which planned tiles overlap: the overlap measured for the model
    (``overlap_check`` in its file's ``extra`` metadata, written by ``bench/tile_overlap.py
    --record`` and kept by a fine-tuning from that file: the smallest that loses at most
    :data:`AUTO_TOLERANCE_DB` of PSNR on the held-out scenes against the receptive radius),
    else the receptive radius, where tiled and whole outputs agree but for the channel
    attention.

    Examples
    --------
    >>> from svcode_core.network import ModelConfig, SVCoDe
    >>> model = SVCoDe(ModelConfig.mini())
    >>> tile_overlap(model) == model.receptive_radius()
    True
    >>> model.overlap_check = {"overlap": 24}
    >>> tile_overlap(model)
    24
    """
    measured = getattr(model, "overlap_check", {}).get("overlap")
    return model.receptive_radius() if measured is None else int(measured)


class TilePlan(NamedTuple):
    """The tiles a :class:`Reconstructor` runs: ``grid``, ``batch_size`` and the estimated
    ``working_bytes`` of one batch (0 for a model that does not say)."""

    grid: TileGrid
    batch_size: int
    working_bytes: int


def tile_plan(
    model: torch.nn.Module | None,
    system: SystemConfig,
    precision: str = "auto",
    tile_size: int | None = None,
    stride: int | None = None,
    batch_size: int | None = None,
    tile_memory_bytes: int = DEFAULT_TILE_MEMORY_BYTES,
    device: str | torch.device = "cpu",
) -> TilePlan:
    """The tiling of :class:`Reconstructor` (its arguments of the same names; a ``None``
    is planned): what ``svcode reconstruct`` and the plugin run and estimate. The tiles
    cover the sub-view, enlarged by the model's :func:`view_margin`.

    Without ``tile_size``, an SV-CoDe model's tiles come from :func:`plan_tiles` and other
    models (or ``None``) take ``system.patch_size``; a given tile is strided by half. Without
    ``batch_size``, up to 8 tiles a batch, as many as fit ``tile_memory_bytes`` (at least
    one).

    Examples
    --------
    >>> system = SystemConfig.preset("cm2-mini")
    >>> plan = tile_plan(None, system, tile_size=7)
    >>> len(plan.grid), plan.grid.stride, plan.batch_size
    (16129, 3, 8)
    """
    planned_batch = 8
    precision = _concrete(precision, model, device)
    field = system.sub_view_size + 2 * view_margin(model)
    if tile_size is None and hasattr(model, "working_bytes_per_pixel"):
        tile_size, planned, planned_batch = plan_tiles(
            model, field, tile_memory_bytes, PRECISIONS[precision]
        )
        stride = planned if stride is None else stride
    elif tile_size is None:
        tile_size = system.patch_size
        stride = system.patch_stride if stride is None else stride
    elif stride is None:
        stride = max(tile_size // 2, 1)
    grid = TileGrid(field, tile_size, stride)
    per_tile = 0
    if hasattr(model, "working_bytes_per_pixel"):
        side = math.ceil(tile_size / model.stride) * model.stride
        per_tile = side**2 * model.working_bytes_per_pixel(PRECISIONS[precision])
        planned_batch = max(1, min(planned_batch, tile_memory_bytes // per_tile))
    batch_size = planned_batch if batch_size is None else batch_size
    return TilePlan(grid, batch_size, batch_size * per_tile)


def view_margin(model: torch.nn.Module | None) -> int:
    """Pixels by which ``model`` sees each sub-view past its window
    (:attr:`~svcode_core.network.ModelConfig.view_margin`; 0 for models without one).

    Examples
    --------
    >>> from svcode_core.network import ModelConfig, SVCoDe
    >>> view_margin(SVCoDe(ModelConfig.mini().replace(view_margin=16)))
    16
    """
    return getattr(getattr(model, "model_config", None), "view_margin", 0)


def _relay(
    tiled: Generator[TileProgress, None, Any], index: int, count: int
) -> Generator[FrameProgress, None, Any]:
    """Re-yield a frame's tile progress as :class:`FrameProgress`; return its output."""
    while True:
        try:
            progress = next(tiled)
        except StopIteration as stop:
            return stop.value
        try:
            yield FrameProgress(index, count, progress.done, progress.total)
        except GeneratorExit:
            tiled.close()
            raise


class Reconstructor(BaseReconstructor):
    """Tiled SV-CoDe reconstruction of raw CM² frames.

    Its options with a ``svcode reconstruct`` flag (``tile_size`` to ``refine_periphery``)
    take their defaults and checks from the method's table
    (:mod:`~svcode_core.methods.registry`); the tiling is :func:`tile_plan`'s.

    Parameters
    ----------
    model : torch.nn.Module
        ``model(views (B, 9, P, P), origins (B, 2) long, sub_view_size) ->
        (demixed (B, 9, P, P), reconstruction (B, 1, P, P))``.
    system : SystemConfig
        The instrument the frames come from (and the model was trained for).
    device : str
        ``"cpu"``, ``"cuda"``, ``"cuda:N"`` or ``"mps"``.
    precision : {"auto", "fp32", "bf16", "fp16"}
        ``"auto"``: :func:`auto_precision`; :attr:`precision` holds the one chosen.
    tile_size : int, optional
        Tile side ``P``. Default: :func:`plan_tiles` within ``tile_memory_bytes`` (the
        whole sub-view when it fits) for an SV-CoDe model, else ``system.patch_size``.
    stride : int, optional
        Default: the planned stride with the planned tile, ``system.patch_stride`` with
        the system's patch size, else ``tile_size // 2``.
    batch_size : int, optional
        Tiles per model call; default planned (8 with the system's patch size).
    skip_empty : bool
        Skip tiles without signal (see :mod:`svcode_core.methods.tiling`).
    skip_factor : float
        ``k`` of the skip threshold ``dark_offset + k · noise_floor``.
    mask_cache_bytes : int
        Memory for frozen coordinate masks (:meth:`SVCoDe.cache_masks`), reused by every
        tile and frame; 0 recomputes them for each batch. For models whose masks sit on a
        lattice (``ModelConfig.mask_spacing``, the bundled one) it keeps each tile's
        interpolated masks, read by every frame after the first: the default (1 GiB)
        holds the bundled ``cm2-mini`` model's whole-sub-view tile (614 MiB; about 1.4×
        faster with them kept). A budget smaller than every tile's masks
        (:meth:`lattice_mask_bytes`; a cm2-v2 frame's 25 tiles need 33 GiB) keeps none.
        Models with exact per-pixel masks keep their masks over the whole sub-view
        (:meth:`SVCoDe.mask_field_bytes`, 640 MiB for a ``cm2-mini`` one; a smaller
        budget caches part of them, 256 MiB: about 4× slower).
    tile_memory_bytes : int
        Working-memory budget of one batch of tiles for the default tiling.
    pool_window : int, optional
        Pool the channel attention over this many pixels around each pixel (the training
        patch size, 96 for the bundled model) instead of the whole tile
        (:attr:`~svcode_core.network.ModelConfig.pool_window`); default: as the model file
        says. Tiles of any size then agree with the whole sub-view (no seams), at about
        1.3× the time of a whole-sub-view tile.
    refine_periphery : int
        LSV-ADMM iterations that refine the field's periphery from the network's
        reconstruction (:class:`~svcode_core.methods.periphery.PeripheryRefinement`); 0
        (default): none. 10 raised the bundled ``cm2-mini`` model's held-out scores in
        every regime, the outer ring most, for 2–4× the time of a frame.
    normalise_exposure : bool
        Bring each frame to the model's training level and scale the output back
        (default); ``False`` runs the frames as they are.

    Examples
    --------
    A trained model comes from a file (``Reconstructor.from_weights(path, device="cuda")``)
    or with the package (:meth:`pretrained`); here an untrained one on a small system:

    >>> from svcode_core.config import SystemConfig
    >>> tiny = SystemConfig.tiny()  # sensor 60 × 80, sub-views 48 × 48
    >>> from svcode_core.network import ModelConfig, SVCoDe
    >>> rec = Reconstructor(SVCoDe(ModelConfig.mini()), tiny)
    >>> result = rec(np.full((60, 80), 0.1, dtype=np.float32))
    >>> result.reconstruction.shape, result.tiles_total
    ((48, 48), 1)
    """

    method = "svcode"

    def __init__(
        self,
        model: torch.nn.Module,
        system: SystemConfig,
        device: str | torch.device = "cpu",
        precision: str = "auto",
        tile_size: int | None = None,
        stride: int | None = None,
        batch_size: int | None = None,
        skip_empty: bool = _DEFAULTS["skip_empty"],
        skip_factor: float = DEFAULT_SKIP_FACTOR,
        mask_cache_bytes: int = DEFAULT_MASK_CACHE_BYTES,
        tile_memory_bytes: int = DEFAULT_TILE_MEMORY_BYTES,
        pool_window: int | None = None,
        refine_periphery: int = _DEFAULTS["refine_periphery"],
        normalise_exposure: bool = True,
    ) -> None:
        if not isinstance(system, SystemConfig):
            raise TypeError(f"system must be a SystemConfig, got {type(system).__name__}")
        self.system = system.validate()
        self.device = resolve_device(device)
        precision = _concrete(precision, model, self.device)
        precision_dtype(precision, self.method)
        if precision == "fp16" and self.device.type == "cpu":
            raise ValueError("precision: fp16 is not supported on the CPU; use bf16 or fp32")
        self.precision = precision
        _SVCODE.check({"tile_size": tile_size, "stride": stride, "batch_size": batch_size,
                       "pool_window": pool_window})  # fmt: skip
        for name, value in (("skip_empty", skip_empty), ("mask_cache_bytes", mask_cache_bytes),
                            ("refine_periphery", refine_periphery)):  # fmt: skip
            _SVCODE.option(name).check(value)  # None refused: these have a default
        plan = tile_plan(model, system, precision, tile_size, stride, batch_size,
                         tile_memory_bytes)  # fmt: skip
        self.grid, self.batch_size = plan.grid, plan.batch_size
        if not math.isfinite(skip_factor) or skip_factor < 0:
            raise ValueError(f"skip_factor must be a finite number >= 0, got {skip_factor!r}")
        self.skip_empty = skip_empty
        self.skip_threshold = system.noise.dark_offset + skip_factor * noise_floor(system.noise)
        self._features = None
        if precision == "bf16":
            model, self._features = bf16_network(model, self.device)
        self.model = model.to(self.device).eval()
        config = getattr(model, "model_config", None)
        #: pixels by which the model sees each sub-view past its window
        self.view_margin = view_margin(model)
        m = self.view_margin
        self._crop_views = (
            functools.partial(context_views, reach=config.context_reach, origin=(-m, -m),
                              size=system.sub_view_size + 2 * m)
            if getattr(config, "lens_context", False)
            else functools.partial(extract_sub_views, margin=m)
        )
        if pool_window is not None:
            if not hasattr(self.model, "set_pool_window"):
                raise ValueError(
                    f"pool_window: {type(model).__name__} has no channel attention to pool"
                )
            self.model.set_pool_window(pool_window)
        if hasattr(self.model, "cache_masks"):
            if 0 < mask_cache_bytes < self.lattice_mask_bytes():
                # the tiles' masks would evict each other (each frame runs them in turn),
                # so a cache would be written and never read: masks are made per tile
                mask_cache_bytes = 0
            self.model.cache_masks(enabled=mask_cache_bytes > 0, max_bytes=mask_cache_bytes)
        self.normalise_exposure = bool(normalise_exposure)
        self.refinement = None
        if refine_periphery > 0:
            self.refinement = PeripheryRefinement(system, refine_periphery, str(self.device))

    def lattice_mask_bytes(self) -> int:
        """Bytes of the interpolated masks of every tile of a frame, for a model whose masks
        sit on a lattice (``ModelConfig.mask_spacing``); 0 for other models.

        The mask cache keeps such a model's masks per tile, so it serves the next frame
        only when it holds them all: with a smaller ``mask_cache_bytes`` the cache is off
        (each tile's masks are interpolated where they are used and not kept).

        Examples
        --------
        >>> from svcode_core.network import ModelConfig, SVCoDe
        >>> system = SystemConfig.preset("cm2-mini")
        >>> model = SVCoDe(ModelConfig.mini().replace(mask_spacing=8))
        >>> round(Reconstructor(model, system).lattice_mask_bytes() / 2**20)  # one tile
        614
        """
        config = getattr(self.model, "model_config", None)
        if not getattr(config, "mask_spacing", 0) or not hasattr(self.model, "mask_field_bytes"):
            return 0
        step, size = self.model.stride, self.grid.size
        cells = math.ceil((size + step - 1) / step) * step  # the side mask_field_bytes counts
        side = math.ceil(self.grid.patch / step) * step  # a tile padded to the stride
        field = self.model.mask_field_bytes(size, PRECISIONS[self.precision])
        return len(self.grid) * field * side**2 // cells**2

    @classmethod
    def build(
        cls,
        method: str,
        system: SystemConfig | None,
        weights: str | Path | None = None,
        model: torch.nn.Module | None = None,
        **options: Any,
    ) -> Reconstructor:
        """From ``model``, else the model file ``weights``, else the bundled model of
        ``system`` (:class:`FileNotFoundError` when there is none)."""
        if model is not None:
            return cls(model, system, **options)
        if weights is None:
            from ..pretrained import require_bundled_weights

            weights = require_bundled_weights(system)
        return cls.from_weights(weights, system, **options)

    @classmethod
    def from_weights(
        cls, path: str | Path, system: SystemConfig | None = None, **options: Any
    ) -> Reconstructor:
        """Load a trained model (and its system, unless given) and wrap it.

        ``system`` may differ from the model's training system only in the fields a network
        does not see (:data:`~svcode_core.methods.model_file.FREE_FIELDS`: chief rays,
        measured PSFs, pixel sizes): the sub-views are then cut at its rays. ``options``
        are those of the constructor (``device``, ``precision`` ...).
        """
        from .model_file import load_model

        model, trained = load_model(path, system=system, device=options.get("device", "cpu"))
        return cls(model, trained if system is None else system, **options)

    @classmethod
    def pretrained(cls, system: SystemConfig | str = "cm2-mini", **options: Any) -> Reconstructor:
        """The model bundled with the package for ``system`` (a configuration or a name).

        Raises
        ------
        FileNotFoundError
            If no model is bundled for that system.
        """
        from ..pretrained import require_bundled_weights

        path = require_bundled_weights(system)
        return cls.from_weights(
            path, system if isinstance(system, SystemConfig) else None, **options
        )

    # ------------------------------------------------------------------ input
    def prepare(self, frame: np.ndarray, index: int = 0) -> np.ndarray:
        """One raw frame → its nine sub-views ``(9, S, S)`` float32 (checked, clipped at 0);
        ``(9 k, S, S)`` with each lens's ``k`` context crops for a model with
        :attr:`~svcode_core.network.ModelConfig.lens_context`; ``S + 2m`` square for a
        model with a :attr:`view_margin` ``m``."""
        return self._cut(self._values(frame, index))

    @staticmethod
    def _values(frame: np.ndarray, index: int) -> np.ndarray:
        return np.maximum(finite_frame(frame, index), 0.0)

    def _cut(self, values: np.ndarray) -> np.ndarray:
        padded = pad_sensor_frame(torch.from_numpy(values), self.system)
        return np.ascontiguousarray(self._crop_views(padded, self.system).numpy())

    @property
    def frames_side_by_side(self) -> bool:  # type: ignore[override]
        """On the CPU with one tile per frame (the whole sub-view): then a frame's network
        layers are too small to keep several cores busy, a frame's working memory is one
        tile's, and frames share nothing but the locked mask cache."""
        return self.device.type == "cpu" and len(self.grid) == 1

    # ------------------------------------------------------------------ model
    def _autocast(self) -> contextlib.AbstractContextManager:
        if self.precision == "fp32" or self._features is not None:
            return contextlib.nullcontext()
        return torch.autocast(self.device.type, dtype=PRECISIONS[self.precision])

    def _run_batch(
        self, tiles: np.ndarray, origins: np.ndarray, want_views: bool
    ) -> tuple[np.ndarray | None, np.ndarray]:
        with torch.inference_mode(), self._autocast():
            inputs = torch.from_numpy(tiles).to(self.device, self._features)
            where = torch.from_numpy(origins - self.view_margin).to(self.device)
            demixed, recon = self.model(inputs, where, self.system.sub_view_size)
        views = demixed.float().cpu().numpy() if want_views else None
        return views, recon.float().cpu().numpy()

    def _warn_all_skipped(self) -> None:
        """Say that a frame with light in it came out 0 because every tile was skipped (the
        same text for every frame, so Python's filter shows it once)."""
        warnings.warn(
            "a frame below the skipping threshold in every tile "
            f"({self.skip_threshold:.3g} of the full scale, above the sensor's noise) is "
            "reconstructed as 0: if the frames are in other units, pass the sensor's "
            "full-scale count (--input-scale); to run every tile anyway, --no-skip "
            "(skip_empty=False)",
            UserWarning,
            stacklevel=3,
        )

    # ---------------------------------------------------------------- running
    def iter_reconstruct(
        self,
        frames: Any,
        return_views: bool = False,
        cancel: threading.Event | None = None,
    ) -> Generator[FrameProgress, None, ReconstructionResult]:
        """Generator form of :meth:`reconstruct`: yields progress after every batch of tiles
        and, with the periphery refinement, once more before it (``refining``).

        Stop it with ``.close()`` or by setting ``cancel`` (then
        :class:`~svcode_core.methods.tiling.Cancelled` is raised); the result is the generator's
        return value.
        """
        stack = self.check_frames(frames)
        single = np.asarray(frames).ndim == 2
        count, size = stack.shape[0], self.system.sub_view_size
        recon = np.empty((count, size, size), dtype=np.float32)
        views = np.empty((count, 9, size, size), dtype=np.float32) if return_views else None
        result = ReconstructionResult(recon, views)
        timings = dict.fromkeys(("prepare", "model", "blend", "refine", "total"), 0.0)
        start_all = time.perf_counter()

        def run(tiles: np.ndarray, origins: np.ndarray) -> tuple[np.ndarray | None, np.ndarray]:
            return self._run_batch(tiles, origins, return_views)

        gains = np.ones(count)
        for index in range(count):
            start = time.perf_counter()
            values = self._values(stack[index], index)
            sub_views = self._cut(values)
            active = None
            if self.skip_empty:  # the sensor's noise is in the frame's own units
                active = tiles_with_signal(sub_views, self.grid, self.skip_threshold)
                if not active.any() and sub_views.max() > 0:
                    self._warn_all_skipped()
            if self.normalise_exposure:
                gains[index] = exposure_gain(values)
                sub_views *= np.float32(gains[index])
            timings["prepare"] += time.perf_counter() - start
            start = time.perf_counter()
            tiled = iter_tiled(
                run, sub_views, self.grid, self.batch_size, active, return_views, cancel
            )
            output = yield from _relay(tiled, index, count)
            timings["model"] += output.model_seconds
            timings["blend"] += time.perf_counter() - start - output.model_seconds
            field = (slice(self.view_margin, self.view_margin + size),) * 2
            recon[index] = output.reconstruction[field] / np.float32(gains[index])
            if self.refinement is not None:
                yield FrameProgress(index, count, output.tiles_run, output.tiles_run, True)
                if cancel is not None and cancel.is_set():
                    raise Cancelled("reconstruction cancelled")
                start = time.perf_counter()
                recon[index] = self.refinement(stack[index], recon[index], index)
                timings["refine"] += time.perf_counter() - start
            if views is not None:
                views[index] = output.views[(slice(None), *field)] / np.float32(gains[index])
            result.tiles_run += output.tiles_run
            result.tiles_skipped += output.tiles_skipped
        result.tiles_total = result.tiles_run + result.tiles_skipped
        result.exposure_gains = gains
        timings["total"] = time.perf_counter() - start_all
        result.timings = timings
        if single:
            result.reconstruction = recon[0]
            result.views = None if views is None else views[0]
        return result
