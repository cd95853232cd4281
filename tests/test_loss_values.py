"""Every loss term of :func:`nepf_core.losses.compute_losses` by value, on three hand-worked rays.

Rays (linear values; the colour terms compare ``E(.)``, the sRGB encoding, written out below as the
scalar :func:`E`; mask = foreground):

    ray   mask  L_gt             L_r              L_surf           L_vol            w_max  sum w
    0     1     (.5, .5, .5)     (.7, .5, .5)     (.4, .5, .5)     (.5, .8, .5)     .75    .9
    1     1     (.1, .2, .3)     (.1, .2, .3)     (.1, .5, .3)     (.1, .2, .0)     .5     .5
    2     0     (0, 0, 0)        (.9, .9, .9)     (.2, .2, .2)     (.3, .3, .3)     .1     .2

Surface quantities at the max-weight point (ray 2 is background and must not count):

    ray   x            n          l              I
    0     (0, 0, 0)    (0, 0, 1)  (1, 0, 0)      1.0
    1     (.2, 0, 0)   (0, 1, 0)  (.6, .8, 0)    1.4
    2     (5, 5, 5)    (1, 0, 0)  (0, 0, -1)     9.0

Batch variances over rays 0, 1 (population, summed over channels): var x = .01, var I = .04,
var n = .25 + .25 = .5, var l = .04 + .16 = .2.

With ``E(.7) = .8543``, ``E(.5) = .7354``, ``E(.4) = .6652``, ``E(.2) = .4845``, ``E(.8) = .9063``,
``E(.3) = .5838``, ``E(.9) = .9547``: L_r = (.1189 + 0) / 6 = .01982, L_surf = (.25 * .1890 / 3
+ .5 * .2509 / 3) / 2 = .02878, L_vol = (.1709 + .5838) / 6 = .1258.
"""

from __future__ import annotations

import math

import pytest
import torch

from nepf_core.color import linear_to_srgb
from nepf_core.losses import LossConfig, compute_losses, light_variance_loss, total_loss
from nepf_core.rays import RayBatch
from nepf_core.render.renderer import RenderOutput
from nepf_core.render.surface import MaterialSample, Surface

T = lambda *v: torch.tensor(v, dtype=torch.float64)  # noqa: E731

GT = T([.5, .5, .5], [.1, .2, .3], [0., 0., 0.])
RGB_R = T([.7, .5, .5], [.1, .2, .3], [.9, .9, .9])
RGB_SURF = T([.4, .5, .5], [.1, .5, .3], [.2, .2, .2])
RGB_VOL = T([.5, .8, .5], [.1, .2, .0], [.3, .3, .3])
W_MAX = T(.75, .5, .1)
W_SUM = T(.9, .5, .2)
MASK = T(1., 1., 0.)



def E(v: float) -> float:
    """The sRGB encoding of one value in [0, 1] (IEC 61966-2-1)."""
    return 12.92 * v if v <= 0.0031308 else 1.055 * v ** (1 / 2.4) - 0.055


# hand-worked values (see the module docstring)
L_R = (abs(E(.7) - E(.5)) + 0.0) / (3 * 2)           # ray 0 only; 3 channels x 2 fg rays
L_SURF = (0.25 * abs(E(.4) - E(.7)) / 3 + 0.5 * abs(E(.5) - E(.2)) / 3) / 2   # (1 - w_max) mean_c |..|, 2 fg rays
L_VOL = (abs(E(.8) - E(.5)) + E(.3)) / (3 * 2)
L_LIGHT_PAPER = 1.0 * abs(.01 - .04) + 1.0 * abs(.5 - .2) + 0.1 * abs(.01 - .2)   # 0.349
L_MASK = -(math.log(.9) + math.log(.5) + math.log(1 - .2)) / 3


def val(t: torch.Tensor) -> float:
    return float(t.detach())


def _out(**over) -> RenderOutput:
    zeros = torch.zeros(3, dtype=torch.float64)
    surf = Surface(x=T([0., 0., 0.], [.2, 0., 0.], [5., 5., 5.]), normal=T([0., 0., 1.], [0., 1., 0.], [1., 0., 0.]),
                   direction=torch.zeros(3, 3, dtype=torch.float64),
                   light_dir=T([1., 0., 0.], [.6, .8, 0.], [0., 0., -1.]), intensity=T(1.0, 1.4, 9.0),
                   albedo=T([.2, .2, .2], [.4, .4, .4], [.9, .9, .9]), roughness=zeros, metallic=zeros,
                   jitter=MaterialSample(T([.5, .2, .2], [.4, .4, .4], [0., 0., 0.]), zeros, zeros))
    kw = dict(rgb_r=RGB_R.clone().requires_grad_(True), rgb_vol=RGB_VOL.clone(),
              rgb_surf=RGB_SURF.clone().requires_grad_(True), weight_sum=W_SUM.clone(),
              w_max=W_MAX.clone().requires_grad_(True), depth=torch.zeros(3, dtype=torch.float64),
              eikonal=T(0.1, 0.3), hessian=T(1.0, 2.0, 6.0), surface=surf)
    kw.update(over)
    return RenderOutput(**kw)


def _rays(**over) -> RayBatch:
    kw = dict(origins=torch.zeros(3, 3, dtype=torch.float64), directions=torch.zeros(3, 3, dtype=torch.float64),
              rgb=GT.clone(), mask=MASK.clone())
    kw.update(over)
    return RayBatch(**kw)


def _cfg(**over) -> LossConfig:
    return LossConfig(**over)


def test_color_terms_by_value():
    L = compute_losses(_out(), _rays(), _cfg(), use_mask=True)
    assert val(L["loss_r"]) == pytest.approx(L_R, abs=1e-12)
    assert val(L["loss_surf"]) == pytest.approx(L_SURF, abs=1e-12)   # 0.02878
    assert val(L["loss_vol"]) == pytest.approx(L_VOL, abs=1e-12)


def test_surf_loss_needs_the_one_minus_wmax_factor_and_the_radiance_target():
    """The paper's L_surf against its two near misses: without ``(1 - w_max)`` it would read
    (.1890 / 3 + .2509 / 3) / 2 = .0733; supervised by L_gt, (.25 |E(.4) - E(.5)| / 3
    + .5 * .2509 / 3) / 2 = .0238."""
    got = val(compute_losses(_out(), _rays(), _cfg(), use_mask=True)["loss_surf"])
    assert got == pytest.approx(0.02878, abs=1e-5)
    no_wmax = (abs(E(.4) - E(.7)) / 3 + abs(E(.5) - E(.2)) / 3) / 2
    gt_target = (0.25 * abs(E(.4) - E(.5)) / 3 + 0.5 * abs(E(.5) - E(.2)) / 3) / 2
    assert abs(got - no_wmax) > 1e-3 and abs(got - gt_target) > 1e-3


def test_surf_loss_gradient_stops_at_the_radiance_and_at_w_max():
    out = _out()
    L = compute_losses(out, _rays(), _cfg(w_r=0.0, lambda2_vol=0.0, w_eikonal=0.0, w_hessian=0.0, w_light=0.0,
                                          w_mask=0.0), use_mask=True)
    total_loss(L, cfg_surf_only := _cfg(w_r=0.0, lambda2_vol=0.0, w_eikonal=0.0, w_hessian=0.0, w_light=0.0,
                                         w_mask=0.0)).backward()
    assert out.rgb_r.grad is None or float(out.rgb_r.grad.abs().sum()) == 0.0
    assert out.w_max.grad is None or float(out.w_max.grad.abs().sum()) == 0.0
    # d/dL_surf of lambda1 (1 - w_max) mean_c |E(L_surf) - E(L_r)| / 2:
    # sign(err) * lambda1 (1 - w_max) E'(L_surf) / (3 * 2), E'(v) = 1.055 / 2.4 v^(1/2.4 - 1)
    lam = cfg_surf_only.lambda1_surf
    slope = lambda v: 1.055 / 2.4 * v ** (1 / 2.4 - 1)  # noqa: E731
    want = torch.zeros(3, 3, dtype=torch.float64)
    want[0, 0] = -lam * 0.25 / 6 * slope(0.4)    # 0.4 < 0.7
    want[1, 1] = lam * 0.5 / 6 * slope(0.5)      # 0.5 > 0.2
    assert torch.allclose(out.rgb_surf.grad, want, atol=1e-15)


def test_without_masks_surface_rays_are_those_with_weight_sum_above_half():
    L = compute_losses(_out(), _rays(mask=None), _cfg(), use_mask=True)
    assert val(L["loss_r"]) == pytest.approx((abs(E(.7) - E(.5)) + 0.0 + 3 * E(.9)) / 9, abs=1e-12)   # every ray
    assert val(L["loss_surf"]) == pytest.approx(0.25 * abs(E(.4) - E(.7)) / 3, abs=1e-12)   # ray 0 only (0.9 > 0.5)
    assert val(L["loss_mask"]) == 0.0


def test_colour_terms_compare_srgb_encoded_values():
    want = sum(abs(E(a) - E(b)) for a, b in zip(RGB_R[:2].flatten().tolist(), GT[:2].flatten().tolist())) / 6
    L = compute_losses(_out(), _rays(), LossConfig(), use_mask=True)
    assert val(L["loss_r"]) == pytest.approx(want, abs=1e-12)
    assert abs(val(L["loss_r"]) - 0.2 / 6) > 1e-3    # not the linear difference
    assert torch.allclose(linear_to_srgb(T(0.5)), T(E(0.5)))


def test_eikonal_hessian_mask_by_value():
    L = compute_losses(_out(), _rays(), _cfg(), use_mask=True)
    assert val(L["loss_eik"]) == pytest.approx(0.2, abs=1e-12)
    assert val(L["loss_hess"]) == pytest.approx(3.0, abs=1e-12)
    assert val(L["loss_mask"]) == pytest.approx(L_MASK, abs=1e-12)
    # importance-weighted eikonal: (1 * 0.1 + 3 * 0.3) / 4
    L = compute_losses(_out(eikonal_weight=T(1.0, 3.0)), _rays(), _cfg(), use_mask=True)
    assert val(L["loss_eik"]) == pytest.approx(0.25, abs=1e-12)
    # weight sums clipped to [1e-3, 1 - 1e-3] before the BCE: finite at exactly 1 and 0
    L = compute_losses(_out(weight_sum=T(1.0, 1.0, 0.0)), _rays(), _cfg(), use_mask=True)
    assert val(L["loss_mask"]) == pytest.approx(-math.log(1 - 1e-3), abs=1e-12)


def test_light_variance_by_value_with_the_papers_lambdas():
    L = compute_losses(_out(), _rays(), _cfg(), use_mask=True)
    assert val(L["loss_light"]) == pytest.approx(L_LIGHT_PAPER, abs=1e-12)   # 0.349
    swapped = 0.1 * abs(.01 - .04) + 1.0 * abs(.5 - .2) + 1.0 * abs(.01 - .2)  # 0.493 (l3 <-> l5)
    assert abs(val(L["loss_light"]) - swapped) > 0.1


def test_light_variance_each_lambda_weighs_its_own_pair():
    """l3 = 1, l4 = 10, l5 = 100: 1 * |.01 - .04| + 10 * |.5 - .2| + 100 * |.01 - .2| = 22.03."""
    s = _out().surface
    keep = slice(0, 2)
    got = light_variance_loss(s.x[keep], s.normal[keep], s.light_dir[keep], s.intensity[keep], 1.0, 10.0, 100.0)
    assert val(got) == pytest.approx(0.03 + 3.0 + 19.0, abs=1e-12)


def test_albedo_priors_by_value():
    # smoothness: ray 0 differs by (0.3, 0, 0) -> 0.1; ray 1 by 0; ray 2 is background
    L = compute_losses(_out(), _rays(), _cfg(w_albedo_smooth=1.0), use_mask=True)
    assert val(L["loss_albedo_smooth"]) == pytest.approx(0.05, abs=1e-12)
    # flatness (lobe off): luminance 0.2 and 0.4 around their mean 0.3 -> |2/3 - 1| = |4/3 - 1| = 1/3
    L = compute_losses(_out(), _rays(), _cfg(w_albedo_flat=1.0), use_mask=True, specular=False)
    assert val(L["loss_albedo_flat"]) == pytest.approx(1 / 3, abs=1e-12)
    L = compute_losses(_out(), _rays(), _cfg(w_albedo_flat=1.0), use_mask=True, specular=True)
    assert val(L["loss_albedo_flat"]) == 0.0


def test_normal_smoothness_by_value():
    """``mean_fg |n(x* + e) + n(x* - e) - 2 n(x*)|`` with the surface normals of ``_out``
    ((0, 0, 1), (0, 1, 0), background): ray 0 keeps (0, 0, 1) on one side and turns to (0, .6, .8)
    on the other -> |(0, .6, -.2)| = sqrt(.4); ray 1 turns the same way on both sides (a constant
    curvature, (0, .8, .6) and (0, .8, -.6)) -> |(0, -.4, 0)| = .4; ray 2 is background and must not
    count."""
    zeros = torch.zeros(3, dtype=torch.float64)
    jitter = MaterialSample(T([.5, .2, .2], [.4, .4, .4], [0., 0., 0.]), zeros, zeros,
                            normal=T([0., 0., 1.], [0., .8, .6], [0., 0., -1.]),
                            normal_mirror=T([0., .6, .8], [0., .8, -.6], [0., 0., 1.]))
    out = _out()
    out.surface.jitter = jitter
    L = compute_losses(out, _rays(), _cfg(w_normal_smooth=1.0), use_mask=True)
    assert val(L["loss_normal_smooth"]) == pytest.approx((math.sqrt(0.4) + 0.4) / 2, abs=1e-12)
    # a render whose jittered points carry no normal (not asked for) has no such term
    assert "loss_normal_smooth" not in compute_losses(_out(), _rays(), _cfg(w_normal_smooth=1.0), use_mask=True)


def test_total_is_each_term_times_its_own_weight():
    cfg = _cfg(w_r=1.0, lambda1_surf=0.5, lambda2_vol=0.25, w_eikonal=0.125, w_hessian=0.0625, w_light=2.0,
               w_mask=4.0)
    L = compute_losses(_out(), _rays(), cfg, use_mask=True)
    assert "loss" not in L
    want = (L_R + 0.5 * L_SURF + 0.25 * L_VOL + 0.125 * 0.2 + 0.0625 * 3.0 + 2.0 * L_LIGHT_PAPER
            + 4.0 * L_MASK)
    assert val(total_loss(L, cfg)) == pytest.approx(want, abs=1e-12)


def test_a_zero_weight_switches_its_term_off():
    cfg = _cfg(w_r=0.0, lambda1_surf=0.0, lambda2_vol=0.0, w_eikonal=0.0, w_hessian=0.0, w_light=0.0, w_mask=0.0)
    L = compute_losses(_out(), _rays(), cfg, use_mask=True)
    assert all(val(v) == 0.0 for v in L.values())


def test_the_normal_prior_asks_the_render_for_the_jittered_normals_only_when_weighted():
    """The renderer computes the jittered points' stencils only when a weighted term reads them."""
    from nepf_core.config import fast
    from nepf_core.losses import needs_jitter_normals
    cfg = fast()
    assert cfg.loss.w_normal_smooth > 0 and needs_jitter_normals(cfg.loss)
    cfg.loss.w_normal_smooth = 0.0
    assert not needs_jitter_normals(cfg.loss)
