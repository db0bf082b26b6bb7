"""Do the edge strips come back when their demixed views are taken from the readings?

The Demixing-Net loses the 16-px column strips (their demixed views carry 0.2-0.4 of
their target's energy as error, against 0.05-0.14 beside them), while the Recon-Net given
true views keeps most of them (`fusion_probe.py`). In a strip's sensor window a lens's
reading is its own image of the strip plus the other lenses' images of points a pitch
away, which lie inside the field and which the model reconstructs well. Without any
training this probe runs the bundled model once, predicts every lens's image of that
first reconstruction ``x̂`` with the nominal forward model, and gives the Recon-Net, in
the strips only, each lens's view explained by the readings::

    v_ℓ = L_ℓ(x̂) + f · crop_ℓ(y − A x̂)

(``L_ℓ``: lens ℓ's image in its own window, ``A``: the whole frame, ``crop_ℓ``: lens ℓ's
window of the sensor, all with the model's view margin; ``f`` the share of the residual,
the environment's ``EXPLAIN_SHARE``, default 1); the second pass's reconstruction
replaces the first in the strips' columns. Measured as ``bench/ring_gap.py`` does (its
options, e.g. ``--regimes matched realistic --no-admm``); cm2-mini, whole sub-views.

Usage (from the repository root)::

    EXPLAIN_SHARE=0.2 python training/cm2-mini-v5/explain_probe.py --no-admm \
        --out runs/explain-probe/share20
"""

from __future__ import annotations

import functools
import os
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "bench"))

import ring_gap  # noqa: E402

from svcode_core.config import SystemConfig  # noqa: E402
from svcode_core.evaluation.metrics import edge_columns  # noqa: E402
from svcode_core.evaluation.zones import EDGE_STRIP  # noqa: E402
from svcode_core.network.models import SVCoDe  # noqa: E402
from svcode_core.physics.cm2 import CM2Operator  # noqa: E402
from svcode_core.physics.geometry import extract_sub_views, pad_sensor_frame  # noqa: E402


@functools.cache
def nominal_operator() -> CM2Operator:
    """The nominal cm2-mini forward model (what the methods are given)."""
    return CM2Operator.from_system(SystemConfig.preset("cm2-mini"))


#: the share ``f`` of the residual given to each lens's view
SHARE = float(os.environ.get("EXPLAIN_SHARE", "1"))


def explained_views(x: torch.Tensor, own: torch.Tensor, margin: int) -> torch.Tensor:
    """``L_ℓ(x) + f · crop_ℓ(y − A x)`` ``(9, S + 2m, S + 2m)`` from the estimate ``x``
    ``(S, S)`` and the readings' own windows ``own`` (the model's input crops,
    exposure-normalised); ``f`` is :data:`SHARE`."""
    op = nominal_operator()
    system = op.system
    predicted = extract_sub_views(pad_sensor_frame(op.measure(x), system), system,
                                  margin=margin)  # fmt: skip
    return op.lens_images(x, past=margin) + SHARE * (own - predicted)


def forward_explained(self: SVCoDe, views, origins, sub_view_size):
    """:meth:`SVCoDe.forward` with the strips' demixed views explained by the readings."""
    padded, masks = self._prepare(views, origins, sub_view_size)
    demixed = self.demix.run(padded, masks)
    recon = self.recon.run(demixed, masks)
    h, w = views.shape[-2:]
    margin = self.model_config.view_margin
    if views.shape[0] != 1 or h != sub_view_size + 2 * margin:
        raise SystemExit("explain_probe: whole sub-views only (cm2-mini's default tiling)")
    field = slice(margin, margin + sub_view_size)
    estimate = recon[0, 0, field, field].float()
    own = views[0, :: self.demix.views_per_lens].float()
    explained = explained_views(estimate, own, margin).to(demixed.dtype)
    field_strips = edge_columns(sub_view_size, EDGE_STRIP)[0]  # and the margin past them
    strips = torch.from_numpy(np.pad(field_strips, margin, constant_values=True))
    second = self.recon.run(torch.where(strips, explained[None], demixed[..., :h, :w]), masks)
    recon = torch.where(strips, second, recon[..., :h, :w])
    return demixed[..., :h, :w], recon


if __name__ == "__main__":
    SVCoDe.forward = forward_explained
    ring_gap.main()
