"""The held-out split (issue 26): the rule and its bounds, ``nepf fit --holdout-every`` end to
end (test records in metrics.jsonl, the split in summary.json and report.json), the default
rule with and without ``--eval-test``, the held-out SSIM, and the progress bar's one ETA."""

from __future__ import annotations

import json

import numpy as np
import pytest

from nepf_core.cli import main as nepf_main
from nepf_core.cli_progress import bar_position, format_duration, progress_text
from nepf_core.data.split import (check_holdout_every, default_holdout_every, eval_stride_for, holdout_indices,
                                  holdout_limits, split_info)
from nepf_core.train.evaluation import mean_ssim
from nepf_core.train.schedule import run_eta
from service_fixtures import make_dtu_dir


# ------------------------------------------------------------------------------ the rule
def test_holdout_indices_are_every_kth_view_from_the_first():
    train, test = holdout_indices(17, 8)
    assert test.tolist() == [0, 8, 16]
    assert train.tolist() == [1, 2, 3, 4, 5, 6, 7, 9, 10, 11, 12, 13, 14, 15]
    train, test = holdout_indices(10, 3)
    assert test.tolist() == [0, 3, 6, 9] and len(train) == 6
    train, test = holdout_indices(5, 0)
    assert test.tolist() == [] and train.tolist() == [0, 1, 2, 3, 4]
    assert split_info(49, 8) == {"holdout_every": 8, "n_train": 42, "n_test": 7,
                                 "test_views": [0, 8, 16, 24, 32, 40, 48]}


def test_default_rule_and_bounds():
    assert default_holdout_every(16) == 8 and default_holdout_every(15) == 0
    assert default_holdout_every(100, has_test_set=True) == 0
    assert holdout_limits(49) == {"holdout_default_every": 8, "holdout_max_every": 24}
    assert check_holdout_every(0, 3) == 0
    assert check_holdout_every(2, 4) == 2 and check_holdout_every(24, 49) == 24
    with pytest.raises(ValueError, match=r"2\.\.24"):
        check_holdout_every(25, 49)
    with pytest.raises(ValueError, match=r"out of range"):
        check_holdout_every(1, 49)
    with pytest.raises(ValueError, match="too few"):
        check_holdout_every(2, 3)
    with pytest.raises(ValueError, match="integer"):
        check_holdout_every(2.5, 49)


def test_eval_stride_keeps_an_evaluation_within_its_pixel_budget():
    # 8 views at 128^2 are exactly 131072 pixels: every pixel
    assert eval_stride_for(8, 128, 128) == 1
    # 7 DTU views at 1600x1200: stride 10 leaves 7 * 120 * 160 = 134400 > 131072; 11: 7 * 110 * 146 = 112420
    assert eval_stride_for(7, 1600, 1200) == 11
    # the fox at 540 px: 9 views of 540x304; stride 3: 9 * 180 * 102 = 165240; 4: 9 * 135 * 76 = 92340
    assert eval_stride_for(9, 540, 304) == 4
    assert eval_stride_for(7, 1600, 1200, max_pixels=1 << 18) == 8   # 7 * 150 * 200 = 210000


def test_held_out_targets_split_the_scene_and_set_the_stride(tmp_path):
    from nepf_core.data.detect import load_scene
    from nepf_core.jobs import held_out_targets
    scene = load_scene(make_dtu_dir(tmp_path / "d17", n=17, size=24))
    # 5 held-out views of 24^2: stride 2 leaves 5 * 144 = 720 > 500 pixels, stride 3 5 * 64 = 320
    train, targets, split = held_out_targets(scene, 4, has_test_set=False, eval_pixels=500)
    assert targets.stride == 3 and split["eval_stride"] == 3 and targets.split is split
    assert train.n_views == 12 and targets.test_scene.n_views == 5
    assert np.array_equal(targets.test_scene.images[1], scene.images[4])
    assert np.array_equal(train.images[3], scene.images[5])   # train views 1, 2, 3, 5, ...
    assert targets.test_scene.split == "test" and train.split == "train"
    _, none, split0 = held_out_targets(scene, 0, has_test_set=False, eval_pixels=500)
    assert none is None and split0["n_test"] == 0


# ------------------------------------------------------------------------------ one ETA
def test_eta_is_the_nearer_of_the_two_limits():
    # 500 of 20000 steps in 100 s: steps end in 19500 * 0.2 = 3900 s; a 300 s budget in 200 s
    assert run_eta(500, 20_000, 100.0, 300.0) == (200.0, "time")
    # 1000 of 2000 steps in 100 s: steps end in 100 s, before the 600 s budget (500 s left)
    assert run_eta(1000, 2000, 100.0, 600.0) == (100.0, "steps")
    # no budget: steps only; before the first step there is no rate
    assert run_eta(250, 1000, 50.0, None) == (150.0, "steps")
    assert run_eta(0, 1000, 0.0, None) == (None, "steps")
    assert run_eta(0, 1000, 0.0, 60.0) == (60.0, "time")
    # past the budget: nothing left, never negative
    assert run_eta(10, 1000, 70.0, 60.0) == (0.0, "time")


def test_progress_text_shows_one_eta_and_the_limit_that_ends_the_run():
    assert format_duration(85) == "1:25" and format_duration(3725.4) == "1:02:05" and format_duration(0) == "0:00"
    info = {"step": 500, "total": 20_000, "fraction": 0.3333, "stage": "training", "eta_s": 200.0,
            "ends_by": "time", "wall_s": 100.0}
    assert progress_text(info) == "training · step 500/20000 · 1:40 · ETA 3:20 (time budget)"
    assert bar_position(info) == 333
    steps = dict(info, eta_s=3900.0, ends_by="steps", fraction=0.025)
    assert progress_text(steps) == "training · step 500/20000 · 1:40 · ETA 1:05:00 (steps)"
    assert bar_position(steps) == 25
    loading = {"step": 0, "total": 0, "fraction": 0.0, "stage": "loading", "eta_s": None, "wall_s": 0.0}
    assert progress_text(loading) == "loading · 0:00"


# ------------------------------------------------------------------------------ SSIM
def test_mean_ssim_foreground_ignores_the_background():
    rng = np.random.default_rng(0)
    gt = rng.uniform(0.2, 0.8, (2, 32, 32, 3))
    masks = np.zeros((2, 32, 32), bool)
    masks[:, 8:24, 8:24] = True
    assert mean_ssim(gt, gt, None) == {"test_ssim_full": 1.0, "test_ssim": 1.0}
    pred = gt.copy()
    pred[~masks] = rng.uniform(0, 1, (int((~masks).sum()), 3))   # wrong only in the background
    s = mean_ssim(pred, gt, masks)
    assert s["test_ssim_full"] < 0.8
    assert s["test_ssim"] > s["test_ssim_full"]
    # the foreground value: SSIM map over pixels whose 11x11 window lies mostly inside
    assert s["test_ssim"] < 1.0
    assert mean_ssim(gt[:, :8, :8], gt[:, :8, :8], None) == {}   # smaller than the window


# ------------------------------------------------------------------------------ nepf fit
def _fit(capsys, data, run, *extra) -> tuple[int, str]:
    code = nepf_main(["fit", str(data), "--out", str(run), "--config", "tiny", "--iters", "3", "--device", "cpu",
                      "--no-export", *map(str, extra)])
    out = capsys.readouterr()
    return code, out.out + out.err


def _tests(run) -> list[dict]:
    recs = [json.loads(ln) for ln in (run / "metrics.jsonl").read_text().splitlines() if ln.strip()]
    return [r for r in recs if r.get("kind") == "test"]


def test_fit_holdout_every_evaluates_the_held_out_views(tmp_path, capsys):
    data = make_dtu_dir(tmp_path / "d17", n=17, size=24)
    run = tmp_path / "run"
    code, out = _fit(capsys, data, run, "--holdout-every", "4")
    assert code == 0, out
    tests = _tests(run)
    assert tests and tests[-1]["final"] is True
    rec = tests[-1]
    assert rec["test_views"] == 5   # views 0, 4, 8, 12, 16
    assert rec["eval_stride"] == 2  # 5 * 24^2 pixels fit the budget (stride 1); tiny's eval_stride is 2
    for k in ("test_psnr", "test_psnr_full", "test_psnr_radiance", "test_psnr_radiance_full",
              "test_ssim", "test_ssim_full"):
        assert rec[k] is not None and np.isfinite(rec[k]), k
    # masks exist: test_psnr is masked, test_psnr_full over every pixel (the black background counts)
    assert rec["test_psnr"] != rec["test_psnr_full"]
    split = {"holdout_every": 4, "n_train": 12, "n_test": 5, "test_views": [0, 4, 8, 12, 16], "eval_stride": 1}
    assert json.loads((run / "summary.json").read_text())["split"] == split
    assert json.loads((run / "report.json").read_text())["split"] == split
    assert '"n_test": 5' in out   # the printed summary says it too
    # the latest evaluation's picture of held-out view 0: render | truth | error at the eval stride
    assert rec["preview"] == "holdout/latest.png"
    from PIL import Image
    from nepf_core.holdout_preview import GAP
    with Image.open(run / rec["preview"]) as im:
        assert im.size == (3 * 12 + 2 * GAP, 12) and im.mode == "RGB"   # 24 px at stride 2


def test_fit_default_split_with_and_without_eval_test(tmp_path, capsys):
    data16 = make_dtu_dir(tmp_path / "d16", n=16, size=24, masks=False)
    code, out = _fit(capsys, data16, tmp_path / "r16")
    assert code == 0, out
    rec = _tests(tmp_path / "r16")[-1]
    assert rec["test_views"] == 2    # 16 views: every 8th held out (0 and 8)
    assert rec["test_psnr"] == rec["test_psnr_full"] and rec["test_ssim"] == rec["test_ssim_full"]   # no masks

    data15 = make_dtu_dir(tmp_path / "d15", n=15, size=24)
    code, out = _fit(capsys, data15, tmp_path / "r15")
    assert code == 0, out
    assert _tests(tmp_path / "r15") == []   # under 16 views: train on all
    assert json.loads((tmp_path / "r15" / "summary.json").read_text())["split"]["n_test"] == 0

    test_dir = make_dtu_dir(tmp_path / "t3", n=3, size=24)
    code, out = _fit(capsys, data16, tmp_path / "re", "--eval-test", test_dir)
    assert code == 0, out
    assert _tests(tmp_path / "re")[-1]["test_views"] == 3   # the given test set, nothing held out
    assert json.loads((tmp_path / "re" / "summary.json").read_text())["split"]["n_train"] == 16


def test_fit_rejects_a_bad_holdout(tmp_path, capsys):
    data = make_dtu_dir(tmp_path / "d6", n=6, size=24)
    code, out = _fit(capsys, data, tmp_path / "r1", "--holdout-every", "4")
    assert code == 1 and "holdout_every = 4 is out of range for 6 views" in out and "2..3" in out
    code, out = _fit(capsys, data, tmp_path / "r2", "--holdout-every", "2", "--eval-test", data)
    assert code == 1 and "use one of them" in out
