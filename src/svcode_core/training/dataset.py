"""Simulated training data: generated once, stored as memory-mapped arrays, resumable.

A dataset folder holds

* ``views.npy``: the nine **noiseless** sub-views of each frame, ``(N, 9, S, S)``; noise is
  drawn afresh by the patch sampler every time a patch is used;
* ``demixed.npy``: the demixing targets, each lens's image alone, ``(N, 9, S, S)``;
  with ``DataRecipe.view_margin`` ``m`` both hold the sub-views enlarged by ``m`` on every
  side, ``(N, 9, S + 2m, S + 2m)``, for models that see each view past its window;
* ``objects.npy``: the ground-truth objects ``(N, S, S)``;
* ``system.json``: the instrument the frames were simulated with;
* ``manifest.json``: the recipe (frames, seed, object mix, brightness range), the
  train/validation split and ``count``, the number of frames written so far.

Arrays are float32 ``.npy`` files opened with :func:`numpy.lib.format.open_memmap`, so
training reads only the patches it needs. ``count``, the frames written without a gap from
the first, is updated atomically (temporary file + :func:`os.replace`) after each frame is
flushed (each block of ``instrument_frames`` frames when several processes simulate side by
side, ``workers``), so an interrupted generation resumes at the first missing frame and
never trusts a half-written one. Frame ``i`` depends only on ``(seed, i)``: a resumed or
parallel dataset equals one written in one go.

With ``DataRecipe.departures`` (domain randomisation) every frame comes from its own draw
of the true instrument (:func:`frame_departures`): the optics are drawn once per block of
``instrument_frames`` frames (a new forward model costs PSFs and a decomposition), haze and
camera once per frame. ``views.npy`` then holds each frame's *expected* reading (haze,
gain and dark-signal maps included) cut at the nominal chief rays, and ``demixed.npy`` the
lens images registered to those nominal sub-views; the random part of the reading is drawn
on use with :meth:`TrainingData.frame_sensor`.
"""

from __future__ import annotations

import dataclasses
import json
import multiprocessing
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm.auto import tqdm

from ..config import N_LENSES, ConfigError, SystemConfig, check_int, check_number
from ..io import write_json_atomic
from ..outputs import preallocate, require_space
from ..phantoms import KINDS, make_object
from ..physics.departures import Departures
from ..physics.noise import SensorModel
from ..physics.simulate import Simulator
from .settings import STORE_DTYPES

__all__ = [
    "DATA_FORMAT",
    "DataRecipe",
    "TrainingData",
    "frame_departures",
    "generate_dataset",
    "split_frames",
    "training_object",
]

DATA_FORMAT = "svcode-training-data-1"
MANIFEST = "manifest.json"
SYSTEM = "system.json"
_ARRAYS = ("views", "demixed", "objects")


@dataclass(frozen=True)
class DataRecipe:
    """What to simulate.

    Attributes
    ----------
    frames : int
        Number of frames ``N``.
    seed : int
        Frame ``i`` uses the object seed ``(seed, i)``; the split uses ``seed`` too.
    val_fraction : float
        Fraction of frames held out for validation (at least one frame each side).
    object_kind : str
        Phantom kind (:data:`svcode_core.phantoms.KINDS`); ``"mixed"`` draws cells, vessels,
        neurons, beads and scikit-image crops, alone or blended.
    brightness : (float, float)
        The object's peak is drawn log-uniformly from this range (dimmer frames see
        relatively more noise).
    departures : Departures or None
        Ranges of the true instrument's departures (:meth:`Departures.sample`); ``None``:
        every frame from the nominal system.
    instrument_frames : int
        Consecutive frames sharing one draw of the optical departures.
    dtype : {"float32", "float16"}
        How the arrays are stored: float16 halves the disk (a paper-scale frame's arrays
        are 438 MB in float32) at a relative rounding of 2⁻¹¹; samples are read as float32.
    view_margin : int
        The stored views and demixing targets run this many pixels past each sub-view's
        window (at most the system's kernel margin), for models with
        :attr:`~svcode_core.network.ModelConfig.view_margin` up to it.
    """

    frames: int
    seed: int = 0
    val_fraction: float = 0.1
    object_kind: str = "mixed"
    brightness: tuple[float, float] = (0.4, 1.0)
    departures: Departures | None = None
    instrument_frames: int = 8
    dtype: str = "float32"
    view_margin: int = 0

    def validate(self) -> DataRecipe:
        """Raise ``ValueError`` (:class:`~svcode_core.config.ConfigError`) naming the first
        bad field; return ``self``."""
        check_int("frames", self.frames, 2)  # train + validation
        check_int("seed", self.seed, 0)
        if not 0 < check_number("val_fraction", self.val_fraction) < 1:
            raise ConfigError(f"val_fraction: must lie in (0, 1), got {self.val_fraction!r}")
        if self.object_kind not in KINDS:
            raise ConfigError(f"object_kind: must be one of {', '.join(KINDS)}, "
                              f"got {self.object_kind!r}")
        low, high = self.brightness
        if not 0 < low <= high <= 1:
            raise ConfigError(f"brightness: must satisfy 0 < low <= high <= 1, "
                              f"got {self.brightness!r}")
        if self.departures is not None:
            if not isinstance(self.departures, Departures):
                raise ConfigError(f"departures: must be Departures, got {self.departures!r}")
            self.departures.validate()
        check_int("instrument_frames", self.instrument_frames, 1)
        check_int("view_margin", self.view_margin, 0)
        if self.dtype not in STORE_DTYPES:
            raise ConfigError(f"dtype: must be one of {', '.join(STORE_DTYPES)}, "
                              f"got {self.dtype!r}")
        return self

    def to_dict(self) -> dict[str, Any]:
        """Plain-JSON form (stored in the manifest; departures only when set)."""
        data = {"frames": self.frames, "seed": self.seed, "val_fraction": self.val_fraction,
                "object_kind": self.object_kind, "brightness": list(self.brightness)}
        if self.departures is not None:
            data["departures"] = self.departures.to_dict()
            data["instrument_frames"] = self.instrument_frames
        # fields written only when set: older datasets keep the recipe they were made with
        if self.dtype != "float32":
            data["dtype"] = self.dtype
        if self.view_margin:
            data["view_margin"] = self.view_margin
        return data

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> DataRecipe:
        """The recipe of :meth:`to_dict` (as stored in a manifest)."""
        data = dict(data)
        data["brightness"] = tuple(data.get("brightness", (0.4, 1.0)))
        if data.get("departures") is not None:
            data["departures"] = Departures.from_dict(data["departures"])
        return cls(**data).validate()


def split_frames(frames: int, val_fraction: float, seed: int) -> tuple[list[int], list[int]]:
    """Split frame indices into train and validation sets by a seeded permutation.

    Returns
    -------
    (train, val)
        Sorted frame indices; ``val`` holds ``round(frames · val_fraction)`` frames, at
        least one, and ``train`` at least one.
    """
    n_val = min(frames - 1, max(1, round(frames * val_fraction)))
    order = np.random.default_rng([seed, 0x5EED]).permutation(frames)
    return sorted(order[n_val:].tolist()), sorted(order[:n_val].tolist())


def frame_departures(recipe: DataRecipe, index: int) -> Departures | None:
    """The true instrument of frame ``index``: depends only on ``(recipe.seed, index)``.

    The optical departures (and the seed fixing jitter and fixed-pattern maps) are drawn
    from ``recipe.departures`` once per block ``index // instrument_frames``; haze and
    camera levels once per frame.

    Returns
    -------
    Departures or None
        ``None`` for a recipe without departures.
    """
    ranges = recipe.departures
    if ranges is None:
        return None
    block = index // recipe.instrument_frames
    optics = ranges.sample(np.random.default_rng([recipe.seed, block, 0x0971C5]))
    frame = ranges.sample(np.random.default_rng([recipe.seed, index, 0xF4A3E]),
                          name=f"{ranges.name}, frame {index}")  # fmt: skip
    return frame.with_optics_of(optics)


def training_object(recipe: DataRecipe, index: int, size: int) -> np.ndarray:
    """The ground-truth object of frame ``index``: depends only on ``(recipe.seed, index)``.

    Returns
    -------
    numpy.ndarray
        float32 ``(size, size)`` in ``[0, 1]``, peak within ``recipe.brightness``
        (or all zeros for an empty phantom).
    """
    rng = np.random.default_rng([recipe.seed, index])
    obj = make_object(recipe.object_kind, size, rng)
    low, high = recipe.brightness
    peak = float(np.exp(rng.uniform(np.log(low), np.log(high))))
    top = float(obj.max())
    return (obj * (peak / top)).astype(np.float32) if top > 0 else obj


class TrainingData:
    """A dataset folder opened read-only (arrays memory-mapped).

    Attributes
    ----------
    path : Path
    system : SystemConfig
    manifest : dict
    views, demixed : numpy.memmap
        ``(count, 9, S + 2m, S + 2m)``: noiseless sub-views and demixing targets, enlarged
        by the recipe's ``view_margin`` ``m`` (:attr:`view_margin`), in the recipe's
        storage type (read them through :meth:`read`; :meth:`sub_views` cuts the views
        at their windows).
    objects : numpy.memmap
        ``(count, S, S)`` ground truth.
    train_frames, val_frames : list of int
    """

    def __init__(self, path: str | Path, allow_partial: bool = False) -> None:
        self.path = Path(path)
        manifest_path = self.path / MANIFEST
        if not manifest_path.is_file():
            raise FileNotFoundError(f"not a training dataset (no {MANIFEST}): {self.path}")
        try:
            self.manifest = json.loads(manifest_path.read_text(encoding="utf-8"))
        except ValueError as err:
            raise ValueError(f"{manifest_path} is damaged ({err}): {_REGENERATE}") from None
        if self.manifest.get("format") != DATA_FORMAT:
            raise ValueError(f"{manifest_path}: not an SV-CoDe training dataset ({DATA_FORMAT})")
        self.system = SystemConfig.load(self.path / SYSTEM)
        count, frames = self.manifest["count"], self.manifest["recipe"]["frames"]
        if count < frames and not allow_partial:
            raise ValueError(f"{self.path}: only {count} of {frames} frames were generated; "
                             "rerun `svcode dataset` with the same arguments to finish it")
        arrays = {name: _open_array(self.path / f"{name}.npy", count) for name in _ARRAYS}
        self.views, self.demixed, self.objects = (arrays[n][:count] for n in _ARRAYS)
        self.train_frames = [i for i in self.manifest["train_frames"] if i < count]
        self.val_frames = [i for i in self.manifest["val_frames"] if i < count]
        self.recipe = DataRecipe.from_dict(self.manifest["recipe"])

    @property
    def view_margin(self) -> int:
        """Pixels by which the stored views and targets run past each sub-view's window."""
        return self.recipe.view_margin

    def sub_views(self, index: int) -> np.ndarray:
        """Frame ``index``'s nine noiseless sub-views cut at their windows, ``(9, S, S)``: a
        view of the stored array (nothing read yet; :meth:`read` reads it)."""
        m, size = self.view_margin, self.system.sub_view_size
        return self.views[index][:, m : m + size, m : m + size]

    def frame_departures(self, index: int) -> Departures | None:
        """The departures frame ``index`` was simulated with (``None``: nominal)."""
        return frame_departures(self.recipe, index)

    def frame_sensor(self, index: int, photon_factor: float = 1.0) -> SensorModel:
        """The camera that reads frame ``index``: ``.read(expected, generator)`` draws noise.

        The stored views already hold the frame's fixed-pattern maps, so the model has
        none; it carries the frame's photon level, read noise, saturation and ADC (the
        nominal ``system.noise`` for a dataset without departures). Its ``read`` acts
        pixel by pixel, so it applies to patches of the views as well as to whole frames.
        ``photon_factor`` scales the frame's photon level (a dimmer sample read by the
        same camera); it needs a dataset with departures that set the photon level.
        """
        from ..physics.instrument import sensor_model

        departures = self.frame_departures(index) or Departures()
        if photon_factor != 1.0:
            if departures.photons is None:
                raise ValueError(f"{self.path}: the photon level of its frames is not "
                                 "recorded (no departures with photons): it cannot be scaled")
            departures = dataclasses.replace(departures,
                                             photons=departures.photons * photon_factor)
        sensor = sensor_model(self.system.noise, departures, (1, 1))
        return SensorModel(sensor.noise, adc_bits=sensor.adc_bits)

    @staticmethod
    def read(array: np.ndarray) -> torch.Tensor:
        """A (sliced) stored array as a float32 tensor of its own."""
        return torch.from_numpy(np.array(array, dtype=np.float32))

    def __len__(self) -> int:
        return len(self.views)

    def __repr__(self) -> str:
        return (f"TrainingData({str(self.path)!r}, {len(self)} frames of {self.system.name}, "
                f"{len(self.train_frames)} train / {len(self.val_frames)} val)")


#: what to do about a damaged dataset
_REGENERATE = "generate the dataset again with `svcode dataset` (into a new --out folder)"


def _open_array(path: Path, count: int) -> np.ndarray:
    """The memory map of one array of a dataset, which must hold ``count`` frames; a
    missing, damaged or truncated file is refused in one line that names it."""
    if not path.is_file():
        raise FileNotFoundError(f"{path} is missing: {_REGENERATE}")
    try:
        array = np.load(path, mmap_mode="r")
    except (ValueError, OSError, EOFError) as err:
        raise ValueError(f"{path} is damaged or truncated ({err}): {_REGENERATE}") from None
    if array.ndim < 1 or len(array) < count:
        raise ValueError(f"{path} holds {len(array) if array.ndim else 0} frames, the "
                         f"manifest {count}: {_REGENERATE}")  # fmt: skip
    return array


def _open_arrays(path: Path, shapes: dict[str, tuple[int, ...]], create: bool,
                 dtype: str = "float32") -> dict:  # fmt: skip
    """The dataset's arrays, memory-mapped; new ones are created with their disk space
    reserved (a full disk is refused at the start, not met as a SIGBUS halfway)."""
    mode = "w+" if create else "r+"
    arrays = {}
    for name, shape in shapes.items():
        array = np.lib.format.open_memmap(
            path / f"{name}.npy", mode=mode, dtype=dtype, shape=shape if create else None
        )
        if array.shape != shape or array.dtype != np.dtype(dtype):
            raise ValueError(f"{path / f'{name}.npy'} has shape {array.shape} {array.dtype}, "
                             f"expected {shape} {dtype}")
        if create:
            preallocate(path / f"{name}.npy")
        arrays[name] = array
    return arrays


def generate_dataset(
    out_dir: str | Path,
    system: SystemConfig,
    recipe: DataRecipe,
    simulator: Simulator | None = None,
    progress: bool = True,
    workers: int = 1,
) -> TrainingData:
    """Simulate ``recipe.frames`` noiseless frames into ``out_dir`` (or finish a partial one).

    Parameters
    ----------
    out_dir : str or Path
        Dataset folder; created if missing. If it holds a partial dataset of the same
        system and recipe, generation resumes at the first missing frame.
    system : SystemConfig
    recipe : DataRecipe
    simulator : Simulator, optional
        Default ``Simulator(system)`` (pupil-model optics); with ``workers > 1`` each
        process builds its own default one.
    progress : bool
        Show a progress bar.
    workers : int
        Processes simulating blocks of ``recipe.instrument_frames`` frames side by side,
        one thread each; the frames are the same as from one process.

    Returns
    -------
    TrainingData

    Raises
    ------
    ValueError
        If ``out_dir`` holds a dataset of another system or recipe, or the recipe's view
        margin is beyond the system's kernel radius.
    """
    system = system.validate()
    recipe = recipe.validate()
    check_int("workers", workers, 1)
    if workers > 1 and simulator is not None:
        raise ValueError("workers: each process builds its own simulator; give either "
                         "a simulator or several workers")  # fmt: skip
    if recipe.view_margin > system.optics.kernel_size // 2:
        raise ConfigError(f"view_margin: {recipe.view_margin} px is beyond the kernel radius "
                          f"of {system.name} ({system.optics.kernel_size // 2} px), the "
                          "farthest a lens's light reaches past its window")
    out = Path(out_dir)
    manifest_path = out / MANIFEST
    shapes = _shapes(system, recipe)
    itemsize = np.dtype(recipe.dtype).itemsize
    if not manifest_path.is_file():
        require_space({out: sum(itemsize * int(np.prod(shape)) + 4096
                                for shape in shapes.values())})
    out.mkdir(parents=True, exist_ok=True)
    if manifest_path.is_file():
        manifest = json.loads(manifest_path.read_text(encoding="utf-8"))
        stored_system = SystemConfig.load(out / SYSTEM)
        if stored_system != system or manifest.get("recipe") != recipe.to_dict():
            raise ValueError(
                f"{out} already holds a dataset of another system or recipe "
                f"({stored_system.name}, {manifest.get('recipe')}); choose a new folder"
            )
        _open_arrays(out, shapes, create=False, dtype=recipe.dtype)
    else:
        train, val = split_frames(recipe.frames, recipe.val_fraction, recipe.seed)
        system.save(out / SYSTEM)
        _open_arrays(out, shapes, create=True, dtype=recipe.dtype)
        manifest = {
            "format": DATA_FORMAT,
            "system": system.name,
            "recipe": recipe.to_dict(),
            "object_seeds": "frame i: numpy.random.default_rng([seed, i])",
            "noise": "none stored: drawn afresh by the patch sampler",
            "departures": (None if recipe.departures is None else
                           "frame i: frame_departures(recipe, i); views hold the expected "
                           "reading of that instrument"),  # fmt: skip
            "dtype": recipe.dtype,
            "shapes": {name: list(shape) for name, shape in shapes.items()},
            "train_frames": train,
            "val_frames": val,
            "count": 0,
            "seconds": 0.0,
        }
        write_json_atomic(manifest_path, manifest)
    start, spent = manifest["count"], manifest["seconds"]
    if start < recipe.frames:
        # one process writes frame after frame; several take blocks of frames sharing one
        # instrument draw, so each builds a forward model once per block, as one process does
        step = 1 if workers == 1 else recipe.instrument_frames
        blocks, low = [], start
        while low < recipe.frames:
            high = min(recipe.frames, (low // step + 1) * step)
            blocks.append((low, high))
            low = high
        clock = time.perf_counter()
        ends: dict[int, int] = {}  # first frame -> end of each block written

        def finished(block: tuple[int, int]) -> None:
            """Count the frames written without a gap (a resumed run trusts those)."""
            ends[block[0]] = block[1]
            while manifest["count"] in ends:
                manifest["count"] = ends[manifest["count"]]
            manifest["seconds"] = round(spent + time.perf_counter() - clock, 3)
            write_json_atomic(manifest_path, manifest)
            bar.update(block[1] - block[0])

        with tqdm(initial=start, total=recipe.frames, desc="simulate frames",
                  disable=not progress) as bar:  # fmt: skip
            if workers == 1:
                simulator = simulator or Simulator(system)
                for block in blocks:
                    simulator = _simulate_block(out, system, recipe, block, simulator)
                    finished(block)
            else:
                _simulate_in_processes(out, system, recipe, blocks, workers, finished)
    return TrainingData(out)


def _shapes(system: SystemConfig, recipe: DataRecipe) -> dict[str, tuple[int, ...]]:
    size, margin = system.sub_view_size, recipe.view_margin
    enlarged = (recipe.frames, N_LENSES, size + 2 * margin, size + 2 * margin)
    return {"views": enlarged, "demixed": enlarged, "objects": (recipe.frames, size, size)}


def _simulate_block(out: Path, system: SystemConfig, recipe: DataRecipe,
                    block: tuple[int, int], simulator: Simulator) -> Simulator:
    """Simulate frames ``block[0]`` to ``block[1] - 1`` into the stored arrays (flushed);
    returns the simulator of the block's instrument, for the next block to start from."""
    arrays = _open_arrays(out, _shapes(system, recipe), create=False, dtype=recipe.dtype)
    for index in range(*block):
        obj = training_object(recipe, index, system.sub_view_size)
        departures = frame_departures(recipe, index)
        if departures is not None:  # reuses the forward model within a block
            simulator = simulator.with_departures(departures)
        scene = simulator.simulate(obj, seed=0, noise=False, margin=recipe.view_margin)
        arrays["views"][index] = scene.views
        arrays["demixed"][index] = scene.demixed
        arrays["objects"][index] = scene.object
    for array in arrays.values():
        array.flush()
    return simulator


_WORKER_SIMULATOR: Simulator | None = None


def _worker_block(out: Path, system: SystemConfig, recipe: DataRecipe,
                  block: tuple[int, int]) -> tuple[int, int]:
    """One block in a worker process, its simulator kept for the process's next block."""
    global _WORKER_SIMULATOR
    torch.set_num_threads(1)
    _WORKER_SIMULATOR = _simulate_block(out, system, recipe, block,
                                        _WORKER_SIMULATOR or Simulator(system))
    return block


def _simulate_in_processes(out: Path, system: SystemConfig, recipe: DataRecipe,
                           blocks: list[tuple[int, int]], workers: int, finished) -> None:
    """The blocks in ``workers`` processes; ``finished(block)`` as each one is written.
    An error or an interruption cancels the blocks not yet started."""
    context = multiprocessing.get_context("spawn")  # no forked copy of torch's thread pools
    with ProcessPoolExecutor(workers, mp_context=context) as pool:
        futures = [pool.submit(_worker_block, out, system, recipe, block) for block in blocks]
        try:
            for future in as_completed(futures):
                finished(future.result())
        except BaseException:
            pool.shutdown(wait=True, cancel_futures=True)
            raise
