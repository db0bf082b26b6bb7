"""The arithmetic of bench/scaling.py's computed figures (no model is run)."""

from __future__ import annotations

import pytest
import scaling

MiB = 2**20


def _step(method: str, system: str, batch: int, patch: int | None, saved: dict[str, float],
          peak_mib: float, params: int) -> tuple[str, dict]:
    case = scaling._case("train", method, system, batch=batch,
                         **({"patch": patch} if patch else {}))
    return case["id"], {"ok": True, "case": case, "saved_bytes": saved, "peak_mib": peak_mib,
                        "params": params}


def test_simple_helpers():
    assert scaling.adam_state_bytes(1000) == 16_000
    assert scaling.padded_area(96, 16) == 96 * 96
    assert scaling.padded_area(100, 16) == 112 * 112
    assert scaling.computed_train_peak(1000, 10.0, 100.0, 1.5) == 16_000 + 10 + 150
    assert scaling.extrapolated_seconds(2.0, 3.0, 25) == 77.0
    curve = {"patches_seen": [100, 200, 300], "val_recon_psnr": [20.0, 26.5, 31.0]}
    assert scaling.patches_to_reach(curve, 26.0) == 200
    assert scaling.patches_to_reach(curve, 32.0) is None


def test_svcode_prediction_recovers_per_sample_and_per_origin_bytes():
    a, m, params, area = 100.0, 40.0, 1000, 96 * 96
    results = dict([
        _step("svcode", "cm2-v2", 1, 96, {"network": (a + m) * area}, 1.0, params),
        _step("svcode", "cm2-v2", 8, 96, {"network": (8 * a + m) * area}, 50.0, params),
    ])
    got = scaling.svcode_prediction(results, "svcode", 8, 480)
    assert got["per_sample_bytes_per_pixel"] == pytest.approx(a)
    assert got["per_origin_bytes_per_pixel"] == pytest.approx(m)
    assert got["saved_bytes"] == pytest.approx((8 * a + m) * 480 * 480)
    ratio = (50.0 * MiB - 16 * params) / ((8 * a + m) * area)  # the largest measured step
    assert got["transient_ratio"] == pytest.approx(ratio)
    assert got["peak_mib"] == pytest.approx((16 * params + ratio * got["saved_bytes"]) / MiB)
