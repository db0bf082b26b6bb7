"""The C allocator setting for long array work: keep freed memory for the next array.

The network and the operators allocate many short-lived arrays of tens to hundreds of MiB
(a paper-scale feature map of 480² pixels × 64 channels is 56 MiB). glibc's ``malloc``
serves every block above 32 MiB with a fresh ``mmap`` and returns it to the system on
``free``, so each such array is paged in again, 4 KiB at a time, on first touch. Measured
on one 480² tile of the reference network (one thread): 4.2-5.4 s per call with the
default setting, 3.2-3.6 s with the blocks kept, and the coordinate masks' share of the
time halves (their interpolated fields are the freshest arrays of all).

:func:`reuse_freed_memory` asks glibc to serve all blocks from its heap and to keep up to
2 GiB of freed memory there, with one heap for all threads: frames reconstructed side by
side on threads (:func:`svcode_core.run.parallel.local_frames`) would otherwise allocate
from heaps of their own, and the paging comes back (measured on a 6-frame ``cm2-mini``
stack on two threads: 3.6 s of system time instead of 1.1). The ``svcode``
command does this at start; a library cannot know what else its host process does, so
``import svcode_core`` never does (napari keeps its own setting). The same effect without
code: ``GLIBC_TUNABLES=glibc.malloc.mmap_max=0:glibc.malloc.arena_max=1`` in the
environment. The resident memory then stays at its peak until the process ends.
"""

from __future__ import annotations

import ctypes
import os
import sys

__all__ = ["reuse_freed_memory"]

_M_TRIM_THRESHOLD = -1  # glibc's mallopt parameters (malloc.h)
_M_MMAP_MAX = -4
_M_ARENA_MAX = -8
_KEEP_BYTES = 2**31 - 1  # the largest trim threshold mallopt takes (an int)


def reuse_freed_memory() -> bool:
    """Make this process's ``malloc`` keep freed blocks for reuse (glibc on Linux only).

    Nothing changes when the environment already configures glibc's ``malloc``
    (``MALLOC_*`` variables or ``glibc.malloc`` tunables in ``GLIBC_TUNABLES``): the
    user's setting wins, e.g. ``MALLOC_MMAP_THRESHOLD_=65536`` for the smallest resident
    memory at about twice the CPU time.

    Returns
    -------
    bool
        ``True`` when the setting was applied; ``False`` on other platforms or C
        libraries, or when the environment sets its own, where nothing changes.
    """
    configured = any(name.startswith("MALLOC_") for name in os.environ) or (
        "glibc.malloc" in os.environ.get("GLIBC_TUNABLES", ""))
    if configured or not sys.platform.startswith("linux"):
        return False
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    settings = ((_M_MMAP_MAX, 0), (_M_TRIM_THRESHOLD, _KEEP_BYTES), (_M_ARENA_MAX, 1))
    return all([bool(mallopt(parameter, value)) for parameter, value in settings])
