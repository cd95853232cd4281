"""The two albedo priors of the fast preset (docs/FAST.md, "Albedo in unlit regions").

* unlit pixels carry no albedo information: on rays flagged ``unlit`` the colour error of
  L_vol / L_surf must not reach the albedo, while it still reaches roughness, metallic and
  the photon field; on lit rays it reaches the albedo;
* the albedo smoothness prior ``mean |c(x*) - c(x* + eps)|`` over surface rays.
"""

from __future__ import annotations

import numpy as np
import torch

from nepf_core.config import tiny
from nepf_core.losses import LossConfig, compute_losses, total_loss
from nepf_core.model import NePFModel
from nepf_core.rays import RayBatch, unlit_threshold
from nepf_core.render.renderer import RenderOutput, render_rays
from nepf_core.render.surface import MaterialSample, Surface


def test_unlit_threshold_is_relative_to_the_foreground_99th_percentile():
    # 100 foreground pixels with max channel 0.00, 0.01, ..., 0.99; background pixels at 5.0
    vals = np.arange(100) / 100.0
    img = np.zeros((1, 10, 20, 3))
    img[0, :, :10, 1] = vals.reshape(10, 10)      # the max channel is G
    img[0, :, 10:, :] = 5.0
    mask = np.zeros((1, 10, 20))
    mask[0, :, :10] = 1.0
    q99 = np.quantile(vals, 0.99)                 # 0.9801 (linear interpolation between 0.98 and 0.99)
    assert abs(q99 - 0.9801) < 1e-12
    assert abs(unlit_threshold(img, mask, 0.01) - 0.01 * 0.9801) < 1e-12
    # without masks every pixel counts: 99th percentile of 100 values in [0, 0.99] and 100 fives = 5
    assert abs(unlit_threshold(img, None, 0.01) - 0.05) < 1e-12
    # a uniformly dark capture (values / 100) gets a threshold 100x lower, not zero lit pixels
    assert abs(unlit_threshold(img / 100.0, mask, 0.01) - 0.01 * 0.009801) < 1e-12


def _model_and_rays(unlit: bool):
    torch.manual_seed(0)
    cfg = tiny()
    cfg.render.unlit_albedo_stopgrad = True
    model = NePFModel(cfg.model)
    R = 64
    g = torch.Generator().manual_seed(1)
    o = torch.tensor([0.0, 0.0, -2.5]).expand(R, 3) + 0.05 * torch.randn(R, 3, generator=g)
    d = torch.nn.functional.normalize(torch.tensor([0.0, 0.0, 1.0]) + 0.05 * torch.randn(R, 3, generator=g), dim=-1)
    rays = RayBatch(o, d, rgb=torch.full((R, 3), 0.5), mask=torch.ones(R),
                    unlit=torch.full((R,), unlit, dtype=torch.bool))
    return cfg, model, rays


def _albedo_and_roughness_grads(unlit: bool):
    cfg, model, rays = _model_and_rays(unlit)
    out = render_rays(model, rays, cfg.render, train=True)
    assert float(out.weight_sum.detach().mean()) > 0.5   # the rays hit the init sphere
    lc = LossConfig(w_r=0.0, w_eikonal=0.0, w_hessian=0.0, w_light=0.0, w_mask=0.0)
    loss = total_loss(compute_losses(out, rays, lc, use_mask=True), lc)
    loss.backward()
    bias_grad = model.material.mlp.layers[-1].bias.grad
    return bias_grad[:3].abs().sum().item(), bias_grad[3:].abs().sum().item(), \
        sum(p.grad.abs().sum().item() for p in model.photon.parameters() if p.grad is not None)


def test_unlit_rays_do_not_train_the_albedo_but_still_train_the_rest():
    albedo_g, rm_g, photon_g = _albedo_and_roughness_grads(unlit=True)
    assert albedo_g == 0.0
    assert rm_g > 0.0 and photon_g > 0.0


def test_lit_rays_train_the_albedo():
    albedo_g, rm_g, photon_g = _albedo_and_roughness_grads(unlit=False)
    assert albedo_g > 0.0 and rm_g > 0.0 and photon_g > 0.0


def _surface_output(R: int, albedo_jitter=None, **surf) -> RenderOutput:
    """A RenderOutput of ``R`` opaque rays whose surface values are zero except ``surf`` (and the
    jittered albedo ``albedo_jitter``)."""
    z3, z1 = torch.zeros(R, 3), torch.zeros(R)
    base = dict(albedo=z3, x=z3, normal=z3, direction=z3, light_dir=z3, intensity=z1, roughness=z1, metallic=z1)
    jitter = None if albedo_jitter is None else MaterialSample(albedo_jitter, z1, z1)
    return RenderOutput(rgb_r=z3, rgb_vol=z3, rgb_surf=z3, weight_sum=torch.ones(R), w_max=z1, depth=z1,
                        eikonal=torch.zeros(0), hessian=torch.zeros(0), surface=Surface(**{**base, **surf}, jitter=jitter))


def _prior_only(**weights) -> LossConfig:
    """Every colour and regulariser term off except the given prior weights."""
    return LossConfig(w_r=0.0, lambda1_surf=0.0, lambda2_vol=0.0, w_eikonal=0.0, w_hessian=0.0, w_light=0.0,
                      w_mask=0.0, **weights)


def test_albedo_smoothness_loss_hand_value_and_renderer_output():
    R = 4
    albedo = torch.tensor([[0.2, 0.4, 0.6], [0.5, 0.5, 0.5], [0.0, 0.0, 0.0], [1.0, 1.0, 1.0]])
    jitter = torch.tensor([[0.3, 0.4, 0.3], [0.5, 0.5, 0.5], [0.9, 0.9, 0.9], [0.0, 0.0, 0.0]])
    out = _surface_output(R, albedo=albedo, albedo_jitter=jitter)
    mask = torch.tensor([1.0, 1.0, 1.0, 0.0])    # the last ray is background: not counted
    rays = RayBatch(torch.zeros(R, 3), torch.zeros(R, 3), rgb=torch.zeros(R, 3), mask=mask)
    lc = _prior_only(w_albedo_smooth=2.0)
    L = compute_losses(out, rays, lc, use_mask=True)
    # per-ray mean |diff|: (0.1 + 0 + 0.3) / 3, 0, 0.9 -> mean over the 3 foreground rays
    expected = ((0.4 / 3) + 0.0 + 0.9) / 3
    assert abs(L["loss_albedo_smooth"].item() - expected) < 1e-6
    assert abs(total_loss(L, lc).item() - 2.0 * expected) < 1e-6

    cfg, model, rays = _model_and_rays(unlit=False)
    cfg.render.albedo_smooth_sigma = 0.02
    out = render_rays(model, rays, cfg.render, train=True)
    assert out.surface.jitter.albedo.shape == (len(rays), 3)
    assert not torch.equal(out.surface.jitter.albedo, out.surface.albedo)
    assert render_rays(model, rays, cfg.render, train=False).surface.jitter is None


def test_albedo_flat_pulls_lit_luminance_toward_the_batch_mean_only_without_the_lobe():
    """Hand-worked: lit surface rays 0, 1, 3 have albedo luminance 0.4, 0.6, 0.8 (mean 0.6), so
    ``L_flat = (|0.4/0.6 - 1| + 0 + |0.8/0.6 - 1|) / 3 = 2/9``; the unlit ray 2 and the background
    ray 4 take no part; with the lobe on the term is 0."""
    R = 5
    albedo = torch.tensor([[0.2, 0.4, 0.6], [0.5, 0.6, 0.7], [0.0, 0.0, 0.0], [0.8, 0.8, 0.8], [0.1, 0.1, 0.1]],
                          requires_grad=True)
    out = _surface_output(R, albedo=albedo)
    rays = RayBatch(torch.zeros(R, 3), torch.zeros(R, 3), rgb=torch.zeros(R, 3),
                    mask=torch.tensor([1.0, 1.0, 1.0, 1.0, 0.0]), unlit=torch.tensor([False, False, True, False, False]))
    lc = _prior_only(w_albedo_flat=2.0)
    assert total_loss(compute_losses(out, rays, lc, use_mask=True), lc).item() == 0.0   # lobe on
    L = compute_losses(out, rays, lc, use_mask=True, specular=False)
    assert abs(L["loss_albedo_flat"].item() - 2.0 / 9.0) < 1e-6
    assert abs(total_loss(L, lc).item() - 4.0 / 9.0) < 1e-6
    total_loss(L, lc).backward()
    g = albedo.grad
    assert torch.all(g[0] < 0) and torch.all(g[3] > 0)         # the dark one brightens, the bright one darkens
    assert torch.all(g[1] == 0) and torch.all(g[2] == 0) and torch.all(g[4] == 0)
    # equal luminance, any colours: nothing to flatten (chroma is left to the images)
    out.surface.albedo = torch.tensor([[0.9, 0.6, 0.3]] * 2 + [[0.6, 0.6, 0.6]] * 3)
    assert compute_losses(out, rays, lc, use_mask=True, specular=False)["loss_albedo_flat"].item() < 1e-7


def test_diffuse_only_shading_sees_only_albedo_times_intensity():
    """Why the albedo flatness prior exists: without the lobe, (c s, I / s) renders the same
    colour for any s > 0, so the images cannot say which of the two carries a pattern; with
    the lobe (F0 = 0.04 at metallic 0) they can."""
    from nepf_core import bsdf
    g = torch.Generator().manual_seed(0)
    N = 64
    n = torch.nn.functional.normalize(torch.randn(N, 3, generator=g), dim=-1)
    l = torch.nn.functional.normalize(n + 0.6 * torch.randn(N, 3, generator=g), dim=-1)
    v = torch.nn.functional.normalize(n + 0.6 * torch.randn(N, 3, generator=g), dim=-1)
    c = 0.1 + 0.4 * torch.rand(N, 3, generator=g)
    rough, metal = torch.full((N, 1), 0.3), torch.zeros(N, 1)
    inten = 1.0 + torch.rand(N, 1, generator=g)
    s = 0.5 + torch.rand(N, 1, generator=g)
    lit = ((n * l).sum(-1) > 0.05) & ((n * v).sum(-1) > 0.05)
    assert lit.sum() > 10
    for spec, same in ((False, True), (True, False)):
        a = bsdf.shade(n, l, v, c, rough, metal, inten, specular=spec)[lit]
        b = bsdf.shade(n, l, v, c * s, rough, metal, inten / s, specular=spec)[lit]
        assert torch.allclose(a, b, rtol=1e-5, atol=1e-7) == same
