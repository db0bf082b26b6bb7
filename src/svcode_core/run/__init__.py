"""Running a reconstruction over recordings: streaming TIFF stacks with resume
(:mod:`.stream`), frames in parallel, in process or on dask (:mod:`.parallel`), and the
allocator setting for long array work (:mod:`.allocator`)."""

