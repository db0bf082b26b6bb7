"""The allocator setting of long array work: freed blocks are reused, not paged in again."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

_PROBE = """
import resource, sys
import torch
from svcode_core.run.allocator import reuse_freed_memory
if sys.argv[1] == "keep":
    assert reuse_freed_memory()
if sys.argv[1] == "user":
    assert not reuse_freed_memory()  # the environment's setting wins
for _ in range(2):  # 128 MiB, allocated, touched and freed: the heap settles in two
    torch.ones(2**25)
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(4):
    torch.ones(2**25)
print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
"""


def _page_faults(mode: str, env: dict[str, str] | None = None) -> int:
    if env is None:  # without allocator settings (dask's nanny leaves one in os.environ)
        env = {k: v for k, v in os.environ.items()
               if not k.startswith("MALLOC_") and k != "GLIBC_TUNABLES"}  # fmt: skip
    out = subprocess.run([sys.executable, "-c", _PROBE, mode], check=True,
                         capture_output=True, text=True, env=env)  # fmt: skip
    return int(out.stdout.split()[-1])


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's malloc only")
def test_freed_blocks_are_reused_instead_of_paged_in_again():
    # by default each of four 128 MiB arrays is paged in again: at least 64 faults each
    # even with 2 MiB pages (32768 with 4 KiB pages); kept, they come back without any.
    # On a loaded machine some runs fault again on one to all four kept arrays (seen with
    # one thread and nothing else in the process: the cause is outside it), so the kept
    # setting must get below a third of the default's faults in one of five runs; what
    # happens outside the process only adds faults
    default = _page_faults("default")
    assert default >= 4 * 64
    kept = []
    for _ in range(5):
        kept.append(_page_faults("keep"))
        if kept[-1] <= default // 3:
            break
    assert min(kept) <= default // 3, (default, kept)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's malloc only")
def test_the_environment_s_allocator_setting_wins():
    env = {k: v for k, v in os.environ.items() if not k.startswith("MALLOC_")}
    env["MALLOC_MMAP_THRESHOLD_"] = "65536"
    assert _page_faults("user", env) >= 4 * 64
