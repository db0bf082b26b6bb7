"""Output files, checked before the work and written without clashes.

:func:`check_outputs` refuses, before anything is computed, an output that is (or resolves
to the same file as) an input, two outputs that are one file, an output that is a
directory, and a location where no file can be created. :class:`OutputLock` keeps two
runs from writing the same output at once; :func:`temporary_sibling` names a unique
temporary file beside an output for an atomic rename.

Space: :func:`require_space` refuses, before the work, outputs of known size that do not
fit on their file system, and :func:`preallocate` reserves a file's blocks, so that writes
through a memory map of it cannot fail later (a full disk under a sparse memory map kills
the process with SIGBUS, without a message). Both raise :class:`NoSpaceError`, whose
message says where, how much is needed and how much is free.
"""

from __future__ import annotations

import errno
import os
import shutil
import socket
import time
import uuid
from collections.abc import Iterable, Mapping
from pathlib import Path

__all__ = [
    "NoSpaceError",
    "OutputBusyError",
    "OutputLock",
    "check_outputs",
    "no_space",
    "preallocate",
    "require_space",
    "same_file",
    "temporary_sibling",
]


class OutputBusyError(OSError):
    """Another run is writing the same output."""


class NoSpaceError(OSError):
    """The outputs do not fit on their file system."""


def same_file(a: Path, b: Path) -> bool:
    """Whether ``a`` and ``b`` name one file (same path after resolving links, or the same
    inode when both exist, e.g. hard links)."""
    try:
        if a.exists() and b.exists():
            return os.path.samefile(a, b)
    except OSError:
        pass
    return a.resolve() == b.resolve()


def _existing_ancestor(path: Path) -> Path:
    parent = path.resolve().parent
    while not parent.exists():
        parent = parent.parent
    return parent


def _check_writable_location(label: str, path: Path) -> None:
    if path.is_dir():
        raise IsADirectoryError(
            errno.EISDIR, f"{path} ({label}) is an existing directory; give a file name"
        )
    ancestor = _existing_ancestor(path)
    if not ancestor.is_dir():
        raise NotADirectoryError(
            errno.ENOTDIR, f"{path} ({label}): {ancestor} is a file, not a directory"
        )
    probe = ancestor / f".svcode-probe-{uuid.uuid4().hex}"
    try:
        _create(probe)
    except OSError as err:
        raise PermissionError(
            err.errno, f"{path} ({label}): cannot write in {ancestor} ({err.strerror})"
        ) from None
    probe.unlink()


def _create(path: Path) -> None:
    """Create the empty file ``path`` (which must not exist)."""
    os.close(os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o600))


Files = Mapping[str, "Path | None"] | Iterable[tuple[str, "Path | None"]]


def _named(files: Files) -> list[tuple[str, Path]]:
    pairs = files.items() if isinstance(files, Mapping) else files
    return [(label, Path(path)) for label, path in pairs if path is not None]


def check_outputs(outputs: Files, inputs: Files) -> None:
    """Refuse outputs that would overwrite an input, clash, or cannot be written.

    Parameters
    ----------
    outputs : mapping or iterable of (label, path)
        The files the run will write, each with a label for the messages (e.g.
        ``"--out"``); ``None`` paths are skipped. Include the bookkeeping files too.
    inputs : mapping or iterable of (label, path)
        The files the run reads; ``None`` paths are skipped.

    Raises
    ------
    ValueError
        If an output is an input, or two outputs are one file.
    OSError
        If an output is a directory or its location is not writable.
    """
    named_outputs, named_inputs = _named(outputs), _named(inputs)
    for label, path in named_outputs:
        for source, given in named_inputs:
            if same_file(path, given):
                raise ValueError(
                    f"{path} ({label}) is the same file as the input {given} ({source}); "
                    "writing it would destroy that input: choose another output name"
                )
    for i, (label, path) in enumerate(named_outputs):
        for other, given in named_outputs[i + 1:]:
            if same_file(path, given):
                raise ValueError(f"{label} and {other} both name {path}; "
                                 "give them different names")  # fmt: skip
    for label, path in named_outputs:
        _check_writable_location(label, path)


def _mib(size: int) -> str:
    return f"{size / 2**20:.1f}"


def free_bytes(path: Path) -> int:
    """Bytes free to this user on the file system that holds (or would hold) ``path``."""
    return shutil.disk_usage(_existing_ancestor(Path(path) / "x")).free


def no_space(folder: Path, needed: int) -> NoSpaceError:
    """The error for ``needed`` bytes that do not fit in ``folder``, with the space free now."""
    folder = _existing_ancestor(Path(folder) / "x")
    return NoSpaceError(errno.ENOSPC, f"no space left on {folder}: {_mib(needed)} MiB needed, "
                                      f"{_mib(free_bytes(folder))} MiB free")  # fmt: skip


def require_space(needs: Mapping[Path, int]) -> None:
    """Refuse files of known sizes that do not fit where they go.

    Parameters
    ----------
    needs : mapping
        Bytes still to be written, by the folder they go to; folders on one file system
        are added up.

    Raises
    ------
    NoSpaceError
        For the first file system short of space.
    """
    by_device: dict[int, tuple[Path, int]] = {}
    for folder, size in needs.items():
        folder = _existing_ancestor(Path(folder) / "x")
        device = os.stat(folder).st_dev
        first, total = by_device.get(device, (folder, 0))
        by_device[device] = (first, total + size)
    for folder, total in by_device.values():
        if total > free_bytes(folder):
            raise no_space(folder, total)


def preallocate(path: Path) -> None:
    """Reserve the disk blocks of every byte of ``path`` (a file created sparse).

    Raises
    ------
    NoSpaceError
        If the file system cannot hold the file. Where the system or file system has no
        preallocation, nothing is done.
    """
    fallocate = getattr(os, "posix_fallocate", None)
    if fallocate is None:  # macOS, Windows
        return
    size = os.path.getsize(path)
    fd = os.open(path, os.O_RDWR)
    try:
        fallocate(fd, 0, size)
    except OSError as err:
        if err.errno == errno.ENOSPC:
            raise no_space(Path(path).parent, size) from None
        if err.errno not in (errno.EINVAL, errno.EOPNOTSUPP, errno.ENOSYS):
            raise
    finally:
        os.close(fd)


def temporary_sibling(path: Path) -> Path:
    """A unique hidden name beside ``path`` for writing it before an atomic rename."""
    return path.with_name(f".{path.name}.{os.getpid()}-{uuid.uuid4().hex[:8]}.partial")


def _lock(fd: int) -> bool:
    """Take an exclusive lock on ``fd`` without waiting; ``False`` if someone holds it."""
    try:
        import fcntl
    except ImportError:  # Windows
        import msvcrt

        try:
            msvcrt.locking(fd, msvcrt.LK_NBLCK, 1)
        except OSError:
            return False
        return True
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        return False
    return True


class OutputLock:
    """Exclusive right to write ``target`` (and its bookkeeping files) for one run.

    The lock is ``TARGET.lock``, locked with the operating system's file lock, so it is
    released when the process ends in any way (also ``kill -9``); the file records who
    holds it and is removed on release.

    Raises
    ------
    OutputBusyError
        On entry, if another run holds the lock; the message says which.
    """

    def __init__(self, target: Path) -> None:
        self.target = Path(target)
        self.path = self.target.with_name(self.target.name + ".lock")
        self._fd: int | None = None

    def __enter__(self) -> OutputLock:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        for _ in range(10):
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
            if not _lock(fd):
                holder = os.read(fd, 200).decode("utf-8", "replace").strip() or "another run"
                os.close(fd)
                raise OutputBusyError(
                    errno.EBUSY,
                    f"{self.target} is being written by {holder}; wait for that run to end "
                    "or choose another output name",
                )
            try:
                current = os.stat(self.path).st_ino
            except FileNotFoundError:
                current = None
            if current == os.fstat(fd).st_ino:  # not removed by a finishing run meanwhile
                os.ftruncate(fd, 0)
                os.write(fd, f"process {os.getpid()} on {socket.gethostname()} since "
                             f"{time.strftime('%H:%M:%S')}".encode())  # fmt: skip
                self._fd = fd
                return self
            os.close(fd)
        raise OutputBusyError(errno.EBUSY, f"could not lock {self.path}")

    def __exit__(self, *exc: object) -> None:
        if self._fd is not None:
            self.path.unlink(missing_ok=True)
            os.close(self._fd)
            self._fd = None
