"""L_surf toward other training cameras (``loss.w_surf_views``, nepf_core/render/surface_views.py):
which cameras are drawn, the loss value, the ambiguity it resolves (a metal seen from one direction
is fit as well by a dark dielectric; seen from several it is not), and its place in a fit."""

import dataclasses
import math

import pytest
import torch
from torch import nn

from nepf_core import bsdf
from nepf_core.color import linear_to_srgb
from nepf_core.config import fast, tiny
from nepf_core.losses import LossConfig, compute_losses
from nepf_core.model import NePFModel
from nepf_core.rays import RayBatch
from nepf_core.render.renderer import render_rays
from nepf_core.render.shading import Shading
from nepf_core.render.surface_views import (MAX_VIEW_ANGLE_DEG, MIN_FACING_COS, SurfaceViews, pick_view_cameras,
                                            shade_surface_views)


def test_only_facing_cameras_near_the_rays_own_direction_are_drawn():
    x, n = torch.zeros(1, 3), torch.tensor([[0.0, 0.0, 1.0]])
    d = torch.tensor([[0.0, 0.0, -1.0]])                       # the ray's camera is straight above
    cams = torch.tensor([[0.0, 0.0, 2.0],     # the ray's own camera: 0 deg
                         [0.8, 0.0, 2.0],     # 21.8 deg off, facing: drawn
                         [2.0, 0.0, 0.1],     # grazing: n . to_cam = 0.05 < MIN_FACING_COS
                         [0.0, 0.0, -2.0],    # behind the surface
                         [2.0, 0.0, 2.0],     # 45 deg off: outside the cone
                         [0.0, 1.0, 1.0]])    # 45 deg off too
    assert MIN_FACING_COS > 0.05 and MAX_VIEW_ANGLE_DEG < 45.0
    g = torch.Generator().manual_seed(0)
    ray, v = pick_view_cameras(x, n, d, cams, k=6, generator=g)
    assert ray.tolist() == [0, 0]
    expected = {(0.0, 0.0, -1.0), tuple((-cams[1] / cams[1].norm()).tolist())}
    assert {tuple(round(float(c), 5) for c in row) for row in v} == {tuple(round(c, 5) for c in e) for e in expected}
    # k caps the draw, and the draw is uniform over the eligible cameras
    picks = [pick_view_cameras(x, n, d, cams, k=1, generator=g)[1] for _ in range(200)]
    own = sum(bool(torch.allclose(p[0], d[0])) for p in picks)
    assert all(p.shape == (1, 3) for p in picks) and 60 < own < 140


def test_a_camera_behind_another_part_of_the_object_does_not_see_the_point():
    from nepf_core.render.surface_views import seen_from

    def two_balls(p):   # a ball of radius 0.2 at the origin and one of radius 0.15 at z = 0.6
        return torch.minimum(p.norm(dim=-1) - 0.2, (p - torch.tensor([0.0, 0.0, 0.6])).norm(dim=-1) - 0.15)

    x = torch.tensor([[0.0, 0.0, 0.2], [0.0, 0.0, 0.2], [0.2, 0.0, 0.0]])     # on the first ball
    cams = torch.tensor([[0.0, 0.0, 3.0], [1.5, 0.0, 3.0], [3.0, 0.0, 0.0]])
    v = torch.nn.functional.normalize(x - cams, dim=-1)                        # camera -> point
    # straight up the second ball hides it; 26.6 deg off and from the side it is seen
    assert seen_from(two_balls, x, v).tolist() == [False, True, True]


def test_no_eligible_camera_gives_no_pairs():
    x, n, d = torch.zeros(2, 3), torch.tensor([[0.0, 0.0, 1.0]] * 2), torch.tensor([[0.0, 0.0, -1.0]] * 2)
    ray, v = pick_view_cameras(x, n, d, torch.tensor([[0.0, 0.0, -2.0], [3.0, 0.0, 0.0]]), k=2, generator=None)
    assert ray.numel() == 0 and v.shape == (0, 3)


class _StubModel(nn.Module):
    """One light, learnable material logits per point, and a radiance network that *is* a gold
    metal (roughness 0.3) under that light: the targets a radiance field fitted to such a surface
    would give."""

    light = torch.nn.functional.normalize(torch.tensor([0.3, -0.2, 1.0]), dim=0)
    gold = torch.tensor([0.95, 0.75, 0.35])

    def __init__(self, points: torch.Tensor, bsdf_kind: str) -> None:
        super().__init__()
        self.kind, self.points = bsdf_kind, points
        start = torch.tensor([0.0, 0.0, 0.0, 0.0, -3.0])            # dielectric start, as the material head
        self.z = nn.Parameter(start.repeat(points.shape[0], 1))

    class _Sphere:
        """The unit sphere's SDF, as ``model.sdf``: ``(sdf, features)`` and ``.sdf``."""

        def __call__(self, x):
            return x.norm(dim=-1) - 1.0, torch.zeros(x.shape[0], 1)

        def sdf(self, x):
            return x.norm(dim=-1) - 1.0

    sdf = _Sphere()

    def photon(self, x, n, f):
        return self.light.expand(x.shape[0], 3), torch.full((x.shape[0],), 3.0)

    def material(self, x, n, f, with_logits=False):
        z = self.z[torch.cdist(x, self.points).argmin(1)]       # each point's own logits
        s = torch.sigmoid(z)
        return (s[:, :3], s[:, 3], s[:, 4], z) if with_logits else (s[:, :3], s[:, 3], s[:, 4])

    def radiance(self, x, v, n, f, with_logits=False):
        k = x.shape[0]
        rgb = bsdf.shade(n, self.light.expand(k, 3), -v, self.gold.expand(k, 3), torch.full((k, 1), 0.3),
                         torch.ones(k, 1), torch.full((k, 1), 3.0), kind=self.kind)
        return rgb.clamp(0.0, 1.0)


def _fit_material(views: int, steps: int = 300) -> tuple[float, float]:
    """Fit the stub's material logits at 32 points of a sphere to its gold radiance, from the ray's
    own direction only (``views = 0``: the paper's L_surf) or with ``views`` other cameras each step.
    Returns the final mean metallic and the own-view L1 (sRGB)."""
    torch.manual_seed(0)
    cfg = fast().render
    phi = torch.linspace(0.0, 2 * math.pi, 33)[:-1]
    n = torch.stack([0.5 * torch.cos(phi), 0.5 * torch.sin(phi), torch.full_like(phi, math.sqrt(0.75))], -1)
    x = n.clone()
    cams = torch.stack([torch.tensor([3.0 * math.cos(a), 3.0 * math.sin(a), 3.5]) for a in torch.linspace(0, 6.28, 25)[:-1]])
    d = torch.nn.functional.normalize(x - cams[(torch.arange(32) * 3) % 24], dim=-1)    # each point's own ray
    model = _StubModel(x, cfg.bsdf_kind)
    opt = torch.optim.Adam(model.parameters(), lr=5e-2)
    g = torch.Generator().manual_seed(0)
    from nepf_core.render.shading import shade_points
    for _ in range(steps):
        opt.zero_grad()
        own = shade_points(model, cfg, Shading(), x, d, n, torch.zeros(32, 1), None).pbr
        own_err = (linear_to_srgb(own) - linear_to_srgb(model.radiance(x, d, n, None))).abs().mean()
        loss = own_err
        if views:
            sv = shade_surface_views(model, cfg, Shading(), x, n, d, torch.ones(32, dtype=torch.bool), cams, g, k=views)
            assert sv.pbr.shape[0] > 0 and not sv.target.requires_grad
            loss = loss + (linear_to_srgb(sv.pbr) - linear_to_srgb(sv.target)).abs().mean()
        loss.backward()
        opt.step()
    return float(torch.sigmoid(model.z[:, 4]).detach().mean()), float(own_err.detach())


def test_several_views_tell_a_metal_from_a_dark_dielectric():
    # from its own direction alone a half-metal fits the gold metal's pixels (the ambiguity); asked
    # to match the radiance from other cameras too, it becomes the metal
    metal_one, err_one = _fit_material(views=0, steps=600)
    metal_many, err_many = _fit_material(views=3, steps=600)
    assert err_one < 0.01 and err_many < 0.01     # both fit the pixels they were shown
    assert metal_one < 0.6
    assert metal_many > 0.8


def test_the_term_is_the_mean_srgb_l1_of_its_pairs():
    torch.manual_seed(0)
    cfg = tiny()
    model = NePFModel(cfg.model)
    g = torch.Generator().manual_seed(1)
    o = torch.tensor([[0.0, 0.0, -2.5]]).repeat(8, 1)
    d = torch.nn.functional.normalize(torch.randn(8, 3, generator=g) * 0.2 + torch.tensor([0.0, 0.0, 1.0]), dim=-1)
    rays = RayBatch(origins=o, directions=d, rgb=torch.zeros(8, 3))
    out = render_rays(model, rays, cfg.render, train=True)
    pbr = torch.tensor([[0.25, 0.5, 1.0], [0.0, 0.04, 0.2]])
    target = torch.tensor([[0.25, 0.25, 0.0], [0.0, 0.04, 0.2]])
    out.surface_views = SurfaceViews(pbr=pbr, target=target, ray=torch.tensor([0, 3]))
    loss_cfg = dataclasses.replace(LossConfig(), w_surf_views=1.0)
    got = compute_losses(out, rays, loss_cfg, use_mask=False)["loss_surf_views"]
    expected = (linear_to_srgb(torch.tensor(0.5)) - linear_to_srgb(torch.tensor(0.25)) + 1.0) / 6.0
    assert float(got) == pytest.approx(float(expected), rel=1e-6)
    out.surface_views = None
    with pytest.raises(ValueError, match="w_surf_views"):
        compute_losses(out, rays, loss_cfg, use_mask=False)


def test_presets():
    assert fast().loss.w_surf_views > 0
    assert LossConfig().w_surf_views == 0          # the paper's L_surf is its own ray's direction only


def test_only_the_material_and_photon_networks_learn_from_it():
    torch.manual_seed(0)
    cfg = tiny()
    model = NePFModel(cfg.model)
    x = torch.nn.functional.normalize(torch.randn(16, 3), dim=-1) * 0.5
    n = torch.nn.functional.normalize(x, dim=-1)
    cams = n[torch.randperm(16)] * 3.0 + torch.randn(16, 3) * 0.3
    d = torch.nn.functional.normalize(x - (n * 3.0), dim=-1)
    x.requires_grad_(True)
    sv = shade_surface_views(model, cfg.render, Shading(), x, n, d, torch.ones(16, dtype=torch.bool), cams,
                             torch.Generator().manual_seed(0), k=4)
    assert sv.pbr.shape[0] > 0 and not sv.target.requires_grad
    params = dict(model.named_parameters())
    grads = torch.autograd.grad(sv.pbr.sum(), list(params.values()) + [x], allow_unused=True)
    reached = {name.split(".")[0] for name, gr in zip(params, grads) if gr is not None and gr.abs().sum() > 0}
    assert reached == {"material", "photon"}
    assert grads[-1] is None                       # the geometry is detached


def test_a_fast_fit_trains_the_term(tmp_path):
    """In a fit the step shades every lit foreground ray's surface point toward other cameras, and
    the term is logged non-zero once the object is found."""
    from nepf_core.data.detect import load_scene
    from nepf_core.data.synth import make_scene
    from nepf_core.fields.sdf_grid import GridSDFConfig
    from nepf_core.train import fit
    from nepf_core.train.hooks import TrainHooks

    make_scene(tmp_path / "s", n_views=8, n_test=0, resolution=24, supersample=1, write_mesh=False)
    cfg = fast()
    cfg.model.sdf_grid = GridSDFConfig(base_resolution=8, max_resolution=32)
    cfg.model.occupancy_resolution = 16
    cfg.train.iters, cfg.train.batch_rays, cfg.train.log_every = 6, 96, 1
    cfg.train.sync_every, cfg.train.eval_every_s = 0, 0.0
    cfg.loss.w_surf_views = 3e-4

    class Seen(TrainHooks):
        rows = []

        def after_step(self, run, step, out, losses):
            self.rows.append((out.surface_views.pbr.shape[0], float(losses["loss_surf_views"])))

    fit(load_scene(tmp_path / "s" / "dtu"), tmp_path / "run", cfg, device="cpu", hooks=[Seen()])
    assert Seen.rows and any(m > 0 and v > 0 for m, v in Seen.rows)
