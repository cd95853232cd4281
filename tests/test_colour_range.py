"""The colour logits' range prior (``loss.w_colour_range``): its value, where the renderer gets the
logits from, and the saturation it prevents (a colour network trained on black must still learn
grey afterwards)."""

import dataclasses

import pytest
import torch

from nepf_core.color import linear_to_srgb
from nepf_core.config import fast, tiny
from nepf_core.fields.heads import HeadConfig, RadianceField
from nepf_core.losses import LossConfig, compute_losses, total_loss
from nepf_core.model import NePFModel
from nepf_core.rays import RayBatch
from nepf_core.render.renderer import render_background_only, render_rays


def _excess(z: torch.Tensor, z_max: float) -> torch.Tensor:
    return (z.abs() - z_max).clamp_min(0.0).mean()


def _train_black_then_grey(w_range: float, z_max: float = 9.0) -> tuple[float, float]:
    """A radiance head of the fast preset's size fit by Adam at the fast preset's learning rate
    through the training loss's path (L1 on sRGB), 300 steps to black targets, then 150 to grey
    (0.2 linear). Returns the mean output at the end and the lowest logit seen."""
    torch.manual_seed(0)
    head = RadianceField(HeadConfig(width=64, depth=2, activation="relu", n_freqs_v=4), 16)
    opt = torch.optim.Adam(head.parameters(), lr=5e-3, betas=(0.9, 0.99), eps=1e-15)
    x, v = torch.rand(256, 3) * 2 - 1, torch.nn.functional.normalize(torch.randn(256, 3), dim=-1)
    n, feat = torch.nn.functional.normalize(torch.randn(256, 3), dim=-1), torch.randn(256, 16) * 3
    lowest = 0.0
    for target, steps in ((0.0, 300), (0.2, 150)):
        goal = linear_to_srgb(torch.full((256, 3), target))
        for _ in range(steps):
            opt.zero_grad()
            rgb, z = head(x, v, n, feat, with_logits=True)
            lowest = min(lowest, float(z.detach().min()))
            ((linear_to_srgb(rgb) - goal).abs().mean() + w_range * _excess(z, z_max)).backward()
            opt.step()
    with torch.no_grad():
        return float(head(x, v, n, feat).mean()), lowest


def test_without_the_prior_black_targets_saturate_the_head_for_good():
    # the mechanism of bench/RESULTS.md's collapse: the logits run far past any finite value,
    # and afterwards no target brings the colour back
    mean, lowest = _train_black_then_grey(0.0)
    assert lowest < -30 and mean < 0.01


@pytest.mark.parametrize("w_range", [1e-2, 1.0])
def test_with_the_prior_the_head_learns_grey_after_black(w_range):
    mean, lowest = _train_black_then_grey(w_range)
    assert abs(mean - 0.2) < 0.02
    assert lowest > -30


def _rays(n: int = 48) -> RayBatch:
    g = torch.Generator().manual_seed(1)
    o = torch.tensor([[0.0, 0.0, -2.5]]).repeat(n, 1)
    d = torch.nn.functional.normalize(torch.randn(n, 3, generator=g) * 0.3 + torch.tensor([0.0, 0.0, 1.0]), dim=-1)
    return RayBatch(origins=o, directions=d, rgb=torch.zeros(n, 3))


def test_training_render_carries_every_evaluated_colour_logit():
    torch.manual_seed(0)
    cfg = tiny()
    model = NePFModel(dataclasses.replace(cfg.model, background=True))
    rays = _rays()
    out = render_rays(model, rays, cfg.render, train=True)
    n_bg = len(rays.origins) * model.background.cfg.n_samples
    assert out.colour_logits.shape == (out.n_head_evals + n_bg, 3)
    # they are the logits of the colours the render composited: the background's reproduce its colour
    torch.manual_seed(0)
    c_bg, z_bg = render_background_only(model, rays, cfg.render, train=False, with_logits=True)
    w, rgb = model.background.weights_and_colours(rays.origins, rays.directions)
    assert torch.allclose(torch.sigmoid(z_bg).reshape(rgb.shape), rgb)
    assert torch.allclose((w[..., None] * rgb).sum(1), c_bg, atol=1e-6)
    assert render_rays(model, rays, cfg.render, train=False).colour_logits is None


def test_loss_term_value_is_hand_worked():
    torch.manual_seed(0)
    cfg = tiny()
    model = NePFModel(cfg.model)
    rays = _rays(16)
    out = render_rays(model, rays, cfg.render, train=True)
    out.colour_logits = torch.tensor([[10.0, -9.0, 0.0], [-12.5, 9.5, 3.0]])
    loss_cfg = dataclasses.replace(LossConfig(), w_colour_range=0.5, colour_logit_max=9.0)
    losses = compute_losses(out, rays, loss_cfg, use_mask=False)
    # excesses 1, 0, 0, 3.5, 0.5, 0 over 6 values
    assert float(losses["loss_colour_range"]) == pytest.approx(5.0 / 6.0)
    without = compute_losses(out, rays, dataclasses.replace(loss_cfg, w_colour_range=0.0), use_mask=False)
    assert float((total_loss(losses, loss_cfg) - total_loss(without, loss_cfg)).detach()) == pytest.approx(0.5 * 5.0 / 6.0, rel=1e-5)


def test_presets():
    assert fast().loss.w_colour_range > 0      # the fast preset keeps its colours out of saturation
    assert LossConfig().w_colour_range == 0     # the paper's losses are as the paper has them


def test_fit_without_masks_holds_the_logits_of_the_rays_the_background_renders_alone(tmp_path):
    """In a fast fit without masks the range prior sees every colour the step evaluated: the
    heads' samples, the background's samples of the SDF batch, and those of the misses the
    empty-ray rule left out and the background rendered alone."""
    from nepf_core.data.detect import load_scene
    from nepf_core.data.synth import make_scene
    from nepf_core.fields.sdf_grid import GridSDFConfig
    from nepf_core.train import fit
    from nepf_core.train.hooks import TrainHooks

    make_scene(tmp_path / "s", n_views=6, n_test=0, resolution=24, supersample=1, fov_deg=75.0, masks=False,
               write_mesh=False)
    cfg = fast()
    cfg.model.sdf_grid = GridSDFConfig(base_resolution=8, max_resolution=32)
    cfg.model.occupancy_resolution = 16
    cfg.train.iters, cfg.train.batch_rays, cfg.train.log_every = 8, 64, 2
    cfg.train.sync_every, cfg.train.eval_every_s, cfg.train.occupancy_every = 0, 0.0, 2

    class Counts(TrainHooks):
        rows = []

        def after_step(self, run, step, out, losses):
            n_bg = run.model.background.cfg.n_samples
            rays = out.weight_sum.shape[0] + run._n_background_rays
            self.rows.append((out.colour_logits.shape[0], out.n_head_evals + rays * n_bg, run._n_background_rays))

    fit(load_scene(tmp_path / "s" / "dtu"), tmp_path / "run", cfg, device="cpu", hooks=[Counts()])
    assert Counts.rows and all(got == want for got, want, _ in Counts.rows)
    assert any(b > 0 for _, _, b in Counts.rows)   # some steps did render misses by the background alone
