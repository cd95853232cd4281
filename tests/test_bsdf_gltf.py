"""The glTF metallic-roughness BRDF (``kind="gltf"``): hand-worked values, reciprocity, energy,
the roughness floor's gradient, and the difference from the paper kind."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from nepf_core import bsdf

N = torch.tensor([[0.0, 0.0, 1.0]])


def _at(theta_l_deg: float, theta_v_deg: float = 0.0, phi_v_deg: float = 180.0):
    """Unit l at polar angle theta_l in the xz plane, v at theta_v and azimuth phi_v; [1, 3] each."""
    tl, tv, pv = map(math.radians, (theta_l_deg, theta_v_deg, phi_v_deg))
    l = torch.tensor([[math.sin(tl), 0.0, math.cos(tl)]])
    v = torch.tensor([[math.sin(tv) * math.cos(pv), math.sin(tv) * math.sin(pv), math.cos(tv)]])
    return l, v


def _f(l, v, albedo, r, m, kind="gltf", n=N):
    return bsdf.bsdf_eval(n, l, v, torch.tensor([albedo]), torch.tensor([[r]]), torch.tensor([[m]]), kind=kind)[0]


def test_normal_incidence_hand_worked():
    # n = l = v: F = F0, n.h = 1, D = 1/(pi a^2), V = 1/4, a = 1e-3 + 0.999 r^2.
    # c = (0.8, 0.5, 0.2), r = 0.5, m = 0.25:
    #   a = 0.25075; F0 = 0.04*0.75 + 0.25 c = (0.23, 0.155, 0.08)
    #   diffuse = (1 - F0) * 0.75 c / pi = (0.77*0.6, 0.845*0.375, 0.92*0.15) / pi
    #   specular = F0 / (4 pi a^2), 4 a^2 = 0.251502
    got = _f(N, N, [0.8, 0.5, 0.2], 0.5, 0.25)
    a = 0.25075
    want = [(0.462 + 0.23 / (4 * a * a)) / math.pi, (0.316875 + 0.155 / (4 * a * a)) / math.pi,
            (0.138 + 0.08 / (4 * a * a)) / math.pi]
    assert got.tolist() == pytest.approx(want, rel=1e-5)
    assert want[0] == pytest.approx(0.438155, rel=1e-5)       # (0.462 + 0.23 / 0.251502) / pi


def test_45_degrees_hand_worked():
    # l at 45 deg, v = n: h at 22.5 deg, n.h = v.h = cos(22.5) = 0.923880, n.l = 0.707107.
    # white dielectric (c = 1, m = 0), r = 1 (a = 1, D = 1/pi):
    #   F = 0.04 + 0.96 (1 - 0.923880)^5 = 0.04 + 0.96 * 2.5483e-6 = 0.04000245
    #   V = 1 / ((0.707107 + 1)(1 + 1)) = 0.292893   (a = 1: sqrt(a^2 + (1-a^2) x^2) = 1)
    #   f = (1 - F)/pi + F * V / pi = (0.95999755 + 0.0117163) / pi = 0.309302
    got = _f(*_at(45.0), [1.0, 1.0, 1.0], 1.0, 0.0)
    assert got.tolist() == pytest.approx([0.309302] * 3, rel=2e-5)


def test_reciprocity_and_back_faces():
    g = torch.Generator().manual_seed(0)
    n = torch.nn.functional.normalize(torch.randn(512, 3, generator=g), dim=-1)
    l = torch.nn.functional.normalize(n + 0.9 * torch.randn(512, 3, generator=g), dim=-1)
    v = torch.nn.functional.normalize(n + 0.9 * torch.randn(512, 3, generator=g), dim=-1)
    c = torch.rand(512, 3, generator=g)
    r = torch.rand(512, 1, generator=g)
    m = torch.rand(512, 1, generator=g)
    f_lv = bsdf.bsdf_eval(n, l, v, c, r, m, kind="gltf")
    f_vl = bsdf.bsdf_eval(n, v, l, c, r, m, kind="gltf")
    assert torch.allclose(f_lv, f_vl, rtol=1e-5, atol=1e-6)
    back = ((n * l).sum(-1) <= 0) | ((n * v).sum(-1) <= 0)
    assert back.any() and (f_lv[back] == 0).all() and (f_lv[~back] > 0).all()


def _directional_albedo(kind: str, theta_v_deg: float, r: float, albedo: float, m: float, n_samples=200_000):
    """``int f(l, v) (n.l) dl`` by Monte Carlo, independent of the BSDF's internals: the specular part
    by GGX importance sampling of h (pdf_l = D (n.h) / (4 v.h)), the diffuse part by cosine sampling;
    each estimator evaluates the full BSDF and weights it by the multiple-importance balance heuristic."""
    g = torch.Generator().manual_seed(1)
    a = bsdf.ggx_alpha_smooth(torch.tensor(r)).double()
    tv = math.radians(theta_v_deg)
    v = torch.tensor([math.sin(tv), 0.0, math.cos(tv)], dtype=torch.float64)

    def pdf_ggx(l):
        h = torch.nn.functional.normalize(l + v, dim=-1)
        nh, vh = h[:, 2].clamp_min(0), (h @ v).clamp_min(1e-12)
        d = a * a / (math.pi * (nh * nh * (a * a - 1) + 1) ** 2)
        return d * nh / (4 * vh)

    def pdf_cos(l):
        return l[:, 2].clamp_min(0) / math.pi

    u1, u2 = torch.rand(n_samples, generator=g, dtype=torch.float64), torch.rand(n_samples, generator=g, dtype=torch.float64)
    phi = 2 * math.pi * u2
    ct = torch.sqrt((1 - u1) / (1 + (a * a - 1) * u1))        # GGX: cos(theta_h)
    st = torch.sqrt(1 - ct * ct)
    h = torch.stack([st * torch.cos(phi), st * torch.sin(phi), ct], -1)
    l_spec = 2 * (h @ v)[:, None] * h - v
    u3, u4 = torch.rand(n_samples, generator=g, dtype=torch.float64), torch.rand(n_samples, generator=g, dtype=torch.float64)
    rr, ph = torch.sqrt(u3), 2 * math.pi * u4
    l_diff = torch.stack([rr * torch.cos(ph), rr * torch.sin(ph), torch.sqrt(1 - u3)], -1)
    total = 0.0
    for l, pdf_own in ((l_spec, pdf_ggx), (l_diff, pdf_cos)):
        ok = l[:, 2] > 0
        lv = l[ok]
        n = torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64).expand_as(lv)
        f = bsdf.bsdf_eval(n.float(), lv.float(), v.expand_as(lv).float(), torch.full((lv.shape[0], 3), albedo),
                           torch.full((lv.shape[0], 1), r), torch.full((lv.shape[0], 1), m), kind=kind)[:, 0].double()
        p_own = pdf_own(lv)
        w = p_own / (pdf_ggx(lv) + pdf_cos(lv))
        total += float((f * lv[:, 2] * w / p_own.clamp_min(1e-300)).sum()) / n_samples
    return total


@pytest.mark.parametrize("theta_v", [0.0, 85.0])
@pytest.mark.parametrize("r", [0.1, 0.5, 1.0])
def test_white_furnace_smith_ggx_lobe_is_bounded(theta_v, r):
    # a white metal (F = 1) is the bare Smith GGX lobe: its directional albedo is at most 1
    # (MC error ~0.3 %) and close to 1 when smooth (no lobe energy is lost but masking)
    metal = _directional_albedo("gltf", theta_v, r, 1.0, 1.0)
    assert 0.3 < metal <= 1.0 + 0.005
    if r <= 0.1:
        assert metal > 0.98


def test_white_furnace_dielectric_bounded_off_grazing_and_not_at_grazing():
    # The specification's dielectric, (1 - F(v.h)) c/pi + F D V, takes the diffuse weight from
    # each light's own half vector, not from the energy the lobe reflects at this view, so it is
    # energy-bounded only away from grazing views. Measured (200k samples, r = 0.1): 1.0005 at
    # 0 deg, 0.9999 at 30, 1.026 at 60, 1.20 at 75, 1.57 at 85 deg. Documented, not fixed: it is
    # the BRDF three.js renders the exported GLB with.
    for theta_v in (0.0, 30.0):
        for r in (0.1, 1.0):
            assert _directional_albedo("gltf", theta_v, r, 1.0, 0.0) <= 1.0 + 0.005
    assert _directional_albedo("gltf", 85.0, 0.1, 1.0, 0.0) > 1.3


def test_gltf_lobe_is_four_times_the_paper_lobe_at_normal_incidence():
    # paper: G / (4 n.v n.l) = 1 / (16 a^2) at n.l = n.v = 1; glTF: 1/4. The "about a quarter".
    assert _directional_albedo("gltf", 0.0, 0.1, 1.0, 1.0) > 0.95    # a smooth white metal reflects ~all
    assert _directional_albedo("paper", 0.0, 0.1, 1.0, 1.0) < 0.3
    f_gltf = _f(N, N, [1.0, 1.0, 1.0], 0.3, 1.0)[0]
    f_paper = _f(N, N, [1.0, 1.0, 1.0], 0.3, 1.0, kind="paper")[0]
    a_g, a_p = 1e-3 + 0.999 * 0.09, 0.09
    assert float(f_gltf) == pytest.approx(1 / (4 * math.pi * a_g * a_g), rel=1e-5)
    assert float(f_paper) == pytest.approx(1 / (16 * math.pi * a_p * a_p), rel=1e-5)


def test_smooth_roughness_floor_keeps_the_gradient():
    # near a mirror configuration the glTF path has d f / d r != 0 down to small r; the paper
    # path's max(r^2, 1e-3) gives exactly 0 below r = sqrt(1e-3) ~ 0.032
    l, v = _at(10.0, 10.0, 180.0)
    for kind, nonzero in (("gltf", True), ("paper", False)):
        r = torch.tensor([[0.02]], requires_grad=True)
        f = bsdf.bsdf_eval(N, l, v, torch.tensor([[0.9, 0.9, 0.9]]), r, torch.tensor([[1.0]]), kind=kind)
        f.sum().backward()
        assert (r.grad.abs().item() > 0) == nonzero, kind
    alpha = bsdf.ggx_alpha_smooth(torch.tensor([0.0, 0.5, 1.0]))
    assert alpha.tolist() == pytest.approx([1e-3, 0.25075, 1.0], rel=1e-6)


def test_visibility_forms_against_the_written_out_spec():
    # G1(x) = 2x / (x + sqrt(a^2 + (1 - a^2) x^2)); V = G1(l) G1(v) / (4 n.l n.v)
    nl, nv, a = torch.tensor([[0.3]]), torch.tensor([[0.8]]), torch.tensor([[0.4]])

    def g1(x, a):
        return 2 * x / (x + math.sqrt(a * a + (1 - a * a) * x * x))
    want = g1(0.3, 0.4) * g1(0.8, 0.4) / (4 * 0.3 * 0.8)
    assert bsdf.smith_visibility_gltf(nl, nv, a).item() == pytest.approx(want, rel=1e-6)
    assert bsdf.smith_g1_gltf(nl, a).item() == pytest.approx(g1(0.3, 0.4), rel=1e-6)
    # three.js' height-correlated V equals it at normal incidence and is larger off it
    one = torch.ones(1, 1)
    assert bsdf.smith_visibility_correlated(one, one, a).item() == pytest.approx(0.25, rel=1e-6)
    corr = bsdf.smith_visibility_correlated(nl, nv, a).item()
    assert corr > want and corr / want < 1.2


def test_disney_vs_lambert_at_normal_incidence_and_45():
    # The paper kind's Disney diffuse equals Lambert at n.l = n.v = 1 (f_l = f_v = 0) and is
    # 1 - f_l/2 + R f_l times it with l at 45 deg, v = n: f_l = (1 - cos 45)^5 = 0.0021601,
    # R = 2 r cos^2(22.5) = 0.853553 at r = 0.5: ratio 1 - 0.00108 + 0.0018437 = 1.000764.
    for (l, v), ratio in ((( N, N), 1.0), (_at(45.0), 1.0007637)):
        d = bsdf.bsdf_eval(N, l, v, torch.ones(1, 3), torch.tensor([[0.5]]), torch.zeros(1, 1), specular=False)
        lam = bsdf.bsdf_eval(N, l, v, torch.ones(1, 3), torch.tensor([[0.5]]), torch.zeros(1, 1),
                             specular=False, lambertian=True)
        assert (d / lam)[0, 0].item() == pytest.approx(ratio, abs=2e-6)


def test_unknown_kind_is_a_clear_error():
    with pytest.raises(ValueError, match="unknown BSDF kind 'phong'"):
        _f(N, N, [1.0, 1.0, 1.0], 0.5, 0.0, kind="phong")


def test_paper_kind_is_unchanged_by_the_selector():
    g = torch.Generator().manual_seed(3)
    n = torch.nn.functional.normalize(torch.randn(64, 3, generator=g) + torch.tensor([0, 0, 3.0]), dim=-1)
    l = torch.nn.functional.normalize(torch.randn(64, 3, generator=g) + torch.tensor([0, 0, 2.0]), dim=-1)
    v = torch.nn.functional.normalize(torch.randn(64, 3, generator=g) + torch.tensor([0, 0, 2.0]), dim=-1)
    c, r, m = torch.rand(64, 3, generator=g), torch.rand(64, 1, generator=g), torch.rand(64, 1, generator=g)
    assert torch.equal(bsdf.bsdf_eval(n, l, v, c, r, m), bsdf.bsdf_eval(n, l, v, c, r, m, kind="paper"))
    assert np.isfinite(bsdf.bsdf_eval(n, l, v, c, r, m, kind="gltf").numpy()).all()
