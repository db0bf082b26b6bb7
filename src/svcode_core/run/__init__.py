"""Running a reconstruction over recordings: streaming TIFF stacks with resume
(:mod:`.stream`) and frames in parallel, in process or on dask (:mod:`.parallel`)."""
