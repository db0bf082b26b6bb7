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
