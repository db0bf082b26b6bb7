"""Training samples: aligned patches of the nine sub-views with their global origins, or
whole padded frames for the full-frame learned baselines (:class:`FrameDataset`).

Every frame is cut into ``P × P`` patches at the configured stride (``P / 2`` in the
presets, the last patch flush with the edge, :class:`~svcode_core.methods.tiling.TileGrid`). A
patch holds the nine noiseless view crops with sensor noise added on access (the frame's
own camera, :meth:`~.dataset.TrainingData.frame_sensor`, when the dataset has departures), the nine
demixing targets, the object crop, and the crop's origin in sub-view pixels, which the
network turns into global coordinates. No flips or rotations: the PSFs depend on the field
position, so a flipped patch would not be a valid measurement at its coordinates.

Noise is drawn only on the pixels that the sensor covers; the zero padding outside the
sensor stays exactly zero, as in a real padded frame. For one origin the nine view crops
come from sensor regions that do not overlap whenever every pair of chief rays is at
least ``P`` apart along rows or columns (lens pitch 144 > 96 in ``cm2-mini``, 900 > 480
in ``cm2-v2``); independent noise per view crop is then exactly noise on the sensor.
:func:`check_disjoint_view_patches` enforces this.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence

import numpy as np
import torch

from ..config import SystemConfig
from ..methods.exposure import exposure_gain
from ..methods.tiling import TileGrid
from ..physics.geometry import (
    assemble_frame,
    assemble_window,
    context_corners,
    crop_to_sensor,
    crops_at,
    pad_sensor_frame,
    sensor_coverage,
)
from ..physics.noise import SensorModel
from .dataset import TrainingData

__all__ = [
    "EpochSampler",
    "FrameDataset",
    "PatchDataset",
    "check_disjoint_view_patches",
    "derive_seed",
]


def derive_seed(*entropy: int) -> int:
    """A 63-bit seed mixed from integers (NumPy ``SeedSequence``): distinct inputs give
    statistically independent seeds."""
    state = np.random.SeedSequence([int(e) for e in entropy]).generate_state(1, np.uint64)
    return int(state[0] >> np.uint64(1))


def check_disjoint_view_patches(system: SystemConfig, patch: int) -> None:
    """Check that the nine view crops of one patch never share a sensor pixel.

    Crop ``ℓ`` of a patch at origin ``o`` covers padded pixels ``c_ℓ - S//2 + o`` to
    ``+ P``, so two crops overlap for every ``o`` exactly when their chief rays are less
    than ``P`` apart along both axes.

    Raises
    ------
    ValueError
        Naming the two lenses whose crops would overlap.
    """
    rays = np.asarray(system.chief_rays)
    for a in range(len(rays)):
        for b in range(a + 1, len(rays)):
            if np.all(np.abs(rays[a] - rays[b]) < patch):
                raise ValueError(
                    f"patches of {patch} px from lenses {a} and {b} (chief rays "
                    f"{tuple(rays[a])}, {tuple(rays[b])}) share sensor pixels: independent "
                    "noise per view would be wrong; use a patch smaller than the lens pitch"
                )


class _NoisySamples(torch.utils.data.Dataset):
    """Samples of some frames of a :class:`TrainingData` with noise drawn on access.

    ``fixed_noise`` (validation): sample ``i`` always gets the draw seeded by ``(seed, i)``;
    otherwise every access draws fresh noise, unless the key is ``(index, noise_seed)``.
    ``photon_range`` ``(low, high)``: every access draws a factor on the frame's photon
    level log-uniformly from it (dimmer samples, the same camera). ``normalise_exposure``:
    the inputs and targets of a frame are multiplied by the gain that brings the frame to
    :data:`~svcode_core.methods.exposure.REFERENCE_LEVEL`, as the reconstructors do: its
    level is measured, once, on one noisy reading of the whole frame, as a reconstructor
    measures the frames it gets (on the noiseless frame an empty scene's level is its
    fixed-pattern residue, and its gain a hundred times what inference applies).
    """

    def __init__(
        self,
        data: TrainingData,
        frames: Sequence[int],
        fixed_noise: bool = False,
        seed: int = 0,
        noise: bool = True,
        photon_range: tuple[float, float] = (1.0, 1.0),
        normalise_exposure: bool = False,
    ) -> None:
        frames = sorted({int(f) for f in frames})
        if not frames:
            raise ValueError(f"no frames selected for the {type(self).__name__}")
        if frames[0] < 0 or frames[-1] >= len(data):
            raise ValueError(f"frame indices must lie in [0, {len(data)}), "
                             f"got {frames[0]}..{frames[-1]}")
        self.data, self.system, self.frames = data, data.system, frames
        self.fixed_noise, self.seed, self.noise = fixed_noise, int(seed), noise
        low, high = photon_range
        if not 0 < low <= high:
            raise ValueError(f"photon_range must satisfy 0 < low <= high, got {photon_range!r}")
        self.photon_range = (float(low), float(high))
        self.normalise_exposure = normalise_exposure
        self._gains: dict[int, float] = {}
        self._generator = torch.Generator().manual_seed(derive_seed(self.seed, 2))

    def sensor(self, frame: int, generator: torch.Generator) -> SensorModel:
        """Frame ``frame``'s camera, at a photon level drawn from ``photon_range``."""
        low, high = self.photon_range
        factor = low  # a range of one value draws nothing (the noise stream stays as it was)
        if high > low:
            u = float(torch.rand((), generator=generator))
            factor = math.exp(math.log(low) + u * (math.log(high) - math.log(low)))
        return self.data.frame_sensor(frame, factor)

    def gain(self, frame: int) -> float:
        """The factor that brings frame ``frame`` to the reference level (1 unless
        ``normalise_exposure``)."""
        if not self.normalise_exposure:
            return 1.0
        if frame not in self._gains:
            views = self.data.read(self.data.sub_views(frame))
            sensor = crop_to_sensor(assemble_frame(views, self.system), self.system)
            if self.noise:
                generator = torch.Generator().manual_seed(derive_seed(self.seed, 4, frame))
                sensor = self.data.frame_sensor(frame).read(sensor, generator)
            self._gains[frame] = exposure_gain(sensor.numpy())
        return self._gains[frame]

    def _resolve(self, key: int | tuple[int, int]) -> tuple[int, torch.Generator]:
        """Sample index and noise generator of an item key."""
        index, noise_seed = (key if isinstance(key, tuple) else (key, None))
        index = int(index)
        if noise_seed is not None:
            return index, torch.Generator().manual_seed(int(noise_seed))
        if self.fixed_noise:
            return index, torch.Generator().manual_seed(derive_seed(self.seed, 1, index))
        return index, self._generator

    def padded_frame(self, frame: int, generator: torch.Generator) -> torch.Tensor:
        """Frame ``frame``'s padded sensor frame, rebuilt from its stored sub-views
        (:func:`~svcode_core.physics.geometry.assemble_frame`), with the sensor model
        applied to the sensor window only, as :class:`~svcode_core.physics.simulate.Simulator`
        does (unless ``noise`` is off)."""
        padded = assemble_frame(self.data.read(self.data.sub_views(frame)), self.system)
        if not self.noise:
            return padded
        sensor = crop_to_sensor(padded, self.system)
        sensor = self.sensor(frame, generator).read(sensor, generator)
        return pad_sensor_frame(sensor, self.system)

    def window_crops(
        self, frame: int, corners: np.ndarray, size: int, generator: torch.Generator
    ) -> torch.Tensor:
        """The ``size``-square crops at padded-frame ``corners`` ``(n, 2)`` of frame
        ``frame``'s noisy padded frame, ``(n, size, size)``: what cropping
        :meth:`padded_frame` gives, drawn on the crops' own pixels only (overlapping crops
        merged into one window, so a sensor pixel gets one draw). At paper scale a patch's
        81 crops cover a twentieth of the frame."""
        windows = _merged_windows(corners, size, self.system.padded_shape)
        sensor = self.sensor(frame, generator) if self.noise else None
        rows, cols = self.system.sensor_window
        crops = torch.zeros(len(corners), size, size)
        for (top, left, bottom, right), members in windows:
            values = assemble_window(self.data.sub_views(frame), self.system, top, left,
                                     bottom - top, right - left)  # fmt: skip
            if sensor is not None:  # the sensor's pixels in the window: read; the rest stays 0
                r0, r1 = max(top, rows.start), min(bottom, rows.stop)
                c0, c1 = max(left, cols.start), min(right, cols.stop)
                read = torch.zeros_like(values)
                if r0 < r1 and c0 < c1:
                    inside = (slice(r0 - top, r1 - top), slice(c0 - left, c1 - left))
                    read[inside] = sensor.read(values[inside], generator)
                values = read
            crops[members] = crops_at(values, corners[members] - (top, left), size)
        return crops


def _merged_windows(
    corners: np.ndarray, size: int, shape: tuple[int, int]
) -> list[tuple[tuple[int, int, int, int], list[int]]]:
    """Disjoint windows ``(top, left, bottom, right)`` inside a frame of ``shape``, each
    with the indices of the ``size``-square crops at ``corners`` that it holds (the parts
    of them inside the frame): overlapping crops share one window."""
    groups = [((int(r), int(c), int(r) + size, int(c) + size), [k])
              for k, (r, c) in enumerate(corners)]  # fmt: skip
    merged = True
    while merged:
        merged, out = False, []
        for box, members in groups:
            for k, (other, together) in enumerate(out):
                if (box[0] < other[2] and other[0] < box[2]
                        and box[1] < other[3] and other[1] < box[3]):  # fmt: skip
                    joined = (min(box[0], other[0]), min(box[1], other[1]),
                              max(box[2], other[2]), max(box[3], other[3]))  # fmt: skip
                    out[k], merged = (joined, together + members), True
                    break
            else:
                out.append((box, members))
        groups = out
    rows, cols = shape
    windows = []
    for (top, left, bottom, right), members in groups:
        box = (max(top, 0), max(left, 0), min(bottom, rows), min(right, cols))
        if box[0] < box[2] and box[1] < box[3]:
            windows.append((box, members))
    return windows


class PatchDataset(_NoisySamples):
    """All patches of some frames of a :class:`TrainingData`, with noise drawn on access.

    Parameters
    ----------
    data : TrainingData
    frames : sequence of int
        Frames to cut (e.g. ``data.train_frames``).
    fixed_noise : bool
        ``True`` (validation): patch ``i`` always gets the same noise draw, seeded by
        ``(seed, i)``. ``False`` (training): every access draws fresh noise.
    seed : int
        Base seed of the noise.
    noise : bool
        ``False`` returns the noiseless views (for checks).
    lens_context : bool
        ``views`` holds each lens's crop and the crops one lens pitch away, ``(81, P, P)``
        (:func:`~svcode_core.physics.geometry.context_views`), for a model with
        :attr:`~svcode_core.network.ModelConfig.lens_context`. These crops share sensor
        pixels, so the noise is drawn once per sensor pixel, on the windows of the frame
        that the crops cover (:meth:`window_crops`).
    context_reach : int
        With ``lens_context``, how many pitches left and right the crops go
        (:attr:`~svcode_core.network.ModelConfig.context_reach`; ``(99, P, P)`` at 2).
    photon_range, normalise_exposure
        Dimmer draws and one exposure level (see ``_NoisySamples``).
    patch : int, optional
        Patch side ``P``, on a grid of stride ``P // 2``; default the system's
        ``patch_size`` and ``patch_stride``.
    view_margin : int
        The patches tile the sub-view enlarged by this many pixels on every side (origins
        from ``-view_margin``), for a model with
        :attr:`~svcode_core.network.ModelConfig.view_margin`: views and demixing targets
        run past the window there (the dataset must hold at least this margin), the
        object is zero beyond the field.

    Notes
    -----
    Items are dictionaries of ``views (9, P, P)``, ``demixed (9, P, P)``, ``object
    (1, P, P)`` float32 tensors, ``origin (2,)`` int64 (row, col in sub-view pixels), the
    frame's exposure ``gain`` (float32, 1 unless ``normalise_exposure``) and ``index``. An
    item may be requested by index, or by ``(index, noise_seed)`` to fix the
    draw (:class:`EpochSampler` does this, so training is reproducible and resumable).
    """

    def __init__(
        self,
        data: TrainingData,
        frames: Sequence[int],
        fixed_noise: bool = False,
        seed: int = 0,
        noise: bool = True,
        lens_context: bool = False,
        context_reach: int = 1,
        photon_range: tuple[float, float] = (1.0, 1.0),
        normalise_exposure: bool = False,
        patch: int | None = None,
        view_margin: int = 0,
    ) -> None:
        super().__init__(data, frames, fixed_noise, seed, noise, photon_range,
                         normalise_exposure)
        system = data.system
        self.patch, stride = system.patch_size, system.patch_stride
        if patch is not None:
            self.patch, stride = patch, max(patch // 2, 1)
        if view_margin > data.view_margin:
            raise ValueError(f"the model sees {view_margin} px past each sub-view, the dataset "
                             f"{data.path} holds {data.view_margin}: make one with "
                             f"`svcode dataset --view-margin {view_margin}`")  # fmt: skip
        self.lens_context, self.context_reach = lens_context, context_reach
        self.view_margin = view_margin
        size = system.sub_view_size + 2 * view_margin
        self.origins = TileGrid(size, self.patch, stride).origins - view_margin
        if not lens_context:  # noise per view crop: needs crops without shared pixels
            check_disjoint_view_patches(system, self.patch)
            coverage = sensor_coverage(system, margin=data.view_margin)
            self.sensor_mask = coverage.numpy().astype(bool)

    def __len__(self) -> int:
        return len(self.frames) * len(self.origins)

    def locate(self, index: int) -> tuple[int, np.ndarray]:
        """Frame and origin ``(row, col)`` of patch ``index``."""
        if not 0 <= index < len(self):
            raise IndexError(f"patch index {index} out of range [0, {len(self)})")
        frame, position = divmod(index, len(self.origins))
        return self.frames[frame], self.origins[position]

    def __getitem__(self, key: int | tuple[int, int]) -> dict[str, torch.Tensor | int]:
        index, generator = self._resolve(key)
        frame, (r, c) = self.locate(index)
        stored = self.data.view_margin  # where sub-view pixel 0 sits in the stored arrays
        crop = (slice(r + stored, r + stored + self.patch),
                slice(c + stored, c + stored + self.patch))  # fmt: skip
        if self.lens_context:
            corners = context_corners(self.system, (int(r), int(c)), self.context_reach)
            views = self.window_crops(frame, corners, self.patch, generator)
        else:
            views = self.data.read(self.data.views[frame][(slice(None), *crop)])
            if self.noise:
                inside = torch.from_numpy(self.sensor_mask[(slice(None), *crop)])
                views = self.sensor(frame, generator).read(views, generator) * inside
        gain = self.gain(frame)
        demixed = self.data.read(self.data.demixed[frame][(slice(None), *crop)])
        return {
            "views": views * gain,
            "demixed": demixed * gain,
            "object": self._object(frame, int(r), int(c))[None] * gain,
            "origin": torch.tensor([r, c], dtype=torch.int64),
            "gain": torch.tensor(gain, dtype=torch.float32),
            "index": index,
        }


    def _object(self, frame: int, r: int, c: int) -> torch.Tensor:
        """The object's patch at sub-view origin ``(r, c)``, zero beyond the field."""
        size, p = self.system.sub_view_size, self.patch
        out = torch.zeros(p, p)
        r0, r1, c0, c1 = max(r, 0), min(r + p, size), max(c, 0), min(c + p, size)
        if r0 < r1 and c0 < c1:
            out[r0 - r : r1 - r, c0 - c : c1 - c] = self.data.read(
                self.data.objects[frame][r0:r1, c0:c1])
        return out


class FrameDataset(_NoisySamples):
    """Whole padded sensor frames of some frames of a :class:`TrainingData`, with noise.

    For methods that filter the whole frame (the learned baselines,
    :mod:`svcode_core.methods.learned`). The padded frame is rebuilt from the stored
    sub-views (:func:`~svcode_core.physics.geometry.assemble_frame`) and the sensor model is
    applied to the sensor window only, as :class:`~svcode_core.physics.simulate.Simulator` does,
    so the nine views of one frame share one noise draw. Parameters as
    :class:`PatchDataset`.

    Notes
    -----
    Items are dictionaries of ``frame (H_pad, W_pad)`` and ``object (1, S, S)`` float32
    tensors, ``gain`` and ``index``; keys as in :class:`PatchDataset`.
    """

    def __len__(self) -> int:
        return len(self.frames)

    def __getitem__(self, key: int | tuple[int, int]) -> dict[str, torch.Tensor | int]:
        index, generator = self._resolve(key)
        if not 0 <= index < len(self):
            raise IndexError(f"frame index {index} out of range [0, {len(self)})")
        frame = self.frames[index]
        gain = self.gain(frame)
        return {
            "frame": self.padded_frame(frame, generator) * gain,
            "object": self.data.read(self.data.objects[frame])[None] * gain,
            "gain": torch.tensor(gain, dtype=torch.float32),
            "index": index,
        }


class EpochSampler(torch.utils.data.Sampler):
    """A seeded random subset of patches per epoch, each with its own noise seed.

    Epoch ``e`` draws ``per_epoch`` patches without replacement (repeating whole
    permutations if ``per_epoch`` exceeds the dataset) from a generator seeded by
    ``(seed, e)``, and one noise seed per draw, so every use of a patch sees fresh noise
    and an epoch is reproduced exactly after a resume. With ``world_size > 1`` rank ``k``
    takes draws (runs, see below) ``k, k + world_size, ...``; each rank gets
    ``per_epoch // world_size`` (rounded down to whole runs).

    With ``group > 1`` the draws come in runs of ``group`` patches that share their origin
    (from different frames, where there are enough): a batch made of whole runs needs the
    coordinate masks of only ``batch / group`` origins, which is most of the training cost
    on a CPU. Every patch is still drawn at least once per permutation.

    Parameters
    ----------
    size : int
        Number of patches in the dataset.
    per_epoch : int
        Patches per epoch (over all ranks).
    seed : int
    rank, world_size : int
    group : int
        Patches per run with a shared origin.
    origins : int
        Origins per frame (patch ``i`` has origin ``i % origins``); needed when ``group > 1``.
    """

    def __init__(
        self, size: int, per_epoch: int, seed: int = 0, rank: int = 0, world_size: int = 1,
        group: int = 1, origins: int = 1,
    ) -> None:
        if size < 1:
            raise ValueError(f"the dataset has no patches (size {size})")
        if not 0 <= rank < world_size:
            raise ValueError(f"rank {rank} out of range for world size {world_size}")
        if per_epoch < world_size:
            raise ValueError(f"per_epoch ({per_epoch}) must be at least the number of "
                             f"processes ({world_size})")
        if not isinstance(group, int) or group < 1:
            raise ValueError(f"group must be a positive integer, got {group!r}")
        if not isinstance(origins, int) or origins < 1 or size % origins:
            raise ValueError(f"origins ({origins!r}) must be a positive divisor of the "
                             f"dataset size ({size})")
        self.size, self.per_epoch, self.seed = size, per_epoch, seed
        self.rank, self.world_size = rank, world_size
        self.group, self.origins = group, origins
        self.epoch = 0

    def set_epoch(self, epoch: int) -> None:
        """Select the epoch whose draws :meth:`__iter__` yields."""
        self.epoch = int(epoch)

    def __len__(self) -> int:
        return self.per_epoch // (self.world_size * self.group) * self.group

    def _permutation(self, generator: torch.Generator) -> torch.Tensor:
        """Every patch once (``group == 1``), or runs of ``group`` patches sharing an
        origin, runs shuffled: each origin's frames in random order, wrapped around to
        fill the last run, so every patch comes at least once and a few twice."""
        if self.group == 1:
            return torch.randperm(self.size, generator=generator)
        frames = self.size // self.origins
        length = -(-frames // self.group) * self.group
        runs = []
        for origin in range(self.origins):
            order = torch.randperm(frames, generator=generator)
            order = order[torch.arange(length) % frames] * self.origins + origin
            runs += list(torch.split(order, self.group))
        shuffled = torch.randperm(len(runs), generator=generator)
        return torch.cat([runs[i] for i in shuffled.tolist()])

    def __iter__(self) -> Iterator[tuple[int, int]]:
        generator = torch.Generator().manual_seed(derive_seed(self.seed, 3, self.epoch))
        rounds = -(-self.per_epoch // self.size)
        order = torch.cat([self._permutation(generator) for _ in range(rounds)])
        order = order[: self.per_epoch]
        noise = torch.randint(0, 2**62, (self.per_epoch,), generator=generator)
        run = self.group
        for start in range(self.rank * run, len(self) * self.world_size, self.world_size * run):
            for position in range(start, start + run):
                yield int(order[position]), int(noise[position])
