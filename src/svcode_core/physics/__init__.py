"""The instrument and its forward model (design.md §1).

Geometry of the nine views (:mod:`.geometry`), field-varying PSFs from a pupil model
(:mod:`.optics`) or measured ones (:mod:`.psf_io`), calibration from a point-source scan
(:mod:`.scan`, :mod:`.registration`, :mod:`.calibration`), the low-rank spatially varying
operator (:mod:`.lowrank`, exact reference :mod:`.reference`), the whole CM² frame
(:mod:`.cm2`), sensor noise (:mod:`.noise`), simulation (:mod:`.simulate`, scene checks
:mod:`.scene_checks`) and the true instrument's departures from the nominal system
(:mod:`.departures`, :mod:`.instrument`).
"""
