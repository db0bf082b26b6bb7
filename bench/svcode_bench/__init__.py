"""The benchmark engine of napari-svcode, beside the benchmark scripts (``bench/*.py``) and
not part of the installed package.

* :mod:`.regimes`: ``svcode bench``, every method and knob in six regimes (scenes, rows,
  the report ``regimes.{json,md,png}``);
* :mod:`.footprint`: parameters and peak memory of a model, at S and 2S;
* :mod:`.stability`: extreme frames (``bench/stability.py``);
* :mod:`.ghosts`: copies a bright object leaves one lens pitch away (``bench/ghosts.py``);
* :mod:`.field_position`: the same content at the centre and in the outer ring
  (``bench/ring_gap.py``);
* :mod:`.resolution` and :mod:`.beads`: a bar target and bead fields
  (``bench/resolution.py``, ``bench/beads.py``).

It imports the installed core (``svcode_core``), never the reverse. The scripts import it
from their own folder; ``svcode bench`` and the tests add the checkout's ``bench`` folder to
``sys.path``.
"""

import platform
from pathlib import Path

#: the benchmark's regimes: name → the departures (:mod:`svcode_core.physics.departures`)
#: of the instrument its test frames come from; here, where ``svcode bench --help`` reads
#: them without importing torch
REGIMES = {
    "matched": "none",
    "calibration": "calibration",
    "model": "model",
    "background": "background",
    "low-light": "low-light",
    "realistic": "realistic",
}


def processor() -> tuple[str, list[str]]:
    """The processor's model name and its bfloat16 flags (``avx512_bf16``, ``amx_bf16``),
    from ``/proc/cpuinfo``; where there is none, the platform's name and no flags."""
    try:
        lines = Path("/proc/cpuinfo").read_text().splitlines()
    except OSError:
        return platform.processor() or platform.machine(), []
    name = next((line.split(":", 1)[1].strip() for line in lines
                 if line.startswith("model name")), platform.machine())
    flags = next((line.split(":", 1)[1].split() for line in lines
                  if line.startswith("flags")), [])
    return name, [f for f in ("avx512_bf16", "amx_bf16") if f in flags]
