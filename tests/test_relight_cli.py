"""``nepf relight`` and ``nepf eval --relight --gt-maps`` end to end on a generated scene, and the
bench oracle checked against the scene maker's own images."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
from PIL import Image

from bench.oracle import oracle_render
from nepf_core.relight.lights import PointLights, load_lights
from nepf_core.relight.metrics import relight_psnr
from tests.datagen import synth_dir

LIGHTS = {"lights": [{"type": "point", "position_world": [3.0, 1.0, 4.0], "intensity_rgb": [60.0, 60.0, 60.0]},
                     {"type": "point", "position_world": [-3.0, -2.0, 2.5], "intensity_rgb": [20.0, 30.0, 40.0],
                      "units": "ignored", "position_normalized": [0, 0, 0]}]}


def nepf(*args, timeout=300):
    return subprocess.run([sys.executable, "-m", "nepf_core.cli", *map(str, args)], capture_output=True, text=True,
                          timeout=timeout)


@pytest.fixture(scope="module")
def scene():
    """The datagen torus (glossy), pixel-centre samples (supersample 1), lit from low down so that
    the near side of the ring casts a shadow on the far side in the test views."""
    return synth_dir(material="glossy", light_position=(4.0, 0.5, 0.8))


@pytest.fixture(scope="module")
def run(scene, tmp_path_factory):
    out = tmp_path_factory.mktemp("relight_run") / "run"
    p = nepf("fit", scene / "dtu", "--out", out, "--config", "tiny", "--iters", "12", "--device", "cpu", "--no-export")
    assert p.returncode == 0, p.stderr[-2000:]
    return out


def test_oracle_reproduces_the_scene_makers_images(scene):
    # the scene maker renders with the paper BSDF and hard shadows (analytic SDF); the oracle
    # shades the GT maps (depth, normals, materials) under the same light with the mesh's shadows:
    # the images agree on the fully covered pixels except along shadow edges (the mesh is the
    # marching-cubes polygonisation of the SDF)
    lights = load_lights(scene / "gt" / "lights.json")
    rgb, alpha = oracle_render(scene, lights, "paper")
    gt = np.load(scene / "gt" / "arrays_test.npz")
    inner = gt["alpha"] == 1.0
    ref = gt["rgb_linear"][inner]
    got = rgb[0][inner]
    close = np.abs(got - ref).max(-1) <= 1e-3 + 1e-3 * ref.max(-1)
    assert inner.sum() > 300 and close.mean() > 0.97, close.mean()
    # cast shadows: lit without the shadow rays, dark with them, and dark in the scene maker's image
    without, _ = oracle_render(scene, lights, "paper", shadows=False)
    cast = (without[0][inner].max(-1) > 0) & (got.max(-1) == 0)
    assert cast.sum() >= 20 and (ref[cast].max(-1) == 0).mean() > 0.95


def test_relight_end_to_end(scene, run, tmp_path):
    lights_path = tmp_path / "lights.json"
    lights_path.write_text(json.dumps(LIGHTS))
    out = tmp_path / "relit"
    p = nepf("relight", run, "--lights", lights_path, "--cameras", scene / "gt" / "dtu_test", "--out", out,
             "--device", "cpu")
    assert p.returncode == 0, p.stderr[-2000:]
    arr = np.load(out / "arrays.npz")
    rgb, alpha = arr["rgb_linear"], arr["alpha"]
    assert rgb.shape == (2, 2, 32, 40, 3) and rgb.dtype == np.float32        # K, V, H, W, 3; <= 64 views
    assert alpha.shape == (2, 32, 40) and alpha.min() >= 0 and alpha.max() <= 1
    assert np.isfinite(rgb).all() and rgb.min() >= 0 and rgb.max() > 0
    assert (rgb[:, alpha == 0] == 0).all()                                    # black where not covered
    for k in range(2):
        files = sorted((out / f"light_{k}").glob("*.png"))
        assert [f.name for f in files] == ["000.png", "001.png"]
        img = np.asarray(Image.open(files[1]))
        assert img.shape == (32, 40, 3) and img.dtype == np.uint8
        want = np.clip(rgb[k, 1], 0, 1)
        want = np.where(want <= 0.0031308, 12.92 * want, 1.055 * want ** (1 / 2.4) - 0.055)
        assert np.abs(img.astype(float) - want * 255).max() <= 0.5 + 1e-3  # sRGB of clip(rgb), 8-bit

    # doubling light 1's intensity doubles its image and leaves light 0's alone
    doubled = json.loads(json.dumps(LIGHTS))
    doubled["lights"][1]["intensity_rgb"] = [40.0, 60.0, 80.0]
    lights_path.write_text(json.dumps(doubled))
    out2 = tmp_path / "relit2"
    p = nepf("relight", run, "--lights", lights_path, "--cameras", scene / "gt" / "dtu_test", "--out", out2,
             "--device", "cpu")
    assert p.returncode == 0, p.stderr[-2000:]
    rgb2 = np.load(out2 / "arrays.npz")["rgb_linear"]
    np.testing.assert_allclose(rgb2[1], 2 * rgb[1], rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(rgb2[0], rgb[0], rtol=1e-6, atol=0)


def test_malformed_lights_file_is_a_clear_error(scene, run, tmp_path):
    bad = tmp_path / "bad_lights.json"
    bad.write_text(json.dumps({"lights": [LIGHTS["lights"][0], {"type": "spot", "position_world": [0, 0, 1],
                                                                  "intensity_rgb": [1, 1, 1]}]}))
    p = nepf("relight", run, "--lights", bad, "--cameras", scene / "gt" / "dtu_test", "--out", tmp_path / "o",
             "--device", "cpu")
    assert p.returncode == 1
    assert "bad_lights.json: light 1: 'type' must be \"point\"" in p.stderr
    assert "Traceback" not in p.stderr and str(tmp_path) not in p.stderr


def test_eval_reports_relight_and_material_scores(scene, run, tmp_path):
    # a relight ground truth for the generated scene: the oracle under two new lights
    lights = PointLights(np.array([l["position_world"] for l in LIGHTS["lights"]], float),
                         np.array([l["intensity_rgb"] for l in LIGHTS["lights"]], float))
    gt_rgb, gt_alpha = oracle_render(scene, lights, "paper")
    relight = tmp_path / "relight"
    relight.mkdir()
    (relight / "lights.json").write_text(json.dumps(lights.to_json()))
    np.savez(relight / "arrays.npz", rgb_linear=gt_rgb.astype(np.float16), alpha=gt_alpha.astype(np.float16))
    out = tmp_path / "eval"
    p = nepf("eval", run, "--test", scene / "gt" / "dtu_test", "--relight", relight, "--gt-maps",
             scene / "gt" / "arrays_test.npz", "--out", out, "--device", "cpu")
    assert p.returncode == 0, p.stderr[-2000:]
    ev = json.loads((out / "eval.json").read_text())
    for k in ("relight_psnr", "albedo_psnr", "roughness_mae", "metallic_mae", "normal_mae_deg"):
        assert ev[k] is not None and np.isfinite(ev[k]), k
    assert 0 <= ev["roughness_mae"] <= 1 and 0 <= ev["metallic_mae"] <= 1 and 0 <= ev["normal_mae_deg"] <= 180
    # the score is that of the relit images it wrote
    relit = np.load(out / "relight" / "arrays.npz")["rgb_linear"]
    want, _ = relight_psnr(relit, gt_rgb.astype(np.float16).astype(np.float32), gt_alpha.astype(np.float16).astype(np.float32))
    assert ev["relight_psnr"] == pytest.approx(want, abs=1e-6)
    assert ev["relight_psnr"] > 5.0                      # a crude fit, but not nothing


def test_bench_child_scores_and_table(scene, run, tmp_path):
    # a copy of the scene with a relight ground truth (the oracle under two lights), as the bench's
    # scenes have: the child's relight_eval holds the same relight PSNR as nepf eval, the oracle
    # scores itself perfectly (100 dB, the metric's cap), and the report prints the section
    import shutil

    from bench.relight_eval import has_relight_truth, relight_metrics
    from bench.relight_report import relight_row, relight_table_lines
    sc = tmp_path / "scene"
    shutil.copytree(scene, sc)
    assert not has_relight_truth(sc)
    lights = PointLights(np.array([l["position_world"] for l in LIGHTS["lights"]], float),
                         np.array([l["intensity_rgb"] for l in LIGHTS["lights"]], float))
    gt_rgb, gt_alpha = oracle_render(sc, lights, "paper")
    (sc / "gt" / "relight").mkdir()
    (sc / "gt" / "relight" / "lights.json").write_text(json.dumps(lights.to_json()))
    np.savez(sc / "gt" / "relight" / "arrays.npz", rgb_linear=gt_rgb, alpha=gt_alpha)
    assert has_relight_truth(sc)
    ev = relight_metrics(run, sc)
    assert ev["relight_oracle_psnr"] == pytest.approx(100.0)
    assert np.isfinite(ev["relight_observable_psnr"]) and ev["relight_observable_psnr"] <= 100.0  # tested in test_observable_oracle
    assert ev["relight_bsdf"] == "paper" and np.isfinite(ev["relight_psnr"]) and ev["relight_psnr"] < 100
    relit = np.load(run / "relight_eval" / "relight" / "arrays.npz")["rgb_linear"]
    assert ev["relight_psnr"] == pytest.approx(relight_psnr(relit, gt_rgb, gt_alpha)[0], abs=1e-9)
    # where the gap lies (bench/relight_attribution.py, tested there): each channel's cost, finite
    from bench.relight_attribution import CHANNELS
    cost = ev["relight_cost_db"]
    assert set(cost) == {*CHANNELS, "missed_pixels"} and all(np.isfinite(v) for v in cost.values())
    row = {"scene": "s", "config": "tiny", "variant": "base",
           **relight_row([{"relight_eval": ev}, {"relight_eval": {**ev, "relight_psnr": ev["relight_psnr"] + 2.0}}])}
    assert row["relight"]["relight_psnr"] == pytest.approx(ev["relight_psnr"] + 1.0)   # median of two
    lines = relight_table_lines([row])
    assert lines[0] == "## Relighting and materials"
    assert f"{100.0 - ev['relight_psnr'] - 1.0:.2f} |" in lines[4]                      # gap to the oracle
