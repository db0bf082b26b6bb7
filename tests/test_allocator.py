"""The allocator setting of long array work: freed blocks are kept in the heap for reuse.

What the setting controls is read from glibc's own bookkeeping (``mallinfo2``): where a
large block is served from, and whether it stays in the heap once freed. Page faults are
not asserted: whether a kept page is touched again without a fault depends on the kernel
below the process (reclaim, transparent huge pages), not on the allocator.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

BLOCK = 2**27  # one 128 MiB array (2**25 float32), above glibc's largest mmap threshold

_PROBE = """
import ctypes, json, sys
import torch
from svcode_core.run.allocator import reuse_freed_memory

class Info(ctypes.Structure):  # struct mallinfo2 (glibc >= 2.33)
    _fields_ = [(name, ctypes.c_size_t) for name in (
        "arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks", "fsmblks",
        "uordblks", "fordblks", "keepcost")]

mallinfo2 = ctypes.CDLL(None).mallinfo2
mallinfo2.restype = Info
if sys.argv[1] == "keep":
    assert reuse_freed_memory()
if sys.argv[1] == "user":
    assert not reuse_freed_memory()  # the environment's setting wins
array = torch.ones(2**25)
alive = mallinfo2()
del array
freed = mallinfo2()
print(json.dumps({"mapped_while_alive": alive.hblkhd, "heap_free_after": freed.fordblks}))
"""


def _probe(mode: str, env: dict[str, str] | None = None) -> dict[str, int]:
    if env is None:  # without allocator settings (dask's nanny leaves one in os.environ)
        env = {k: v for k, v in os.environ.items()
               if not k.startswith("MALLOC_") and k != "GLIBC_TUNABLES"}  # fmt: skip
    out = subprocess.run([sys.executable, "-c", _PROBE, mode], check=True,
                         capture_output=True, text=True, env=env)  # fmt: skip
    return json.loads(out.stdout.splitlines()[-1])


def _has_mallinfo2() -> bool:
    import ctypes

    try:
        return hasattr(ctypes.CDLL(None), "mallinfo2")
    except OSError:
        return False


needs_glibc = pytest.mark.skipif(
    not sys.platform.startswith("linux") or not _has_mallinfo2(),
    reason="glibc's malloc (2.33 or later) only")


@needs_glibc
def test_freed_blocks_stay_in_the_heap_for_the_next_array():
    default = _probe("default")
    # by default the block is a fresh mapping, returned to the system when freed
    assert default["mapped_while_alive"] >= BLOCK
    assert default["heap_free_after"] < BLOCK
    kept = _probe("keep")
    # kept: served from the heap, and still there once freed, for the next array
    assert kept["mapped_while_alive"] < BLOCK
    assert kept["heap_free_after"] >= BLOCK


@needs_glibc
def test_the_environment_s_allocator_setting_wins():
    env = {k: v for k, v in os.environ.items() if not k.startswith("MALLOC_")}
    env["MALLOC_MMAP_THRESHOLD_"] = "65536"
    assert _probe("user", env)["mapped_while_alive"] >= BLOCK
