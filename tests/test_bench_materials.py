"""The materials suite's table and adoption rule (bench/materials.py) on hand-made results."""

from __future__ import annotations

import json

import pytest

from bench.materials import cost_rows, format_cost_table, format_table, suite_rows, verdict


def _run(scene, relight, oracle, psnr, steps=100, seed=0):
    return {"scene": scene, "steps": steps, "id": f"{scene}__fast__adaptive__r{seed}",
            "test_curve": [{"step": steps, "wall_s": 1.0, "test_psnr": psnr, "final": True}],
            "relight_eval": {"relight_psnr": relight, "relight_oracle_psnr": oracle, "metallic_mae": 0.5}}


def _rows(table: dict[str, tuple[float, float]]) -> dict:
    return {s: {"relight_psnr": r, "relight_oracle_psnr": o, "gap": o - r} for s, (r, o) in table.items()}


def test_suite_rows_take_the_median_over_seeds_and_the_gap(tmp_path):
    runs = [_run("a", 20.0, 25.0, 30.0, seed=0), _run("a", 22.0, 25.0, 31.0, seed=1), _run("a", 30.0, 25.0, 32.0, seed=2),
            _run("b", 10.0, 24.0, 18.0)]
    (tmp_path / "results.json").write_text(json.dumps({"runs": runs}))
    rows = suite_rows(tmp_path)
    assert rows["a"]["relight_psnr"] == 22.0 and rows["a"]["gap"] == 3.0 and rows["a"]["test_psnr"] == 31.0
    assert rows["b"]["gap"] == 14.0 and rows["b"]["steps"] == 100
    text = format_table(rows)
    assert "mean relight gap 8.50 dB over 2 scenes; worst b (14.00 dB)" in text


def test_verdict_adopts_a_lower_mean_gap_with_no_scene_worse():
    base = _rows({"a": (20.0, 25.0), "b": (10.0, 24.0)})
    adopt, why = verdict(_rows({"a": (19.7, 25.0), "b": (14.0, 24.0)}), base)
    assert adopt, why          # a drops 0.3 dB: within the noise


@pytest.mark.parametrize("cand", [{"a": (19.0, 25.0), "b": (16.0, 24.0)},    # a drops 1 dB though the mean improves
                                  {"a": (20.0, 25.0), "b": (10.0, 24.0)},    # no change: the mean gap must improve
                                  {"a": (30.0, 25.0)}])                       # b not scored
def test_verdict_refuses_a_trade_or_no_gain(cand):
    adopt, why = verdict(_rows(cand), _rows({"a": (20.0, 25.0), "b": (10.0, 24.0)}))
    assert not adopt, why


def test_cost_rows_take_the_median_and_the_geometry_is_the_rest_of_the_gap(tmp_path):
    runs = []
    for seed, (relight, albedo, all_four) in enumerate([(20.0, 1.0, 3.0), (21.0, 2.0, 2.0), (23.0, 6.0, 1.0)]):
        r = _run("a", relight, 25.0, 30.0, seed=seed)
        r["relight_eval"]["relight_cost_db"] = {"albedo": albedo, "roughness": 0.5, "metallic": 0.0, "normal": 1.5,
                                                "materials": 1.5, "all four": all_four, "missed_pixels": 3}
        runs.append(r)
    runs.append(_run("b", 10.0, 24.0, 18.0))            # a run scored before the attribution: no row
    (tmp_path / "results.json").write_text(json.dumps({"runs": runs}))
    costs = cost_rows(tmp_path)
    assert set(costs) == {"a"}
    # geometry per seed: gaps 5, 4, 2 minus all four 3, 2, 1 -> 2, 2, 1; medians of each column
    assert costs["a"]["albedo"] == 2.0 and costs["a"]["all four"] == 2.0 and costs["a"]["geometry"] == 2.0
    assert "| a | 2.00 | 0.50 | 0.00 | 1.50 | 1.50 | 2.00 | 2.00 |" in format_cost_table(costs)
