"""The specular-lobe rule: drop, fade, return, view spread, kept-lobe report (fake render outputs),
and one real fit that drops the lobe and exports what the surface was shaded with."""

from __future__ import annotations

import json

import pytest
import torch

from nepf_core.train.rules.lobe_evidence import lobe_residual_gain
from rule_fixtures import batch, check, fake_out, losses, make_adapt, named, records, resumed, tiny


def test_specular_dropped_after_patience_diffuse_checks():
    a, rs = make_adapt()
    assert rs.specular
    asks = [batch(a, None, None, step=s).request.lobe_split for s in (100, 150, 0)]
    assert asks == [True, False, False]   # every check_every steps, none at the start
    check(a, 50, fake_out(share=0.0), losses())   # before the warm-up (10% of 1000 steps)
    assert a.specular.diffuse_streak == 0
    for k, step in enumerate((100, 200)):
        check(a, step, fake_out(share=0.001, metallic=0.01), losses())
        assert rs.specular and a.specular.diffuse_streak == k + 1
    check(a, 300, fake_out(share=0.5, metallic=0.01), losses())   # a glossy check resets the streak
    assert rs.specular and a.specular.diffuse_streak == 0
    check(a, 400, fake_out(share=0.001, metallic=0.5), losses())  # metallic alone is "not diffuse"
    assert a.specular.diffuse_streak == 0
    for step in (500, 600, 700):
        check(a, step, fake_out(share=0.001, metallic=0.01), losses())
    assert not rs.specular and rs.diffuse_metal_weight == 1.0   # the drop: the same image, then the fade
    (d,) = named(a, "specular_lobe")
    assert d["value"] is False and d["step"] == 700 and "diffuse" in d["reason"]
    assert a.step_stats()["specular_share"] == pytest.approx(0.001)


def test_specular_warmup_is_capped_for_long_nominal_runs():
    """A time-budgeted fast run has iters=20000 but does ~1-2k steps: 10% would never end."""
    a, rs = make_adapt(iters=20000)
    check(a, a.rc.warmup_max_steps - 100, fake_out(share=0.0), losses())
    assert a.specular.diffuse_streak == 0
    steps = [a.rc.warmup_max_steps + 100 * k for k in range(a.rc.patience)]
    for step in steps:
        check(a, step, fake_out(share=0.0), losses())
    assert not rs.specular
    assert named(a, "specular_lobe")[0]["step"] == steps[-1] < 0.1 * 20000


def test_specular_needs_enough_surface_rays():
    a, rs = make_adapt()
    for step in (100, 200, 300, 400):
        check(a, step, fake_out(share=0.0, opaque=False), losses())   # no ray with sum w > 0.5
    assert rs.specular and a.specular.diffuse_streak == 0


def _dropped(**kw):
    a, rs = make_adapt(**kw)
    for step in (100, 200, 300):
        check(a, step, fake_out(share=0.0), losses())
    assert not rs.specular
    return a, rs


def test_specular_reenabled_when_share_would_be_large_for_patience_checks():
    a, rs = _dropped()
    check(a, 400, fake_out(share=0.03), losses())   # above spec_thr but below 2 spec_thr: no vote
    assert not rs.specular and a.specular.return_streak == 0
    check(a, 500, fake_out(share=0.2), losses())    # one vote ...
    check(a, 600, fake_out(share=0.01), losses())   # ... broken by a check that does not vote
    assert not rs.specular and a.specular.return_streak == 0
    steps = [700 + 100 * k for k in range(a.rc.patience)]
    for k, step in enumerate(steps):
        assert not rs.specular
        check(a, step, fake_out(share=0.2), losses())
        assert a.specular.return_streak == (0 if k == a.rc.patience - 1 else k + 1)
        if k < a.rc.patience - 1:
            assert a.step_stats()["lobe_return_votes"] == k + 1   # logged while the lobe is off
    assert rs.specular and "lobe_return_votes" not in a.step_stats()
    d = named(a, "specular_lobe")[-1]
    assert d["value"] is True and d["step"] == steps[-1] and "share" in d["reason"]


def test_lobe_return_streak_and_the_switch_survive_a_checkpoint_resume():
    a, rs = _dropped()
    check(a, 400, fake_out(share=0.2), losses())
    b, rs_b = resumed(a, rs)
    assert not rs_b.specular and b.specular.return_streak == 1
    for step in range(500, 400 + 100 * a.rc.patience, 100):
        check(b, step, fake_out(share=0.2), losses())
    assert rs_b.specular


def test_albedo_flatness_prior_is_recorded_on_exactly_while_the_lobe_is_off():
    a, rs = _dropped()
    for k in range(a.rc.patience):
        check(a, 400 + 100 * k, fake_out(share=0.2), losses())
    assert rs.specular and not named(a, "albedo_flatness_prior")   # tiny has no flatness prior
    b, _ = make_adapt(w_albedo_flat=3e-5)
    for step in (100, 200, 300):
        check(b, step, fake_out(share=0.0), losses())
    back = 400 + 100 * (b.rc.patience - 1)
    for step in range(400, back + 1, 100):
        check(b, step, fake_out(share=0.2), losses())
    assert [(d["value"], d["step"]) for d in named(b, "albedo_flatness_prior")] == [(True, 300), (False, back)]


def test_specular_reenabled_by_highlight_residual_for_patience_checks():
    a, rs = _dropped()
    a.specular.vote_on_highlight(400, 2.0, rs.specular)   # below highlight_ratio = 3: no vote
    check(a, 400, fake_out(share=0.0), losses())
    assert not rs.specular and a.specular.return_streak == 0
    steps = [500 + 100 * k for k in range(a.rc.patience)]
    for step in steps:
        a.specular.vote_on_highlight(step, 7.5, rs.specular)
        check(a, step, fake_out(share=0.0), losses())
    assert rs.specular
    d = named(a, "specular_lobe")[-1]
    assert d["value"] is True and d["step"] == steps[-1] and "brightest" in d["reason"]
    # a vote counts only at its own check: a later check without one breaks the streak
    b, rs_b = _dropped()
    b.specular.vote_on_highlight(400, 7.5, rs_b.specular)
    check(b, 400, fake_out(share=0.0), losses())
    check(b, 500, fake_out(share=0.0), losses())
    assert b.specular.return_streak == 0
    # while the lobe is on, a residual changes nothing
    n = len(a.decisions)
    a.specular.vote_on_highlight(900, 9.0, rs.specular)
    check(a, 900, fake_out(share=0.2), losses())
    assert len(a.decisions) == n and rs.specular


def test_disabled_adaptivity_keeps_every_term():
    a, rs = make_adapt(enabled=False)
    assert not batch(a, None, None, step=100).request.lobe_split
    for step in range(100, 1001, 100):
        check(a, step, fake_out(share=0.0), losses(eik=0.0))
    a.specular.vote_on_highlight(500, 10.0, rs.specular)
    assert rs.specular and rs.w_hessian == 5e-4
    assert not named(a, "specular_lobe") and not named(a, "hessian_loss")


def test_lobe_residual_gain_hand_values():
    d = torch.ones(2, 3)
    t = torch.tensor([[1.0] * 3, [3.0] * 3])
    # best gain k = (1 + 3) / (1 + 1) = 2: E_d = mean((2-1)^2, (2-3)^2) = 1; E = mean(0, 0.5^2) = 0.125
    full = torch.tensor([[1.0] * 3, [2.5] * 3])
    assert lobe_residual_gain(full, d, t) == pytest.approx(1 / 0.125 - 1)
    # the lobe only adds a uniform brightness the albedo can absorb: g = 0 / E - 1 = -1
    assert lobe_residual_gain(0.5 * d + 0.1, d, 0.5 * d) == pytest.approx(-1.0)
    # black targets -> k = 0, E_d = 0 -> g = -1
    assert lobe_residual_gain(d * 0.1, d, torch.zeros(2, 3)) == pytest.approx(-1.0)


def test_kept_specular_lobe_is_reported_with_its_numbers():
    a, rs = make_adapt(iters=1000)
    a.specular.lobe_gain = 0.3
    for step in range(1, 301):
        check(a, step, fake_out(share=0.1, metallic=0.5), losses())
    assert a.step_stats()["lobe_residual_gain"] == pytest.approx(0.3)
    rep = a.report(step=300, status="succeeded", nonfinite=0)
    (d,) = [x for x in rep["decisions"] if x["decision"] == "specular_lobe"]
    assert d["value"] is True and "kept" in d["reason"] and "0.500" in d["reason"] and "+30%" in d["reason"]
    assert rep["final_switches"]["specular"] is True and rep["run_state"]["specular"] is True
    b, _ = make_adapt(iters=1000)   # a dropped lobe gets no extra "kept" record
    for step in range(1, 501):
        check(b, step, fake_out(share=0.0, metallic=0.0), losses())
    rep = b.report(step=500, status="succeeded", nonfinite=0)
    assert [x["value"] for x in rep["decisions"] if x["decision"] == "specular_lobe"] == [False]


def test_view_independent_radiance_drops_the_lobe_whatever_the_material_says():
    """metallic 0.6 and a 12 % lobe share, yet the learned radiance changes by 0.5 % across the
    cameras: the spread decides."""
    a, rs = make_adapt()
    a.specular.view_spread = 0.005
    for step in (100, 200, 300):
        check(a, step, fake_out(share=0.12, metallic=0.6), losses())
    assert not rs.specular
    d = named(a, "specular_lobe")
    assert len(d) == 1 and d[0]["value"] is False and d[0]["step"] == 300
    assert "view-independent" in d[0]["reason"] and "0.50%" in d[0]["reason"]


def test_view_dependent_radiance_keeps_the_lobe_even_if_the_material_looks_diffuse():
    a, rs = make_adapt()
    a.specular.view_spread = 0.05
    for step in range(100, 1100, 100):
        check(a, step, fake_out(share=0.0, metallic=0.0), losses())
    assert rs.specular and a.specular.diffuse_streak == 0
    rep = a.report(step=1000, status="succeeded", nonfinite=0)
    kept = [d for d in rep["decisions"] if d["decision"] == "specular_lobe"]
    assert kept and kept[0]["value"] is True and "5.00%" in kept[0]["reason"]


def test_lobe_returns_when_the_radiance_becomes_view_dependent():
    a, rs = make_adapt()
    a.specular.view_spread = 0.01
    for step in (100, 200, 300):
        check(a, step, fake_out(share=0.3, metallic=0.5), losses())
    assert not rs.specular
    a.specular.view_spread = 0.03   # between thr and 2 thr: hysteresis, no vote
    check(a, 400, fake_out(share=0.3, metallic=0.5), losses())
    assert not rs.specular and a.specular.return_streak == 0
    a.specular.view_spread = 0.06
    for k in range(a.rc.patience):
        assert not rs.specular
        check(a, 500 + 100 * k, fake_out(share=0.3, metallic=0.5), losses())
    assert rs.specular
    assert [d["value"] for d in named(a, "specular_lobe")] == [False, True]


def test_highlight_residual_cannot_bring_the_lobe_back_while_the_radiance_is_flat():
    a, rs = make_adapt()
    a.specular.view_spread = 0.01
    for step in (100, 200, 300):
        check(a, step, fake_out(share=0.3, metallic=0.5), losses())
    for step in (400, 500, 600):
        a.specular.vote_on_highlight(step, 10.0, rs.specular)
        check(a, step, fake_out(share=0.3, metallic=0.5), losses())
    assert not rs.specular and a.specular.return_streak == 0
    a.specular.view_spread = 0.03
    for step in (700, 800, 900):
        a.specular.vote_on_highlight(step, 10.0, rs.specular)
        check(a, step, fake_out(share=0.3, metallic=0.5), losses())
    assert rs.specular


def test_dropped_lobe_fades_the_metallic_dimmer_out_linearly():
    a, rs = make_adapt()
    a.specular.view_spread = 0.01
    for step in (100, 200, 300):
        check(a, step, fake_out(share=0.3, metallic=0.5), losses())
    assert not rs.specular and rs.diffuse_metal_weight == 1.0
    n = a.rc.lobe_fade_steps
    check(a, 300 + n // 4, fake_out(share=0.3, metallic=0.5), losses())
    assert rs.diffuse_metal_weight == pytest.approx(0.75)
    b, rs_b = resumed(a, rs)
    assert rs_b.diffuse_metal_weight == pytest.approx(0.75) and not rs_b.specular
    check(b, 300 + n // 2, fake_out(share=0.3, metallic=0.5), losses())
    assert rs_b.diffuse_metal_weight == pytest.approx(0.5)
    check(b, 300 + 2 * n, fake_out(share=0.3, metallic=0.5), losses())
    assert rs_b.diffuse_metal_weight == 0.0


def test_fit_that_drops_the_lobe_exports_the_diffuse_equivalent_material(tmp_path):
    """End to end: a fit whose radiance counts as flat (threshold raised to 1) drops the lobe;
    config.json keeps what was asked (lobe on), ``load_model`` returns the run state of the
    checkpoint, and the export's material query returns what the surface was shaded with:
    metallic 0, roughness 1, albedo (1 - w m) c with the fade weight ``w`` of the run's last step;
    ``nepf relight``'s surfaces keep the network's roughness (shaded without a lobe, as the run)."""
    from nepf_core.data.detect import load_scene
    from nepf_core.data.synth import make_scene
    from nepf_core.model import ModelFieldQuery
    from nepf_core.train import fit, load_model

    # enough views that surface points face two cameras within 53 degrees (min_cos 0.6)
    make_scene(tmp_path / "s", n_views=16, n_test=0, resolution=24, supersample=1, write_mesh=False)
    scene = load_scene(tmp_path / "s" / "dtu")
    cfg = tiny()
    cfg.train.iters, cfg.train.batch_rays, cfg.train.log_every, cfg.train.sync_every = 20, 128, 1, 0
    cfg.train.ema_decay = 0.9
    rules = {"check_every": 5, "patience": 1, "view_spread_thr": 1.0,
             "radiance_fit_max": float("inf")}   # 20 steps do not fit the radiance
    fit(scene, tmp_path / "run", cfg, device="cpu", rules=rules)
    # the weight average restarts at every step of the fade: at the end it is the live model
    ck = torch.load(tmp_path / "run" / "checkpoints" / "latest.pt", weights_only=False)
    assert ck["extra"]["ema"]["updates"] == 0
    for name, value in ck["extra"]["ema"]["params"].items():
        assert torch.equal(value, ck["model"][name]), name
    rep = json.loads((tmp_path / "run" / "report.json").read_text())
    d = [x for x in rep["decisions"] if x["decision"] == "specular_lobe"]
    assert d and d[0]["value"] is False and rep["final_switches"]["specular"] is False
    assert rep["run_state"]["specular"] is False and rep["run_state"] == ck["extra"]["run_state"]
    assert json.loads((tmp_path / "run" / "config.json").read_text())["render"]["specular"] is True
    train = [r for r in records(tmp_path / "run") if r.get("kind", "train") == "train"]
    assert any("radiance_view_spread" in r for r in train)
    assert any(r.get("radiance_fit_error_lit", -1) > 0 for r in train)
    assert train[-1]["specular_on"] is False
    model, cfg2, state = load_model(tmp_path / "run", "cpu")
    assert cfg2.render.specular is True   # the config as asked ...
    shading = state["run_state"].shading()
    assert shading.specular is False      # ... and the switch in effect
    x = torch.randn(50, 3) * 0.3
    n = torch.nn.functional.normalize(torch.randn(50, 3), dim=-1)
    a0, r0, m0 = ModelFieldQuery(model).material(x, n)
    a1, r1, m1 = ModelFieldQuery(model, shading=shading).material(x, n)
    w = shading.diffuse_metal_weight
    assert 0.0 < w < 1.0  # mid-fade after 20 steps (fade over 500): restored from the checkpoint
    assert float(m0.min()) > 0 and torch.all(m1 == 0)
    m0c = m0 if m0.dim() == 2 else m0[:, None]
    assert torch.allclose(a1, a0 * (1 - w * m0c))
    assert float((r0 - 1).abs().max()) > 1e-3 and torch.all(r1 == 1.0)   # the widest glTF lobe, not r0
    # nepf relight shades the run's own BSDF without a lobe: it keeps the network's roughness
    from nepf_core.rays import RayBatch
    from nepf_core.relight.render import model_surfaces
    from nepf_core.render.renderer import render_rays
    o = torch.tensor([[0.0, 0.0, 3.0]]).repeat(16, 1)
    d = torch.nn.functional.normalize(torch.randn(16, 3) * 0.1 + torch.tensor([0.0, 0.0, -1.0]), dim=-1)
    rays = RayBatch(o, d)
    samples, _ = model_surfaces(model, cfg2.render, shading)(rays)
    own = render_rays(model, rays, cfg2.render, train=False, shading=shading).surface
    assert torch.equal(samples.roughness, own.roughness.detach()) and torch.all(samples.metallic == 0)
