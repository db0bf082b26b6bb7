"""``svcode calibrate``: a simulated bead scan of a departed instrument, calibrated back."""

from __future__ import annotations

import dataclasses
import json
import tracemalloc

import numpy as np
import pytest
import torch

from svcode_core.cli import main
from svcode_core.config import SystemConfig
from svcode_core.io import read_tiff, write_tiff
from svcode_core.methods.periphery import periphery_weight
from svcode_core.physics.calibration import CalibrationError, calibrate, read_positions
from svcode_core.physics.cm2 import CM2Operator
from svcode_core.physics.departures import Departures
from svcode_core.physics.instrument import departed_system
from svcode_core.physics.psf_io import load_measured_psfs, positions_path
from svcode_core.physics.scan import (
    bead_object,
    scan_grid,
    simulate_scan,
    with_dark_offset,
    write_positions,
)
from svcode_core.physics.simulate import Simulator

#: Larger than the ``calibration`` set (scaled to the tiny system's 1-px Airy radius it
#: moves the lenses by a quarter pixel), so that the fit has something to find.
DEPARTURES = Departures(name="test", mla_shift_px=(1.3, -0.7), mla_rotation_deg=0.4,
                        lens_jitter_px=0.3, seed=3)
#: Black level: 8 read-noise deviations, so the dark pixels are never clipped at zero.
BLACK_LEVEL = 2e-3
TOLERANCE = 1e-3


@pytest.fixture(scope="module")
def scan(tiny_system):
    """A 7×7 bead scan of the tiny system through DEPARTURES, with its dark stack."""
    system = with_dark_offset(tiny_system, BLACK_LEVEL)
    simulator = Simulator(system, departures=DEPARTURES)
    positions = scan_grid(system, 7)
    frames, dark = simulate_scan(simulator, positions, seed=1)
    # a tighter tolerance than the truth's own (1e-2): its PSFs are already of low rank
    calibration = calibrate(frames, positions, system, dark=dark, tolerance=TOLERANCE)
    return system, simulator, positions, frames, dark, calibration


@pytest.fixture(scope="module")
def stage_scan(tiny_system):
    """A 7×7 scan of the tiny system through DEPARTURES at positions a stage gives: a
    raster off the pixel centres by (0.4, -0.3) px, each position a little off its own."""
    system = with_dark_offset(tiny_system, BLACK_LEVEL)
    simulator = Simulator(system, departures=DEPARTURES)
    jitter = np.random.default_rng(0).uniform(-0.1, 0.1, (49, 2))
    positions = np.clip(scan_grid(system, 7) + (0.4, -0.3) + jitter, 0, system.sub_view_size - 1)
    frames, dark = simulate_scan(simulator, positions, seed=1)
    calibration = calibrate(frames, positions, system, dark=dark, tolerance=TOLERANCE)
    return system, simulator, positions, frames, dark, calibration


def _relative(a, b) -> float:
    return float(np.linalg.norm(a - b) / np.linalg.norm(b))


def test_chief_rays_within_a_quarter_pixel(scan):
    system, _, _, _, _, calibration = scan
    truth = DEPARTURES.lens_offsets(system)
    error = np.abs(calibration.offsets - truth)
    assert error.max() < 0.25, error
    # the array motion is found too (per-lens jitter of 0.3 px limits the split)
    np.testing.assert_allclose(calibration.array_shift, DEPARTURES.mla_shift_px, atol=0.2)
    assert abs(calibration.array_rotation_deg - DEPARTURES.mla_rotation_deg) < 0.2
    truth_system, _ = departed_system(system, DEPARTURES)
    moved = np.abs(np.asarray(calibration.system.chief_rays) - truth_system.chief_rays)
    assert moved.max() <= 1  # rounding may differ for an offset near a half pixel


def test_psfs_and_frames_reproduce_the_departed_instrument(scan):
    system, simulator, positions, frames, dark, calibration = scan
    calibrated = CM2Operator.from_psfs(calibration.system, calibration.psfs,
                                       dtype=torch.float64)
    nominal = CM2Operator.from_system(system, dtype=torch.float64)
    size = system.sub_view_size
    beads = torch.zeros(len(positions), size, size, dtype=torch.float64)
    beads[torch.arange(len(positions)), positions[:, 0], positions[:, 1]] = 1.0
    clean, black = simulate_scan(simulator, positions, noise=False, dark_frames=1)
    truth = clean - black  # the expected readings, less the camera's black level
    # PSFs at every scanned position (the scan frames, noiseless): within 3 % (noiseless
    # scan: 1.9 %, the rest is the scan's noise, 3 % of a frame's norm, fitted over 49)
    psf_error = _relative(calibrated.measure(beads).numpy(), truth)
    assert psf_error < 0.03
    assert _relative(nominal.measure(beads).numpy(), truth) > 10 * psf_error
    # an extended object the calibration never saw: within 3 %
    from svcode_core.phantoms import make_object

    obj = make_object("cells", size, 0)
    frame = simulator.simulate(obj, noise=False).measurement - black[0]
    x = torch.as_tensor(obj, dtype=torch.float64)
    assert _relative(calibrated.measure(x).numpy(), frame) < 0.03
    # grid PSFs of the lens whose whole field is on the sensor, against the truth's own
    # (its pupil-model PSFs reduced to its low rank, which is what made the frames)
    truth_grid = np.stack([np.einsum("kab,kij->abij", d.grid_weights, d.kernels).reshape(
        -1, *d.kernels.shape[1:]) for d in simulator.operator.decompositions])
    assert _relative(calibration.psfs[4], truth_grid[4]) < 0.03
    assert calibration.brightness == pytest.approx(1.0, abs=0.02)


def test_sub_pixel_positions_recover_the_drift(stage_scan):
    system, simulator, positions, frames, dark, calibration = stage_scan
    truth = DEPARTURES.lens_offsets(system)
    error = np.abs(calibration.offsets - truth).max()
    # rounded to whole pixels (all a positions file could hold before), the raster's
    # (0.4, -0.3) px offset goes into the array shift
    rounded = calibrate(frames, np.rint(positions), system, dark=dark, tolerance=TOLERANCE)
    assert error < 0.2 < 0.35 < np.abs(rounded.offsets - truth).max()
    np.testing.assert_allclose(calibration.array_shift, DEPARTURES.mla_shift_px, atol=0.1)
    assert np.abs(rounded.array_shift - DEPARTURES.mla_shift_px).max() > 0.25
    # the fitted chief rays predict the spots better: the rounded positions leave most of
    # the stage's jitter (uniform ±0.1 px per axis, 0.082 px rms) unexplained, in quadrature
    jitter_rms = 0.2 / np.sqrt(12) * np.sqrt(2)
    excess = rounded.residual_rms.mean() ** 2 - calibration.residual_rms.mean() ** 2
    assert excess > (0.8 * jitter_rms) ** 2
    # the PSFs, moved back to whole pixels, make a forward model of a scene it never saw
    # (the tiny system's 1-px Airy core is too coarsely sampled to move exactly: 7 %)
    from svcode_core.phantoms import make_object

    size = system.sub_view_size
    _, black = simulate_scan(simulator, positions[:1], noise=False, dark_frames=1)
    obj = make_object("cells", size, 0)
    frame = simulator.simulate(obj, noise=False).measurement - black[0]
    x = torch.as_tensor(obj, dtype=torch.float64)
    fitted, whole = (_relative(CM2Operator.from_psfs(cal.system, cal.psfs, dtype=torch.float64)
                               .measure(x).numpy(), frame) for cal in (calibration, rounded))
    assert fitted < 0.09 and fitted < 0.6 * whole


def test_micrometre_positions_through_the_command(stage_scan, tmp_path, capsys):
    system, _, positions, frames, dark, calibration = stage_scan
    nominal = system.save(tmp_path / "nominal.json")
    write_tiff(tmp_path / "scan.tif", frames, system, kind="scan")
    write_tiff(tmp_path / "dark.tif", dark, system, kind="dark")
    centre = system.sub_view_size // 2
    pixel_size = 2.5  # um per object pixel
    y, x = ((positions - centre) * pixel_size).T
    lines = [f"{a:.4f},{b:.4f}" for a, b in zip(x, y, strict=True)]
    (tmp_path / "pos.csv").write_text("x_um,y_um\n" + "\n".join(lines) + "\n")
    out = tmp_path / "cal"
    assert main(["calibrate", str(tmp_path / "scan.tif"), "--positions",
                 str(tmp_path / "pos.csv"), "--pixel-size", str(pixel_size), "--system",
                 str(nominal), "--dark", str(tmp_path / "dark.tif"), "--out", str(out)]) == 0
    assert "calibrated tiny from 49 frames" in capsys.readouterr().out
    saved = json.loads((out / "calibration.json").read_text())
    np.testing.assert_allclose(saved["offsets_px"], calibration.offsets, atol=1e-3)
    # the default pixel size: the system's
    sized = system.replace(object_pixel_um=pixel_size).save(tmp_path / "sized.json")
    assert main(["calibrate", str(tmp_path / "scan.tif"), "--positions",
                 str(tmp_path / "pos.csv"), "--system", str(sized), "--dark",
                 str(tmp_path / "dark.tif"), "--out", str(tmp_path / "default")]) == 0
    capsys.readouterr()
    again = json.loads((tmp_path / "default" / "calibration.json").read_text())
    np.testing.assert_allclose(again["offsets_px"], calibration.offsets, atol=1e-3)
    # without a pixel size anywhere: one line naming the file's header
    unsized = system.replace(object_pixel_um=None).save(tmp_path / "unsized.json")
    assert main(["calibrate", str(tmp_path / "scan.tif"), "--positions",
                 str(tmp_path / "pos.csv"), "--system", str(unsized), "--out", str(out)]) != 0
    error = capsys.readouterr().err
    assert "pos.csv line 1: positions in micrometres" in error and "--pixel-size" in error
    assert error.count("\n") == 1


def test_a_shuffled_scan_gives_the_same_calibration(stage_scan):
    system, _, positions, frames, dark, calibration = stage_scan
    order = np.random.default_rng(1).permutation(len(positions))
    shuffled = calibrate(frames[order], positions[order], system, dark=dark,
                         tolerance=TOLERANCE)  # fmt: skip
    assert shuffled.system == calibration.system
    for name in ("offsets", "offset_errors", "psfs", "throughput"):
        np.testing.assert_allclose(getattr(shuffled, name), getattr(calibration, name),
                                   rtol=1e-9, atol=1e-12, err_msg=name)  # fmt: skip
    # the spots stay with their frames
    np.testing.assert_array_equal(shuffled.centroids, calibration.centroids[order])


def test_repeated_frames_are_averaged(scan):
    system, _, positions, frames, dark, calibration = scan
    # two frames of every position whose mean is the scan's frame: the same calibration
    wobble = np.random.default_rng(2).normal(0.0, 1e-4, frames.shape)
    twice = np.concatenate([frames + wobble, frames - wobble])
    repeated = calibrate(twice, np.concatenate([positions, positions]), system, dark=dark,
                         tolerance=TOLERANCE)  # fmt: skip
    assert repeated.system == calibration.system
    for name in ("offsets", "offset_errors", "psfs", "throughput"):
        np.testing.assert_allclose(getattr(repeated, name), getattr(calibration, name),
                                   rtol=1e-6, atol=1e-9, err_msg=name)  # fmt: skip
    assert repeated.brightness == pytest.approx(calibration.brightness, rel=1e-9)
    # one frame's noise: the mean of two has sqrt(2) less
    assert repeated.noise_sigma == pytest.approx(calibration.noise_sigma * np.sqrt(2), rel=1e-6)
    assert repeated.centroids.shape == (98, 9, 2)
    np.testing.assert_array_equal(repeated.centroids[49:], repeated.centroids[:49])
    # an error names every frame of the position
    empty = twice.copy()
    empty[[7, 56]] = dark[0]
    with pytest.raises(CalibrationError, match=r"frames 7, 56 \(averaged\): no spot"):
        calibrate(empty, np.concatenate([positions, positions]), system, dark=dark)


def test_the_command_maps_the_scan_and_reads_a_compressed_one(scan, tmp_path):
    import tifffile

    from svcode_core.cli.calibrate import _scan

    system, _, _, frames, _, _ = scan
    write_tiff(tmp_path / "scan.tif", frames, system, kind="scan")
    tifffile.imwrite(tmp_path / "packed.tif", frames, compression="zlib")
    mapped, read = _scan(tmp_path / "scan.tif"), _scan(tmp_path / "packed.tif")
    assert isinstance(mapped, np.memmap) and not isinstance(read, np.memmap)
    np.testing.assert_array_equal(mapped, frames)
    np.testing.assert_array_equal(read, frames)


def test_the_working_memory_does_not_grow_with_the_frames_of_a_position(scan):
    # A paper-scale scan is gigabytes: the calibration keeps one float32 mean frame per
    # position and reads the scan's frames one at a time (float64 copies of the whole stack
    # made the peak 8x the scan).
    system, _, positions, frames, dark, _ = scan
    peaks = []
    for repeats in (1, 4):
        stack, where = np.repeat(frames, repeats, axis=0), np.repeat(positions, repeats, axis=0)
        tracemalloc.start()
        try:
            calibrate(stack, where, system, dark=dark, tolerance=TOLERANCE)
            peaks.append(tracemalloc.get_traced_memory()[1])
        finally:
            tracemalloc.stop()
    assert peaks[1] < 1.05 * peaks[0]  # three more copies of the scan would be +3 × 0.9 MB


def test_simulated_bead_between_pixels():
    np.testing.assert_array_equal(bead_object(8, (2, 5)), np.eye(8)[2][:, None] * np.eye(8)[5])
    # between pixels, its image through a smooth blur is centred on the position
    from scipy import ndimage

    rows, cols = np.mgrid[:64, :64]
    window = (slice(18, 45), slice(8, 35))
    for position in [(30.25, 20.5), (31.4, 19.7)]:
        image = ndimage.gaussian_filter(bead_object(64, position).astype(np.float64), 2.0)
        centre = [(image[window] * axis[window]).sum() / image[window].sum()
                  for axis in (rows, cols)]
        np.testing.assert_allclose(centre, position, atol=1e-3)


def test_positions_csv(tmp_path):
    path = tmp_path / "pos.csv"
    written = np.array([[0, 1], [2.5, 3.125], [47, 0.000001]])
    np.testing.assert_array_equal(read_positions(write_positions(path, written)), written)
    assert path.read_text().splitlines()[:3] == ["row,col", "0,1", "2.5,3.125"]
    path.write_text("0,1\n2.5,3\n")  # no header: row,col
    np.testing.assert_array_equal(read_positions(path), [[0, 1], [2.5, 3]])
    path.write_text("Col , Row\n0,1\n\n2.5,3\n")
    np.testing.assert_array_equal(read_positions(path), [[1, 0], [3, 2.5]])
    # micrometres from the field's centre, pixel (24, 24) of the tiny system's 48×48 grid
    path.write_text("x_um,y_um\n0,0\n-5,7.5\n")
    np.testing.assert_array_equal(read_positions(path, 2.5, size=48), [[24, 24], [27, 22]])
    path.write_text("y_um,x_um\n7.5,-5\n")
    np.testing.assert_array_equal(read_positions(path, 2.5, size=48), [[27, 22]])


@pytest.mark.parametrize(("text", "options", "message"), [
    ("row,col\n0,1\n2,abc\n", {}, r"pos.csv line 3: 'abc' is not a number"),
    ("row,col\n0,1\nnan,3\n", {}, r"pos.csv line 3: 'nan' is not a number"),
    ("row,col\n0,1\n2,3,4\n", {}, r"pos.csv line 3: expected 2 values row,col, got 3"),
    ("0,1\n2\n", {}, r"pos.csv line 2: expected 2 values row,col, got 1"),
    ("x,y\n0,1\n", {}, r"pos.csv line 1: unknown header 'x,y'"),
    ("row,col,z\n0,1,2\n", {}, r"pos.csv line 1: unknown header 'row,col,z'"),
    ("x_um,y_um\n0,0\n", {"size": 48}, r"pos.csv line 1: positions in micrometres"),
    ("row,col\n0,1\n\n2,48\n", {"size": 48},
     r"pos.csv line 4: position \(2, 48\) lies outside the 48×48 object grid"),
    ("row,col\n0,-0.5\n", {"size": 48}, r"pos.csv line 2: position \(0, -0.5\) lies outside"),
    ("x_um,y_um\n0,0\n61,0\n", {"size": 48, "pixel_size": 2.5},
     r"pos.csv line 3: position \(24, 48.4\) \(x_um,y_um = 61,0\) lies outside"),
    ("row,col\n0,1\n2,3\n", {"frames": 3},
     r"pos.csv: 2 positions for 3 frames: frame 2 has no position \(the last is on line 3\)"),
    ("row,col\n0,1\n2,3\n", {"frames": 1}, r"pos.csv line 3: more positions than the 1 "),
    ("row,col\n", {}, r"pos.csv: no positions after the header line 1"),
    ("\n", {}, r"pos.csv: no positions"),
])  # fmt: skip
def test_bad_positions_files_name_the_line(tmp_path, text, options, message):
    path = tmp_path / "pos.csv"
    path.write_text(text)
    with pytest.raises(CalibrationError, match=message) as error:
        read_positions(path, **options)
    assert "\n" not in str(error.value)


def test_bad_scans_name_the_frame(scan):
    system, _, positions, frames, dark, _ = scan
    with pytest.raises(CalibrationError, match="49 frames but the positions list 48: frame 48"):
        calibrate(frames, positions[:-1], system, dark=dark)
    outside = positions.astype(float)
    outside[5] = (3, 47.5)
    with pytest.raises(CalibrationError, match=r"frame 5: position \(3, 47.5\) lies outside"):
        calibrate(frames, outside, system, dark=dark)
    empty = frames.copy()
    empty[7] = dark[0]
    with pytest.raises(CalibrationError, match="frame 7: no spot above the detection threshold"):
        calibrate(empty, positions, system, dark=dark)
    bright = frames.copy()
    bright[9] *= 10.0
    with pytest.raises(CalibrationError, match="frame 9: saturated spot"):
        calibrate(bright, positions, system, dark=dark)
    counts = np.clip(frames * 4000, 0, 65535).astype(np.uint16)  # a 16-bit camera
    counts[11, 30, 40] = 65535
    with pytest.raises(CalibrationError, match=r"frame 11: saturated spot .* >= 65535"):
        calibrate(counts, positions, system)
    with pytest.raises(CalibrationError, match="frame 0 is 60×79 px but system 'tiny' has a "
                       "60×80 sensor"):  # fmt: skip
        calibrate(frames[:, :, :79], positions, system, dark=dark)


def test_calibrate_command_and_every_command_uses_the_system(scan, tiny_model_config, tmp_path,
                                                             capsys):
    system, _, positions, frames, dark, _ = scan
    nominal = system.save(tmp_path / "nominal.json")
    write_tiff(tmp_path / "scan.tif", frames, system, kind="scan")
    write_tiff(tmp_path / "dark.tif", dark, system, kind="dark")
    write_positions(tmp_path / "pos.csv", positions)
    out = tmp_path / "cal"
    assert main(["calibrate", str(tmp_path / "scan.tif"), "--positions",
                 str(tmp_path / "pos.csv"), "--system", str(nominal), "--dark",
                 str(tmp_path / "dark.tif"), "--out", str(out)]) == 0
    assert "calibrated tiny from 49 frames" in capsys.readouterr().out
    for name in ("system.json", "psfs.tif", "psfs.positions.json", "calibration.json",
                 "report.txt", "report.png"):
        assert (out / name).is_file(), name
    assert '"psf_model": "psfs.tif"' in (out / "system.json").read_text()
    assert "lens array: shift" in (out / "report.txt").read_text()
    # the folder moves as a whole: the PSF path is relative to the JSON
    moved = tmp_path / "elsewhere"
    (out).rename(moved)
    calibrated = SystemConfig.load(moved / "system.json")
    assert calibrated.psf_model == str((moved / "psfs.tif").resolve())
    stack = load_measured_psfs(moved / "psfs.tif", positions_path(moved / "psfs.tif"), calibrated)
    operator = CM2Operator.from_system(calibrated, dtype=torch.float64)
    reference = CM2Operator.from_psfs(calibrated, stack, dtype=torch.float64)
    x = torch.rand(48, 48, dtype=torch.float64)
    torch.testing.assert_close(operator.forward(x), reference.forward(x))
    calibrated_json = str(moved / "system.json")

    sim = tmp_path / "sim"
    assert main(["simulate", "--system", calibrated_json, "--object", "beads", "--out",
                 str(sim)]) == 0
    _, recorded, _ = read_tiff(sim / "measurement.tif")
    assert recorded.psf_model == calibrated.psf_model
    assert SystemConfig.load(sim / "system.json") == calibrated
    for method in ("admm", "wiener", "rl"):
        args = ["reconstruct", str(sim / "measurement.tif"), "--method", method,
                "--out", str(tmp_path / f"{method}.tif"), "--quiet"]
        if method != "wiener":
            args += ["--iterations", "3"]
        assert main(args) == 0, method  # system from the TIFF: the calibrated one
    assert main(["reconstruct", str(sim / "measurement.tif"), "--system", calibrated_json,
                 "--method", "admm", "--iterations", "2", "--out",
                 str(tmp_path / "admm2.tif"), "--quiet"]) == 0
    data = tmp_path / "data"
    assert main(["dataset", "--system", calibrated_json, "--frames", "2", "--out",
                 str(data), "--no-progress"]) == 0
    assert SystemConfig.load(data / "system.json") == calibrated
    model = tmp_path / "model.json"
    model.write_text(tiny_model_config.to_json())
    assert main(["train", "--data", str(data), "--out", str(tmp_path / "run"), "--epochs", "1",
                 "--model-config", str(model), "--batch-size", "2", "--patches-per-epoch", "2",
                 "--val-patches", "1", "--device", "cpu", "--no-progress"]) == 0
    # the network trained on the calibrated system reconstructs with it
    assert main(["reconstruct", str(sim / "measurement.tif"), "--weights",
                 str(tmp_path / "run" / "best.safetensors"), "--out",
                 str(tmp_path / "svcode.tif"), "--quiet"]) == 0
    # and refines its periphery with the calibrated operator
    assert main(["reconstruct", str(sim / "measurement.tif"), "--weights",
                 str(tmp_path / "run" / "best.safetensors"), "--refine-periphery", "2", "--out",
                 str(tmp_path / "refined.tif"), "--quiet"]) == 0
    plain, refined = (read_tiff(tmp_path / f"{name}.tif")[0] for name in ("svcode", "refined"))
    centre = periphery_weight(calibrated.sub_view_size) == 0
    np.testing.assert_array_equal(refined[centre], plain[centre])
    assert not np.array_equal(refined, plain)
    bench = tmp_path / "bench"
    assert main(["bench", "--quick", "--system", calibrated_json, "--methods", "deconvolution",
                 "--regimes", "matched", "--out", str(bench)]) == 0
    assert (bench / "regimes.json").is_file()


def test_progress_is_reported_in_order_and_can_stop_the_calibration(scan):
    system, _, positions, frames, dark, _ = scan
    calls: list[tuple[str, float]] = []
    calibrate(frames, positions, system, dark=dark,
              progress=lambda stage, fraction: calls.append((stage, fraction)))
    fractions = [fraction for _, fraction in calls]
    assert fractions == sorted(fractions) and fractions[0] == 0.0 and fractions[-1] == 1.0
    stages = [stage for stage, _ in calls]
    assert f"finding spots: position {len(frames)} of {len(frames)}" in stages
    assert "fitting the PSFs: lens 9 of 9" in stages

    class Stop(Exception):
        pass

    def stop_at_the_psfs(stage: str, fraction: float) -> None:
        if stage.startswith("fitting the PSFs"):
            raise Stop

    with pytest.raises(Stop):
        calibrate(frames, positions, system, dark=dark, progress=stop_at_the_psfs)


def test_report_gives_the_psf_fwhm_in_pixels_and_micrometres(scan, tmp_path):
    """Per field point of the PSF grid, over the lenses; micrometres through the
    system's object pixel (10 µm for the tiny system)."""
    from svcode_core.physics.calibration import psf_fwhm, report_text, save_calibration
    from svcode_core.physics.optics import system_psfs

    system, _, _, frames, _, calibration = scan
    fwhm = psf_fwhm(calibration.psfs)
    grid = system.optics.psf_grid
    assert fwhm.shape == (9, grid * grid) and np.isfinite(fwhm).all()
    # the fitted PSFs are about as wide as the departed instrument's nominal ones
    nominal = np.median(psf_fwhm(system_psfs(system)))
    assert 0.7 * nominal < np.median(fwhm) < 1.5 * nominal
    text = report_text(calibration, system)
    assert "PSF FWHM by field point" in text and "(object pixel 10 um)" in text
    row = next(line for line in text.splitlines() if line.startswith("(+0.00, +0.00)"))
    centre = np.median(fwhm[:, grid * grid // 2])
    assert f"{centre:6.2f}" in row and f"{centre * 10:7.2f}" in row
    files = save_calibration(calibration, tmp_path / "cal", system)
    saved = json.loads(files["calibration"].read_text())
    assert saved["object_pixel_um"] == 10.0
    np.testing.assert_allclose(saved["psf_fwhm_um"], 10 * np.asarray(saved["psf_fwhm_px"]),
                               rtol=1e-3)
    # the spots' move off the nominal optics: its coefficients and its value at h = 1
    assert list(saved["field_shift_px"]) == ["h^1", "h^3"]
    edge = sum(saved["field_shift_px"].values())
    assert f"{edge:+.3f} px at the edge of a lens's field" in text
    unknown = calibration.system.replace(object_pixel_um=None)
    text = report_text(dataclasses.replace(calibration, system=unknown), system)
    assert "pixel size unknown" in text and f"{centre:6.2f}" in text


def test_offsets_are_fitted_beside_a_centroid_shift_the_lenses_share(tiny_system):
    """Noise-free centroid moves: the lens offsets plus a departure ``b_1 f + b_3 |f|² f``
    shared by the lenses, where each outer lens sees only the half of its field towards
    the lattice centre (as on a sensor). The joint fit recovers both to float64 rounding;
    the mean move of each lens, what the offsets were before, is biased (the corner lenses
    by 0.07 px here)."""
    from svcode_core.physics.calibration import FIELD_POWERS, _field_vectors, _fit_offsets

    positions = scan_grid(tiny_system, 9).astype(float)
    field = _field_vectors(positions, tiny_system)  # (N, 9, 2)
    offsets = np.random.default_rng(0).uniform(-0.5, 0.5, (9, 2))
    b = np.array([0.3, -0.2])[: len(FIELD_POWERS)]
    h = np.linalg.norm(field, axis=-1, keepdims=True)
    shift = offsets + sum(c * field * h ** (p - 1) for c, p in zip(b, FIELD_POWERS, strict=True))
    axes = np.asarray(tiny_system.lens_axes)
    use = np.einsum("nlc,lc->nl", field, axes) <= 0  # towards the centre; all for lens 4
    fitted, errors, field_shift = _fit_offsets(shift, use, field)
    np.testing.assert_allclose(fitted, offsets, atol=1e-12)
    np.testing.assert_allclose(field_shift, b, atol=1e-12)
    assert errors.max() < 1e-12
    mean = np.stack([shift[use[:, lens], lens].mean(axis=0) for lens in range(9)])
    assert np.linalg.norm(mean - offsets, axis=1)[[0, 2, 6, 8]].min() > 0.05


def test_aberration_errors_do_not_bias_the_chief_rays(tiny_system, monkeypatch):
    """A departed tiny instrument whose distortion and coma are off by half their nominal
    values, its truth rendered close to its full PSFs: every chief ray within 0.1 px (the
    centre lens, which no field shift biases, is about 0.04 px off from the scan's noise
    and sampling); fitted as a mean per lens, the outer lenses were 0.15-0.3 px off."""
    import svcode_core.physics.calibration as calibration_module

    optics = tiny_system.optics
    departures = Departures(name="aberrations", mla_shift_px=(1.3, -0.7), mla_rotation_deg=0.4,
                            distortion_error_px=0.5 * optics.distortion,
                            coma_error_waves=0.5 * optics.coma, truth_rank_tolerance=1e-4)
    system = with_dark_offset(tiny_system, BLACK_LEVEL)
    positions = scan_grid(system, 7)
    frames, dark = simulate_scan(Simulator(system, departures=departures), positions, seed=1)
    truth = departures.lens_offsets(system)
    calibration = calibrate(frames, positions, system, dark=dark, tolerance=TOLERANCE)
    error = np.linalg.norm(calibration.offsets - truth, axis=1)
    assert error.max() < 0.1, error
    assert calibration.field_shift.sum() > 0.1  # the distortion error is positive
    monkeypatch.setattr(calibration_module, "FIELD_POWERS", ())
    mean = calibrate(frames, positions, system, dark=dark, tolerance=TOLERANCE)
    assert np.linalg.norm(mean.offsets - truth, axis=1).max() > 0.15
