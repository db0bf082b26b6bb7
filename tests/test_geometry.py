import numpy as np
import pytest
import torch

from svcode_core.physics.geometry import (
    CONTEXT_SHIFTS,
    context_views,
    extract_sub_views,
    lens_pitch,
    normalized_coordinates,
    pad_sensor_frame,
    sensor_coverage,
    sub_view_origins,
)


def test_normalized_coordinates_edges_exact():
    coords = normalized_coordinates(384)
    assert coords[0].item() == -1.0 and coords[-1].item() == 1.0
    assert coords[383 // 2].item() < 0 < coords[384 // 2].item()
    tail = normalized_coordinates(384, start=380, length=8, dtype=torch.float64)
    step = 2.0 / 383
    np.testing.assert_allclose(np.diff(tail.numpy()), step, rtol=1e-12)
    assert tail[-1].item() > 1.0  # padding continues the line


def test_sub_view_centred_on_chief_ray(mini_system):
    frame = torch.zeros(mini_system.padded_shape)
    for lens, (r, c) in enumerate(mini_system.chief_rays):
        frame[r, c] = lens + 1
    views = extract_sub_views(frame, mini_system)
    half = mini_system.sub_view_size // 2
    for lens in range(9):
        assert views[lens, half, half].item() == lens + 1


def test_out_of_frame_crops_are_zero(tiny_system):
    shifted = tiny_system.replace(
        chief_rays=((2, 2),) + tuple(tiny_system.chief_rays[1:])
    )
    views = extract_sub_views(torch.ones(shifted.padded_shape), shifted)
    origin = sub_view_origins(shifted)[0]
    assert (origin < 0).all()
    assert views[0, : -origin[0]].abs().sum() == 0
    assert views[0, -origin[0]:, -origin[1]:].min() == 1


def test_wrong_frame_shape_raises(tiny_system):
    with pytest.raises(ValueError, match="padded sensor frame must have shape"):
        extract_sub_views(torch.zeros(10, 10), tiny_system)
    with pytest.raises(ValueError, match="raw sensor frame"):
        pad_sensor_frame(torch.zeros(10, 10), tiny_system)


def test_context_views_are_the_sub_views_moved_by_a_pitch(mini_system):
    """Against numpy slicing of one large zero-padded frame, pixel by pixel."""
    frame = torch.rand(mini_system.padded_shape, generator=torch.Generator().manual_seed(0))
    pitch = lens_pitch(mini_system)
    assert pitch == (144, 144)
    big = 1000  # wider than every crop can reach
    padded = np.pad(frame.numpy(), big)
    origin, size = (40, 250), 96
    context = context_views(frame, mini_system, origin, size)
    assert context.shape == (81, size, size)
    for lens, (r0, c0) in enumerate(sub_view_origins(mini_system)):
        for k, (dr, dc) in enumerate(CONTEXT_SHIFTS):
            r = big + r0 + origin[0] + dr * pitch[0]
            c = big + c0 + origin[1] + dc * pitch[1]
            np.testing.assert_array_equal(context[9 * lens + k].numpy(),
                                          padded[r : r + size, c : c + size])
    whole = context_views(frame, mini_system)  # channel 9ℓ is lens ℓ's sub-view
    assert torch.equal(whole[::9], extract_sub_views(frame, mini_system))
    # the right lens column moved one pitch right leaves the padded frame partly: zeros
    assert (whole[9 * 2 + 5, :, -144:] == 0).all()


def test_sensor_coverage_is_the_sensor_window_seen_from_each_sub_view(mini_system):
    coverage = sensor_coverage(mini_system, torch.float64)
    rows, cols = mini_system.sensor_window
    size = mini_system.sub_view_size
    for lens, (r0, c0) in enumerate(sub_view_origins(mini_system)):
        r, c = np.arange(r0, r0 + size), np.arange(c0, c0 + size)
        on_rows, on_cols = (r >= rows.start) & (r < rows.stop), (c >= cols.start) & (c < cols.stop)
        inside = on_rows[:, None] & on_cols[None, :]
        np.testing.assert_array_equal(coverage[lens].numpy(), inside.astype(np.float64))
    assert coverage.dtype == torch.float64
