"""fit(): exact resume, the non-finite guard, cancel, time budget, and records written."""

import json
import math

import numpy as np
import pytest
import torch

from nepf_core.callbacks import FitCallbacks
from nepf_core.config import tiny
from nepf_core.train import FitError, fit


def _cfg(iters=6):
    cfg = tiny()
    cfg.train.iters = iters
    cfg.train.log_every = 1
    cfg.train.sync_every = 0
    cfg.train.checkpoint_every = 3
    cfg.train.batch_rays = 64
    return cfg


def _losses(run):
    recs = [json.loads(l) for l in (run / "metrics.jsonl").read_text().splitlines()]
    return {r["step"]: r["loss"] for r in recs if r.get("kind") == "train"}


def test_resume_gives_the_same_losses_as_an_uninterrupted_run(small_scene, tmp_path):
    a = tmp_path / "a"
    fit(small_scene, a, _cfg(), device="cpu")
    b = tmp_path / "b"
    stop_after = {"n": 0}

    def should_stop():
        stop_after["n"] += 1
        return stop_after["n"] > 3  # checked before each step: 3 steps run, then stop

    r1 = fit(small_scene, b, _cfg(), device="cpu", callbacks=FitCallbacks(should_stop=should_stop))
    assert r1.status == "cancelled" and r1.step == 3
    r2 = fit(small_scene, b, _cfg(), device="cpu", resume=True)
    assert r2.status == "succeeded" and r2.step == 6
    la, lb = _losses(a), _losses(b)
    assert sorted(la) == [1, 2, 3, 4, 5, 6]
    for s in range(1, 7):
        assert la[s] == pytest.approx(lb[s], rel=1e-6, abs=1e-9), (s, la[s], lb[s])


def test_a_resume_after_a_kill_lists_each_step_once(small_scene, tmp_path):
    """Issue 37: a worker killed at step 5 with its checkpoint at 3 trains 4 and 5 again when it
    resumes; metrics.jsonl listed them twice. The run is stopped at 5 and its checkpoint files put
    back as they were at step 3 (what a kill -9 at 5 leaves); the resumed run cuts the log back to
    the checkpoint, so steps 1..6 are listed once each, with the losses of an uninterrupted run."""
    import shutil

    from nepf_core.resume import checkpoint_step

    a = tmp_path / "a"
    fit(small_scene, a, _cfg(), device="cpu")
    b = tmp_path / "b"
    saved = tmp_path / "at_step_3"

    def on_checkpoint(step, path):
        if step == 3:
            shutil.copytree(b / "checkpoints", saved)
    calls = {"n": 0}

    def should_stop():
        calls["n"] += 1
        return calls["n"] > 5
    fit(small_scene, b, _cfg(), device="cpu", callbacks=FitCallbacks(should_stop=should_stop, on_checkpoint=on_checkpoint))
    assert sorted(_losses(b)) == [1, 2, 3, 4, 5]
    shutil.rmtree(b / "checkpoints")
    shutil.copytree(saved, b / "checkpoints")            # the state a kill -9 at step 5 leaves
    r = fit(small_scene, b, _cfg(), device="cpu", resume=True)
    assert r.step == 6
    steps = [json.loads(l)["step"] for l in (b / "metrics.jsonl").read_text().splitlines()]
    assert steps == [1, 2, 3, 4, 5, 6], steps
    la, lb = _losses(a), _losses(b)
    for s in range(1, 7):
        assert la[s] == pytest.approx(lb[s], rel=1e-6, abs=1e-9), (s, la[s], lb[s])
    assert checkpoint_step(b) == 6


def test_cut_metrics_to_checkpoint_without_or_with_a_stale_info_file(tmp_path):
    """Without ``checkpoints/latest.json`` (an older run folder), or with one a checkpoint behind
    (a kill between ``latest.pt`` and its info file), the records above the step go, a line cut
    by the kill too; with a matching one, the file is cut to its recorded length."""
    from nepf_core.resume import cut_metrics_to_checkpoint, write_checkpoint_info

    log = tmp_path / "metrics.jsonl"
    text = "".join(json.dumps(r) + "\n" for r in ({"step": 1}, {"step": 2}, {"step": 2, "kind": "sync"},
                                                   {"note": "no step"}, {"step": 3}))
    log.write_text(text + '{"step": 4, "lo')
    assert cut_metrics_to_checkpoint(tmp_path, 2) == 2
    assert [json.loads(l).get("step") for l in log.read_text().splitlines()] == [1, 2, 2, None]
    write_checkpoint_info(tmp_path, 1, 0.5, metrics_bytes=len(json.dumps({"step": 1})) + 1)
    assert cut_metrics_to_checkpoint(tmp_path, 2) == 0             # info names step 1, not 2: by step
    assert cut_metrics_to_checkpoint(tmp_path, 1) > 0              # matching: cut to its length
    assert log.read_text() == '{"step": 1}\n'


def test_records_and_report(small_scene, tmp_path):
    cfg = _cfg(8)
    cfg.train.sync_every = 4
    cfg.train.sync_rays = 128
    res = fit(small_scene, tmp_path / "r", cfg, device="cpu")
    recs = [json.loads(l) for l in (tmp_path / "r" / "metrics.jsonl").read_text().splitlines()]
    train = [r for r in recs if r["kind"] == "train"]
    sync = [r for r in recs if r["kind"] == "sync"]
    assert len(train) == 8 and len(sync) == 2
    for key in ("loss_r", "loss_surf", "loss_vol", "loss_eik", "loss_light", "loss_mask", "inv_s",
                "rays_per_s", "samples_per_s", "wall_s"):
        assert key in train[0] and math.isfinite(train[0][key])
    walls = [r["wall_s"] for r in train]
    assert walls == sorted(walls)
    for k in ("psnr_r", "psnr_surf", "psnr_vol"):
        assert math.isfinite(sync[0][k])
    rep = json.loads((tmp_path / "r" / "report.json").read_text())
    names = [d["decision"] for d in rep["decisions"]]
    assert "mask_loss" in names and "background_model" in names
    assert (tmp_path / "r" / "checkpoints" / "latest.pt").exists()
    assert (tmp_path / "r" / "error_vs_time.png").stat().st_size > 1000
    prog = json.loads((tmp_path / "r" / "progress.json").read_text())
    assert prog["step"] == 8 and prog["fraction"] == 1.0


def test_nonfinite_loss_skips_then_fails(small_scene, tmp_path, monkeypatch):
    import nepf_core.train.loop as loopmod
    real = loopmod.compute_losses
    calls = {"n": 0}

    def poisoned(out, rays, cfg, use_mask, **kw):
        L = real(out, rays, cfg, use_mask=use_mask, **kw)
        calls["n"] += 1
        if calls["n"] in (2, 3):
            L["loss_r"] = L["loss_r"] * float("nan")
        return L

    monkeypatch.setattr(loopmod, "compute_losses", poisoned)
    res = fit(small_scene, tmp_path / "ok", _cfg(5), device="cpu")
    assert res.nonfinite_steps == 2 and res.status == "succeeded"
    ck = torch.load(tmp_path / "ok" / "checkpoints" / "latest.pt", weights_only=False)
    assert all(torch.isfinite(v).all() for v in ck["model"].values() if v.is_floating_point())
    recs = [json.loads(l) for l in (tmp_path / "ok" / "metrics.jsonl").read_text().splitlines()]
    assert recs[-1]["nonfinite_steps"] == 2

    calls["n"] = -100  # poison every step now
    monkeypatch.setattr(loopmod, "compute_losses",
                        lambda out, rays, cfg, use_mask, **kw: {**real(out, rays, cfg, use_mask=use_mask, **kw),
                                                                "loss_r": torch.tensor(float("inf"))})
    cfg = _cfg(20)
    cfg.train.max_nonfinite_steps = 4
    with pytest.raises(FitError, match="non-finite"):
        fit(small_scene, tmp_path / "bad", cfg, device="cpu")


def test_time_budget_stops_and_writes_outputs(small_scene, tmp_path):
    cfg = _cfg(10_000)
    res = fit(small_scene, tmp_path / "t", cfg, device="cpu", time_budget_s=2.0)
    assert res.status == "succeeded" and 0 < res.step < 10_000
    assert res.wall_s >= 2.0
    assert (tmp_path / "t" / "checkpoints" / "latest.pt").exists()


def test_metrics_log_starts_a_new_line_after_a_line_cut_by_a_kill(tmp_path):
    """A kill -9 mid-write leaves a partial last line; the resumed log must not glue its first
    record onto it (that record would be lost to every reader)."""
    from nepf_core.train import MetricsLog

    p = tmp_path / "metrics.jsonl"
    p.write_text('{"step": 1, "loss": 0.5}\n{"step": 2, "lo')
    seen = []
    log = MetricsLog(p, FitCallbacks(on_metrics=seen.append))
    log.write({"step": 3, "loss": 0.25})
    log.close()
    lines = p.read_text().splitlines()
    assert lines[0] == '{"step": 1, "loss": 0.5}' and lines[1] == '{"step": 2, "lo'
    assert json.loads(lines[2]) == {"step": 3, "loss": 0.25} and len(lines) == 3
    assert seen == [{"step": 3, "loss": 0.25}]
    # a clean file gets no blank line
    q = tmp_path / "clean.jsonl"
    q.write_text('{"step": 1}\n')
    log = MetricsLog(q, FitCallbacks())
    log.write({"step": 2})
    log.close()
    assert q.read_text() == '{"step": 1}\n{"step": 2}\n'


@pytest.mark.parametrize("channel, exact_key, other_key", [("radiance", "test_psnr_radiance", "test_psnr"),
                                                           ("pbr", "test_psnr", "test_psnr_radiance")])
def test_held_out_psnr_keys_score_their_own_channel(small_scene, channel, exact_key, other_key):
    """Held-out views whose images ARE the model's render of one channel: that channel's PSNR hits
    the MSE floor (100 dB, masked and full) and the other channel's does not."""
    import dataclasses

    from nepf_core.evaluate import render_view
    from nepf_core.train import EvalTargets, evaluate_test
    from nepf_core.model import NePFModel
    from nepf_core.rays import PixelSampler

    torch.manual_seed(0)
    cfg = _cfg()
    model = NePFModel(cfg.model)
    dev = torch.device("cpu")
    sampler = PixelSampler(small_scene, dev)
    imgs = np.stack([render_view(model, sampler, k, cfg.render)[channel] for k in range(small_scene.n_views)])
    test = dataclasses.replace(small_scene, images=imgs.astype(np.float32))
    rec = evaluate_test(model, cfg, EvalTargets(test_scene=test), dev, np.eye(4), 1, False)
    assert rec[exact_key] == pytest.approx(100.0) and rec[exact_key + "_full"] == pytest.approx(100.0)
    assert rec[other_key] < 60.0
