"""``svcode bench`` in every regime: the departed instruments, the report and its figure."""

import json

import numpy as np

from svcode_bench.regimes import INVERSE_CRIME, REGIMES, SCENES, merge_reports
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
