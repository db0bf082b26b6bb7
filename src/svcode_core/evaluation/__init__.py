"""Judging the methods (design.md §6): image metrics (:mod:`.metrics`), model size and
memory (:mod:`.footprint`), extreme frames (:mod:`.stability`), ghosts of bright isolated
objects (:mod:`.ghosts`), the outer ring against the centre on the same content
(:mod:`.field_position`), the benchmark in six regimes (:mod:`.bench`) and figures
(:mod:`.figures`)."""
