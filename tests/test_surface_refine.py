"""L_surf at the SDF zero crossing (``RenderConfig.surface_refine``), on the ``fast`` model at
initialisation, whose SDF is exactly the sphere ``|x| - 0.5`` (the grid residual starts at 0)."""

from __future__ import annotations

import math

import pytest
import torch

from nepf_core.config import fast
from nepf_core.model import NePFModel
from nepf_core.rays import RayBatch
from nepf_core.render.renderer import render_rays

R0 = 0.5


def _model(inv_s: float):
    cfg = fast()
    torch.manual_seed(0)
    model = NePFModel(cfg.model)
    with torch.no_grad():
        model.deviation.variance.fill_(math.log(inv_s) / 10.0)
    return cfg, model


def _rays(n=64):
    """Rays from distance 2.5 aimed within 0.3 of the centre: all hit the sphere r = 0.5."""
    g = torch.Generator().manual_seed(3)
    p = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1)
    o = 2.5 * p
    aim = 0.3 * (torch.rand(n, 3, generator=g) - 0.5)
    d = torch.nn.functional.normalize(aim - o, dim=-1)
    return RayBatch(o, d, torch.rand(n, 3, generator=g), torch.ones(n), torch.zeros(n, dtype=torch.long))


def _surf(cfg, model, rays, *, refine, n_samples, n_importance, train=False):
    cfg.render.surface_refine = refine
    cfg.render.n_samples, cfg.render.n_importance = n_samples, n_importance
    cfg.render.perturb = False
    return render_rays(model, rays, cfg.render, train=train)


@pytest.mark.parametrize("inv_s", [64.0, 2000.0])
def test_refined_surface_point_lies_on_the_surface_whatever_the_sampling(inv_s):
    cfg, model = _model(inv_s)
    rays = _rays()
    with torch.no_grad():
        coarse = _surf(cfg, model, rays, refine=True, n_samples=24, n_importance=8)
        dense = _surf(cfg, model, rays, refine=True, n_samples=64, n_importance=32)
        plain = _surf(cfg, model, rays, refine=False, n_samples=24, n_importance=8)
    off_ref = (coarse.surface.x.norm(dim=-1) - R0).abs()
    off_plain = (plain.surface.x.norm(dim=-1) - R0).abs()
    # the secant of |x| - r across one section is off by ~ spacing^2 / r; the max-weight sample
    # itself is up to one spacing in front of the surface
    assert float(off_ref.max()) < 2e-4
    assert float(off_plain.mean()) > 1e-3 and float(off_plain.mean()) > 20 * float(off_ref.mean())
    # independent of the sample placement, to the same precision
    assert float((coarse.surface.x - dense.surface.x).norm(dim=-1).max()) < 2e-4
    # its normal is the sphere's, from its own finite differences
    n_true = torch.nn.functional.normalize(coarse.surface.x, dim=-1)
    assert float((coarse.surface.normal * n_true).sum(-1).min()) > 0.999
    # the surface colour is the BSDF at that point: the same shading the refined quantities give,
    # summed over the lights (fast's traced emitters: each one's irradiance carries its shadow)
    from nepf_core import bsdf
    s = coarse.surface
    dirs, irr = s.every_light()
    ref = sum(bsdf.shade(s.normal, dirs[:, k], -rays.directions, s.albedo, s.roughness[:, None],
                         s.metallic[:, None], irr[:, k, None], lambertian=cfg.render.lambertian,
                         specular=True, kind=cfg.render.bsdf_kind) for k in range(dirs.shape[1]))
    assert torch.allclose(coarse.rgb_surf, ref, atol=1e-6)
    # the volume colours do not change: only L_surf moves
    assert torch.allclose(coarse.rgb_vol, plain.rgb_vol) and torch.allclose(coarse.rgb_r, plain.rgb_r)


def test_refined_surface_colour_trains_the_material_photon_and_sdf():
    cfg, model = _model(500.0)
    rays = _rays(32)
    out = _surf(cfg, model, rays, refine=True, n_samples=24, n_importance=8, train=True)
    assert torch.isfinite(out.rgb_surf).all()
    out.rgb_surf.sum().backward()
    for name, mod in (("material", model.material), ("photon", model.photon), ("sdf", model.sdf)):
        g = [p.grad for p in mod.parameters() if p.grad is not None]
        assert g and any(float(x.abs().sum()) > 0 for x in g), name


def test_rays_that_miss_keep_the_max_weight_sample():
    cfg, model = _model(500.0)
    o = torch.tensor([[2.0, 2.0, 0.0], [0.0, 0.0, 2.5]])
    d = torch.nn.functional.normalize(torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0]]), dim=-1)
    rays = RayBatch(o, d)
    with torch.no_grad():
        ref = _surf(cfg, model, rays, refine=True, n_samples=24, n_importance=8)
        plain = _surf(cfg, model, rays, refine=False, n_samples=24, n_importance=8)
    assert torch.isfinite(ref.rgb_surf).all()
    assert torch.allclose(ref.surface.x[0], plain.surface.x[0])          # a miss: unchanged
    assert abs(float(ref.surface.x[1].norm()) - R0) < 2e-4                # a hit: on the sphere


def test_the_smoothness_priors_points_get_their_own_normal():
    """``refine_surface`` with a jitter: the points ``x_j = x* + e`` and their mirror images
    ``x* - e`` get the SDF's normal from their own stencils. On the sphere ``|x| - r`` that is
    ``x / |x|`` wherever the point lies. The first difference ``|n(x_j) - n(x*)|`` grows with the
    jitter as the sphere turns (``~|e_t| / r``); the second difference the normal prior uses
    cancels that first-order turn, so a smoothly curved surface costs it several times less."""
    from nepf_core.render.surface import refine_surface
    cfg, model = _model(500.0)
    rays = _rays()
    R = rays.origins.shape[0]
    z = torch.linspace(1.2, 2.4, 48).expand(R, -1).contiguous()
    with torch.no_grad():
        pts = rays.origins[:, None, :] + rays.directions[:, None, :] * z[..., None]
        f = model.sdf.sdf(pts.reshape(-1, 3)).reshape(R, -1)
        idx = (f > 0).sum(-1) - 1          # the last sample outside: the first crossing follows it
        torch.manual_seed(2)
        xr, nr, _, xj, fj, (nj, nm) = refine_surface(model, rays.origins, rays.directions, z, f, idx,
                                                      jitter_sigma=0.05, jitter_normals=True)
    radial = lambda x: torch.nn.functional.normalize(x, dim=-1)  # noqa: E731
    assert float((nr * radial(xr)).sum(-1).min()) > 0.999
    assert float((nj * radial(xj)).sum(-1).min()) > 0.999
    assert float((nm * radial(2 * xr - xj)).sum(-1).min()) > 0.999
    first = float((nj - nr).norm(dim=-1).mean())
    second = float((nj + nm - 2 * nr).norm(dim=-1).mean())
    assert first > 0.02
    assert second < first / 3
    with torch.no_grad():
        torch.manual_seed(2)
        *_, none = refine_surface(model, rays.origins, rays.directions, z, f, idx, jitter_sigma=0.0,
                                  jitter_normals=True)
        torch.manual_seed(2)
        xr2, nr2, _, xj2, fj2, unasked = refine_surface(model, rays.origins, rays.directions, z, f, idx,
                                                        jitter_sigma=0.05)
    assert none is None
    # not asked for (no normal prior): the same points, normals and features, without the stencils
    assert unasked is None
    for a, b in ((xr, xr2), (nr, nr2), (xj, xj2), (fj, fj2)):
        assert torch.allclose(a, b, atol=1e-6)
