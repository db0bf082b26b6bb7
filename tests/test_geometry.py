import numpy as np
import pytest
import torch

from svcode_core.physics.geometry import (
    CONTEXT_SHIFTS,
    assemble_frame,
    assemble_window,
    context_shifts,
    context_views,
    crops_at,
    extract_sub_views,
    field_radius,
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


def test_field_radius_from_the_pixel_indices():
    size = 7
    rows, cols = np.indices((size, size))
    centre = (size - 1) / 2
    expected = np.sqrt((rows - centre) ** 2 + (cols - centre) ** 2) / centre
    radius = field_radius(size)
    assert radius.dtype == np.float64 and radius.shape == (size, size)
    np.testing.assert_allclose(radius, expected, rtol=0, atol=4 * np.finfo(float).eps)
    assert radius[3, 3] == 0.0 and radius[3, 0] == radius[0, 3] == 1.0


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


def test_crops_are_slices_of_the_zero_padded_frame():
    """Crops inside, partly outside and wholly outside the frame, cut into memory that
    held other values just before: every pixel off the frame is 0, the rest the frame's."""
    frame = torch.from_numpy(np.random.default_rng(0).random((2, 20, 30), dtype=np.float32))
    corners = np.array([[3, 4], [-5, 2], [12, 25], [-8, -9], [40, 0], [0, -20]])
    size, pad = 10, 50
    padded = np.pad(frame.numpy(), ((0, 0), (pad, pad), (pad, pad)))
    expected = np.stack([padded[:, r + pad : r + pad + size, c + pad : c + pad + size]
                         for r, c in corners], axis=1)  # fmt: skip
    del_me = torch.full((2, len(corners), size, size), float("nan"))
    del del_me  # its memory is free for the crops
    np.testing.assert_array_equal(crops_at(frame, corners, size).numpy(), expected)


def test_wrong_frame_shape_raises(tiny_system):
    with pytest.raises(ValueError, match="padded sensor frame must have shape"):
        extract_sub_views(torch.zeros(10, 10), tiny_system)
    with pytest.raises(ValueError, match="raw sensor frame"):
        pad_sensor_frame(torch.zeros(10, 10), tiny_system)


@pytest.mark.parametrize("reach, shifts", [
    (1, CONTEXT_SHIFTS),
    (2, CONTEXT_SHIFTS + ((0, -2), (0, 2))),
])
def test_context_views_are_the_sub_views_moved_by_whole_pitches(mini_system, reach, shifts):
    """Against numpy slicing of one large zero-padded frame, pixel by pixel."""
    frame = torch.rand(mini_system.padded_shape, generator=torch.Generator().manual_seed(0))
    pitch = lens_pitch(mini_system)
    assert pitch == (144, 144)
    assert context_shifts(reach) == shifts
    big = 1000  # wider than every crop can reach
    padded = np.pad(frame.numpy(), big)
    origin, size = (40, 250), 96
    context = context_views(frame, mini_system, origin, size, reach)
    k = len(shifts)
    assert context.shape == (9 * k, size, size)
    for lens, (r0, c0) in enumerate(sub_view_origins(mini_system)):
        for j, (dr, dc) in enumerate(shifts):
            r = big + r0 + origin[0] + dr * pitch[0]
            c = big + c0 + origin[1] + dc * pitch[1]
            np.testing.assert_array_equal(context[k * lens + j].numpy(),
                                          padded[r : r + size, c : c + size])
    whole = context_views(frame, mini_system, reach=reach)  # channel kℓ: lens ℓ's sub-view
    assert torch.equal(whole[::k], extract_sub_views(frame, mini_system))
    # the right lens column moved one pitch right leaves the padded frame partly: zeros
    assert (whole[k * 2 + 5, :, -144:] == 0).all()


def test_context_reach_two_holds_the_reading_the_left_strip_needs(mini_system):
    """The left edge strip's one reading that a single lens column sees alone (sub-view
    column u seen at padded column u + 4 pitches, by the right lens column only) is in no
    crop at reach 1, and at reach 2 in the right lens's crop moved two pitches right."""
    frame = torch.zeros(mini_system.padded_shape)
    row, u = 100, 5
    r0 = sub_view_origins(mini_system)[4][0]  # the middle lens row
    column = u + 4 * 144
    assert mini_system.sensor_window[1].start <= column < mini_system.sensor_window[1].stop
    frame[r0 + row, column] = 1.0
    assert context_views(frame, mini_system)[:, row, u].sum() == 0
    far = context_views(frame, mini_system, reach=2)[:, row, u]
    assert far.nonzero().flatten().tolist() == [11 * 5 + 10]  # lens 5, shift (0, 2)


@pytest.mark.parametrize("reach", [0, -1, 1.5, True])
def test_context_shifts_refuse_a_reach_below_one_or_not_an_integer(reach):
    with pytest.raises(ValueError, match="reach must be an integer >= 1"):
        context_shifts(reach)


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


def test_assemble_window_reads_stored_float32_views_without_a_warning(tiny_system, tmp_path):
    """A dataset's float32 views are read-only memory maps: the window is assembled from
    copies (torch warns about tensors over read-only arrays) and equals the whole frame's."""
    import warnings

    views = np.random.default_rng(0).random((9, *(tiny_system.sub_view_size,) * 2))
    np.save(tmp_path / "views.npy", views.astype(np.float32))
    stored = np.load(tmp_path / "views.npy", mmap_mode="r")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        window = assemble_window(stored, tiny_system, 3, -2, 20, 24)
    expected = assemble_frame(torch.from_numpy(views).float(), tiny_system)[3:23, :22]
    torch.testing.assert_close(window[:, 2:], expected)
