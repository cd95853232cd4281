"""The learned radiance's view spread (nepf_core.view_dependence) and the diffuse-only material."""

from __future__ import annotations

import math

import pytest
import torch
from torch import nn

from nepf_core.bsdf import bsdf_eval, diffuse_only_material
from nepf_core.view_dependence import radiance_view_spread


class _PlaneSDF(nn.Module):
    """f(x) = x_z: the plane z = 0 with normal +z; a 2-channel feature."""

    def forward(self, x):
        return x[:, 2], torch.zeros(x.shape[0], 2)

    def sdf(self, x):
        return x[:, 2]


class _Radiance(nn.Module):
    """``Y = base`` from most cameras, ``base (1 + h)`` from the camera at +y (``v_y < -0.1``);
    100 from a camera under the plane (``v_z > 0``) or at grazing incidence (``v_x < -0.8``):
    those two must never be used."""

    def __init__(self, h: float, base: float = 0.5):
        super().__init__()
        self.h, self.base = h, base

    def forward(self, x, v, g, feat):
        y = torch.full((x.shape[0],), self.base)
        y = torch.where(v[:, 1] < -0.1, self.base * (1.0 + self.h), y)
        y = torch.where((v[:, 2] > 0) | (v[:, 0] < -0.8), torch.full_like(y, 100.0), y)
        return y[:, None].expand(-1, 3)


def _model(h):
    m = nn.Module()
    m.sdf, m.radiance = _PlaneSDF(), _Radiance(h)
    return m


# three cameras facing the plane (cos > 0.96), one under it, one grazing (cos 0.16)
CAMS = torch.tensor([[0.5, 0.0, 2.0], [-0.5, 0.0, 2.0], [0.0, 0.5, 2.0], [0.0, 0.0, -2.0], [3.0, 0.0, 0.5]])


def _points(n=64):
    g = torch.Generator().manual_seed(0)
    xy = (torch.rand(n, 2, generator=g) - 0.5) * 0.2
    return torch.cat([xy, torch.zeros(n, 1)], -1)


def test_view_independent_radiance_has_zero_spread():
    r = radiance_view_spread(_model(0.0), _points(), CAMS, fd_step=1e-3)
    assert r["n_points"] == 64
    assert r["spread"] == 0.0


@pytest.mark.parametrize("h", [0.05, 0.3, 2.0])
def test_one_bright_view_of_three_gives_the_hand_worked_excess(h):
    """Views ``b, b, b (1 + h)``: max - median = b h, mean = b (1 + h / 3), so
    spread = h / (1 + h / 3). The cameras under the plane and at grazing incidence
    (radiance 100) are never used."""
    r = radiance_view_spread(_model(h), _points(), CAMS, fd_step=1e-3)
    assert r["n_points"] == 64
    assert r["spread"] == pytest.approx(h / (1 + h / 3), rel=1e-5)


def test_spread_is_scale_invariant_and_needs_two_facing_cameras():
    m = _model(0.2)
    a = radiance_view_spread(m, _points(), CAMS, fd_step=1e-3)
    m.radiance.base = 0.05
    b = radiance_view_spread(m, _points(), CAMS, fd_step=1e-3)
    assert a["spread"] == pytest.approx(b["spread"], rel=1e-5)
    one = radiance_view_spread(m, _points(), CAMS[[0, 3, 4]], fd_step=1e-3)  # one facing camera only
    assert one["n_points"] == 0 and math.isnan(one["spread"])


def test_many_cameras_are_subsampled_evenly():
    """100 facing cameras on a ring, every 4th of them bright: subsampled to 25 (every 4th
    index kept, bright ones included), still a quarter bright."""
    ang = torch.arange(100) * (2 * math.pi / 100)
    cams = torch.stack([0.5 * torch.cos(ang), 0.5 * torch.sin(ang), torch.full((100,), 2.0)], -1)
    bright = torch.zeros(100, dtype=torch.bool)
    bright[::4] = True

    def rad(x, v, g, feat):  # bright when the ray comes from a bright camera
        c = x - v * ((x[:, 2:3] - 2.0) / v[:, 2:3])  # back to the camera plane z = 2
        k = torch.atan2(c[:, 1], c[:, 0]).remainder(2 * math.pi) / (2 * math.pi / 100)
        y = torch.where(bright[k.round().long() % 100], 1.0, 0.5)
        return y[:, None].expand(-1, 3)
    from types import SimpleNamespace
    m = SimpleNamespace(sdf=_PlaneSDF(), radiance=rad)
    r = radiance_view_spread(m, _points(8), cams, fd_step=1e-3, max_cams=25)
    # 25 cameras, indices 0, 4.125, ... rounded: those at multiples of 4 are bright
    idx = torch.linspace(0, 99, 25).round().long()
    nb = int(bright[idx].sum())
    assert 0 < nb < 13  # the median view is a dim one
    expect = 0.5 / ((nb * 1.0 + (25 - nb) * 0.5) / 25)
    assert r["spread"] == pytest.approx(expect, rel=1e-4)


def test_without_the_lobe_metallic_no_longer_changes_the_shading():
    """Lobe dropped (``Shading(specular=False)``): the surface PBR is ``f_d(c) I (n.l)`` whatever
    the material network says of metallic (two metallic fields, same image), and equals the
    BSDF evaluated with metallic 0; with the lobe on, the two metallic fields differ."""
    from nepf_core.config import tiny
    from nepf_core.model import NePFModel
    from nepf_core.rays import RayBatch
    from nepf_core.render.renderer import Shading, render_rays

    torch.manual_seed(0)
    cfg = tiny()
    fade = {"w": 0.0}
    model = NePFModel(cfg.model)
    base = model.material.forward
    g = torch.Generator().manual_seed(1)
    o = torch.tensor([[0.0, 0.0, -2.5]]).repeat(64, 1)
    d = torch.nn.functional.normalize(torch.tensor([[0.0, 0.0, 1.0]]) + 0.08 * torch.randn(64, 3, generator=g), dim=-1)
    rays = RayBatch(o, d)

    def surf_rgb(metal_value, specular):
        model.material.forward = lambda x, n, f: (base(x, n, f)[0], base(x, n, f)[1],
                                                  torch.full((x.shape[0],), metal_value))
        with torch.no_grad():
            return render_rays(model, rays, cfg.render, train=False,
                               shading=Shading(specular=specular, diffuse_metal_weight=fade["w"]))
    a, b = surf_rgb(0.1, False), surf_rgb(0.9, False)
    assert torch.equal(a.rgb_surf, b.rgb_surf) and float(a.rgb_surf.abs().max()) > 1e-3
    s = a.surface
    ref = bsdf_eval(s.normal, s.light_dir, -d, s.albedo, s.roughness[:, None],
                    torch.zeros(64, 1), specular=False) * s.intensity[:, None] * \
        (s.normal * s.light_dir).sum(-1, keepdim=True).clamp_min(0)
    assert torch.allclose(a.rgb_surf, ref, atol=1e-6)
    c, e = surf_rgb(0.1, True), surf_rgb(0.9, True)
    assert not torch.allclose(c.rgb_surf, e.rgb_surf)
    albedo, rough, metal = diffuse_only_material(s.albedo, s.roughness, torch.full((64,), 0.7))
    assert torch.equal(albedo, s.albedo) and torch.all(metal == 0) and metal.shape == (64,)
    assert torch.all(rough == 1.0) and rough.shape == s.roughness.shape
    # mid-fade: (1 - w m) f_d(c) + w f_s. Its diffuse part is the diffuse of ((1 - w m) c,
    # metallic 0); linear in w, so at w = 0.5 it is the mean of the lobe-on image (w = 1,
    # (1 - m) f_d + f_s) and the dielectric diffuse (w = 0, f_d)
    fade["w"] = 0.5
    h = surf_rgb(0.9, False)
    c2, _, m2 = diffuse_only_material(h.surface.albedo, h.surface.roughness, torch.full((64,), 0.9), 0.5)
    ref2 = bsdf_eval(h.surface.normal, h.surface.light_dir, -d, c2, h.surface.roughness[:, None],
                     m2[:, None], specular=False) * h.surface.intensity[:, None] * \
        (h.surface.normal * h.surface.light_dir).sum(-1, keepdim=True).clamp_min(0)
    lobe = e.rgb_surf - (1 - 0.9) * a.rgb_surf
    assert float(lobe.abs().max()) > 1e-3
    assert torch.allclose(h.rgb_surf, ref2 + 0.5 * lobe, atol=1e-6)
    assert torch.allclose(h.rgb_surf, 0.5 * (a.rgb_surf + e.rgb_surf), atol=1e-6)
    fade["w"] = 1.0      # the drop itself: the lobe-on image exactly
    assert torch.allclose(surf_rgb(0.9, False).rgb_surf, e.rgb_surf, atol=1e-6)


@pytest.mark.parametrize("lambertian", [False, True])
@pytest.mark.parametrize("w", [1.0, 0.4])
def test_diffuse_only_material_renders_the_same_as_the_faded_diffuse(lambertian, w):
    """``(1 - w m) f_d(c) = f_d((1 - w m) c)`` (both diffuse models are linear in the albedo):
    the shaded BSDF of (c, m) with the lobe off and fade weight w equals that of the exported
    pair, on random configurations."""
    g = torch.Generator().manual_seed(0)
    N = 4096

    def unit(t):
        return t / t.norm(dim=-1, keepdim=True)
    n, l, v = (unit(torch.randn(N, 3, generator=g)) for _ in range(3))
    c = torch.rand(N, 3, generator=g)
    r, m = torch.rand(N, 1, generator=g), torch.rand(N, 1, generator=g)
    c2, r2, m2 = diffuse_only_material(c, r, m, w)
    assert torch.all(m2 == 0) and m2.shape == m.shape and torch.all(r2 == 1) and r2.shape == r.shape
    f1 = bsdf_eval(n, l, v, c, r, w * m, lambertian=lambertian, specular=False)
    f2 = bsdf_eval(n, l, v, c2, r, m2, lambertian=lambertian, specular=False)
    assert torch.allclose(f1, f2, atol=1e-7, rtol=1e-5)
    assert f1.abs().max() > 0.01


def test_the_lobe_rule_measures_the_spread_on_lit_pixels_only():
    """A near-mirror under a grazing light: most pixels are black, and a black point shows no
    highlight in any view. Points at x < 0 (their pixels unlit) have a flat radiance, points at
    x >= 0 one bright view of three (h = 0.3). On all points the spread would be diluted;
    :func:`lit_view_spread` skips unlit rays and gets the lit points' hand-worked
    h / (1 + h / 3); with fewer than 8 lit points, or while the radiance misses the lit pixels
    by more than 25 %, it measures nothing (the material decides then)."""
    from types import SimpleNamespace

    from nepf_core.train.rules.lobe_evidence import lit_view_spread

    h, base = 0.3, 0.5

    def rad(x, v, g, feat):
        y = torch.full((x.shape[0],), base)
        y = torch.where((v[:, 1] < -0.1) & (x[:, 0] >= 0), base * (1 + h), y)
        return y[:, None].expand(-1, 3)
    model = SimpleNamespace(sdf=_PlaneSDF(), radiance=rad)
    x = _points(64)
    unlit = x[:, 0] < 0
    assert 8 <= int((~unlit).sum()) < 64
    out = SimpleNamespace(weight_sum=torch.ones(64), surface=SimpleNamespace(x=x))

    def measure(rays):
        return lit_view_spread(model, out, rays, CAMS, view_points=256, radiance_fit_max=0.25)
    n_lit = int((~unlit).sum())
    diluted = n_lit * base * h / (64 * base + n_lit * base * h / 3)
    status, spread, _ = measure(SimpleNamespace(mask=None, unlit=None))
    assert status == "measured" and spread == pytest.approx(diluted, rel=1e-5)
    status, spread, _ = measure(SimpleNamespace(mask=None, unlit=unlit))
    assert spread == pytest.approx(h / (1 + h / 3), rel=1e-5)
    # a radiance that does not explain the lit pixels is no evidence: relative L1 error
    # sum |L_r - I| / sum |I| over the lit foreground; 0.2 passes, 0.3 > 0.25 leaves no measurement
    gt = torch.full((64, 3), 0.4)
    for rel, want in ((0.2, "measured"), (0.3, "unfit")):
        out.rgb_r = gt * (1.0 - rel)
        status, spread, err = measure(SimpleNamespace(mask=None, unlit=unlit, rgb=gt))
        assert err == pytest.approx(rel, rel=1e-5) and status == want
        assert (spread is not None) is (want == "measured")
    few = torch.ones(64, dtype=torch.bool)
    few[:7] = False                                          # 7 lit points: no measurement
    assert measure(SimpleNamespace(mask=None, unlit=few)) == ("none", None, None)
