"""``bench.relight_attribution``: the oracle with one recovered channel at a time, on a generated
glossy scene whose relight truth is the oracle itself (so every row that keeps the GT's channels
is exact, and a wrong channel shows only in the rows that take it)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from bench.oracle import oracle_render
from bench.relight_attribution import CHANNELS, attribution
from nepf_core.relight.lights import load_lights
from tests.datagen import copy_scene

LIGHTS = {"lights": [{"type": "point", "position_world": [3.0, 1.0, 4.0], "intensity_rgb": [60.0, 60.0, 60.0]}]}


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """A glossy torus with ``gt/relight`` written from the oracle (GT maps, GT-mesh shadows)."""
    sc = copy_scene(tmp_path_factory.mktemp("attribution"), material="glossy")
    relight = sc / "gt" / "relight"
    relight.mkdir()
    (relight / "lights.json").write_text(json.dumps(LIGHTS))
    rgb, alpha = oracle_render(sc, load_lights(relight / "lights.json"), "gltf")
    np.savez(relight / "arrays.npz", rgb_linear=rgb, alpha=alpha)
    return sc


def renders_from_gt(scene) -> dict:
    """The GT maps in the layout of a run's ``relight_eval/renders/arrays.npz``."""
    gt = np.load(scene / "gt" / "arrays_test.npz")
    return {"albedo": gt["albedo"], "roughness": gt["roughness"][..., None], "metallic": gt["metallic"][..., None],
            "normal": gt["normal_world"], "alpha": gt["alpha"][..., None].astype(np.float32)}


def test_the_ground_truth_as_the_run_costs_nothing(scene):
    rows = attribution(scene, renders_from_gt(scene), "gltf")
    assert rows.pop("missed_pixels") == 0
    assert rows["oracle"] >= 60                       # the truth is the oracle's own image
    assert set(rows) == {"oracle", *CHANNELS}
    assert all(v == rows["oracle"] for v in rows.values()), rows


def test_a_wrong_channel_shows_only_in_the_rows_that_take_it(scene):
    r = renders_from_gt(scene)
    gt_rough = r["roughness"].copy()
    r["roughness"] = np.clip(1.0 - gt_rough, 0.05, 1.0)     # broad where sharp, and the reverse
    fg = r["alpha"][..., 0] > 0.5
    v, i, j = np.argwhere(fg)[0]
    r["alpha"][v, i, j, 0] = 0.0                            # one pixel the run missed
    rows = attribution(scene, r, "gltf")
    assert rows.pop("missed_pixels") == 1
    for row, keys in CHANNELS.items():
        if "roughness" in keys:
            assert rows[row] < rows["oracle"] - 3.0, (row, rows)
        else:
            assert rows[row] == rows["oracle"], (row, rows)
