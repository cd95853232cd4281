"""The material priors of the fast preset (nepf_core.losses): the logit range term and the
unseen-lobe metallic term, by hand-worked values, the renderer feeding them, and the
per-region evidence behind the unseen-lobe term (nepf_core.train.metal_evidence)."""

import pytest
import torch

from nepf_core.losses import LossConfig, compute_losses
from nepf_core.rays import RayBatch

from loss_fixtures import render_output


def _cfg(**kw):
    base = dict(w_r=0, lambda1_surf=0, lambda2_vol=0, w_eikonal=0, w_hessian=0, w_light=0, w_mask=0)
    base.update(kw)
    return LossConfig(**base)


def test_material_range_by_hand():
    logits = torch.tensor([[0.0, 4.0, -2.5, 5.5, 0.0],     # over by 1 and 2.5: mean 3.5 / 5 = 0.7
                           [2.5, -2.9, 2.9, 0.0, 0.0],      # within: 0
                           [10.0, 0.0, 0.0, 0.0, 0.0]])     # a ray off the surface: not counted
    surf = {"material_logits": logits.clone().requires_grad_(True)}
    rays = RayBatch(origins=torch.zeros(3, 3), directions=torch.ones(3, 3), rgb=torch.zeros(3, 3),
                    mask=torch.tensor([1.0, 1.0, 0.0]))
    L = compute_losses(render_output(3, surf=surf), rays, _cfg(w_material_range=2.0), use_mask=True)
    assert float(L["loss_material_range"].detach()) == pytest.approx((0.7 + 0.0) / 2)
    assert float(L["loss"].detach()) == pytest.approx(2.0 * 0.35)
    L["loss"].backward()
    g = surf["material_logits"].grad
    # d/dz of 2 * mean_rays mean_k relu(|z| - 3): 2 / (2 rays * 5 channels) * sign(z) where over
    assert g[0, 1] == pytest.approx(0.2) and g[0, 3] == pytest.approx(0.2)
    assert g[0, 2] == 0 and g[1].abs().sum() == 0 and g[2].abs().sum() == 0


def test_metallic_unseen_by_hand():
    metallic = torch.tensor([0.8, 0.8, 0.5, 0.9]).requires_grad_(True)
    evidence = torch.tensor([0.0, 1.0, 0.5, 0.0])   # ray 3 is unlit: not counted
    surf = {"metallic": metallic, "metal_evidence": evidence}
    rays = RayBatch(origins=torch.zeros(4, 3), directions=torch.ones(4, 3), rgb=torch.zeros(4, 3),
                    mask=torch.ones(4), unlit=torch.tensor([False, False, False, True]))
    L = compute_losses(render_output(4, surf=surf), rays, _cfg(w_metallic_unseen=1.0), use_mask=True)
    # (0.8 * 1 + 0.8 * 0 + 0.5 * 0.5) / 3 lit rays
    assert float(L["loss_metallic_unseen"].detach()) == pytest.approx((0.8 + 0.25) / 3)
    L["loss"].backward()
    assert torch.allclose(metallic.grad, torch.tensor([1 / 3, 0.0, 0.5 / 3, 0.0]))


def test_training_render_feeds_both_priors():
    """A training render returns the material logits at the surface point (sigmoid of them is
    the shaded material) and L_surf split into its lobe and the rest; an inference render
    returns no logits."""
    from nepf_core.config import fast
    from nepf_core.model import NePFModel
    from nepf_core.render.renderer import render_rays

    torch.manual_seed(0)
    cfg = fast()
    model = NePFModel(cfg.model)
    o = torch.tensor([[0.0, 0.0, -2.5]]).repeat(32, 1)
    d = torch.nn.functional.normalize(torch.tensor([[0.0, 0.0, 1.0]]) + 0.1 * torch.randn(32, 3), dim=-1)
    out = render_rays(model, RayBatch(o, d), cfg.render, train=True, need_metal_hypothesis=True)
    s = out.surf
    z = s["material_logits"]
    assert z.shape == (32, 5)
    assert torch.allclose(torch.sigmoid(z[:, :3]), s["albedo"], atol=1e-6)
    assert torch.allclose(torch.sigmoid(z[:, 3]), s["roughness"], atol=1e-6)
    assert torch.allclose(torch.sigmoid(z[:, 4]), s["metallic"], atol=1e-6)
    # the shading is linear in the (1 - m) diffuse and the F0 = lerp(0.04, albedo, m) lobe, so the
    # render at metallic 0 (diffuse + a 0.04 lobe) minus the diffuse alone is a 0.04-lobe that,
    # with a white albedo, is 0.04 of the metal's lobe; here: every term non-negative and the
    # metal hypothesis has no diffuse (its colour is zero where the lobe is)
    assert (s["dielectric_diffuse_rgb"] >= 0).all() and (s["metal_lobe_rgb"] >= 0).all()
    m1 = torch.ones_like(s["metallic"])[:, None]
    from nepf_core import bsdf
    want = bsdf.shade(s["normal"], s["light_dir"], -d, s["albedo"], s["roughness"][:, None], m1,
                      s["intensity"][:, None], lambertian=cfg.render.lambertian, kind=cfg.render.bsdf_kind)
    assert torch.allclose(s["metal_lobe_rgb"], want)
    want = bsdf.shade(s["normal"], s["light_dir"], -d, s["albedo"], s["roughness"][:, None], 0 * m1,
                      s["intensity"][:, None], lambertian=cfg.render.lambertian, specular=False, kind=cfg.render.bsdf_kind)
    assert torch.allclose(s["dielectric_diffuse_rgb"], want)
    # the lobe rule's statistics keep their own cadence: only on renders that ask for them
    assert "specular" not in s and "diffuse_only" not in s
    out = render_rays(model, RayBatch(o, d), cfg.render, train=True, need_surface_extras=True, need_metal_hypothesis=True)
    assert "specular" in out.surf and "metal_lobe_rgb" in out.surf
    with torch.no_grad():
        out = render_rays(model, RayBatch(o, d), cfg.render, train=False)
    assert "material_logits" not in out.surf


def test_lobe_confirmation_by_hand():
    from nepf_core.train.metal_evidence import lobe_confirmation
    metal = torch.tensor([[0.6, 0.6, 0.6],      # a metal's highlight, the pixel holds all of it
                          [0.6, 0.6, 0.6],      # the same lobe, the pixel holds only a dielectric's 0.04 / 0.6 of it
                          [0.3, 0.3, 0.3],      # the pixel brighter still than diffuse + lobe: rho clips to 1
                          [0.0, 0.0, 0.0],      # no lobe: no evidence, whatever the pixel
                          [0.2, 0.2, 0.2]])     # the pixel darker than the diffuse: rho clips to 0
    diffuse = torch.tensor([[0.2, 0.2, 0.2], [0.2, 0.2, 0.2], [0.1, 0.1, 0.1], [0.5, 0.5, 0.5], [0.3, 0.3, 0.3]])
    target = torch.tensor([[0.8, 0.8, 0.8], [0.24, 0.24, 0.24], [0.9, 0.9, 0.9], [0.9, 0.9, 0.9], [0.1, 0.1, 0.1]])
    e = lobe_confirmation(metal, diffuse, target)
    # q = 0.6 / 0.8, rho = 1; q = 0.75, rho = 0.04 / 0.6; q = 0.3 / 0.4, rho = 1; 0; q = 0.4, rho = 0
    want = torch.tensor([0.75, 0.75 * 0.04 / 0.6, 0.75, 0.0, 0.0])
    assert torch.allclose(e, want, atol=1e-6)
    # a colour-weighted projection: a gold lobe, the pixel holds half of it in every channel
    gold = torch.tensor([[0.9, 0.6, 0.2]])
    e = lobe_confirmation(gold, torch.zeros(1, 3), 0.5 * gold)
    assert float(e) == pytest.approx(1.0 * 0.5)


def test_metal_evidence_grid_keeps_a_decaying_maximum():
    from nepf_core.train.metal_evidence import MetalEvidence
    ev = MetalEvidence(resolution=4, bound=1.0, half_life_steps=2.0)   # cells of side 0.5
    a, b = torch.tensor([[0.1, 0.1, 0.1]]), torch.tensor([[-0.9, 0.6, 0.3]])
    assert int(ev.cells(a)) == (2 * 4 + 2) * 4 + 2 and int(ev.cells(b)) == (0 * 4 + 3) * 4 + 2
    assert int(ev.cells(torch.tensor([[5.0, -5.0, 0.0]]))) == (3 * 4 + 0) * 4 + 2   # outside: the border cell
    x = torch.cat([a, a + 0.05, b])                     # two points in a's cell, one in b's
    ev.observe(x, torch.tensor([0.4, 0.8, 0.3]), keep=torch.tensor([True, True, False]))
    assert torch.allclose(ev.lookup(x), torch.tensor([0.8, 0.8, 0.0]))   # the maximum; b was not kept
    ev.observe(x, torch.tensor([0.1, 0.1, 0.1]), keep=torch.tensor([True, False, False]))
    assert float(ev.lookup(a)) == pytest.approx(0.8 * 0.5 ** 0.5)      # one step of a 2-step half-life
    ev.observe(x, torch.zeros(3), keep=torch.zeros(3, dtype=torch.bool))
    assert float(ev.lookup(a)) == pytest.approx(0.4)                    # two steps: half
    fresh = MetalEvidence(resolution=4, bound=1.0, half_life_steps=2.0)
    fresh.load_state_dict(ev.state_dict())
    assert torch.equal(fresh.grid, ev.grid)
    with pytest.raises(ValueError, match="8\\^3 here"):
        MetalEvidence(resolution=8).load_state_dict(ev.state_dict())


def test_evidence_lifts_the_prior_in_a_confirmed_region_only():
    """A region where one view's pixel confirms the metal's highlight keeps its metallic in every
    other view; a region whose lobe no pixel confirms gets the full prior."""
    from nepf_core.train.metal_evidence import MetalEvidence, lobe_confirmation
    ev = MetalEvidence(resolution=8)
    metal_x, dark_x = torch.tensor([[0.5, 0.5, 0.5]]), torch.tensor([[-0.5, -0.5, -0.5]])
    # highlight view of both, albedo (0.9, 0.7, 0.3) under both hypotheses: the metal's pixel holds
    # a metal's lobe; the other pixel a dielectric's (0.04 / albedo of it) over its diffuse
    lobe, diffuse = torch.tensor([[0.9, 0.7, 0.3]]), torch.tensor([[0.01, 0.008, 0.003]])
    e_metal = lobe_confirmation(lobe, diffuse, lobe)
    e_dark = lobe_confirmation(lobe, diffuse, diffuse + 0.04 * torch.ones(1, 3))   # a white 0.04 highlight
    ev.observe(torch.cat([metal_x, dark_x]), torch.cat([e_metal, e_dark]), torch.tensor([True, True]))
    # a later view of both regions away from the highlight: the per-ray share would be 0 in both
    metallic = torch.tensor([0.9, 0.9]).requires_grad_(True)
    surf = {"metallic": metallic, "metal_evidence": ev.lookup(torch.cat([metal_x, dark_x]))}
    rays = RayBatch(origins=torch.zeros(2, 3), directions=torch.ones(2, 3), rgb=torch.zeros(2, 3), mask=torch.ones(2))
    L = compute_losses(render_output(2, surf=surf), rays, _cfg(w_metallic_unseen=1.0), use_mask=True)
    L["loss"].backward()
    g = metallic.grad
    # e_metal = q rho = (1.9 / 1.921) (1 - <d, l> / <l, l>) = 0.978; e_dark = q 0.04 * 1.9 / 1.39 = 0.054
    assert float(g[0]) == pytest.approx((1 - 1.9 / 1.921 * (1 - 0.0155 / 1.39)) / 2, rel=1e-3)
    assert float(g[1]) == pytest.approx((1 - 1.9 / 1.921 * 0.04 * 1.9 / 1.39) / 2, rel=1e-3)
