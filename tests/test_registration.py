"""Chief-ray self-registration: the interface; its accuracy is measured in bench/calibration.py."""

from __future__ import annotations

import numpy as np
import pytest

from svcode_core.phantoms import make_object
from svcode_core.physics.registration import register_frame
from svcode_core.physics.simulate import Simulator


def test_register_frame_reports_offsets_relative_to_the_reference(tiny_system):
    frame = Simulator(tiny_system).simulate(make_object("cells", 48, 1), noise=False).measurement
    registration = register_frame(frame, tiny_system)
    assert registration.offsets.shape == (9, 2)
    np.testing.assert_array_equal(registration.offsets[4], 0.0)
    # the nominal frame of the nominal system: no drift beyond the method's own bias
    assert np.abs(registration.offsets).max() < 0.5
    record = registration.to_dict()
    assert set(record) == {"reference_lens", "lens_offsets_px", "array_shift_px",
                           "array_rotation_deg"}
    with pytest.raises(ValueError, match="frame is 60×79 px"):
        register_frame(frame[:, :79], tiny_system)
