"""The ghost probe reads a disc's own brightness and its copies one lens pitch away."""

from __future__ import annotations

import numpy as np
import pytest

from svcode_bench.ghosts import ghost_probe, lens_pitch
from svcode_core.physics.simulate import Simulator


def _disc(size, centre, radius):
    rows, cols = np.mgrid[:size, :size]
    return ((rows - centre[0]) ** 2 + (cols - centre[1]) ** 2 < radius**2).astype(float)


@pytest.mark.parametrize(("centre", "inside"), [
    ((24, 24), {"up", "down", "left", "right"}),  # every neighbour inside the field
    ((4, 24), {"down", "left", "right"}),  # the one above lies outside
])
def test_probe_reads_a_known_ghost(tiny_system, centre, inside):
    size = tiny_system.sub_view_size
    pitch = lens_pitch(tiny_system)
    simulator = Simulator(tiny_system)
    radius, level = 6, 0.5

    def with_ghost(raw):  # the truth plus a quarter-bright copy one pitch down
        ghost_centre = (centre[0] + pitch[0], centre[1])
        return level * (_disc(size, centre, radius) + 0.25 * _disc(size, ghost_centre, radius))

    reading = ghost_probe(with_ghost, simulator, centre, radius, level)
    assert set(reading.ghosts) == inside
    assert reading.own == pytest.approx(1.0, abs=1e-12)
    expected = {name: 0.25 if name == "down" else 0.0 for name in inside}
    assert reading.ghosts == pytest.approx(expected, abs=1e-12)
    assert reading.worst == pytest.approx(0.25, abs=1e-12)


def test_bundled_model_leaves_no_ghost_where_three_lens_rows_see_the_copy(mini_system):
    """Object rows 96-287 are seen by all three lens rows: a bright disc whose copy one
    pitch away lands there comes back alone (measured: copies of 2 % of its level). In
    rows 0-95 and 288-383 the bundled model leaves 10-17 % (bench/results/ghosts.md)."""
    import torch

    from svcode_core import Reconstructor

    torch.set_num_threads(2)
    reconstructor = Reconstructor.pretrained(mini_system)
    reading = ghost_probe(lambda raw: reconstructor.reconstruct(raw).reconstruction,
                          Simulator(mini_system), (100, 192), radius=40, level=1.0)
    assert set(reading.ghosts) == {"down", "left", "right"}  # "up" is outside the field
    assert reading.worst < 0.05
    assert 0.85 < reading.own < 1.15
