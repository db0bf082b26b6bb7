"""Streaming stacks to TIFF: frame-by-frame equality, resume after a crash, dask workers."""

from __future__ import annotations

import functools
import time

import numpy as np
import pytest
import tifffile
import torch

from svcode_core.io import read_tiff, write_tiff
from svcode_core.methods.exposure import exposure_gain
from svcode_core.methods.svcode import Reconstructor
from svcode_core.run.stream import FrameReader, reconstruct_file

FRAMES = 20


class ConvModel(torch.nn.Module):
    """Small random non-linear stand-in with the SV-CoDe signature; can fail on purpose."""

    def __init__(self, fail_after: int | None = None, failure: type = KeyboardInterrupt):
        super().__init__()
        torch.manual_seed(0)
        self.demix = torch.nn.Conv2d(9, 9, 3, padding=1)
        self.recon = torch.nn.Conv2d(9, 1, 3, padding=1)
        self.fail_after, self.failure = fail_after, failure
        self.calls = 0

    def forward(self, views, origins, sub_view_size):
        if self.fail_after is not None and self.calls >= self.fail_after:
            raise self.failure("simulated crash")
        self.calls += 1
        demixed = torch.sigmoid(self.demix(views))
        return demixed, torch.sigmoid(self.recon(demixed))


def _reconstructor(system, model=None):
    # one batch per frame, so model calls count frames
    return Reconstructor(model or ConvModel(), system, batch_size=64, skip_empty=False)


@pytest.fixture
def stack(tiny_system, tmp_path):
    rng = np.random.default_rng(0)
    frames = rng.random((FRAMES, *tiny_system.sensor_shape), dtype=np.float32)
    write_tiff(tmp_path / "meas.tif", frames, tiny_system, kind="measurement")
    return frames


def _expected(system, frames):
    rec = _reconstructor(system)
    results = [rec(frame, return_views=True) for frame in frames]
    return (np.stack([r.reconstruction for r in results]), np.stack([r.views for r in results]))


def _leftovers(tmp_path):
    return sorted(
        p.name for p in tmp_path.iterdir() if p.name not in {"meas.tif", "out.tif", "views.tif"}
    )


def test_stack_streams_and_matches_frame_by_frame(tiny_system, stack, tmp_path):
    rec = _reconstructor(tiny_system)
    summary = reconstruct_file(
        tmp_path / "meas.tif",
        tmp_path / "out.tif",
        lambda: rec,
        views_path=tmp_path / "views.tif",
        settings={"method": "test"},
        progress=False,
    )
    assert summary.frames == summary.computed == FRAMES
    recon, system, meta = read_tiff(tmp_path / "out.tif")
    views, _, views_meta = read_tiff(tmp_path / "views.tif")
    expected_recon, expected_views = _expected(tiny_system, stack)
    np.testing.assert_array_equal(recon, expected_recon)
    np.testing.assert_array_equal(views, expected_views)
    assert system == tiny_system
    assert meta["kind"] == "reconstruction" and meta["method"] == "test"
    assert views_meta["kind"] == "views"
    # each frame's exposure gain, as float32 stores it, in both outputs' metadata
    gains = np.float32([exposure_gain(frame) for frame in stack]).tolist()
    assert meta["exposure_gains"] == views_meta["exposure_gains"] == gains
    assert _leftovers(tmp_path) == []


def test_a_method_that_does_not_normalise_records_no_gains(tiny_system, stack, tmp_path):
    from svcode_core.methods.baselines.reconstructor import BaselineReconstructor

    reconstruct_file(tmp_path / "meas.tif", tmp_path / "out.tif",
                     lambda: BaselineReconstructor("wiener", tiny_system), progress=False)
    assert "exposure_gains" not in read_tiff(tmp_path / "out.tif")[2]


def test_single_frame_gives_one_image(tiny_system, stack, tmp_path):
    write_tiff(tmp_path / "one.tif", stack[0], tiny_system)
    reconstruct_file(
        tmp_path / "one.tif",
        tmp_path / "out.tif",
        lambda: _reconstructor(tiny_system),
        progress=False,
    )
    recon, _, _ = read_tiff(tmp_path / "out.tif")
    np.testing.assert_array_equal(recon, _expected(tiny_system, stack[:1])[0][0])


def test_interrupted_run_resumes_every_frame_exactly_once(tiny_system, stack, tmp_path):
    args = (tmp_path / "meas.tif", tmp_path / "out.tif")
    crashing = _reconstructor(tiny_system, ConvModel(fail_after=7))  # Ctrl-C after 7 frames
    with pytest.raises(KeyboardInterrupt, match="simulated crash"):
        reconstruct_file(*args, lambda: crashing, views_path=tmp_path / "views.tif", progress=False)
    assert not (tmp_path / "out.tif").exists()
    assert np.load(tmp_path / "out.tif.done.npy").sum() == 7

    model = ConvModel()
    summary = reconstruct_file(
        *args,
        lambda: _reconstructor(tiny_system, model),
        views_path=tmp_path / "views.tif",
        progress=False,
    )
    assert summary.computed == model.calls == FRAMES - 7  # nothing recomputed
    recon, _, _ = read_tiff(tmp_path / "out.tif")
    views, _, _ = read_tiff(tmp_path / "views.tif")
    expected_recon, expected_views = _expected(tiny_system, stack)
    np.testing.assert_array_equal(recon, expected_recon)
    np.testing.assert_array_equal(views, expected_views)
    assert _leftovers(tmp_path) == []


def test_changed_settings_start_afresh(tiny_system, stack, tmp_path):
    args = (tmp_path / "meas.tif", tmp_path / "out.tif")
    crashing = _reconstructor(tiny_system, ConvModel(fail_after=5))
    with pytest.raises(KeyboardInterrupt):
        reconstruct_file(*args, lambda: crashing, settings={"tile": 16}, progress=False)
    model = ConvModel()
    summary = reconstruct_file(
        *args, lambda: _reconstructor(tiny_system, model), settings={"tile": 32}, progress=False
    )
    assert summary.computed == model.calls == FRAMES


def test_system_comes_from_file_or_beside_it(tiny_system, stack, tmp_path):
    tifffile.imwrite(tmp_path / "raw.tif", stack[:5], compression="zlib")  # no metadata
    factory = functools.partial(_reconstructor, tiny_system)
    with pytest.raises(ValueError, match="no system configuration"):
        reconstruct_file(tmp_path / "raw.tif", tmp_path / "out.tif", factory, progress=False)
    tiny_system.save(tmp_path / "system.json")
    with FrameReader(tmp_path / "raw.tif") as reader:  # compressed: read page by page
        assert reader.system == tiny_system and len(reader) == 5
        np.testing.assert_array_equal(reader[3], stack[3])
    reconstruct_file(tmp_path / "raw.tif", tmp_path / "out.tif", factory, progress=False)
    np.testing.assert_array_equal(
        read_tiff(tmp_path / "out.tif")[0], _expected(tiny_system, stack[:5])[0]
    )


def test_wrong_frame_size_fails_before_writing(tiny_system, tmp_path):
    write_tiff(tmp_path / "meas.tif", np.zeros((5, 30, 30), np.float32), tiny_system)
    with pytest.raises(ValueError, match="30×30 pixels but system 'tiny'"):
        reconstruct_file(
            tmp_path / "meas.tif",
            tmp_path / "out.tif",
            lambda: _reconstructor(tiny_system),
            progress=False,
        )
    assert sorted(p.name for p in tmp_path.iterdir()) == ["meas.tif"]


def test_two_dask_workers_match_one_process(tiny_system, stack, tmp_path):
    pytest.importorskip("distributed")
    start = time.perf_counter()
    factory = functools.partial(_reconstructor, tiny_system)
    reconstruct_file(
        tmp_path / "meas.tif",
        tmp_path / "out.tif",
        factory,
        views_path=tmp_path / "views.tif",
        workers=2,
        progress=False,
    )
    recon, _, _ = read_tiff(tmp_path / "out.tif")
    views, _, _ = read_tiff(tmp_path / "views.tif")
    expected_recon, expected_views = _expected(tiny_system, stack)
    np.testing.assert_allclose(recon, expected_recon, atol=1e-6, rtol=0)
    np.testing.assert_allclose(views, expected_views, atol=1e-6, rtol=0)
    print(f"2-worker dask run: {time.perf_counter() - start:.1f} s")


def _sigint_handler() -> str:
    import signal

    return str(signal.getsignal(signal.SIGINT))


def test_local_dask_workers_leave_ctrl_c_to_the_client():
    """Ctrl-C reaches every process of the terminal's group: the local cluster's workers
    ignore it (else each prints its traceback, above all while still importing), and this
    process alone handles it."""
    import signal

    pytest.importorskip("distributed")
    from svcode_core.run.parallel import dask_client

    before = signal.getsignal(signal.SIGINT)  # ignored already when run in the background
    with dask_client(workers=1) as client:
        handlers = client.run(_sigint_handler)
    assert list(handlers.values()) == [str(signal.SIG_IGN)]
    assert signal.getsignal(signal.SIGINT) is before  # this process's handling unchanged


def _cli(argv):
    import argparse

    from svcode_core.cli import reconstruct as command

    parser = argparse.ArgumentParser()
    command.add_parser(parser.add_subparsers())
    args = parser.parse_args(["reconstruct", *map(str, argv)])
    return args.func(args)


def test_cli_reconstructs_a_stack(tiny_system, stack, tmp_path, monkeypatch, capsys):
    from svcode_core.methods.build import MethodSpec

    built = []

    def build(spec):
        built.append(spec)
        return _reconstructor(tiny_system)

    monkeypatch.setattr(MethodSpec, "__call__", build)
    (tmp_path / "model.safetensors").write_bytes(b"stand-in")
    status = _cli(
        [
            tmp_path / "meas.tif",
            "--out",
            tmp_path / "out.tif",
            "--weights",
            tmp_path / "model.safetensors",
            "--tile",
            "16",
            "--stride",
            "8",
            "--precision",  # "auto" would read the stand-in file's metadata
            "fp32",
            "--quiet",
        ]
    )
    assert status == 0 and "reconstructed 20 frame(s)" in capsys.readouterr().out
    assert built[0].system == tiny_system
    assert built[0].options["tile_size"] == 16 and built[0].options["stride"] == 8
    recon, system, meta = read_tiff(tmp_path / "out.tif")
    np.testing.assert_array_equal(recon, _expected(tiny_system, stack)[0])
    assert meta["method"] == "svcode" and meta["tile_size"] == 16


def test_cli_without_weights_says_so(tiny_system, stack, tmp_path):
    with pytest.raises(FileNotFoundError, match="no bundled SV-CoDe model for system 'tiny'"):
        _cli([tmp_path / "meas.tif", "--out", tmp_path / "out.tif"])
    with pytest.raises(FileNotFoundError, match="weights not found"):
        _cli([tmp_path / "meas.tif", "--out", tmp_path / "out.tif", "--weights", tmp_path / "x"])


def test_cli_runs_a_baseline_with_its_options(tiny_system, stack, tmp_path, capsys):
    out = tmp_path / "wiener.tif"
    status = _cli([tmp_path / "meas.tif", "--out", out, "--method", "wiener",
                   "--wiener-balance", "0.05", "--quiet"])
    assert status == 0 and "reconstructed 20 frame(s)" in capsys.readouterr().out
    recon, system, meta = read_tiff(out)
    assert recon.shape == (20, tiny_system.sub_view_size, tiny_system.sub_view_size)
    assert np.isfinite(recon).all() and meta["method"] == "wiener" and meta["balance"] == 0.05
    with pytest.raises(ValueError, match="--tv-weight does not apply to --method wiener"):
        _cli([tmp_path / "meas.tif", "--out", out, "--method", "wiener", "--tv-weight", "1"])
    with pytest.raises(ValueError, match="--rho applies to the model-based baselines"):
        _cli([tmp_path / "meas.tif", "--out", out, "--rho", "1"])


@pytest.mark.parametrize("refine", [0, 3])
def test_frames_side_by_side_match_one_after_another(tiny_system, tiny_model_config, refine):
    """A whole-sub-view SV-CoDe model runs a stack's frames on threads side by side (one
    torch thread each) with the same output as one after another, its periphery
    refinement too, and torch's thread count is restored."""
    from svcode_core.network import SVCoDe
    from svcode_core.run.parallel import local_frames

    rec = Reconstructor(SVCoDe(tiny_model_config), tiny_system, skip_empty=False,
                        refine_periphery=refine)
    assert rec.frames_side_by_side
    frames = np.random.default_rng(1).random((7, *tiny_system.sensor_shape), dtype=np.float32)
    before = torch.get_num_threads()
    side = list(local_frames(lambda: rec, frames, range(7), True, threads=3))
    assert torch.get_num_threads() == before
    alone = list(local_frames(lambda: rec, frames, range(7), True, threads=1))
    assert [index for index, *_ in alone] == list(range(7))
    assert sorted(index for index, *_ in side) == list(range(7))
    by_index = {index: (recon, views) for index, recon, views, _ in side}
    for index, recon, views, _ in alone:
        # only the threads' summation order differs: a few float32 roundings per layer
        tolerance = 64 * np.finfo(np.float32).eps * max(float(np.abs(recon).max()), 1.0)
        np.testing.assert_allclose(by_index[index][0], recon, rtol=0, atol=tolerance)
        np.testing.assert_allclose(by_index[index][1], views, rtol=0, atol=tolerance)


def test_reconstructors_that_do_not_allow_it_run_frames_in_order(tiny_system):
    """A reconstructor that does not allow it (here: tiles smaller than the sub-view) runs
    frames one after another, in order."""
    from svcode_core.run.parallel import local_frames

    rec = _reconstructor(tiny_system)
    assert not rec.frames_side_by_side
    frames = np.zeros((4, *tiny_system.sensor_shape), dtype=np.float32)
    order = [index for index, *_ in local_frames(lambda: rec, frames, [3, 0, 2, 1], False, 2)]
    assert order == [3, 0, 2, 1]


def test_mask_cache_keeps_its_accounts_under_threads():
    """Threads storing and reading masks at once (frames side by side) leave the cache's
    byte count equal to what it holds, within its budget."""
    from concurrent.futures import ThreadPoolExecutor

    from svcode_core.network import MaskCache

    cache = MaskCache(max_bytes=40 * 4096)

    def churn(seed: int) -> None:
        rng = np.random.default_rng(seed)
        for _ in range(400):
            cache.new_call()
            key = int(rng.integers(100))
            if cache.get(key) is None:
                cache.put(key, (torch.zeros(1024),))

    with ThreadPoolExecutor(4) as pool:
        list(pool.map(churn, range(4)))
    held = sum(m.nbytes for masks, _ in cache._entries.values() for m in masks)
    assert cache.info()["bytes"] == held <= cache.max_bytes
    assert cache.info()["hits"] + cache.info()["misses"] == 1600
