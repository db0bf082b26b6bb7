"""The zones of the field that the metrics and the training loss single out: plain numbers,
importable without torch (``svcode train --help`` quotes them).

* :data:`CENTRE_RADIUS`, :data:`RING_RADIUS`: the centre and the outer ring of the field,
  in normalised field radius (:func:`svcode_core.evaluation.metrics.field_zones`; the
  loss's :func:`~svcode_core.training.loss.field_weights` weighs the same ring);
* :data:`EDGE_STRIP`: the width of the sub-view's edge strips that
  :func:`~svcode_core.training.loss.field_weights` weighs.
"""

__all__ = ["CENTRE_RADIUS", "EDGE_STRIP", "RING_RADIUS"]

#: Normalised field radius below which a pixel lies in the centre (seen by all nine lenses).
CENTRE_RADIUS = 0.5
#: Normalised field radius above which a pixel lies in the outer ring (corners included).
RING_RADIUS = 0.8
#: Width in sub-view pixels of the edge strips that
#: :func:`~svcode_core.training.loss.field_weights` weighs.
EDGE_STRIP = 16
