"""bench.metal_split: the metallic error by true kind, by the light that reaches a pixel, by albedo."""

from __future__ import annotations

import json

import numpy as np
import pytest

from bench.metal_split import DARK, main, metal_split


def _truth() -> dict:
    """One 2x4 view, two lights. Row 0: metal; row 1: dielectric. Columns: key-lit, fill-lit,
    dark, outside the foreground (lit by the key, must not count)."""
    per_light = np.zeros((1, 2, 2, 4, 3), np.float32)
    per_light[0, 0, :, 0] = 0.5          # key on column 0
    per_light[0, 1, :, 0] = 0.1          # a weaker fill there too: still key-dominant
    per_light[0, 1, :, 1] = 0.3          # fill on column 1
    per_light[0, 0, :, 1] = DARK / 2     # the key barely reaches it
    per_light[0, 0, :, 3] = 0.9          # outside the mask
    alpha = np.ones((1, 2, 4), np.float32)
    alpha[0, :, 3] = 0.0
    metallic = np.zeros((1, 2, 4), np.float32)
    metallic[0, 0] = 1.0
    albedo = np.full((1, 2, 4, 3), 0.8, np.float32)
    albedo[0, 1, 2] = 0.05               # the dark dielectric is the dark, unlit one
    return {"alpha": alpha, "metallic": metallic, "albedo": albedo, "rgb_linear_per_light": per_light}


def test_hand_worked_split():
    pred = np.array([[[0.9, 0.2, 0.6, 0.0],      # metal: key right, fill wrong, dark right
                      [0.1, 0.0, 0.8, 1.0]]], np.float32)   # dielectric: key, fill right, dark wrong
    res = metal_split(pred, _truth())
    metal, diel = res["metal"], res["dielectric"]
    assert metal["key"] == {"pixels": 1, "called_metal": 1.0, "mae": pytest.approx(0.1)}
    assert metal["fill"] == {"pixels": 1, "called_metal": 0.0, "mae": pytest.approx(0.8)}
    assert metal["dark"] == {"pixels": 1, "called_metal": 1.0, "mae": pytest.approx(0.4)}
    assert "dark albedo" not in metal
    assert diel["key"] == {"pixels": 1, "called_metal": 0.0, "mae": pytest.approx(0.1)}
    assert diel["fill"]["mae"] == 0.0
    assert diel["dark"] == {"pixels": 1, "called_metal": 1.0, "mae": pytest.approx(0.8)}
    assert diel["dark albedo"] == diel["dark"]


def test_groups_partition_the_lit_and_dark_foreground():
    rng = np.random.default_rng(3)
    gt = {"alpha": (rng.random((2, 6, 6)) > 0.3).astype(np.float32),
          "metallic": (rng.random((2, 6, 6)) > 0.5).astype(np.float32),
          "albedo": rng.random((2, 6, 6, 3)).astype(np.float32),
          "rgb_linear_per_light": (rng.random((2, 2, 6, 6, 3)) * 0.05).astype(np.float32)}
    res = metal_split(rng.random((2, 6, 6, 1)), gt)
    fg = int((gt["alpha"] > 0.5).sum())
    counted = sum(r["pixels"] for rows in res.values() for name, r in rows.items() if name != "dark albedo")
    assert counted == fg


def test_cli_reads_a_run_and_a_scene(tmp_path, capsys):
    gt = _truth()
    (tmp_path / "run" / "relight_eval" / "renders").mkdir(parents=True)
    (tmp_path / "scene" / "gt").mkdir(parents=True)
    pred = np.zeros((1, 2, 4, 1), np.float32)
    np.savez(tmp_path / "run" / "relight_eval" / "renders" / "arrays.npz", metallic=pred)
    np.savez(tmp_path / "scene" / "gt" / "arrays_test.npz", **gt)
    main([str(tmp_path / "run"), str(tmp_path / "scene"), "--json"])
    res = json.loads(capsys.readouterr().out)
    assert res["metal"]["key"]["called_metal"] == 0.0 and res["metal"]["key"]["mae"] == 1.0
    with pytest.raises(SystemExit, match="arrays.npz is missing"):
        main([str(tmp_path / "scene"), str(tmp_path / "scene")])
    del gt["rgb_linear_per_light"]
    np.savez(tmp_path / "scene" / "gt" / "arrays_test.npz", **gt)
    with pytest.raises(SystemExit, match="has no rgb_linear_per_light"):
        main([str(tmp_path / "run"), str(tmp_path / "scene")])
