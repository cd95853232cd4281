"""Decisions from the data (masks, background, visual hull) and empty space (occupancy grid,
rays that meet no occupied cell, their importance weights), with two short real fits."""

from __future__ import annotations

import dataclasses
import json
import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from nepf_core.fields.sdf_grid import GridSDFConfig
from nepf_core.train.adaptivity import Adaptivity
from nepf_core.train.run_state import RunState
from rule_fixtures import fast, make_adapt, named, records, tiny


def _scene(has_masks: bool, outside: float = 0.0):
    """A stand-in scene: one 4x4 view, half of it inside the mask, ``outside`` the linear value of
    the pixels outside the mask (0: black, as the synthetic scenes are)."""
    img = np.full((4, 4, 3), outside, np.float32)
    mask = np.zeros((4, 4), bool)
    mask[:2] = True
    img[mask] = 0.5
    return SimpleNamespace(has_masks=has_masks, images=[img], masks=[mask] if has_masks else None,
                           intrinsics=np.eye(3)[None], c2w=np.eye(4)[None])


@pytest.mark.parametrize("has_masks", [True, False])
def test_mask_and_background_decisions(has_masks):
    a, rs = make_adapt()
    rs.background = not has_masks  # the opposite of what should be decided
    a.before_training(_scene(has_masks))
    assert rs.use_mask_loss is has_masks
    assert rs.background is (not has_masks)
    (m,) = named(a, "mask_loss")
    (b,) = named(a, "background_model")
    assert m["value"] is has_masks and b["value"] is (not has_masks)
    assert m["reason"] and b["reason"]
    assert not named(a, "empty_space_skipping")  # tiny has no occupancy grid
    # without masks the support plane is looked for; one 4x4 view triangulates nothing
    regions = named(a, "object_region")
    assert (not regions) if has_masks else (regions[0]["value"] is False and "too few points" in regions[0]["reason"])
    assert rs.object_halfspace is None


def test_masks_with_a_lit_outside_get_the_background_volume():
    """A masked capture whose images show something outside the masks (DTU) gets the background
    volume as well as the mask loss; black outside (the synthetic scenes) gets none."""
    for outside, want in ((0.3, True), (0.0, False)):
        a, rs = make_adapt()
        a.before_training(_scene(True, outside))
        assert rs.use_mask_loss is True and rs.background is want
        (b,) = named(a, "background_model")
        assert b["value"] is want


def test_mask_loss_off_when_its_weight_is_zero_and_occupancy_recorded():
    cfg = fast()
    cfg.loss.w_mask = 0.0
    rs = RunState.from_config(cfg)
    a = Adaptivity(cfg, rs, iters_fixed=True)
    a.before_training(_scene(True))
    assert rs.use_mask_loss is False and rs.background is False
    (e,) = named(a, "empty_space_skipping")
    assert e["value"] is True and "64^3" in e["reason"]


def test_fit_without_masks_uses_background_and_no_mask_loss(tmp_path):
    from nepf_core.data.detect import load_scene
    from nepf_core.data.synth import make_scene
    from nepf_core.train import fit, load_model

    make_scene(tmp_path / "s", n_views=4, n_test=0, resolution=24, supersample=1, masks=False, write_mesh=False)
    scene = load_scene(tmp_path / "s" / "dtu")
    assert not scene.has_masks
    cfg = tiny()
    cfg.train.iters, cfg.train.batch_rays, cfg.train.log_every, cfg.train.sync_every = 4, 64, 2, 0
    res = fit(scene, tmp_path / "run", cfg, device="cpu")
    rep = json.loads((tmp_path / "run" / "report.json").read_text())
    dec = {d["decision"]: d for d in rep["decisions"]}
    assert dec["mask_loss"]["value"] is False and dec["background_model"]["value"] is True
    assert rep["final_switches"]["mask_loss"] is False and rep["final_switches"]["background"] is True
    assert rep["run_state"]["background"] is True and rep["run_state"]["use_mask_loss"] is False
    assert res.report == rep
    for r in records(tmp_path / "run"):
        assert r["loss_mask"] == 0.0
    # config.json is what was asked (no background); the checkpoint's run state rebuilds it
    assert json.loads((tmp_path / "run" / "config.json").read_text())["model"]["background"] is False
    model, _, _ = load_model(tmp_path / "run", "cpu")
    assert model.background is not None


@pytest.mark.parametrize("adaptive", [True, False])
def test_fast_fit_with_masks_carves_the_visual_hull_and_leaves_empty_rays_out(tmp_path, adaptive):
    from nepf_core.data.detect import load_scene
    from nepf_core.data.synth import make_scene
    from nepf_core.train import fit

    # a wide field of view, so the object covers part of each frame and the hull culls cells
    make_scene(tmp_path / "s", n_views=6, n_test=0, resolution=24, supersample=1, fov_deg=75.0, write_mesh=False)
    scene = load_scene(tmp_path / "s" / "dtu")
    cfg = fast()
    cfg.model.sdf_grid = GridSDFConfig(base_resolution=8, max_resolution=32)
    cfg.model.occupancy_resolution = 16
    cfg.train.iters, cfg.train.batch_rays, cfg.train.log_every = 6, 64, 2
    cfg.train.sync_every, cfg.train.eval_every_s, cfg.train.occupancy_every = 0, 0.0, 3
    cfg.train.adaptive = adaptive
    run = tmp_path / "run"
    fit(scene, run, cfg, device="cpu")
    rep = json.loads((run / "report.json").read_text())
    dec = {d["decision"]: d for d in rep["decisions"]}
    if not adaptive:  # the everything-on baseline keeps the whole grid: no hull carving
        assert dec["visual_hull"]["value"] is False and "disabled" in dec["visual_hull"]["reason"]
        assert dec["empty_space_skipping"]["value"] is False and "rays_left_out_fraction" not in rep
        ck = torch.load(run / "checkpoints" / "latest.pt", weights_only=False)["model"]
        assert bool(ck["hull"].all())
        return
    assert dec["mask_loss"]["value"] is True and dec["background_model"]["value"] is False
    assert dec["empty_space_skipping"]["value"] is True
    assert dec["visual_hull"]["value"] is True and "culled" in dec["visual_hull"]["reason"]
    assert 0.0 < rep["occupied_fraction"] < 1.0
    train = [r for r in records(run) if r["kind"] == "train"]
    assert 0.0 < rep["rays_left_out_fraction"] < 1.0 and rep["rays_left_out_note"]
    assert "no occupied cell" in dec["empty_rays"]["reason"]
    assert train and all(0.0 <= r["rays_left_out"] < 1.0 for r in train)
    assert any(r["batch_rays"] < cfg.train.batch_rays for r in train)
    # no samples outside the mask bounds: the occupancy grid never exceeds the visual hull
    ck = torch.load(run / "checkpoints" / "latest.pt", weights_only=False)["model"]
    hull, occ = ck["hull"], ck["occupancy.occ"]
    assert 0.0 < hull.float().mean() < 1.0
    assert not (occ & ~hull).any()


def _sphere_model_and_rays(n_hit=24, n_miss=40):
    """fast model whose occupancy grid holds the init sphere (r = 0.5): rays from distance 3
    towards the centre hit it, rays pointing away miss every occupied cell."""
    from nepf_core.model import NePFModel
    from nepf_core.rays import RayBatch
    cfg = fast()
    model = NePFModel(cfg.model)
    model.occupancy.update(model.sdf.sdf, inv_s=1e4)
    g = torch.Generator().manual_seed(0)
    p = torch.nn.functional.normalize(torch.randn(n_hit + n_miss, 3, generator=g), dim=-1)
    o = 3.0 * p
    d = torch.cat([-p[:n_hit], p[n_hit:]])
    n = n_hit + n_miss
    rays = RayBatch(o, d, torch.rand(n, 3, generator=g), (torch.arange(n) < n_hit).float(),
                    torch.arange(n), torch.zeros(n, dtype=torch.bool))
    return cfg, model, rays


def _adapt(cfg, enabled=True, **rules):
    cfg.train.adaptive = enabled
    cfg.rules = dataclasses.replace(cfg.rules, **rules)
    return Adaptivity(cfg, RunState.from_config(cfg), iters_fixed=False)


def test_rays_that_meet_no_occupied_cell_leave_the_batch():
    cfg, model, rays = _sphere_model_and_rays()
    a = _adapt(cfg, miss_keep=0.0)
    kept, left_out = a.thin_empty_rays(model, rays, step=0, generator=torch.Generator().manual_seed(1))
    assert torch.equal(kept.view, torch.arange(24))            # exactly the hits, in order
    assert left_out is None                                     # no background shows the misses
    from nepf_core.fields.background import BackgroundVolume
    model.background = BackgroundVolume()
    _, left_out = _adapt(cfg, miss_keep=0.0).thin_empty_rays(model, rays, step=0,
                                                             generator=torch.Generator().manual_seed(1))
    # the misses, for the background alone: as many as the SDF batch, each standing for 40 / 24
    assert len(left_out) == 24 and bool((left_out.view >= 24).all()) and len(set(left_out.view.tolist())) == 24
    assert torch.allclose(left_out.weight, torch.full((24,), 40 / 24))
    assert torch.equal(kept.mask, rays.mask[:24]) and kept.unlit.shape == (24,)
    (d,) = named(a, "empty_rays")
    assert d["value"]["left_out_fraction"] == pytest.approx(40 / 64, abs=1e-4) and "62.5%" in d["reason"]
    assert a.step_stats()["rays_left_out"] == pytest.approx(40 / 64)
    # a random share of the misses stays: about miss_keep of them, the hits always
    b = _adapt(cfg, miss_keep=0.5)
    n_kept = [len(b.thin_empty_rays(model, rays, step=s, generator=torch.Generator().manual_seed(s))[0])
              for s in range(1, 41)]
    assert min(n_kept) >= 24 and 24 + 0.35 * 40 < sum(n_kept) / len(n_kept) < 24 + 0.65 * 40
    assert len(named(b, "empty_rays")) == 1                   # recorded once
    rep = b.report(step=41, status="succeeded", nonfinite=0)
    assert rep["rays_left_out_fraction"] == pytest.approx(sum(64 - k for k in n_kept) / 64 / 40)


def test_empty_rays_stay_without_adaptivity_or_before_the_first_refresh():
    cfg, model, rays = _sphere_model_and_rays()
    assert _adapt(cfg, enabled=False).thin_empty_rays(model, rays, step=0) == (rays, None)
    from nepf_core.model import NePFModel
    fresh = NePFModel(cfg.model)                                # never refreshed: everything occupied
    on = _adapt(cfg)
    assert on.thin_empty_rays(fresh, rays, step=0) == (rays, None) and not named(on, "empty_rays")


def test_kept_misses_carry_importance_weights_and_the_mask_loss_stays_unbiased():
    from nepf_core.losses import mask_bce
    cfg, model, rays = _sphere_model_and_rays()
    a = _adapt(cfg, miss_keep=0.25)
    g = torch.Generator().manual_seed(7)
    ws = torch.rand(len(rays), generator=g)            # a fixed "rendered" opacity per drawn ray
    full = float(mask_bce(ws, rays.mask))               # mean over the whole drawn batch
    vals = []
    for s in range(400):
        kept, _ = a.thin_empty_rays(model, rays, step=s, generator=torch.Generator().manual_seed(100 + s))
        hit = kept.view < 24
        assert torch.equal(kept.weight[hit], torch.ones(int(hit.sum())))
        assert torch.allclose(kept.weight[~hit], torch.full((int((~hit).sum()),), 4.0))
        vals.append(float(mask_bce(ws[kept.view], kept.mask, kept.weight)))
    assert abs(sum(vals) / len(vals) - full) < 0.02 * full
    # hand value of the weighted mean: BCE(0.5, 1) = BCE(0.5, 0) = ln 2, BCE(0.9, 1) = -ln 0.9
    w = torch.tensor([0.5, 0.9]); m = torch.tensor([0.0, 1.0]); q = torch.tensor([3.0, 1.0])
    assert float(mask_bce(w, m, q)) == pytest.approx((3 * math.log(2) - math.log(0.9)) / 4, rel=1e-5)
    assert float(mask_bce(w, m)) == pytest.approx((math.log(2) - math.log(0.9)) / 2, rel=1e-5)


def test_eikonal_mean_weighs_each_sample_by_its_rays_importance_weight():
    """A ray kept with weight 3 counts like three copies of it, in the eikonal mean as in the
    mask loss, so thinning a batch does not turn the eikonal into a near-surface term."""
    from nepf_core.losses import compute_losses, needs_lobe_split, weighted_mean
    from nepf_core.render.renderer import SurfaceRequest, render_rays
    assert float(weighted_mean(torch.tensor([1.0, 2.0, 3.0]), torch.tensor([1.0, 1.0, 2.0]))) == pytest.approx(2.25)
    assert float(weighted_mean(torch.tensor([1.0, 2.0, 3.0]), None)) == pytest.approx(2.0)
    cfg, model, rays = _sphere_model_and_rays(n_hit=3, n_miss=3)
    with torch.no_grad():   # an SDF that is not eikonal-exact, so the residual is not 0
        for p in model.sdf.parameters():
            p.add_(0.05 * torch.randn(p.shape, generator=torch.Generator().manual_seed(3)))
    cfg.render.perturb = False
    cfg.render.eikonal_fraction = 0.0   # deterministic sample set: head samples only
    cfg.render.n_samples, cfg.render.n_importance = 48, 0
    reps = torch.tensor([1, 2, 1, 3, 1, 2])
    dup = rays.index(torch.repeat_interleave(torch.arange(6), reps))
    weighted = rays.index(torch.arange(6))
    weighted.weight = reps.float()

    def terms(batch):
        out = render_rays(model, batch, cfg.render, train=True,
                          request=SurfaceRequest(lobe_split=needs_lobe_split(cfg.loss)))
        L = compute_losses(out, batch, cfg.loss, use_mask=True)
        return {k: float(v.detach()) for k, v in L.items()}
    lw, ld, lu = terms(weighted), terms(dup), terms(rays.index(torch.arange(6)))
    assert ld["loss_eik"] > 1e-3
    assert lw["loss_eik"] == pytest.approx(ld["loss_eik"], rel=1e-4)
    assert lw["loss_mask"] == pytest.approx(ld["loss_mask"], rel=1e-4)
    assert abs(lu["loss_eik"] - ld["loss_eik"]) > 1e-4   # the weights matter here


def test_left_out_misses_train_the_background_as_if_rendered_whole():
    """With a background volume, the misses left out of the SDF batch are rendered by the
    background alone, and the colour losses over ``kept + left out`` equal those of rendering
    every drawn ray in full (a miss's SDF weights sum to ~0, so its colour is ``C_bg``); when
    there are more misses than SDF rays, a subset as large as the SDF batch stands for them with
    importance weights, and the losses are right in expectation. Without them, the background
    pixels would train only through the ``miss_keep`` share."""
    from nepf_core.losses import compute_losses, needs_lobe_split
    from nepf_core.model import NePFModel
    from nepf_core.render.renderer import SurfaceRequest, render_background_only, render_rays

    def setup(n_hit, n_miss):
        cfg, _, rays = _sphere_model_and_rays(n_hit=n_hit, n_miss=n_miss)
        cfg.model.background = True
        torch.manual_seed(0)
        model = NePFModel(cfg.model)
        model.occupancy.update(model.sdf.sdf, inv_s=1e4)
        cfg.render.perturb = False
        return cfg, model, rays, _adapt(cfg, miss_keep=0.0)

    def losses(cfg, model, batch, **kw):
        out = render_rays(model, batch, cfg.render, train=True,
                          request=SurfaceRequest(lobe_split=needs_lobe_split(cfg.loss)))
        return compute_losses(out, batch, cfg.loss, use_mask=False, background=True, **kw)

    cfg, model, rays, a = setup(24, 16)
    kept, left_out = a.thin_empty_rays(model, rays, step=0, generator=torch.Generator().manual_seed(1))
    assert len(kept) == 24 and len(left_out) == 16 and left_out.weight is None
    whole = losses(cfg, model, rays)
    split = losses(cfg, model, kept, background_rays=(render_background_only(model, left_out, cfg.render, train=True),
                                                      left_out))
    for k in ("loss_r", "loss_vol"):
        assert float(split[k].detach()) == pytest.approx(float(whole[k].detach()), rel=1e-4, abs=1e-6)
    only_kept = losses(cfg, model, kept)
    assert abs(float(only_kept["loss_r"].detach()) - float(whole["loss_r"].detach())) > 1e-3   # the misses matter
    # the left-out rays reach the background's parameters
    model.zero_grad()
    split["loss_r"].backward()
    g = sum(float(p.grad.abs().sum()) for p in model.background.parameters() if p.grad is not None)
    model.zero_grad()
    losses(cfg, model, kept)["loss_r"].backward()
    g_kept = sum(float(p.grad.abs().sum()) for p in model.background.parameters() if p.grad is not None)
    assert g > 2.0 * g_kept

    # more misses than SDF rays: 8 of the 24 stand for all of them, weight 3, unbiased on average
    cfg, model, rays, a = setup(8, 24)
    whole = float(losses(cfg, model, rays)["loss_r"].detach())
    with torch.no_grad():
        c_bg = render_background_only(model, rays, cfg.render, train=True)
        vals = []
        for s in range(300):
            kept, left_out = a.thin_empty_rays(model, rays, step=s, generator=torch.Generator().manual_seed(s))
            assert len(kept) == 8 and len(left_out) == 8 and torch.allclose(left_out.weight, torch.full((8,), 3.0))
            vals.append(float(losses(cfg, model, kept, background_rays=(c_bg[left_out.view], left_out))["loss_r"]))
    assert abs(sum(vals) / len(vals) - whole) < 0.02 * whole
    assert max(vals) - min(vals) > 1e-3     # the subsets differ


def test_surface_point_prior_is_the_mean_absolute_sdf_at_the_points():
    """Hand-worked on the fast SDF's initial sphere (r = 0.5, exact at start): points at radius
    0.7 and 0.4 give |f| = 0.2 and 0.1; drawn with replacement the mean lies between, and the
    gradient moves the zero level set towards both."""
    from nepf_core.model import NePFModel
    from nepf_core.train.surface_points import SurfacePointPrior
    model = NePFModel(fast().model)
    far = np.array([[0.7, 0.0, 0.0]] * 3)
    prior = SurfacePointPrior(far, "cpu", n_samples=8)
    assert float(prior.loss(model).detach()) == pytest.approx(0.2, abs=1e-4)
    mixed = SurfacePointPrior(np.array([[0.0, 0.7, 0.0], [0.0, 0.0, -0.4]]), "cpu", n_samples=4000)
    assert 0.1 - 1e-3 < float(mixed.loss(model, torch.Generator().manual_seed(0)).detach()) < 0.2 + 1e-3
    assert float(mixed.loss(model, torch.Generator().manual_seed(0)).detach()) == pytest.approx(0.15, abs=0.01)
    assert float(SurfacePointPrior(np.zeros((0, 3)), "cpu").loss(model)) == 0.0
