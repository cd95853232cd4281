"""The evidence's radiance network (nepf_core/fields/evidence_radiance.py): the reflected view
input by hand, its fit L_e reaching that network alone, the evidence reading it, and a fit that
trains it."""

import math

import pytest
import torch

from nepf_core.color import linear_to_srgb
from nepf_core.config import fast, tiny
from nepf_core.fields.evidence_radiance import reflected_view
from nepf_core.losses import LossConfig, compute_losses
from nepf_core.model import NePFModel
from nepf_core.rays import RayBatch
from nepf_core.render import material_evidence as me
from nepf_core.render.renderer import render_rays


def test_the_reflected_view_by_hand():
    s = 1.0 / math.sqrt(2.0)
    got = reflected_view(torch.tensor([[s, 0.0, -s]]), torch.tensor([[0.0, 0.0, 2.0]]))   # n of any length
    assert torch.allclose(got, torch.tensor([[s, 0.0, s, -s]]), atol=1e-7)
    g = torch.Generator().manual_seed(0)
    v = torch.nn.functional.normalize(torch.randn(50, 3, generator=g), dim=-1)
    n = torch.randn(50, 3, generator=g)
    rv = reflected_view(v, n)
    nu = torch.nn.functional.normalize(n, dim=-1)
    assert torch.allclose(rv[:, :3].norm(dim=-1), torch.ones(50), atol=1e-6)                # a mirror keeps length
    assert torch.allclose((rv[:, :3] * nu).sum(-1), -(v * nu).sum(-1), atol=1e-6)         # flips the normal part
    assert torch.allclose(torch.linalg.cross(rv[:, :3] - v, nu), torch.zeros(50, 3), atol=1e-6)   # moves along n
    assert torch.allclose(rv[:, 3], (v * nu).sum(-1), atol=1e-6)


def _render_with_evidence_colour():
    torch.manual_seed(0)
    cfg = tiny()
    cfg.model.evidence_radiance = True
    model = NePFModel(cfg.model)
    g = torch.Generator().manual_seed(1)
    o = torch.tensor([[0.0, 0.0, -2.5]]).repeat(16, 1)
    d = torch.nn.functional.normalize(torch.randn(16, 3, generator=g) * 0.3 + torch.tensor([0.0, 0.0, 1.0]), dim=-1)
    rays = RayBatch(origins=o, directions=d, rgb=torch.rand(16, 3, generator=g))
    out = render_rays(model, rays, cfg.render, train=True)
    s = out.surface
    _, feat = model.sdf(s.x.detach())
    out.evidence_colour = model.evidence_radiance(s.x, s.direction, s.normal, feat)
    return model, rays, out


def test_its_fit_is_the_surface_rays_l1_and_trains_that_network_alone():
    model, rays, out = _render_with_evidence_colour()
    losses = compute_losses(out, rays, LossConfig(), use_mask=False)
    fg = out.weight_sum.detach() > 0.5
    assert 0 < int(fg.sum()) < len(fg)         # the test means something: some rays miss
    err = (linear_to_srgb(out.evidence_colour) - linear_to_srgb(rays.rgb)).abs().mean(-1)
    assert float(losses["loss_evidence_radiance"].detach()) == pytest.approx(float(err[fg].mean().detach()), rel=1e-5)
    grads = torch.autograd.grad(losses["loss_evidence_radiance"], list(model.parameters()), allow_unused=True)
    reached = {name.split(".")[0] for (name, _), gr in zip(model.named_parameters(), grads)
               if gr is not None and gr.abs().sum() > 0}
    assert reached == {"evidence_radiance"}    # not the geometry, not the radiance of L_r
    out.evidence_colour = None                 # a model without one: the term is left out
    assert "loss_evidence_radiance" not in compute_losses(out, rays, LossConfig(), use_mask=False)


def test_the_evidence_reads_the_evidence_network_where_the_model_has_one():
    class Const(torch.nn.Module):
        def __init__(self, value):
            super().__init__()
            self.value = value

        def forward(self, x, v, n, f, with_logits=False):
            return torch.full((x.shape[0], 3), self.value)

    class SDF:          # a sphere of radius 0.5 with a 2-wide feature
        def __call__(self, p):
            return self.sdf(p), torch.zeros(p.shape[0], 2)

        def sdf(self, p):
            return p.norm(dim=-1) - 0.5

    class Model:
        def __init__(self, evidence):
            self.sdf, self.radiance, self.evidence_radiance = SDF(), Const(0.25), evidence

    x = torch.tensor([[0.0, 0.0, 0.5]])
    cams = torch.tensor([[0.0, 0.0, 3.0], [1.0, 0.0, 3.0], [0.0, 1.0, 3.0]])
    for evidence, want in ((None, 0.25), (Const(0.75), 0.75)):
        c, _, valid = me.views_of_points(Model(evidence), x, x / 0.5, cams, 3, torch.Generator().manual_seed(0))
        assert bool(valid.all()) and torch.allclose(c, torch.full_like(c, want))


def test_a_fast_fit_trains_it(tmp_path):
    from nepf_core.data.detect import load_scene
    from nepf_core.data.synth import make_scene
    from nepf_core.fields.sdf_grid import GridSDFConfig
    from nepf_core.train import fit
    from nepf_core.train.hooks import TrainHooks

    make_scene(tmp_path / "s", n_views=8, n_test=0, resolution=24, supersample=1, write_mesh=False)
    cfg = fast()
    cfg.model.evidence_radiance = True
    cfg.model.sdf_grid = GridSDFConfig(base_resolution=8, max_resolution=32)
    cfg.model.occupancy_resolution = 16
    cfg.train.iters, cfg.train.batch_rays, cfg.train.log_every = 30, 128, 1
    cfg.train.sync_every, cfg.train.eval_every_s = 0, 0.0

    class Seen(TrainHooks):
        rows = []

        def after_step(self, run, step, out, losses):
            self.rows.append(float(losses["loss_evidence_radiance"].detach()))

    fit(load_scene(tmp_path / "s" / "dtu"), tmp_path / "run", cfg, device="cpu", hooks=[Seen()])
    assert len(Seen.rows) == 30 and all(math.isfinite(r) for r in Seen.rows)
    assert sum(Seen.rows[-5:]) < sum(Seen.rows[:5])     # it learns the surface colours
