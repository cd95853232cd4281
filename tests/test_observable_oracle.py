"""``bench.observable_oracle``: the relight oracle with the GT material kept only where the training
light reaches. Hand-worked masks and maps, then a generated torus whose relight truth is the
oracle itself: with the texture only where the training light reaches, the observable oracle is
the oracle (the metric's cap); with texture in the shadow too, it falls below."""

from __future__ import annotations

import json

import numpy as np
import pytest

from bench.observable_oracle import observable_maps, observable_oracle, reached_mask, white_maps
from bench.oracle import oracle_render, oracle_renders
from nepf_core.relight.lights import load_lights
from nepf_core.relight.metrics import FOREGROUND_ALPHA
from tests.datagen import copy_scene

# a novel light on the side opposite the generated scene's training light (3, -2, 4): it shows the
# part of the torus that the training light never reaches
RELIGHT = {"lights": [{"type": "point", "position_world": [-3.0, 2.5, -1.0], "intensity_rgb": [60.0, 60.0, 60.0]},
                      {"type": "point", "position_world": [3.0, -2.0, 4.0], "intensity_rgb": [40.0, 40.0, 40.0]}]}


def test_reached_is_relative_to_the_foreground_q90_summed_over_lights():
    fg = np.ones((1, 1, 10), bool)
    fg[0, 0, 9] = False
    e = np.array([0.0, 0.004, 0.006, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 50.0], np.float32)  # q90 over fg = 1
    white = np.zeros((2, 1, 1, 10, 3), np.float32)
    white[0, 0, 0, :, :] = e[:, None] / 2
    white[1, 0, 0, :, :] = e[:, None] / 2                  # two lights, half each: the sum is e
    got = reached_mask(white, fg, tau=0.005)
    assert got[0, 0].tolist() == [False, False, True] + [True] * 6 + [False]   # the background never


def test_unreached_pixels_take_the_reached_mean_material():
    alb = np.array([[[[0.2, 0.4, 0.6], [0.4, 0.4, 0.4], [0.9, 0.0, 0.1], [0.5, 0.5, 0.5]]]], np.float32)
    gt = {"albedo": alb, "roughness": np.array([[[0.2, 0.6, 0.9, 0.3]]], np.float32),
          "metallic": np.array([[[1.0, 0.0, 1.0, 0.0]]], np.float32)}
    fg = np.array([[[True, True, True, False]]])
    reached = np.array([[[True, True, False, False]]])
    m = observable_maps(gt, reached, fg)
    np.testing.assert_allclose(m["albedo"][0, 0, 2], [0.3, 0.4, 0.5], atol=1e-6)   # mean of the two reached
    np.testing.assert_allclose(m["albedo"][0, 0, [0, 1, 3]], alb[0, 0, [0, 1, 3]])  # reached and background kept
    assert m["roughness"][0, 0, 2] == pytest.approx(0.4) and m["metallic"][0, 0, 2] == pytest.approx(0.5)
    assert gt["roughness"][0, 0, 2] == pytest.approx(0.9)                           # the input is not changed


@pytest.fixture(scope="module")
def torus(tmp_path_factory):
    """A generated glossy torus, its test maps' albedo textured, ``gt/relight`` from the oracle."""
    sc = copy_scene(tmp_path_factory.mktemp("observable"), material="glossy")
    (sc / "gt" / "relight").mkdir()
    (sc / "gt" / "relight" / "lights.json").write_text(json.dumps(RELIGHT))
    return sc


def write_truth(sc, albedo):
    """Replace the test maps' albedo and write the oracle under RELIGHT as the relight truth."""
    gt = dict(np.load(sc / "gt" / "arrays_test.npz"))
    gt["albedo"] = albedo.astype(np.float32)
    np.savez(sc / "gt" / "arrays_test.npz", **gt)
    rgb, alpha = oracle_render(sc, load_lights(sc / "gt" / "relight" / "lights.json"), "gltf")
    np.savez(sc / "gt" / "relight" / "arrays.npz", rgb_linear=rgb, alpha=alpha)


def test_texture_where_no_training_light_reaches_is_what_the_data_cannot_close(torus):
    gt = dict(np.load(torus / "gt" / "arrays_test.npz"))
    fg = gt["alpha"] > FOREGROUND_ALPHA
    (white,), _ = oracle_renders(torus, load_lights(torus / "gt" / "lights.json"), "gltf", True, [white_maps(gt)])
    reached = reached_mask(white, fg)
    assert 0.2 < reached.sum() / fg.sum() < 0.95           # the scene has both kinds of pixel
    rng = np.random.default_rng(0)
    texture = rng.uniform(0.1, 0.9, gt["albedo"].shape).astype(np.float32)
    flat = texture.copy()
    flat[fg & ~reached] = texture[reached].mean(0)          # the texture only where the light reaches
    write_truth(torus, flat)
    r = observable_oracle(torus, "gltf")
    assert r["oracle"] == pytest.approx(100.0) and r["observable"] == pytest.approx(100.0)
    assert r["reached_fraction"] == pytest.approx(reached.sum() / fg.sum())
    write_truth(torus, texture)                              # now the shadow is textured too
    r = observable_oracle(torus, "gltf")
    assert r["oracle"] == pytest.approx(100.0)
    assert r["observable"] < 40.0
