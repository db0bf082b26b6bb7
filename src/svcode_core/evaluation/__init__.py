"""Judging reconstructions (design.md §6): image metrics (:mod:`.metrics`, also the
training's validation) and figures (:mod:`.figures`: the demo's, the calibration
report's). The benchmark engine (regimes, footprint, stability, ghosts, field position,
bars and beads) is ``svcode_bench``, beside the benchmark scripts in the checkout's
``bench`` folder, not part of the installed package."""
