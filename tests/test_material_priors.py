"""The material priors of the fast preset (nepf_core.losses): the logit range term and the
unseen-lobe metallic term, by hand-worked values, and the renderer feeding them."""

import pytest
import torch

from nepf_core.losses import LossConfig, compute_losses, total_loss
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
    z = logits.clone().requires_grad_(True)
    rays = RayBatch(origins=torch.zeros(3, 3), directions=torch.ones(3, 3), rgb=torch.zeros(3, 3),
                    mask=torch.tensor([1.0, 1.0, 0.0]))
    cfg = _cfg(w_material_range=2.0)
    L = compute_losses(render_output(3, surface={"material_logits": z}), rays, cfg, use_mask=True)
    assert float(L["loss_material_range"].detach()) == pytest.approx((0.7 + 0.0) / 2)
    assert float(total_loss(L, cfg).detach()) == pytest.approx(2.0 * 0.35)
    total_loss(L, cfg).backward()
    g = z.grad
    # d/dz of 2 * mean_rays mean_k relu(|z| - 3): 2 / (2 rays * 5 channels) * sign(z) where over
    assert g[0, 1] == pytest.approx(0.2) and g[0, 3] == pytest.approx(0.2)
    assert g[0, 2] == 0 and g[1].abs().sum() == 0 and g[2].abs().sum() == 0


def test_metallic_unseen_by_hand():
    metallic = torch.tensor([0.8, 0.8, 0.5, 0.9]).requires_grad_(True)
    share = torch.tensor([0.0, 1.0, 0.5, 0.0])   # ray 3 is unlit: not counted
    rays = RayBatch(origins=torch.zeros(4, 3), directions=torch.ones(4, 3), rgb=torch.zeros(4, 3),
                    mask=torch.ones(4), unlit=torch.tensor([False, False, False, True]))
    cfg = _cfg(w_metallic_unseen=1.0)
    out = render_output(4, surface={"metallic": metallic}, lobe_share=share)
    L = compute_losses(out, rays, cfg, use_mask=True)
    # (0.8 * 1 + 0.8 * 0 + 0.5 * 0.5) / 3 lit rays
    assert float(L["loss_metallic_unseen"].detach()) == pytest.approx((0.8 + 0.25) / 3)
    total_loss(L, cfg).backward()
    assert torch.allclose(metallic.grad, torch.tensor([1 / 3, 0.0, 0.5 / 3, 0.0]))
    # where the metal record says metal the prior is lifted: m (1 - s) (1 - share)
    out.metal_share = torch.tensor([0.75, 0.0, 0.2, 1.0])
    L = compute_losses(out, rays, cfg, use_mask=True)
    assert float(L["loss_metallic_unseen"].detach()) == pytest.approx((0.8 * 0.25 + 0.25 * 0.8) / 3)
    # the term reads the render's lobe split: a render not asked for it is an error, not a silent 0
    with pytest.raises(ValueError, match="lobe_split"):
        compute_losses(render_output(4, surface={"metallic": metallic}), rays, cfg, use_mask=True)


def test_training_render_feeds_both_priors():
    """A training render returns the material logits at the surface point (sigmoid of them is
    the shaded material); asked for it, the lobe split of L_surf, which is L_surf's part above the
    same surface shaded without the lobe, ``s = max(0, sum_c (L_surf - L_d)) / sum_c L_surf``
    (recomputed here from the BSDF); an inference render returns no logits."""
    from nepf_core import bsdf
    from nepf_core.config import fast
    from nepf_core.model import NePFModel
    from nepf_core.render.renderer import SurfaceRequest, render_rays

    torch.manual_seed(0)
    cfg = fast()
    model = NePFModel(cfg.model)
    o = torch.tensor([[0.0, 0.0, -2.5]]).repeat(32, 1)
    d = torch.nn.functional.normalize(torch.tensor([[0.0, 0.0, 1.0]]) + 0.1 * torch.randn(32, 3), dim=-1)
    out = render_rays(model, RayBatch(o, d), cfg.render, train=True, request=SurfaceRequest(lobe_split=True))
    s = out.surface
    z = s.material_logits
    assert z.shape == (32, 5)
    assert torch.allclose(torch.sigmoid(z[:, :3]), s.albedo, atol=1e-6)
    assert torch.allclose(torch.sigmoid(z[:, 3]), s.roughness, atol=1e-6)
    assert torch.allclose(torch.sigmoid(z[:, 4]), s.metallic, atol=1e-6)
    with torch.no_grad():
        lit = bsdf.shade(s.normal, s.light_dir, -d, s.albedo, s.roughness[:, None], s.metallic[:, None],
                         s.intensity[:, None], specular=True, kind=cfg.render.bsdf_kind)
        diffuse = bsdf.shade(s.normal, s.light_dir, -d, s.albedo, s.roughness[:, None], s.metallic[:, None],
                             s.intensity[:, None], specular=False, kind=cfg.render.bsdf_kind)
    assert torch.allclose(out.rgb_surf, lit, atol=1e-6)          # L_surf is the full BSDF at the surface
    want = (lit.sum(-1) - diffuse.sum(-1)).clamp_min(0) / lit.sum(-1).clamp_min(1e-6)
    assert torch.allclose(out.lobe.share, want, atol=1e-6)
    assert torch.allclose(out.lobe.diffuse_only, diffuse, atol=1e-6)
    assert float(out.lobe.share.max()) > 0.0 and ((out.lobe.share >= 0) & (out.lobe.share <= 1)).all()
    # the lobe split is computed only when asked for
    assert render_rays(model, RayBatch(o, d), cfg.render, train=True).lobe is None
    with torch.no_grad():
        out = render_rays(model, RayBatch(o, d), cfg.render, train=False)
    assert out.surface.material_logits is None


def test_light_direction_terms_pull_directions_toward_the_normals_spread():
    """The paper's ``l4 |var n - var l|``: for one distant light (every ``l`` the same) and spread
    normals, its gradient spreads the directions (descent moves each ``l`` away from their mean),
    which tilts them toward the normals. ``fast`` drops the two direction terms and keeps the
    intensity one: no gradient on ``l``, the same on ``I`` as ``paper``."""
    from nepf_core.config import fast, paper
    from nepf_core.losses import light_variance_loss

    torch.manual_seed(0)
    x = torch.randn(64, 3) * 0.3
    n = torch.nn.functional.normalize(torch.randn(64, 3), dim=-1)
    l0 = torch.nn.functional.normalize(torch.tensor([[0.3, -0.5, 1.0]]), dim=-1) + 0.01 * torch.randn(64, 3)
    I0 = 4.0 + 0.1 * torch.randn(64)
    grads = {}
    for name, cfg in (("paper", paper().loss), ("fast", fast().loss)):
        l, I = l0.clone().requires_grad_(True), I0.clone().requires_grad_(True)
        light_variance_loss(x, n, l, I, cfg.lambda3, cfg.lambda4, cfg.lambda5).backward()
        grads[name] = (l.grad, I.grad)
    g_l, g_I = grads["paper"]
    # descent step -g moves every l away from the mean direction (var l < var n here)
    away = l0 - l0.mean(0, keepdim=True)
    assert float((-g_l * away).sum()) > 0
    assert torch.count_nonzero(grads["fast"][0]) == 0
    assert torch.allclose(grads["fast"][1], g_I) and float(g_I.abs().sum()) > 0
