"""``svcode bench`` in every regime: the departed instruments, the report and its figure."""

import json
from dataclasses import replace

import numpy as np
import pytest
import torch

from svcode_bench import regimes
from svcode_bench.regimes import INVERSE_CRIME, REGIMES, SCENES, Row, Scene, merge_reports
from svcode_core.cli import main
from svcode_core.phantoms import HELD_OUT_IMAGES


def test_scenes_include_every_held_out_image():
    kinds = {name: kind for name, kind, _ in SCENES}
    for image in HELD_OUT_IMAGES:
        assert kinds[image.removesuffix(".png")] == "held-out"


def test_quick_bench_runs_every_regime(tiny_system, tmp_path, capsys):
    system_json = tiny_system.save(tmp_path / "tiny.json")
    out = tmp_path / "results"
    assert main(["bench", "--quick", "--system", str(system_json), "--methods", "admm",
                 "wiener", "rl", "--out", str(out)]) == 0
    report = json.loads((out / "regimes.json").read_text())
    assert report["regimes"] == list(REGIMES)
    assert report["departures"]["matched"] is None
    assert report["departures"]["realistic"]["photons"] == 1000.0
    for regime in REGIMES:
        rows = [r for r in report["rows"] if r["regime"] == regime]
        assert {r["method"] for r in rows} == {"LSV-ADMM", "Wiener", "Richardson-Lucy"}
        assert all(np.isfinite(r["psnr"]) and r["seconds"] > 0 for r in rows)
    text = (out / "regimes.md").read_text()
    assert f"## matched ({INVERSE_CRIME})" in text and "## PSNR (dB) per regime" in text
    assert "`photons` = 200.0" in text  # the low-light departures are listed
    assert (out / "regimes.png").stat().st_size > 0
    # rerunning one regime with --merge keeps the other regimes' rows
    assert main(["bench", "--quick", "--system", str(system_json), "--methods", "deconvolution",
                 "--regimes", "background", "--merge", "--out", str(out)]) == 0
    merged = json.loads((out / "regimes.json").read_text())
    assert len(merged["rows"]) == len(report["rows"])
    assert merged["regimes"] == list(REGIMES)
    assert "[realistic]" in capsys.readouterr().out
    # LSV-ADMM at the system's K: only when asked for, merged beside the K = 3 rows
    assert main(["bench", "--quick", "--system", str(system_json), "--methods",
                 "admm-system-k", "--regimes", "realistic", "--merge", "--out", str(out)]) == 0
    merged = json.loads((out / "regimes.json").read_text())
    [row] = [r for r in merged["rows"] if r["method"] == "LSV-ADMM at the system's K"]
    assert row["regime"] == "realistic" and row["settings"]["iterations"] == 200
    assert row["settings"]["rank"] == report["simulator_rank"] and np.isfinite(row["psnr"])
    assert row["settings"]["tv_weight"] != "auto"  # the fixed λ, not the default's
    assert len(merged["rows"]) == len(report["rows"]) + 1
    # one --method name of a family keeps only its own rows
    assert main(["bench", "--quick", "--system", str(system_json), "--methods", "wiener",
                 "--regimes", "matched", "--out", str(tmp_path / "wiener")]) == 0
    alone = json.loads((tmp_path / "wiener" / "regimes.json").read_text())
    assert {r["method"] for r in alone["rows"]} == {"Wiener"}


def test_merge_keys_rows_by_regime_and_method():
    base = {"system": "tiny", "scenes": ["a"], "quick": True, "simulator_rank": 3,
            "total_seconds": 1.0, "note": None}  # fmt: skip
    earlier = {**base, "regimes": ["matched", "model"], "rows": [
        {"regime": "matched", "method": "Wiener", "psnr": 1.0},
        {"regime": "model", "method": "Wiener", "psnr": 2.0}]}  # fmt: skip
    now = {**base, "regimes": ["model"], "rows": [{"regime": "model", "method": "Wiener",
                                                   "psnr": 3.0}]}  # fmt: skip
    merged = merge_reports(earlier, now)
    assert [(r["regime"], r["psnr"]) for r in merged["rows"]] == [("matched", 1.0), ("model", 3.0)]


def test_merge_reads_the_equal_time_row_out_again_when_its_reference_runs_anew():
    """Rerunning SV-CoDe alone (``--methods svcode --merge``) must not leave LSV-ADMM at
    the old model's seconds: the row is read out of its trace at the new ones, and left
    out, with a note, when the earlier report kept no trace."""
    steps = [(float(n), dict.fromkeys(regimes.METRICS, 20.0 + n)) for n in (1, 2, 3, 4)]
    admm = Row("LSV-ADMM", "K=3, 10 it", {"rank": 3, "tv_weight": 1e-3}, setup_seconds=5.0)
    scores = dict.fromkeys(regimes.METRICS, 30.0)
    old = Row("SV-CoDe", "planned", {}, per_scene={"a": {**scores, "seconds": 1.5}})
    base = {"system": "tiny", "scenes": ["a"], "quick": False, "simulator_rank": 3,
            "total_seconds": 1.0, "note": None, "regimes": ["matched"]}  # fmt: skip
    equal = regimes.equal_time_row(admm, {"a": steps}, old).summary()
    earlier = {**base, "rows": [old.summary(), json.loads(json.dumps(equal))]}
    new = Row("SV-CoDe", "planned", {}, per_scene={"a": {**scores, "seconds": 3.2}})
    merged = merge_reports(earlier, {**base, "rows": [new.summary()]})
    again = [r for r in merged["rows"] if r["method"] == "LSV-ADMM"]
    assert equal["psnr"] == 21.0 and len(again) == 1
    assert again[0]["psnr"] == 23.0 and again[0]["per_scene"]["a"]["iterations"] == 3
    assert again[0]["knob"] == "K=3, at SV-CoDe's time (3 it)"
    assert again[0]["setup_seconds"] == 5.0 and merged["note"] is None
    del earlier["rows"][1]["settings"]["trace"]
    merged = merge_reports(earlier, {**base, "rows": [new.summary()]})
    assert [r["method"] for r in merged["rows"]] == ["SV-CoDe"]
    assert "left out" in merged["note"]


def test_lsv_admm_at_sv_codes_time_is_read_from_its_own_trace(tiny_system):
    """The equal-time row takes, frame by frame, the last iteration done within the
    reference's seconds: its scores are the traced ones, which are the rows' own at the
    read-out iterations."""
    from svcode_core.phantoms import make_object
    from svcode_core.physics.cm2 import CM2Operator

    tiny_op = CM2Operator.from_system(tiny_system)
    scenes = []
    for index, kind in enumerate(("cells", "vessels")):
        truth = make_object(kind, tiny_op.system.sub_view_size, index)
        scenes.append(Scene(kind, truth, tiny_op.measure(torch.from_numpy(truth)).numpy()))
    trace: dict = {}
    rows = regimes.admm_rows(tiny_op, scenes, (3, 6), "K=3", 0.5, trace=trace)
    assert [len(trace[s.name]) for s in scenes] == [6, 6]
    for row, n in zip(rows, (3, 6), strict=True):
        for scene in scenes:
            seconds, quality = trace[scene.name][n - 1]
            assert row.per_scene[scene.name]["psnr"] == quality["psnr"]
            assert row.per_scene[scene.name]["seconds"] == seconds
    times = {name: [seconds for seconds, _ in steps] for name, steps in trace.items()}
    assert all(np.all(np.diff(t) > 0) for t in times.values())
    reference = Row("SV-CoDe", "planned", {}, per_scene={
        "cells": {"seconds": (times["cells"][3] + times["cells"][4]) / 2},  # within 4
        "vessels": {"seconds": times["vessels"][0] / 2}})  # not even one: one all the same
    equal = regimes.equal_time_row(rows[0], trace, reference)
    assert [equal.per_scene[n]["iterations"] for n in ("cells", "vessels")] == [4, 1]
    assert equal.per_scene["cells"]["psnr"] == trace["cells"][3][1]["psnr"]
    assert equal.knob == f"K={tiny_op.rank}, at SV-CoDe's time (1–4 it)"
    assert equal.setup_seconds == rows[0].setup_seconds and equal.settings["iterations"] == [1, 4]
    assert np.isfinite(equal.summary()["psnr"])


def test_paper_scale_plan_runs_its_rows(tiny_system, tiny_model_config, tmp_path, monkeypatch):
    """The paper-scale plan (here on the tiny system, with one scene): LSV-ADMM at 10
    iterations and at SV-CoDe's time, Wiener, SV-CoDe's planned tiling, in its two regimes."""
    from svcode_core.methods.model_file import save_model
    from svcode_core.network import SVCoDe

    weights = save_model(tmp_path / "m.safetensors", SVCoDe(tiny_model_config), tiny_system)
    plan = replace(regimes.PAPER, scenes=("cells",))
    monkeypatch.setattr(regimes, "plan_for", lambda system, quick=False: plan)
    report = regimes.run_benchmark(tiny_system, weights=weights, progress=lambda line: None)
    assert report["plan"] == "paper-scale" and report["regimes"] == ["matched", "realistic"]
    for regime in report["regimes"]:
        knobs = [(r["method"], r["knob"]) for r in report["rows"] if r["regime"] == regime]
        assert knobs[0] == ("LSV-ADMM", "K=3, 10 it") and knobs[1][0] == "Wiener"
        assert knobs[2][0] == "SV-CoDe" and "refine" not in knobs[2][1]
        assert knobs[3][0] == "LSV-ADMM" and knobs[3][1].startswith("K=3, at SV-CoDe's time")
        assert len(knobs) == 4


def test_bench_never_writes_over_a_report_on_another_system(tiny_system, tmp_path, capsys):
    out = tmp_path / "results"
    out.mkdir()
    (out / "regimes.json").write_text(json.dumps({"system": "cm2-v2", "rows": []}))
    system_json = tiny_system.save(tmp_path / "tiny.json")
    assert main(["bench", "--quick", "--system", str(system_json), "--methods", "wiener",
                 "--out", str(out)]) == 2
    assert "holds a report on system 'cm2-v2'" in capsys.readouterr().err


def test_bench_adds_the_ring_gap_and_the_exposure_sweeps(tiny_system, tmp_path, capsys):
    """``--ring-gap`` and ``--exposure`` run the checkout's scripts for the methods and
    regimes asked for, into the same folder; LSV-ADMM is scale-equivariant, so its two
    exposure points agree to float32 rounding."""
    system_json = tiny_system.save(tmp_path / "tiny.json")
    out = tmp_path / "results"
    assert main(["bench", "--quick", "--system", str(system_json), "--methods", "admm",
                 "--regimes", "realistic", "--ring-gap", "--exposure", "--out", str(out)]) == 0
    gap = json.loads((out / "ring_gap.json").read_text())
    assert gap["system"] == "tiny" and {r["regime"] for r in gap["rows"]} == {"realistic"}
    assert all(r["method"].startswith("LSV-ADMM") for r in gap["rows"])
    for row in gap["rows"]:  # the strips' gap is the difference of its two recorded ends
        ends = row["strips_content_centre"] - row["strips_content_strips"]
        assert ends == pytest.approx(row["same_gap_column_strips"], abs=1e-9)
    sweep = json.loads((out / "exposure.json").read_text())
    scales = {r["scale"]: r["psnr"] for r in sweep["rows"] if r["sweep"] == "exposure"}
    assert set(scales) == {1.0, 0.05} and abs(scales[1.0] - scales[0.05]) < 0.01
    assert (out / "ring_gap.md").is_file() and (out / "exposure.md").is_file()


def test_ablations_of_one_network_are_told_apart_by_file(tiny_system, tiny_model_config,
                                                         tmp_path):
    from svcode_core.methods.model_file import save_model
    from svcode_core.network import SVCoDe

    system_json = tiny_system.save(tmp_path / "tiny.json")
    paths = []
    for name in ("a", "b", "c"):
        config = tiny_model_config.replace(padding="reflect" if name == "c" else "zeros")
        (tmp_path / name).mkdir()
        paths.append(save_model(tmp_path / name / "best.safetensors", SVCoDe(config),
                                tiny_system))
    out = tmp_path / "results"
    assert main(["bench", "--quick", "--system", str(system_json), "--methods", "--ablations",
                 *map(str, paths), "--regimes", "matched", "--out", str(out)]) == 0
    report = json.loads((out / "regimes.json").read_text())
    assert [r["method"] for r in report["rows"]] == [
        "SV-CoDe (a/best.safetensors)", "SV-CoDe (b/best.safetensors)",
        "SV-CoDe (mirrored padding)"]
