"""The background volume outside the unit sphere (nepf_core.fields.background) and the rule that
turns it on (nepf_core.train.rules.masks): hand-worked values and invariants."""

import math

import numpy as np
import pytest
import torch

from nepf_core.fields.background import BackgroundConfig, BackgroundVolume, contract, sphere_exit
from nepf_core.losses import LossConfig, compute_losses, total_loss
from nepf_core.train.rules.masks import decide_masks, lit_outside_masks

from loss_fixtures import render_output


def test_contract_by_hand():
    x = torch.tensor([[0.5, 0.0, 0.0], [0.0, 2.0, 0.0], [0.0, 0.0, -4.0], [3.0, 4.0, 0.0]])
    c = contract(x)
    # inside: unchanged; |x| = 2 -> 1.5, |x| = 4 -> 1.75, |x| = 5 -> 1.8 along x / |x|
    want = torch.tensor([[0.5, 0.0, 0.0], [0.0, 1.5, 0.0], [0.0, 0.0, -1.75], [1.8 * 0.6, 1.8 * 0.8, 0.0]])
    assert torch.allclose(c, want, atol=1e-6)
    far = contract(torch.tensor([[1e6, 0.0, 0.0]]))
    assert float(far.norm()) < 2.0


def test_sphere_exit_by_hand():
    o = torch.tensor([[0.0, 0.0, -3.0], [0.0, 0.6, -3.0], [0.0, 2.0, -3.0], [0.0, 0.0, 0.0]])
    d = torch.tensor([[0.0, 0.0, 1.0]]).expand(4, 3)
    t = sphere_exit(o, d)
    # through the centre: leaves at z = 1 (t = 4); offset 0.6: z = 0.8 (t = 3.8); a miss: closest
    # approach at z = 0 (t = 3); from the centre: t = 1
    assert torch.allclose(t, torch.tensor([4.0, 3.8, 3.0, 1.0]), atol=1e-5)


def test_samples_lie_outside_the_sphere_and_are_sorted():
    bg = BackgroundVolume(BackgroundConfig(n_samples=16))
    o = torch.randn(64, 3)
    o = 3.0 * o / o.norm(dim=-1, keepdim=True)
    d = torch.nn.functional.normalize(-o + 0.5 * torch.randn(64, 3), dim=-1)
    for perturb in (False, True):
        t = bg.sample_distances(sphere_exit(o, d), perturb=perturb)
        assert (t[:, 1:] >= t[:, :-1]).all()
        x = o[:, None] + t[..., None] * d[:, None]
        hit = torch.linalg.vector_norm(o + ((-o * d).sum(-1, keepdim=True)) * d, dim=-1) < 1.0
        assert (x[hit].norm(dim=-1) >= 1.0 - 1e-4).all()
        assert float(t.max()) <= bg.cfg.far * 1.0001


def test_constant_colour_comes_back_exactly_and_the_volume_is_opaque():
    """Whatever the densities, the weights sum to 1 (the last sample is opaque), so a constant
    colour comes back unchanged."""
    torch.manual_seed(0)
    bg = BackgroundVolume(BackgroundConfig(n_samples=8, resolutions=(4, 8), n_levels=2))
    with torch.no_grad():
        last = bg.color.layers[-1]
        last.weight.zero_()
        last.bias.copy_(torch.tensor([0.0, math.log(3.0), -math.log(3.0)]))  # sigmoid -> 0.5, 0.75, 0.25
    o = torch.tensor([[0.0, 0.0, -3.0], [0.5, 0.2, -3.0]])
    d = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    rgb = bg(o, d)
    assert torch.allclose(rgb, torch.tensor([[0.5, 0.75, 0.25]]).expand(2, 3), atol=1e-5)


def test_lit_outside_masks_and_the_decision():
    img = np.zeros((4, 4, 3), np.float32)
    mask = np.zeros((4, 4), bool)
    mask[:2] = True                      # 8 pixels inside, 8 outside
    img[2, :3] = 0.5                     # 3 of the 8 outside pixels are lit
    img[0, 0] = 1.0                      # inside the mask: not counted
    assert lit_outside_masks([img], [mask]) == pytest.approx(3 / 8)
    use, bg, _ = decide_masks(True, 0.1, 3 / 8)
    assert use and bg
    use, bg, _ = decide_masks(True, 0.1, 0.0)       # black outside the masks (synthetic scenes)
    assert use and not bg
    use, bg, _ = decide_masks(False, 0.1)
    assert not use and bg


def test_background_loss_by_hand():
    """L_bg is the sRGB L1 over the rays outside the masks alone; the foreground L_r is unchanged."""
    from nepf_core.rays import RayBatch
    gt = torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [0.0, 0.0, 0.0], [1.0, 1.0, 1.0]])
    pred = torch.tensor([[1.0, 1.0, 1.0], [1.0, 1.0, 1.0], [0.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    mask = torch.tensor([1.0, 1.0, 0.0, 0.0])
    rays = RayBatch(origins=torch.zeros(4, 3), directions=torch.ones(4, 3), rgb=gt, mask=mask)
    cfg = LossConfig(lambda1_surf=0, lambda2_vol=0, w_eikonal=0, w_hessian=0, w_light=0, w_mask=0)
    L = compute_losses(render_output(4, rgb=pred), rays, cfg, use_mask=True, background=True)
    assert float(L["loss_r"]) == pytest.approx(3 / 6)        # foreground: one ray off by 1 in 3 channels
    assert float(L["loss_bg"]) == pytest.approx(2 / 6)       # outside: one ray off by 1 in 2 channels
    assert float(total_loss(L, cfg)) == pytest.approx(3 / 6 + 2 / 6)
    L = compute_losses(render_output(4, rgb=pred), rays, cfg, use_mask=True, background=False)
    assert float(L["loss_bg"]) == 0.0

