"""Bad inputs and faults through the command line (issue 19): nothing lost, nothing silently
wrong. Every case calls ``svcode_core.cli.main`` and checks the exit status, the message and
the files left behind."""

from __future__ import annotations

import errno
import json
import os

import numpy as np
import pytest
import tifffile
import torch

from svcode_core import outputs
from svcode_core.cli import main
from svcode_core.io import read_tiff, write_tiff
from svcode_core.methods.baselines import reconstruct_with_baseline
from svcode_core.outputs import OutputLock

BOOKKEEPING = (".partial", ".done.npy", ".resume.json", ".lock")


@pytest.fixture
def scene(tiny_system, tmp_path):
    """A folder with a smooth raw frame in [0, 1] (``meas.tif``) and the system beside it."""
    rows, cols = np.mgrid[: tiny_system.sensor_shape[0], : tiny_system.sensor_shape[1]]
    frame = (0.5 + 0.4 * np.sin(rows / 5.0) * np.cos(cols / 7.0)).astype(np.float32)
    write_tiff(tmp_path / "meas.tif", frame, tiny_system, kind="measurement")
    tiny_system.save(tmp_path / "system.json")
    return tmp_path


@pytest.fixture
def weights(tiny_weights):
    return tiny_weights


def run(capsys, *argv) -> tuple[int, str]:
    """``svcode ARGV`` → (exit status, stderr)."""
    status = main([str(a) for a in argv])
    return status, capsys.readouterr().err


def wiener(capsys, source, out, *more) -> tuple[int, str]:
    return run(capsys, "reconstruct", source, "--out", out, "--method", "wiener", "--quiet", *more)


def names(folder) -> list[str]:
    return sorted(p.name for p in folder.iterdir())


def one_error_line(err: str, *fragments: str) -> None:
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("svcode "), err
    assert "Traceback" not in err
    for fragment in fragments:
        assert fragment in lines[0], (fragment, err)


# ------------------------------------------------------------ 1. output is an input
@pytest.mark.parametrize("spelling", ["same", "dotted", "symlink", "hardlink"])
def test_out_that_is_the_input_is_refused_before_any_work(scene, capsys, spelling):
    source = scene / "meas.tif"
    before = source.read_bytes()
    out = {"same": source, "dotted": scene / "sub" / ".." / "meas.tif",
           "symlink": scene / "link.tif", "hardlink": scene / "hard.tif"}[spelling]
    if spelling == "symlink":
        out.symlink_to(source)
    elif spelling == "hardlink":
        os.link(source, out)
        (scene / "sub").mkdir()
    else:
        (scene / "sub").mkdir()
    status, err = wiener(capsys, source, out)
    assert status == 2
    one_error_line(err, "is the same file as the input", "meas.tif")
    assert source.read_bytes() == before
    assert not [n for n in names(scene) if n.endswith(BOOKKEEPING)]


def test_views_or_bookkeeping_onto_the_input_is_refused(scene, capsys):
    source = scene / "meas.tif"
    status, err = wiener(capsys, source, scene / "out.tif", "--views", source)
    assert status == 2 and "views output" in err and "is the same file as the input" in err
    # the input is named like the output's partial file: the run would write over it
    partial = scene / "out.tif.partial"
    source.rename(partial)
    status, err = wiener(capsys, partial, scene / "out.tif")
    assert status == 2 and "out.tif.partial" in err and "same file as the input" in err
    assert names(scene) == ["out.tif.partial", "system.json"]


def test_out_onto_the_system_json_beside_the_input_is_refused(scene, capsys):
    before = (scene / "system.json").read_bytes()
    status, err = wiener(capsys, scene / "meas.tif", scene / "system.json")
    assert status == 2 and "the system.json beside the input" in err
    assert (scene / "system.json").read_bytes() == before


def test_out_onto_the_weights_or_system_file_is_refused(scene, weights, capsys):
    before = weights.read_bytes()
    status, err = run(capsys, "reconstruct", scene / "meas.tif", "--out", weights,
                      "--weights", weights, "--quiet")
    assert status == 2
    one_error_line(err, "same file as the input", "(--weights)")
    assert weights.read_bytes() == before
    other = scene / "other.json"
    other.write_bytes((scene / "system.json").read_bytes())
    status, err = wiener(capsys, scene / "meas.tif", other, "--system", other)
    assert status == 2 and "(--system)" in err


def test_simulate_onto_its_object_or_system_is_refused(tiny_system, scene, capsys):
    image = np.zeros((30, 30), np.float32)
    image[10:20, 5:15] = 1.0
    tifffile.imwrite(scene / "object.tif", image)
    status, err = run(capsys, "simulate", "--system", scene / "system.json",
                      "--object", scene / "object.tif", "--out", scene)
    assert status == 2
    one_error_line(err, "object.tif (--out) is the same file as the input", "(--object)")
    np.testing.assert_array_equal(tifffile.imread(scene / "object.tif"), image)
    status, err = run(capsys, "simulate", "--system", scene / "system.json", "--out", scene)
    assert status == 2 and "(--system)" in err
    assert names(scene) == ["meas.tif", "object.tif", "system.json"]


# ------------------------------------------------------- 2. outputs checked before work
def _no_work(monkeypatch):
    """Make building any reconstructor fail loudly: the check must come first."""
    from svcode_core.methods.build import MethodSpec

    def refuse(self):
        raise AssertionError("the reconstructor was built before the output check")

    monkeypatch.setattr(MethodSpec, "__call__", refuse)


def test_out_an_existing_directory_is_refused_first(scene, capsys, monkeypatch):
    _no_work(monkeypatch)
    (scene / "results").mkdir()
    status, err = wiener(capsys, scene / "meas.tif", scene / "results")
    assert status == 2
    one_error_line(err, "is an existing directory")
    assert names(scene / "results") == []


def test_views_equal_to_out_is_refused_first(scene, capsys, monkeypatch):
    _no_work(monkeypatch)
    status, err = wiener(capsys, scene / "meas.tif", scene / "out.tif", "--views",
                         scene / "out.tif")
    assert status == 2
    one_error_line(err, "both name", "out.tif")
    assert names(scene) == ["meas.tif", "system.json"]


def _unwritable(folder, monkeypatch):
    """Make ``folder`` refuse new files (by permissions; as root, which ignores them, by
    making file creation there fail as a read-only file system would)."""
    folder.mkdir()
    folder.chmod(0o555)
    if os.geteuid() == 0:
        create = outputs._create

        def read_only(path):
            if path.parent == folder:
                raise OSError(30, "Read-only file system")
            create(path)

        monkeypatch.setattr(outputs, "_create", read_only)


def test_unwritable_locations_are_refused_first(scene, capsys, monkeypatch):
    _no_work(monkeypatch)
    locked = scene / "locked"
    _unwritable(locked, monkeypatch)
    status, err = wiener(capsys, scene / "meas.tif", locked / "out.tif")
    assert status == 2
    one_error_line(err, "cannot write in", "locked")
    status, err = run(capsys, "simulate", "--system", scene / "system.json", "--out",
                      locked / "sim")
    assert status == 2 and "cannot write in" in err
    locked.chmod(0o755)
    assert names(locked) == []


def test_outputs_under_a_file_are_refused(scene, capsys):
    (scene / "notes.txt").write_text("x")
    status, err = wiener(capsys, scene / "meas.tif", scene / "notes.txt" / "out.tif")
    assert status == 2 and "is a file, not a directory" in err
    status, err = run(capsys, "simulate", "--system", scene / "system.json", "--out",
                      scene / "notes.txt")
    assert status == 2
    one_error_line(err, "notes.txt", "is a file, not a directory")
    assert (scene / "notes.txt").read_text() == "x"


# ----------------------------------------------------------------------- 3. input range
def _float_result(scene, capsys):
    assert wiener(capsys, scene / "meas.tif", scene / "float.tif")[0] == 0
    return read_tiff(scene / "float.tif")[0]


@pytest.mark.parametrize("dtype", [np.uint16, np.uint8, np.int16])
def test_integer_frames_follow_the_type_rule(scene, capsys, dtype):
    frame = read_tiff(scene / "meas.tif")[0]
    top = np.iinfo(dtype).max
    tifffile.imwrite(scene / "counts.tif", np.round(frame * top).astype(dtype))
    expected = _float_result(scene, capsys)
    status, err = wiener(capsys, scene / "counts.tif", scene / "out.tif")
    assert status == 0, err
    result = read_tiff(scene / "out.tif")[0]
    # stated error: the rounding of the counts (1/255 for 8 bits) at most, relative to the peak
    assert np.abs(result - expected).max() <= 2.0 / top * np.abs(expected).max() + 1e-6


def test_input_scale_converts_a_12_bit_sensor(scene, capsys):
    frame = read_tiff(scene / "meas.tif")[0]
    tifffile.imwrite(scene / "12bit.tif", np.round(frame * 4095).astype(np.uint16))
    expected = _float_result(scene, capsys)
    status, err = wiener(capsys, scene / "12bit.tif", scene / "plain.tif")
    assert status == 0 and "uses at most 12 bits" not in err  # warning text below
    assert "--input-scale 4095" in err and "warning" in err
    status, err = wiener(capsys, scene / "12bit.tif", scene / "scaled.tif", "--input-scale",
                         "4095")
    assert status == 0 and "warning" not in err
    result, _, meta = read_tiff(scene / "scaled.tif")
    assert meta["input_scale"] == 4095
    assert np.abs(result - expected).max() <= 2e-3 * np.abs(expected).max()


def test_wide_integer_frames_are_refused_with_the_fix(scene, capsys):
    frame = read_tiff(scene / "meas.tif")[0]
    tifffile.imwrite(scene / "int32.tif", np.round(frame * 4095).astype(np.int32))
    status, err = wiener(capsys, scene / "int32.tif", scene / "out.tif")
    assert status == 2
    one_error_line(err, "int32", "--input-scale")
    assert names(scene) == ["int32.tif", "meas.tif", "system.json"]
    assert wiener(capsys, scene / "int32.tif", scene / "out.tif", "--input-scale", "4095")[0] == 0


@pytest.mark.parametrize("value", [1e6, 4095.0, 11.0])
def test_frames_far_above_full_scale_are_refused(scene, tiny_system, capsys, value):
    write_tiff(scene / "bright.tif", np.full(tiny_system.sensor_shape, value, np.float32),
               tiny_system)
    status, err = wiener(capsys, scene / "bright.tif", scene / "out.tif")
    assert status == 2
    one_error_line(err, "far above the sensor's full scale", "--input-scale")
    assert not (scene / "out.tif").exists()


def test_frames_a_little_above_full_scale_run_with_a_warning(scene, tiny_system, capsys):
    write_tiff(scene / "over.tif", np.full(tiny_system.sensor_shape, 4.0, np.float32),
               tiny_system)
    status, err = wiener(capsys, scene / "over.tif", scene / "out.tif")
    assert status == 0 and np.isfinite(read_tiff(scene / "out.tif")[0]).all()
    assert err.count("warning: frames reach more than 2× the sensor's full scale") == 1
    # noiseless simulations exceed the full scale a little where views overlap: no warning
    write_tiff(scene / "over.tif", np.full(tiny_system.sensor_shape, 1.5, np.float32),
               tiny_system)
    status, err = wiener(capsys, scene / "over.tif", scene / "out2.tif")
    assert status == 0 and err == ""


@pytest.mark.parametrize("value", [1e-30, 1e-12])
def test_frames_far_below_one_count_are_refused_and_rescaled(scene, tiny_system, capsys, value):
    frame = read_tiff(scene / "meas.tif")[0]
    write_tiff(scene / "tiny.tif", (frame * value).astype(np.float32), tiny_system)
    status, err = wiener(capsys, scene / "tiny.tif", scene / "out.tif")
    assert status == 2
    one_error_line(err, "below one count of a 32-bit sensor", "--input-scale")
    assert not (scene / "out.tif").exists()
    status, err = wiener(capsys, scene / "tiny.tif", scene / "out.tif", "--input-scale",
                         repr(value))  # fmt: skip
    assert status == 0
    expected = reconstruct_with_baseline("wiener", frame, tiny_system)
    result = read_tiff(scene / "out.tif")[0]
    assert np.abs(result - expected).max() <= 1e-5 * np.abs(expected).max()  # float32 rounding


def test_all_negative_frame_is_refused(scene, tiny_system, capsys):
    write_tiff(scene / "neg.tif", np.full(tiny_system.sensor_shape, -0.2, np.float32),
               tiny_system)
    status, err = wiener(capsys, scene / "neg.tif", scene / "out.tif")
    assert status == 2
    one_error_line(err, "no positive value")


def test_zero_frame_is_valid(scene, tiny_system, capsys):
    write_tiff(scene / "zero.tif", np.zeros(tiny_system.sensor_shape, np.float32), tiny_system)
    assert wiener(capsys, scene / "zero.tif", scene / "out.tif")[0] == 0
    assert not read_tiff(scene / "out.tif")[0].any()


@pytest.mark.filterwarnings("ignore:.*zero-size array")
def test_empty_stack_is_refused(scene, tiny_system, capsys):
    write_tiff(scene / "empty.tif", np.zeros((0, *tiny_system.sensor_shape), np.float32),
               tiny_system)
    status, err = wiener(capsys, scene / "empty.tif", scene / "out.tif")
    assert status == 2
    one_error_line(err, "empty (0 frames)")
    assert not (scene / "out.tif").exists()


def test_bad_frame_deep_in_a_stack_is_refused_before_any_work(scene, tiny_system, capsys):
    stack = np.full((6, *tiny_system.sensor_shape), 0.3, np.float32)
    stack[4, 5, 5] = np.nan
    write_tiff(scene / "stack.tif", stack, tiny_system)
    status, err = wiener(capsys, scene / "stack.tif", scene / "out.tif")
    assert status == 2
    one_error_line(err, "frame 4 holds 1 NaN or Inf")
    assert names(scene) == ["meas.tif", "stack.tif", "system.json"]


def test_the_core_rule_holds_for_the_api(tiny_system):
    from svcode_core.methods.frames import as_frame_stack

    frame = np.linspace(0, 1, np.prod(tiny_system.sensor_shape), dtype=np.float32)
    frame = frame.reshape(tiny_system.sensor_shape)
    expected = reconstruct_with_baseline("wiener", frame, tiny_system)
    counts = np.round(frame * 65535).astype(np.uint16)
    result = reconstruct_with_baseline("wiener", counts, tiny_system)
    assert np.abs(result - expected).max() <= 1e-3 * np.abs(expected).max()
    with pytest.raises(ValueError, match="booleans"):
        as_frame_stack(frame > 0.5)
    with pytest.raises(ValueError, match="real numbers"):
        reconstruct_with_baseline("wiener", frame.astype(np.complex64), tiny_system)
    with pytest.raises(ValueError, match="far above"):
        reconstruct_with_baseline("wiener", frame * 1e4, tiny_system)


@pytest.mark.parametrize("image", [np.full((30, 30), 7, np.uint16), np.ones((1, 1), np.float32)])
def test_simulate_refuses_a_constant_or_one_pixel_object(scene, capsys, image):
    tifffile.imwrite(scene / "flat.tif", image)
    status, err = run(capsys, "simulate", "--system", scene / "system.json",
                      "--object", scene / "flat.tif", "--out", scene / "sim")
    assert status == 2
    one_error_line(err, "zero everywhere", "flat.tif")
    assert not (scene / "sim").exists()


def _system_with_rays(scene, rays, name):
    data = json.loads((scene / "system.json").read_text())
    data["chief_rays"] = rays
    (scene / name).write_text(json.dumps(data))
    return scene / name


def test_simulate_refuses_a_system_with_every_chief_ray_off_the_sensor(scene, capsys):
    system = _system_with_rays(scene, [[3, 3]] * 9, "off.json")  # one point in the padding
    status, err = run(capsys, "simulate", "--system", system, "--out", scene / "sim")
    assert status == 2
    one_error_line(err, "all nine chief rays lie outside")
    assert not (scene / "sim").exists()


def test_simulate_warns_about_a_lens_off_the_sensor_or_shared(scene, tiny_system, capsys):
    rays = [list(ray) for ray in tiny_system.chief_rays]
    rays[0], rays[2] = [3, 3], rays[1]
    system = _system_with_rays(scene, rays, "odd.json")
    status, err = run(capsys, "simulate", "--system", system, "--out", scene / "sim")
    assert status == 0
    assert "warning: system 'tiny': the chief rays of lenses [0] lie outside" in err
    assert "lenses 1 and 2 share the chief ray" in err


# ----------------------------------------------------------------------- 4. concurrency
def test_a_second_run_onto_a_busy_output_is_refused(scene, capsys):
    out = scene / "out.tif"
    with OutputLock(out):  # a first run is writing out.tif
        status, err = wiener(capsys, scene / "meas.tif", out)
        assert status == 2
        one_error_line(err, "out.tif is being written by process", str(os.getpid()))
        assert not out.exists() and not (scene / "out.tif.partial").exists()
    assert wiener(capsys, scene / "meas.tif", out)[0] == 0  # free again
    assert names(scene) == ["meas.tif", "out.tif", "system.json"]


def test_a_shared_views_output_is_locked_too(scene, capsys):
    with OutputLock(scene / "views.tif"):
        status, err = wiener(capsys, scene / "meas.tif", scene / "b.tif", "--views",
                             scene / "views.tif")
    assert status == 2 and "views.tif is being written" in err


def test_a_lock_left_by_a_killed_run_does_not_block(scene, capsys):
    (scene / "out.tif.lock").write_text("process 999999 on elsewhere")  # holder is gone
    assert wiener(capsys, scene / "meas.tif", scene / "out.tif")[0] == 0
    assert names(scene) == ["meas.tif", "out.tif", "system.json"]


def test_concurrent_writers_of_one_tiff_never_mix(tiny_system, tmp_path):
    import threading

    path, errors = tmp_path / "same.tif", []

    def writer(value):
        try:
            for _ in range(5):
                write_tiff(path, np.full((64, 64), value, np.float32), tiny_system,
                           extra={"value": value})
        except Exception as err:  # e.g. a temporary file renamed away by another writer
            errors.append(err)

    threads = [threading.Thread(target=writer, args=(v,)) for v in (1.0, 2.0, 3.0)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert errors == []
    data, _, meta = read_tiff(path)
    assert np.all(data == meta["value"])
    assert names(tmp_path) == ["same.tif"]


# ------------------------------------------------------------------------- 5. leftovers
def _svcode(capsys, scene, *more):
    return run(capsys, "reconstruct", scene / "meas.tif", "--out", scene / "out.tif",
               "--quiet", *more)


@pytest.mark.parametrize("case", ["nan", "bad-weights", "system-mismatch", "tile", "cuda"])
def test_failed_runs_leave_nothing_behind(scene, weights, tiny_system, capsys, case):
    args = ["--weights", weights]
    if case == "nan":
        frame = read_tiff(scene / "meas.tif")[0]
        frame[7, 9] = np.nan
        write_tiff(scene / "meas.tif", frame, tiny_system)
        fragment = "NaN or Inf"
    elif case == "bad-weights":
        (scene / "junk.safetensors").write_bytes(os.urandom(256))
        args, fragment = ["--weights", scene / "junk.safetensors"], "junk.safetensors"
    elif case == "system-mismatch":
        args, fragment = args + ["--system", "cm2-mini"], "expects raw sensor frames"
    elif case == "tile":
        args, fragment = args + ["--tile", "1000"], "1000"
    else:
        args, fragment = args + ["--device", "cuda"], "CUDA is not available"
    status, err = _svcode(capsys, scene, *args)
    assert status == 2
    one_error_line(err, fragment)
    assert names(scene) == sorted(["meas.tif", "system.json", weights.name]
                                  + (["junk.safetensors"] if case == "bad-weights" else []))


def test_a_run_failing_midway_removes_its_partial_files(scene, tiny_system, capsys, monkeypatch):
    from svcode_core.methods.baselines import BaselineReconstructor

    stack = np.full((4, *tiny_system.sensor_shape), 0.4, np.float32)
    write_tiff(scene / "stack.tif", stack, tiny_system)
    original, calls = BaselineReconstructor.reconstruct, []

    def fails_on_third(self, frames, return_views=False):
        calls.append(1)
        if len(calls) == 3:
            raise OSError(28, "No space left on device")
        return original(self, frames, return_views)

    monkeypatch.setattr(BaselineReconstructor, "reconstruct", fails_on_third)
    status, err = wiener(capsys, scene / "stack.tif", scene / "out.tif")
    assert status == 2
    one_error_line(err, "No space left on device")
    assert names(scene) == ["meas.tif", "stack.tif", "system.json"]


def test_an_interrupted_run_keeps_its_files_and_resumes(scene, tiny_system, capsys, monkeypatch):
    from svcode_core.methods.baselines import BaselineReconstructor

    stack = np.stack([np.full(tiny_system.sensor_shape, 0.1 * (i + 1), np.float32)
                      for i in range(4)])  # fmt: skip
    write_tiff(scene / "stack.tif", stack, tiny_system)
    original, calls = BaselineReconstructor.reconstruct, []

    def interrupted_on_third(self, frames, return_views=False):
        calls.append(1)
        if len(calls) == 3:
            raise KeyboardInterrupt
        return original(self, frames, return_views)

    monkeypatch.setattr(BaselineReconstructor, "reconstruct", interrupted_on_third)
    status, err = wiener(capsys, scene / "stack.tif", scene / "out.tif")
    assert status == 130 and "interrupted" in err
    assert {"out.tif.partial", "out.tif.done.npy", "out.tif.resume.json"} <= set(names(scene))
    monkeypatch.setattr(BaselineReconstructor, "reconstruct", original)
    assert main(["reconstruct", str(scene / "stack.tif"), "--out", str(scene / "out.tif"),
                 "--method", "wiener", "--quiet"]) == 0
    assert "(2 resumed from an earlier run)" in capsys.readouterr().out
    assert names(scene) == ["meas.tif", "out.tif", "stack.tif", "system.json"]
    expected = np.stack([reconstruct_with_baseline("wiener", f, tiny_system) for f in stack])
    np.testing.assert_allclose(read_tiff(scene / "out.tif")[0], expected, atol=1e-6)


# ---------------------------------------------------------------- 6. one-line messages
def test_simulate_zero_frames_is_refused_first(scene, capsys):
    status, err = run(capsys, "simulate", "--system", scene / "system.json", "--frames", "0",
                      "--out", scene / "sim")
    assert status == 2
    one_error_line(err, "--frames must be >= 1")
    assert not (scene / "sim").exists()


def test_simulate_onto_an_existing_file_is_one_line(scene, capsys):
    status, err = run(capsys, "simulate", "--system", scene / "system.json", "--out",
                      scene / "meas.tif")
    assert status == 2
    one_error_line(err, "meas.tif", "is a file, not a directory")


def test_cuda_on_a_cpu_build_is_one_line_and_debug_shows_the_traceback(scene, capsys):
    if torch.cuda.is_available():
        pytest.skip("this machine has CUDA")
    status, err = wiener(capsys, scene / "meas.tif", scene / "out.tif", "--device", "cuda")
    assert status == 2
    one_error_line(err, "svcode reconstruct: error: device: CUDA is not available")
    with pytest.raises(ValueError, match="CUDA is not available"):
        main(["reconstruct", str(scene / "meas.tif"), "--out", str(scene / "out.tif"),
              "--method", "wiener", "--device", "cuda", "--debug"])
    with pytest.raises(ValueError, match="CUDA is not available"):
        main(["--debug", "reconstruct", str(scene / "meas.tif"), "--out",
              str(scene / "out.tif"), "--device", "cuda:0"])


def test_tile_options_of_the_network_are_refused_for_a_baseline(scene, capsys):
    status, err = wiener(capsys, scene / "meas.tif", scene / "out.tif", "--tile", "16")
    assert status == 2
    one_error_line(err, "--tile applies to --method svcode, not to --method wiener")
    for option in (["--pool-window", "96"], ["--mask-cache", "0"], ["--no-skip"],
                   ["--batch-size", "2"], ["--refine-periphery", "10"]):
        status, err = wiener(capsys, scene / "meas.tif", scene / "out.tif", *option)
        assert status == 2
        one_error_line(err, f"{option[0]} applies to --method svcode")
    status, err = wiener(capsys, scene / "meas.tif", scene / "out.tif", "--tile", "16",
                         "--stride", "8")
    one_error_line(err, "--tile and --stride apply to --method svcode")


def test_missing_and_unreadable_inputs_are_one_line(scene, capsys):
    status, err = wiener(capsys, scene / "nope.tif", scene / "out.tif")
    assert status == 2
    one_error_line(err, "nope.tif")
    status, err = wiener(capsys, scene, scene / "out.tif")
    assert status == 2
    one_error_line(err, "is a directory, not a TIFF file")
    (scene / "text.tif").write_text("not a tiff")
    status, err = wiener(capsys, scene / "text.tif", scene / "out.tif")
    assert status == 2
    one_error_line(err, "text.tif")


# ------------------------------------------------------- 7. the second battery (issue 47)
def _full_disk(monkeypatch, how, free=100_000):
    """Make the disk look full: ``"free"`` reports ``free`` bytes free, ``"fallocate"``
    lets the space check pass and reserving the blocks fail as a full disk does."""
    if how == "free":
        real = outputs.shutil.disk_usage

        def usage(path):
            total, used, _ = real(path)
            return type(real(path))(total, used, free)

        monkeypatch.setattr(outputs.shutil, "disk_usage", usage)
    else:

        def fallocate(fd, offset, length):
            raise OSError(errno.ENOSPC, "No space left on device")

        monkeypatch.setattr(os, "posix_fallocate", fallocate, raising=False)


@pytest.mark.parametrize("how", ["free", "fallocate"])
@pytest.mark.parametrize("source", ["stack", "frame-with-views"])
def test_reconstruct_onto_a_full_disk_is_refused_before_any_work(
    scene, tiny_system, capsys, monkeypatch, how, source
):
    _no_work(monkeypatch)
    more = []
    if source == "stack":
        write_tiff(scene / "input.tif", np.full((5, *tiny_system.sensor_shape), 0.3, np.float32),
                   tiny_system)  # fmt: skip
        (scene / "meas.tif").unlink()
    else:
        (scene / "meas.tif").rename(scene / "input.tif")
        more = ["--views", scene / "views.tif"]
    _full_disk(monkeypatch, how)
    status, err = wiener(capsys, scene / "input.tif", scene / "out.tif", *more)
    assert status == 2
    one_error_line(err, f"no space left on {scene}: ", " MiB needed, ", " MiB free")
    assert names(scene) == ["input.tif", "system.json"]


def test_reconstruct_reserves_the_space_of_its_outputs(scene, capsys, monkeypatch):
    reserved = []
    monkeypatch.setattr(os, "posix_fallocate",
                        lambda fd, offset, length: reserved.append(length), raising=False)
    assert wiener(capsys, scene / "meas.tif", scene / "out.tif", "--views",
                  scene / "views.tif")[0] == 0  # fmt: skip
    size = scene.joinpath("out.tif").stat().st_size, scene.joinpath("views.tif").stat().st_size
    assert set(size) <= set(reserved)  # the whole files, before a pixel was written


@pytest.mark.parametrize("how", ["free", "midway"])
def test_simulate_onto_a_full_disk_leaves_nothing(scene, capsys, monkeypatch, how):
    from svcode_core import io
    from svcode_core.physics import simulate

    if how == "free":
        _full_disk(monkeypatch, "free")
    else:  # the second TIFF fails as numpy's writer says it, without an errno
        write, calls = io._write_tiff_data, []

        def fails_second(*args, **kwargs):
            calls.append(1)
            if len(calls) == 2:
                raise OSError("1327104 requested and 214720 written")
            return write(*args, **kwargs)

        monkeypatch.setattr(io, "_write_tiff_data", fails_second)
        monkeypatch.setattr(simulate, "free_bytes", lambda path: 214720)
    status, err = run(capsys, "simulate", "--system", scene / "system.json", "--out",
                      scene / "sim")  # fmt: skip
    assert status == 2
    one_error_line(err, f"no space left on {scene}", " MiB needed, ", " MiB free")
    assert names(scene) == ["meas.tif", "system.json"]


def test_a_failed_simulation_keeps_the_earlier_scene_whole(scene, capsys, monkeypatch):
    from svcode_core import io

    args = ["simulate", "--system", scene / "system.json", "--out", scene / "sim"]
    assert run(capsys, *args, "--seed", "1")[0] == 0
    before = {name: (scene / "sim" / name).read_bytes() for name in names(scene / "sim")}
    write, calls = io._write_tiff_data, []

    def fails_third(*args, **kwargs):
        calls.append(1)
        if len(calls) == 3:
            raise OSError(errno.ENOSPC, "No space left on device")
        return write(*args, **kwargs)

    monkeypatch.setattr(io, "_write_tiff_data", fails_third)
    status, err = run(capsys, *args, "--seed", "2")
    assert status == 2 and "no space left on" in err
    assert {name: (scene / "sim" / name).read_bytes() for name in names(scene / "sim")} == before


def test_reconstruct_refuses_a_system_with_every_chief_ray_off_the_sensor(scene, capsys,
                                                                          monkeypatch):
    _no_work(monkeypatch)
    system = _system_with_rays(scene, [[3, 3]] * 9, "off.json")
    status, err = wiener(capsys, scene / "meas.tif", scene / "out.tif", "--system", system)
    assert status == 2
    one_error_line(err, "all nine chief rays lie outside")
    assert names(scene) == ["meas.tif", "off.json", "system.json"]


def test_bench_refuses_zero_threads(tmp_path, capsys):
    status, err = run(capsys, "bench", "--threads", "0", "--out", tmp_path / "bench")
    assert status == 2
    one_error_line(err, "--threads must be >= 1 (torch CPU threads), got 0")
    assert not (tmp_path / "bench").exists()


@pytest.mark.parametrize("option, fragment", [
    (["--method", "admm", "--iterations", "-1"], "--iterations must be >= 1, got -1"),
    (["--method", "rl", "--iterations", "0"], "--iterations must be >= 1, got 0"),
    (["--method", "admm", "--tv-weight", "nan"], "--tv-weight must be a finite number >= 0"),
    (["--method", "admm", "--cg-iterations", "0"], "--cg-iterations must be >= 1"),
    (["--method", "admm", "--rho", "-1"], "--rho must be a finite number > 0, got -1"),
    (["--method", "admm", "--tolerance", "nan"], "--tolerance must be a finite number >= 0"),
    (["--method", "wiener", "--wiener-balance", "-1"], "--wiener-balance must be a finite"),
    (["--method", "wiener", "--rank", "0"], "--rank must be >= 1, got 0"),
    (["--mask-cache", "-5"], "--mask-cache must be >= 0 (MiB; 0 recomputes the masks), got -5"),
    (["--tile", "-3"], "--tile must be >= 1 (pixels), got -3"),
    (["--stride", "0"], "--stride must be >= 1 (pixels), got 0"),
    (["--batch-size", "0"], "--batch-size must be >= 1 (tiles), got 0"),
    (["--pool-window", "-1"], "--pool-window must be >= 0 (pixels), got -1"),
    (["--refine-periphery", "-2"], "--refine-periphery must be >= 0 (iterations), got -2"),
    (["--method", "admm", "--weights", "tiny.safetensors"],
     "--weights does not apply to --method admm"),
])  # fmt: skip
def test_reconstruct_options_are_checked_before_any_work(scene, weights, capsys, monkeypatch,
                                                         option, fragment):
    _no_work(monkeypatch)
    option = [str(weights) if o == "tiny.safetensors" else o for o in option]
    args = [] if "--method" in option or "--weights" in option else ["--weights", weights]
    status, err = _svcode(capsys, scene, *args, *option)
    assert status == 2
    one_error_line(err, fragment)
    assert "mask_cache" not in err and " balance must" not in err
    assert names(scene) == sorted(["meas.tif", "system.json", weights.name])


def test_reconstruct_options_are_checked_before_the_registration(scene, capsys, monkeypatch):
    from svcode_core.cli import reconstruct

    def refuse(*args):
        raise AssertionError("registered before the options were checked")

    monkeypatch.setattr(reconstruct, "_register", refuse)
    status, err = wiener(capsys, scene / "meas.tif", scene / "out.tif", "--register",
                         "--wiener-balance", "-1")  # fmt: skip
    assert status == 2 and "--wiener-balance must be" in err


def test_demo_onto_an_existing_file_is_refused_before_any_work(scene, capsys, monkeypatch):
    from svcode_core.physics import simulate

    def refuse(*args, **kwargs):
        raise AssertionError("simulated before the output check")

    monkeypatch.setattr(simulate.Simulator, "__init__", refuse)
    (scene / "notes.txt").write_text("x")
    status, err = run(capsys, "demo", "--out", scene / "notes.txt")
    assert status == 2
    one_error_line(err, "notes.txt", "is a file, not a directory")
    assert (scene / "notes.txt").read_text() == "x"


def test_a_terminated_run_releases_its_lock_and_resumes(scene, tiny_system, capsys,
                                                        monkeypatch):
    import signal

    from svcode_core.methods.baselines import BaselineReconstructor

    stack = np.stack([np.full(tiny_system.sensor_shape, 0.1 * (i + 1), np.float32)
                      for i in range(4)])  # fmt: skip
    write_tiff(scene / "stack.tif", stack, tiny_system)
    original, calls = BaselineReconstructor.reconstruct, []

    def killed_on_third(self, frames, return_views=False):
        calls.append(1)
        if len(calls) == 3:
            os.kill(os.getpid(), signal.SIGTERM)
        return original(self, frames, return_views)

    monkeypatch.setattr(BaselineReconstructor, "reconstruct", killed_on_third)
    before = signal.getsignal(signal.SIGTERM)
    status, err = wiener(capsys, scene / "stack.tif", scene / "out.tif")
    assert status == 143
    one_error_line(err, "svcode reconstruct: terminated")
    assert signal.getsignal(signal.SIGTERM) == before
    assert not (scene / "out.tif.lock").exists()
    assert {"out.tif.partial", "out.tif.done.npy", "out.tif.resume.json"} <= set(names(scene))
    monkeypatch.setattr(BaselineReconstructor, "reconstruct", original)
    assert wiener(capsys, scene / "stack.tif", scene / "out.tif")[0] == 0
    assert names(scene) == ["meas.tif", "out.tif", "stack.tif", "system.json"]


@pytest.mark.parametrize("channels", [3, 4])
def test_simulate_says_a_colour_object_is_taken_as_grey(scene, capsys, channels):
    image = np.zeros((30, 30, channels), np.uint8)
    image[10:20, 5:15] = 200
    tifffile.imwrite(scene / "colour.tif", image, photometric="rgb")
    status, err = run(capsys, "simulate", "--system", scene / "system.json",
                      "--object", scene / "colour.tif", "--out", scene / "sim")
    assert status == 0
    assert err.count("\n") == 1 and "warning: --object colour.tif is a colour image" in err
    assert "from its luminance" in err


def test_dataset_onto_a_full_disk_is_refused_before_any_work(scene, capsys, monkeypatch):
    _full_disk(monkeypatch, "free")
    status, err = run(capsys, "dataset", "--system", scene / "system.json", "--frames", "4",
                      "--out", scene / "data", "--no-progress")  # fmt: skip
    assert status == 2
    one_error_line(err, f"no space left on {scene}: ", " MiB needed, ")
    assert names(scene) == ["meas.tif", "system.json"]
