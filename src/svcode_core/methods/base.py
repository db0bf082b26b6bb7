"""The contract every reconstruction method keeps: raw frames in, a result out.

:class:`BaseReconstructor` is what SV-CoDe (:class:`~svcode_core.methods.svcode.Reconstructor`),
the model-based baselines and the learned baselines have in common, so that the streaming
command line, the dask back end, the benchmark and the napari plugin run any of them the
same way:

* ``reconstruct(frames, return_views=False)`` (also ``reconstructor(frames)``) takes a raw
  frame ``(H, W)`` or a stack ``(T, H, W)`` and returns a :class:`ReconstructionResult`
  shaped like its input;
* ``iter_reconstruct(frames, return_views, cancel)`` does the same as a generator that
  yields :class:`FrameProgress` and returns the result;
* the input is checked before any work by :meth:`BaseReconstructor.check_frames`
  (:func:`~svcode_core.methods.frames.as_frame_stack` and :func:`check_frame_shape`) and
  frame by frame with :func:`~svcode_core.methods.frames.finite_frame`;
* ``precision`` is one of the method's precisions in the registry
  (:mod:`svcode_core.methods.registry`), turned into a dtype by :func:`precision_dtype`.

:class:`FrameByFrame` supplies the loop for the methods that reconstruct a whole frame at a
time (yielding before every frame and, for the iterative ones, after every iteration);
SV-CoDe yields tile by tile instead.
"""

from __future__ import annotations

import contextlib
import threading
import time
from abc import ABC, abstractmethod
from collections.abc import Generator
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from ..config import SystemConfig
from . import registry
from .frames import as_frame_stack, finite_frame
from .tiling import Cancelled, exhaust

__all__ = [
    "PRECISIONS",
    "BaseReconstructor",
    "FrameByFrame",
    "FrameProgress",
    "ReconstructionResult",
    "check_frame_shape",
    "native_bf16",
    "precision_dtype",
    "resolve_device",
]

#: every compute precision by name; each method accepts those of its registry entry
#: (SV-CoDe also ``"auto"``, which chooses one of these: :func:`.svcode.auto_precision`)
PRECISIONS: dict[str, torch.dtype] = {
    "fp32": torch.float32,
    "fp64": torch.float64,
    "bf16": torch.bfloat16,
    "fp16": torch.float16,
}


def precision_dtype(precision: str, method_name: str, reason: str = "") -> torch.dtype:
    """The dtype of ``precision`` if method ``method_name`` accepts it.

    Parameters
    ----------
    precision : str
    method_name : str
        A name of :data:`~svcode_core.methods.registry.METHODS`.
    reason : str
        Why the method refuses the precisions it does not accept, for the message.

    Raises
    ------
    ValueError
        For a precision the method does not accept.

    Examples
    --------
    >>> precision_dtype("fp64", "admm")
    torch.float64
    >>> precision_dtype("bf16", "admm")
    Traceback (most recent call last):
    ...
    ValueError: precision: bf16 is not supported by LSV-ADMM (TV); use fp32 or fp64
    """
    entry = registry.method(method_name)
    if precision not in entry.precisions:
        known = " or ".join(entry.precisions)
        if precision in PRECISIONS:
            raise ValueError(
                f"precision: {precision} is not supported by {entry.title}"
                f"{' (' + reason + ')' if reason else ''}; use {known}"
            )
        raise ValueError(f"precision: {precision!r} is not one of {known}")
    return PRECISIONS[precision]


def native_bf16(device: torch.device) -> bool:
    """Whether ``device`` computes in bfloat16 in hardware, where bf16 is faster than fp32:
    a CPU with AVX-512 BF16 or AMX units, or a CUDA GPU with bf16 arithmetic (elsewhere
    bf16 is emulated and slower)."""
    if device.type == "cpu":
        probes = ("_is_avx512_bf16_supported", "_is_amx_tile_supported")
        return any(getattr(torch.cpu, name, lambda: False)() for name in probes)
    if device.type == "cuda":
        return torch.cuda.is_bf16_supported(including_emulation=False)
    return False


def resolve_device(device: str | torch.device) -> torch.device:
    """A :class:`torch.device` for ``device``, or a clear error when it is unavailable."""
    try:
        resolved = torch.device(device)
    except (RuntimeError, TypeError) as err:
        raise ValueError(f"device: {device!r} is not a device name ({err})") from None
    if resolved.type == "cuda" and not torch.cuda.is_available():
        raise ValueError("device: CUDA is not available (no GPU, or PyTorch built without CUDA)")
    if resolved.type == "cuda" and resolved.index is not None:
        if resolved.index >= torch.cuda.device_count():
            raise ValueError(
                f"device: {device} does not exist ({torch.cuda.device_count()} CUDA devices)"
            )
    if resolved.type == "mps" and not torch.backends.mps.is_available():
        raise ValueError("device: MPS (Apple GPU) is not available on this machine")
    if resolved.type not in ("cpu", "cuda", "mps"):
        raise ValueError(f"device: {device!r} is not supported; use cpu, cuda or mps")
    return resolved


def check_frame_shape(shape: tuple[int, ...], system: SystemConfig) -> None:
    """Raise :class:`ValueError` unless ``shape`` is the raw sensor size of ``system``."""
    expected = tuple(system.sensor_shape)
    if tuple(shape) == expected:
        return
    got = "×".join(map(str, shape))
    hint = ""
    if tuple(shape) == tuple(system.padded_shape):
        hint = " (this is the padded size: pass the raw, unpadded sensor frame)"
    elif len(shape) == 2 and shape[-1] in (3, 4):
        hint = (
            " (a colour image, read as a stack of its rows? a CM² frame is grey: one "
            "value per sensor pixel)"
        )
    raise ValueError(
        f"frame is {got} pixels but system {system.name!r} expects raw sensor frames of "
        f"{expected[0]}×{expected[1]}{hint}; check that the system configuration "
        "(--system, or the one stored with the data) matches the input"
    )


@dataclass(frozen=True)
class FrameProgress:
    """Progress of a reconstruction: frame ``frame`` of ``frames``, tiles of that frame;
    ``refining`` when the frame's tiles are done and its periphery refinement starts
    (SV-CoDe with ``refine_periphery``)."""

    frame: int
    frames: int
    tiles_done: int
    tiles_total: int
    refining: bool = False


@dataclass
class ReconstructionResult:
    """What every reconstructor's ``reconstruct`` returns.

    Attributes
    ----------
    reconstruction : numpy.ndarray
        ``(S, S)`` for a frame, ``(T, S, S)`` for a stack; float32.
    views : numpy.ndarray or None
        Demixed views ``(9, S, S)`` or ``(T, 9, S, S)`` when requested.
    timings : dict
        Seconds, summed over frames: always ``total``; SV-CoDe also per stage:
        ``prepare`` (checks, padding, sub-views, skip test), ``model`` (inside the network),
        ``blend`` (the rest of the tiling loop) and ``refine`` (the periphery refinement,
        0 without it).
    tiles_total, tiles_run, tiles_skipped : int
        Summed over frames; 0 for the methods that do not tile.
    exposure_gains : numpy.ndarray or None
        The learned methods: the factor each frame was multiplied by before the network
        (its output divided by it, :mod:`~svcode_core.methods.exposure`); ``None`` for the
        model-based ones.
    """

    reconstruction: np.ndarray
    views: np.ndarray | None
    timings: dict[str, float] = field(default_factory=dict)
    tiles_total: int = 0
    tiles_run: int = 0
    tiles_skipped: int = 0
    exposure_gains: np.ndarray | None = None


class BaseReconstructor(ABC):
    """Reconstruct raw CM² frames of ``system`` with one method (see the module).

    Attributes
    ----------
    method : str
        Its name in :mod:`svcode_core.methods.registry`.
    system : SystemConfig
        The instrument the frames come from.
    precision : str
        One of the method's precisions.
    """

    method: str
    system: SystemConfig
    precision: str
    #: whether frames of one recording may run side by side on threads of one process
    #: (nothing is carried from frame to frame and shared caches are locked), one CPU
    #: thread each (:func:`svcode_core.run.parallel.local_frames`)
    frames_side_by_side: bool = False

    @classmethod
    def build(
        cls,
        method: str,
        system: SystemConfig | None,
        weights: Any = None,
        model: Any = None,
        **options: Any,
    ) -> BaseReconstructor:
        """The reconstructor of ``method``, one this class runs, for ``system``: the work of
        :func:`~svcode_core.methods.build.build_reconstructor` (the registry names the class
        of each method, :func:`~svcode_core.methods.registry.reconstructor_class`)."""
        raise NotImplementedError(f"{cls.__name__} is built by its constructor")

    def check_frames(self, frames: Any) -> np.ndarray:
        """The input as a ``(T, H, W)`` array (a view where possible), checked for type,
        rank, emptiness and the sensor size of :attr:`system`."""
        stack = as_frame_stack(frames)
        check_frame_shape(stack.shape[1:], self.system)
        return stack

    @abstractmethod
    def iter_reconstruct(
        self, frames: Any, return_views: bool = False, cancel: threading.Event | None = None
    ) -> Generator[FrameProgress, None, ReconstructionResult]:
        """Generator form of :meth:`reconstruct`: yields progress, returns the result.

        Stop it with ``.close()`` or by setting ``cancel`` (then
        :class:`~svcode_core.methods.tiling.Cancelled` is raised).
        """

    def reconstruct(self, frames: Any, return_views: bool = False) -> ReconstructionResult:
        """Reconstruct a raw frame ``(H, W)`` or a stack ``(T, H, W)``.

        Parameters
        ----------
        frames : array_like
            Raw sensor reading(s) of shape ``system.sensor_shape`` (or a stack of them).
        return_views : bool
            Also return the nine demixed views of every frame.

        Returns
        -------
        ReconstructionResult
        """
        return exhaust(self.iter_reconstruct(frames, return_views))

    def __call__(self, frames: Any, return_views: bool = False) -> ReconstructionResult:
        return self.reconstruct(frames, return_views)


class FrameByFrame(BaseReconstructor):
    """A method that reconstructs one whole frame at a time and implements
    :meth:`reconstruct_frame`.

    It yields before every frame (``tiles_done`` 0 of :attr:`frame_steps`) and, for an
    iterative method that overrides :meth:`iter_reconstruct_frame`, after every iteration
    (``tiles_done`` the iterations done), so that a frame's progress is known and a cancel
    stops between iterations. A method without demixed views sets ``has_views = False``:
    asking for them raises :class:`ValueError` before any work.
    """

    has_views = True
    #: the steps :meth:`iter_reconstruct_frame` reports for a frame (its ``tiles_total``)
    frame_steps: int = 1

    def start_stack(self) -> None:
        """Called before the first frame of every input (e.g. to drop a warm start)."""

    @abstractmethod
    def reconstruct_frame(
        self, frame: np.ndarray, index: int, return_views: bool
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """Frame ``index`` of the input (checked for size) → ``(reconstruction (S, S),
        views (9, S, S) or None)`` as float32 arrays."""

    def iter_reconstruct_frame(
        self, frame: np.ndarray, index: int, return_views: bool
    ) -> Generator[int, None, tuple[np.ndarray, np.ndarray | None]]:
        """Generator form of :meth:`reconstruct_frame`: yields the steps done (of
        :attr:`frame_steps`) after every step and returns its result; this one runs it as
        one step that reports nothing."""
        output = self.reconstruct_frame(frame, index, return_views)
        yield from ()
        return output

    def iter_reconstruct(
        self, frames: Any, return_views: bool = False, cancel: threading.Event | None = None
    ) -> Generator[FrameProgress, None, ReconstructionResult]:
        if return_views and not self.has_views:
            title = registry.method(self.method).title
            raise ValueError(
                f"{title} reconstructs the object directly and has no demixed "
                "views; use --method svcode (or a model-based baseline) for views"
            )
        single = np.ndim(frames) == 2
        stack = self.check_frames(frames)
        start = time.perf_counter()
        self.start_stack()
        recons, views = [], []
        count, total = len(stack), self.frame_steps
        for index, frame in enumerate(stack):
            if cancel is not None and cancel.is_set():
                raise Cancelled("reconstruction cancelled")
            yield FrameProgress(index, count, 0, total)
            if np.any(frame):
                steps = self.iter_reconstruct_frame(frame, index, return_views)
                with contextlib.closing(steps):  # a close or cancel here stops the frame too
                    while True:
                        try:
                            done = next(steps)
                        except StopIteration as stop:
                            recon, view = stop.value
                            break
                        yield FrameProgress(index, count, done, total)
                        if cancel is not None and cancel.is_set():
                            raise Cancelled("reconstruction cancelled")
            else:  # a blank frame is 0 by every method (no warm start from the last frame)
                finite_frame(frame, index)  # says so
                size = self.system.sub_view_size
                recon = np.zeros((size, size), np.float32)
                view = np.zeros((9, size, size), np.float32) if return_views else None
            recons.append(recon)
            views.append(view)
        recon = np.stack(recons)
        view_array = np.stack(views) if return_views else None
        if single:
            recon = recon[0]
            view_array = None if view_array is None else view_array[0]
        return ReconstructionResult(recon, view_array,
                                    timings={"total": time.perf_counter() - start})
