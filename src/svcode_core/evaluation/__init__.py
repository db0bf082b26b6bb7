"""Judging the methods (design.md §6): image metrics (:mod:`.metrics`), model size and
memory (:mod:`.footprint`), extreme frames (:mod:`.stability`), ghosts of bright isolated
objects (:mod:`.ghosts`), the benchmark in six
regimes (:mod:`.bench`) and figures (:mod:`.figures`)."""
