"""The global-emitter light model (nepf_core.fields.emitters): hand-worked values, the shading's
sum over lights, and a point light recovered from the shading of a sphere."""

from __future__ import annotations

import math
from types import SimpleNamespace

import torch

from nepf_core import bsdf
from nepf_core.fields.emitters import VISIBILITY_INIT_LOGIT, EmitterLight, dominant
from nepf_core.fields.heads import HeadConfig, MaterialField, PhotonField
from nepf_core.render.renderer import RenderConfig
from nepf_core.render.shading import Shading, shade_points

HEAD = HeadConfig(width=16, depth=2, n_freqs_x=2, use_feature=False)


def _flat_visibility(light: EmitterLight, logit: float = 0.0) -> None:
    """Make the visibility network output ``logit`` everywhere: ``v = sigmoid(logit + 4)``."""
    last = light.visibility.layers[-1]
    with torch.no_grad():
        last.weight.zero_()
        last.bias.fill_(logit)


def test_illuminate_is_inverse_square_towards_each_emitter():
    light = EmitterLight(HEAD, 2)
    _flat_visibility(light)
    with torch.no_grad():
        light.positions.copy_(torch.tensor([[0.0, 0.0, 3.0], [4.0, 0.0, 0.0]]))
        light.log_intensity.copy_(torch.log(torch.tensor([9.0, 32.0])))
    x = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 0.0]])
    dirs, irr = light.illuminate(x, torch.zeros(2, 3), torch.zeros(2, 0))
    v = 1.0 / (1.0 + math.exp(-VISIBILITY_INIT_LOGIT))
    # point (0,0,1): emitter 0 is 2 away straight up, emitter 1 at (4,0,-1)/sqrt(17)
    assert torch.allclose(dirs[0, 0], torch.tensor([0.0, 0.0, 1.0]))
    assert torch.allclose(dirs[0, 1], torch.tensor([4.0, 0.0, -1.0]) / math.sqrt(17.0))
    assert torch.allclose(irr[0], torch.tensor([v * 9.0 / 4.0, v * 32.0 / 17.0]))
    assert torch.allclose(irr[1], torch.tensor([v * 9.0 / 9.0, v * 32.0 / 16.0]))


def test_dominant_is_the_light_with_most_irradiance_times_cosine():
    dirs = torch.tensor([[[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]]] * 2)
    irr = torch.tensor([[1.0, 5.0], [1.0, 5.0]])
    n = torch.tensor([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8]])
    l, e = dominant(dirs, irr, n)
    # first point: the second light grazes (n.l = 0), so the first wins; second: 5 * 0.6 > 1 * 0.8
    assert torch.equal(l[0], dirs[0, 0]) and e[0] == 1.0
    assert torch.equal(l[1], dirs[1, 1]) and e[1] == 5.0


def test_place_starts_at_the_cameras_farthest_apart_and_keeps_the_irradiance():
    light = EmitterLight(HEAD, 2)
    before = (light.log_intensity.exp() / (light.positions ** 2).sum(-1)).sum()
    cams = torch.tensor([[3.0, 0.0, 0.0], [2.9, 0.5, 0.0], [-3.0, 0.0, 0.1], [0.0, 3.0, 0.0]])
    light.place(cams)
    mean = cams.mean(0)
    first = int(((cams - mean) ** 2).sum(-1).argmin())
    far = int(torch.cdist(cams, cams[first:first + 1])[:, 0].argmax())
    assert torch.allclose(light.positions, torch.stack([cams[first], cams[far]]) * 1.5)
    after = (light.log_intensity.exp() / (light.positions ** 2).sum(-1)).sum()
    assert torch.allclose(before, after)


def _shade_with(light, material, n_points=64, specular=True):
    g = torch.Generator().manual_seed(0)
    x = torch.randn(n_points, 3, generator=g) * 0.3
    n = torch.nn.functional.normalize(torch.randn(n_points, 3, generator=g), dim=-1)
    v = -torch.nn.functional.normalize(x - torch.tensor([0.0, 0.0, 3.0]), dim=-1)   # rays from a camera
    f = torch.randn(n_points, 8, generator=g)
    model = SimpleNamespace(photon=light, material=material)
    cfg = RenderConfig(bsdf_kind="gltf")
    return x, v, n, f, shade_points(model, cfg, Shading(specular=specular), x, v, n, f, None)


def test_shading_sums_one_bsdf_term_per_emitter():
    torch.manual_seed(0)
    light, material = EmitterLight(HEAD, 3), MaterialField(HeadConfig(width=16, depth=2), 8)
    x, v, n, f, p = _shade_with(light, material)
    dirs, irr = light.illuminate(x, n, f)
    albedo, rough, metal = material(x, n, f)
    want = sum(bsdf.shade(n, dirs[:, k], -v, albedo, rough[:, None], metal[:, None], irr[:, k, None], kind="gltf")
               for k in range(3))
    assert torch.allclose(p.pbr, want, atol=1e-6)
    assert p.lights is not None and p.lights[0].shape == (64, 3, 3)
    # each emitter contributes: the sum differs from every single term where it is lit
    single = bsdf.shade(n, dirs[:, 0], -v, albedo, rough[:, None], metal[:, None], irr[:, 0, None], kind="gltf")
    assert not torch.allclose(p.pbr, single)


def test_photon_field_shades_as_one_light():
    torch.manual_seed(0)
    light, material = PhotonField(HEAD, 8), MaterialField(HeadConfig(width=16, depth=2), 8)
    x, v, n, f, p = _shade_with(light, material)
    l, intensity = light(x, n, f)
    albedo, rough, metal = material(x, n, f)
    want = bsdf.shade(n, l, -v, albedo, rough[:, None], metal[:, None], intensity[:, None], kind="gltf")
    assert torch.equal(p.pbr, want) and p.lights is None
    assert torch.equal(p.light_dir, l) and torch.equal(p.intensity, intensity)


def test_a_point_light_is_recovered_from_a_lambertian_sphere():
    """Shading of a unit sphere under a point light at p* (Lambert, albedo 0.6, every point
    visible to the light or facing away): fitting one emitter and the albedo from a start at the
    camera side finds p* within 3 degrees and 10 % of its distance."""
    torch.manual_seed(0)
    g = torch.Generator().manual_seed(1)
    n = torch.nn.functional.normalize(torch.randn(512, 3, generator=g), dim=-1)
    x = n.clone()
    p_true, i_true, albedo_true = torch.tensor([2.0, -3.0, 4.0]), 60.0, 0.6
    to = p_true - x
    d2 = (to ** 2).sum(-1)
    l_true = to / d2.sqrt()[:, None]
    target = albedo_true / math.pi * i_true / d2 * (n * l_true).sum(-1).clamp_min(0)
    light = EmitterLight(HEAD, 1)
    _flat_visibility(light, 10.0)           # fully visible (the sphere casts no shadow on itself)
    light.visibility.requires_grad_(False)
    light.place(torch.tensor([[0.0, 0.0, 4.0]]))   # one camera above: start far from p*
    raw_albedo = torch.zeros((), requires_grad=True)
    opt = torch.optim.Adam([light.positions, light.log_intensity, raw_albedo], lr=0.1)
    for _ in range(300):
        dirs, irr = light.illuminate(x, n, None)
        pred = torch.sigmoid(raw_albedo) / math.pi * irr[:, 0] * (n * dirs[:, 0]).sum(-1).clamp_min(0)
        loss = (pred - target).abs().mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    p = light.positions.detach()[0]
    angle = math.degrees(math.acos(float(torch.dot(p, p_true) / (p.norm() * p_true.norm()))))
    assert angle < 3.0, (p, angle)
    assert abs(float(p.norm() / p_true.norm()) - 1.0) < 0.1, p
