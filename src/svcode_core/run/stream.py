"""Stream a recording through the reconstructor into TIFF files, resumably.

Input frames are read one at a time (memory-mapped where the TIFF allows it), so a
``T × H × W`` recording of any length is reconstructed in constant memory.

Output and resume scheme
    The result is written as it goes into ``OUT.tif.partial``, an uncompressed TIFF created
    at its final size, with its disk blocks reserved, and memory-mapped (likewise
    ``VIEWS.tif.partial``). After a frame is written and flushed, its byte in
    ``OUT.tif.done.npy`` is set and flushed (and, for a learned method, its exposure gain
    stored in ``OUT.tif.gains.npy``). The run's settings (input file, size and
    modification time, system, method, options) are in ``OUT.tif.resume.json``, written
    atomically once the partial files exist. A rerun with the same settings reopens the
    partial files and computes only the frames not marked done; every frame has its own
    slot, so a frame interrupted between its write and its mark is simply written again
    into the same slot: nothing is lost or duplicated. When every frame is done, the
    partial files are renamed to their final names and the bookkeeping files removed. A
    rerun with different settings starts afresh. A learned method's gains go into the
    outputs' metadata (``exposure_gains``, one per frame: each frame was multiplied by its
    gain before the network and the output divided by it).

Safety
    Before anything is computed, the outputs are checked (none may be an input or another
    output, a directory, or in a place where no file can be created), the system is checked
    (:func:`~svcode_core.physics.scene_checks.check_system_geometry`: refused if no chief
    ray lies on the sensor), every frame is read once and checked
    (:func:`~svcode_core.methods.frames.finite_frame`: integer frames converted, NaN/Inf
    and out-of-range frames refused), each output is locked (``OUT.tif.lock``,
    :class:`~svcode_core.outputs.OutputLock`, so a second run onto the same file is refused
    instead of mixing its settings and pixels into the first's), the partial files are
    created with their space reserved (a full disk is refused in one line,
    :class:`~svcode_core.outputs.NoSpaceError`, instead of killing the run midway with
    SIGBUS) and, when reconstructing in this process, the reconstructor is built. A run
    that fails with an error removes the partial and bookkeeping files it created; an
    interrupted one (Ctrl-C, ``kill``) keeps them, to resume.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import tifffile
from tqdm import tqdm

from ..config import N_LENSES, SystemConfig
from ..io import (
    METADATA_KEY,
    add_tiff_metadata,
    mapped_tiff,
    resolution_tags,
    tiff_metadata,
    write_json_atomic,
)
from ..methods.base import check_frame_shape
from ..methods.frames import finite_frame, require_frames
from ..outputs import NoSpaceError, OutputLock, check_outputs, no_space, preallocate, require_space
from ..physics.scene_checks import check_system_geometry
from .parallel import Factory, FrameResult, dask_client, dask_frames, local_frames

__all__ = ["FrameReader", "StreamSummary", "reconstruct_file"]


class FrameReader:
    """Frames of a TIFF, read one at a time; also its stored system and metadata.

    Parameters
    ----------
    path : str or Path
        A 2-D frame or a 3-D ``T × H × W`` stack.

    Attributes
    ----------
    shape : tuple
        Of the stored image series.
    is_stack : bool
        ``True`` for 3-D input.
    system : SystemConfig or None
        From the file's metadata, else ``system.json`` beside it.
    metadata : dict
        The remaining ``svcode`` metadata.
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        if self.path.is_dir():
            raise IsADirectoryError(errno.EISDIR, f"{self.path} is a directory, not a TIFF file")
        if not self.path.is_file():
            raise FileNotFoundError(f"no such file: {self.path}")
        try:
            self._tif = tifffile.TiffFile(self.path)
        except (tifffile.TiffFileError, ValueError) as err:
            raise ValueError(f"{self.path}: not a readable TIFF ({err})") from None
        series = self._tif.series[0]
        self.shape = tuple(series.shape)
        if len(self.shape) not in (2, 3):
            self._tif.close()
            raise ValueError(
                f"{self.path.name}: expected a frame (H×W) or a stack (T×H×W), "
                f"got an image of shape {self.shape}"
            )
        self.is_stack = len(self.shape) == 3
        self.system, self.metadata = tiff_metadata(self._tif)
        self._pages = list(series.pages) if self.is_stack else []
        self._memmap = mapped_tiff(self.path)

    def __len__(self) -> int:
        return self.shape[0] if self.is_stack else 1

    def __getitem__(self, index: int) -> np.ndarray:
        if not 0 <= index < len(self):
            raise IndexError(f"frame {index} out of range ({len(self)} frames)")
        if self._memmap is not None:
            frame = self._memmap[index] if self.is_stack else self._memmap
            return np.array(frame)
        if not self.is_stack:
            return self._tif.series[0].asarray()
        if len(self._pages) == self.shape[0] and self._pages[index] is not None:
            return self._pages[index].asarray()
        return self._tif.series[0].asarray()[index]  # unusual layout: no constant memory

    def close(self) -> None:
        """Release the file."""
        self._memmap = None
        self._tif.close()

    def __enter__(self) -> FrameReader:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


@dataclass
class StreamSummary:
    """What :func:`reconstruct_file` did.

    Attributes
    ----------
    frames : int
        Frames in the output.
    computed : int
        Frames computed in this run (the others were resumed from a previous one).
    tiles_run, tiles_skipped : int
        Over the frames computed in this run.
    """

    frames: int
    computed: int
    tiles_run: int = 0
    tiles_skipped: int = 0


#: bytes allowed per output file beyond its pixels (TIFF header, metadata, alignment)
_HEADROOM = 1 << 16


def _sibling(path: Path, suffix: str) -> Path:
    return path.with_name(path.name + suffix)


class _CheckedFrames:
    """The frames of a reader in normalised units, each checked as it is read."""

    def __init__(self, reader: FrameReader, scale: float | None) -> None:
        self.reader, self.scale = reader, scale

    def __len__(self) -> int:
        return len(self.reader)

    def __getitem__(self, index: int) -> np.ndarray:
        return finite_frame(self.reader[index], index, scale=self.scale)

    def check_all(self) -> None:
        """Read and check every frame once (:class:`ValueError` naming the first bad one)."""
        for index in range(len(self)):
            try:
                self[index]
            except ValueError as err:
                raise ValueError(f"{self.reader.path.name}: {err}") from None


def _written_files(out: Path, views: Path | None) -> dict[str, Path | None]:
    """Every file a run onto ``out`` (and ``views``) writes, by label."""
    files: dict[str, Path | None] = {"output": out, "views output": views}
    for suffix in (".partial", ".done.npy", ".gains.npy", ".resume.json", ".lock"):
        files[f"output's {suffix} file"] = _sibling(out, suffix)
    if views is not None:
        files["views' .partial file"] = _sibling(views, ".partial")
        files["views' .lock file"] = _sibling(views, ".lock")
    return files


class _ResumableOutput:
    """The partial output TIFF(s), the done flags and the resume state of one run."""

    def __init__(
        self,
        out: Path,
        views: Path | None,
        frames: int,
        stacked: bool,
        system: SystemConfig,
        settings: dict[str, Any],
        fingerprint: dict[str, Any],
    ) -> None:
        self.targets = {"reconstruction": out, "views": views}
        self.frames, self.size = frames, system.sub_view_size
        self.state_path = _sibling(out, ".resume.json")
        self.done_path = _sibling(out, ".done.npy")
        self.gains_path = _sibling(out, ".gains.npy")
        lead = (frames,) if stacked else ()
        self.shapes = {
            "reconstruction": (*lead, self.size, self.size),
            "views": (*lead, N_LENSES, self.size, self.size),
        }
        self.meta = {"system": system.to_dict(), **settings}
        self.resolution = resolution_tags(system.object_pixel_um)  # a scale bar in µm
        self.fingerprint = fingerprint
        self.arrays: dict[str, np.ndarray] = {}
        self.resumed = self._reopen()
        if not self.resumed:
            try:
                self._create()
            except BaseException:
                self.discard()
                raise

    def _partial(self, kind: str) -> Path:
        return _sibling(self.targets[kind], ".partial")

    def _kinds(self) -> list[str]:
        return [kind for kind, path in self.targets.items() if path is not None]

    def _reopen(self) -> bool:
        try:
            state = json.loads(self.state_path.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            return False
        if state != self.fingerprint or not self.done_path.is_file():
            return False
        try:
            done = np.load(self.done_path, mmap_mode="r+")
            gains = np.load(self.gains_path, mmap_mode="r+")
            arrays = {
                kind: tifffile.memmap(self._partial(kind), mode="r+") for kind in self._kinds()
            }
        except (OSError, ValueError):
            return False
        if (done.shape, gains.shape) != ((self.frames,),) * 2 or any(
            arrays[kind].shape != self.shapes[kind] for kind in arrays
        ):
            return False
        for path in (*map(self._partial, self._kinds()), self.done_path, self.gains_path):
            preallocate(path)  # already reserved, unless written by an older version
        self.done, self.gains, self.arrays = done, gains, arrays
        return True

    def _needs(self) -> dict[Path, int]:
        """Bytes of the files :meth:`_create` writes, by folder (the TIFF headers and the
        metadata rounded up)."""
        needs: dict[Path, int] = {}
        for kind in self._kinds():
            folder = self._partial(kind).parent
            size = 4 * int(np.prod(self.shapes[kind])) + _HEADROOM
            needs[folder] = needs.get(folder, 0) + size
        folder = self.done_path.parent
        needs[folder] = needs.get(folder, 0) + 5 * self.frames + 3 * _HEADROOM
        return needs

    def _create(self) -> None:
        for path in (self.state_path, self.done_path, self.gains_path):
            path.unlink(missing_ok=True)
        needs = self._needs()
        require_space(needs)
        for kind in self._kinds():
            target = self._partial(kind)
            target.parent.mkdir(parents=True, exist_ok=True)
            self.arrays[kind] = tifffile.memmap(
                target,
                shape=self.shapes[kind],
                dtype=np.float32,
                photometric="minisblack",
                metadata={METADATA_KEY: {"kind": kind, **self.meta}},
                **self.resolution,
            )
            try:
                preallocate(target)
            except NoSpaceError:  # taken meanwhile by others: say what the whole run needs
                raise no_space(target.parent, needs[target.parent]) from None
        self.done = np.lib.format.open_memmap(
            self.done_path, mode="w+", dtype=np.uint8, shape=(self.frames,)
        )
        self.gains = np.lib.format.open_memmap(
            self.gains_path, mode="w+", dtype=np.float32, shape=(self.frames,)
        )
        self.gains[:] = np.nan  # no gain: a method that does not normalise
        for array, path in ((self.done, self.done_path), (self.gains, self.gains_path)):
            array.flush()
            preallocate(path)
        write_json_atomic(self.state_path, self.fingerprint)

    def pending(self) -> list[int]:
        """Frames not yet written, in order."""
        return np.flatnonzero(self.done == 0).tolist()

    def write(self, index: int, reconstruction: np.ndarray, views: np.ndarray | None,
              gain: float | None = None) -> None:  # fmt: skip
        """Store one frame (and its exposure gain), flush it, then mark it done."""
        for kind, data in (("reconstruction", reconstruction), ("views", views)):
            if kind in self.arrays:
                array = self.arrays[kind]
                array[index if array.ndim > data.ndim else ...] = data
                array.flush()
        if gain is not None:
            self.gains[index] = gain
            self.gains.flush()
        self.done[index] = 1
        self.done.flush()

    def discard(self) -> None:
        """Remove the partial files and the bookkeeping (after a failed run)."""
        self.arrays.clear()
        for name in ("done", "gains"):
            with contextlib.suppress(AttributeError):
                delattr(self, name)
        bookkeeping = (self.done_path, self.gains_path, self.state_path)
        for path in (*map(self._partial, self._kinds()), *bookkeeping):
            path.unlink(missing_ok=True)

    def finish(self) -> None:
        """Rename the complete partial files to their final names; remove the bookkeeping."""
        if not self.done.all():
            raise RuntimeError(f"{len(self.pending())} frames are still missing")
        self.arrays.clear()
        gains = np.array(self.gains)
        del self.done, self.gains
        for kind in self._kinds():
            if not np.isnan(gains).all():
                add_tiff_metadata(self._partial(kind), exposure_gains=gains.tolist())
            os.replace(self._partial(kind), self.targets[kind])
        for path in (self.done_path, self.gains_path, self.state_path):
            path.unlink()


def _fingerprint(
    reader: FrameReader, system: SystemConfig, settings: dict[str, Any], views: bool
) -> dict[str, Any]:
    stat = reader.path.stat()
    fingerprint = {
        "input": str(reader.path.resolve()),
        "input_bytes": stat.st_size,
        "input_mtime_ns": stat.st_mtime_ns,
        "shape": list(reader.shape),
        "system": system.to_dict(),
        "settings": settings,
        "views": views,
    }
    return json.loads(json.dumps(fingerprint))  # as it reads back from the file


def reconstruct_file(
    input_path: str | Path,
    out_path: str | Path,
    factory: Factory,
    system: SystemConfig | None = None,
    views_path: str | Path | None = None,
    settings: dict[str, Any] | None = None,
    workers: int = 0,
    scheduler: str | None = None,
    progress: bool = True,
    input_scale: float | None = None,
    inputs: dict[str, Path | None] | None = None,
) -> StreamSummary:
    """Reconstruct a TIFF frame or stack into ``out_path``, resuming an interrupted run.

    Parameters
    ----------
    input_path : str or Path
        Raw sensor frame ``H × W`` or stack ``T × H × W``.
    out_path : str or Path
        Output TIFF: ``S × S`` or ``T × S × S`` float32, with the system in its metadata.
    factory : callable
        Builds the reconstructor of any method (picklable for dask,
        e.g. a :class:`~svcode_core.methods.build.MethodSpec`).
    system : SystemConfig, optional
        Default: the one stored in the input TIFF, else ``system.json`` beside it.
    views_path : str or Path, optional
        Also write the demixed views, ``9 × S × S`` or ``T × 9 × S × S``.
    settings : dict, optional
        JSON-serialisable description of the method and options; recorded in the output
        metadata and part of the resume check.
    workers : int
        ``0``: reconstruct in this process; ``N``: on a local dask cluster of ``N`` processes.
    scheduler : str, optional
        Address of an existing dask scheduler (takes precedence over ``workers``).
    progress : bool
        Show a progress bar on stderr.
    input_scale : float, optional
        Divide every frame by this full-scale value (see :mod:`svcode_core.methods.frames` for the
        default rule of integer frames); recorded in the settings.
    inputs : dict, optional
        Further files the run reads (label → path, e.g. the weights), which no output may
        overwrite.

    Returns
    -------
    StreamSummary

    Raises
    ------
    ValueError
        Before any work: no system, one whose chief rays all miss the sensor, wrong frame
        size, no frames, a bad frame, an output that is an input or another output.
    OSError
        Before any work: an output that is a directory or cannot be written;
        :class:`~svcode_core.outputs.OutputBusyError` when another run writes an output;
        :class:`~svcode_core.outputs.NoSpaceError` when the outputs do not fit on the disk.
    """
    out_path = Path(out_path)
    views = Path(views_path) if views_path is not None else None
    settings = dict(settings or {})
    if input_scale is not None:
        settings["input_scale"] = input_scale
    with FrameReader(input_path) as reader:
        system = system or reader.system
        if system is None:
            raise ValueError(
                f"{reader.path.name}: no system configuration in the file or beside it "
                "(system.json); pass one (--system FILE or a preset name)"
            )
        check_frame_shape(reader.shape[-2:], system)
        check_system_geometry(system)
        require_frames(len(reader), reader.path.name)
        beside = reader.path.with_name("system.json")
        read = {"input": reader.path, "the system.json beside the input":
                beside if beside.is_file() else None, **(inputs or {})}  # fmt: skip
        check_outputs(_written_files(out_path, views), read)
        frames = _CheckedFrames(reader, input_scale)
        frames.check_all()
        with contextlib.ExitStack() as locks:
            for target in (out_path, views):
                if target is not None:
                    locks.enter_context(OutputLock(target))
            output = _ResumableOutput(
                out_path,
                views,
                len(reader),
                reader.is_stack,
                system,
                settings,
                _fingerprint(reader, system, settings, views is not None),
            )
            try:
                local = None if scheduler or workers > 0 else factory()
                summary = _run(output, frames, factory if local is None else (lambda: local),
                               workers, scheduler, progress)  # fmt: skip
                output.finish()
            except Exception:
                if not output.resumed:
                    output.discard()
                raise
    return summary


def _run(
    output: _ResumableOutput,
    frames: _CheckedFrames,
    factory: Factory,
    workers: int,
    scheduler: str | None,
    progress: bool,
) -> StreamSummary:
    """Reconstruct the frames ``output`` is missing and write them into it."""
    todo = output.pending()
    summary = StreamSummary(frames=len(frames), computed=0)
    bar = tqdm(
        total=len(frames),
        initial=len(frames) - len(todo),
        unit="frame",
        file=sys.stderr,
        disable=not progress,
        desc="reconstruct",
    )
    views = "views" in output.arrays
    backend = _frame_results(factory, frames, todo, views, workers, scheduler)
    with bar, backend as results:
        for index, recon, demixed, counters in results:
            output.write(index, recon, demixed, counters["exposure_gain"])
            summary.computed += 1
            summary.tiles_run += counters["tiles_run"]
            summary.tiles_skipped += counters["tiles_skipped"]
            bar.update()
    return summary


@contextlib.contextmanager
def _frame_results(
    factory: Factory,
    frames: _CheckedFrames,
    todo: list[int],
    views: bool,
    workers: int,
    scheduler: str | None,
) -> Iterator[Iterator[FrameResult]]:
    """The chosen backend's iterator of finished frames (a dask cluster lives meanwhile)."""
    if not todo:
        yield iter(())
    elif scheduler or workers > 0:
        with dask_client(workers, scheduler) as client:
            yield dask_frames(factory, frames, todo, views, client)
    else:
        yield local_frames(factory, frames, todo, views)
