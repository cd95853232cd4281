"""The highlight light cue (nepf_core/render/highlight_light.py): the mirror direction, a point-lit
glossy sphere whose saturated pixels point at the light, an over-exposed diffuse sphere that must
not count, the gathering on a stand-in model, and the loss term's value."""

import math

import torch

from nepf_core import bsdf
from nepf_core.losses import loss_highlight_light
from nepf_core.render import highlight_light as hl


def _unit(t):
    return torch.nn.functional.normalize(t, dim=-1)


def test_the_mirror_direction_by_hand():
    d = _unit(torch.tensor([[1.0, 0.0, -1.0], [0.0, 0.0, -1.0]]))
    n = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    r = hl.mirror_direction(d, n)
    assert torch.allclose(r, torch.tensor([[1.0 / math.sqrt(2.0), 0.0, 1.0 / math.sqrt(2.0)], [0.0, 0.0, 1.0]]))


def _sphere_view(light_pos, albedo, roughness, metallic, intensity, res=96):
    """A unit sphere at the origin seen from (0, 0, 3) (pinhole, 40 deg), lit by a point light:
    ``(x, n, d, rgb, l_true)`` of the pixels that hit it, shaded by the glTF BSDF, clipped to 1."""
    s = torch.linspace(-0.36, 0.36, res)
    yy, xx = torch.meshgrid(s, s, indexing="ij")
    d = _unit(torch.stack([xx, yy, -torch.ones_like(xx)], -1).reshape(-1, 3))
    o = torch.tensor([0.0, 0.0, 3.0])
    b = (d * o).sum(-1)
    disc = b * b - (o @ o - 1.0)
    hit = disc > 0
    d, b, disc = d[hit], b[hit], disc[hit]
    x = o + (-b - disc.sqrt())[:, None] * d
    n = _unit(x)
    to_light = light_pos - x
    l = _unit(to_light)
    k = x.shape[0]
    e = (intensity / (to_light * to_light).sum(-1))[:, None]
    rgb = bsdf.shade(n, l, -d, torch.tensor(albedo).expand(k, 3), torch.full((k, 1), roughness),
                     torch.full((k, 1), metallic), e, kind="gltf").clamp(0.0, 1.0)
    return x, n, d, rgb, l


def _angle_deg(a, b):
    return torch.rad2deg(torch.acos((a * b).sum(-1).clamp(-1.0, 1.0)))


def test_the_saturated_pixels_of_a_glossy_sphere_point_at_the_light():
    """A white metal of roughness 0.1 (GGX alpha 0.01) under a light 5 units away: its saturated
    patch is where the half vector is within a few degrees of the normal, so the mirror direction
    there lies within twice that of the true light direction at each point."""
    light = torch.tensor([2.0, 1.5, 4.3])
    x, n, d, rgb, l = _sphere_view(light, (0.9, 0.9, 0.9), 0.1, 1.0, 60.0)
    sat = rgb.amin(-1) >= hl.SATURATED
    assert 5 <= int(sat.sum()) < 0.05 * len(rgb)          # a highlight, not the whole disc
    r = hl.mirror_direction(d[sat], n[sat])
    # the half vector's largest angle from the normal over the saturated patch bounds the error
    h = _unit(l[sat] - d[sat])
    bound = 2.0 * float(_angle_deg(h, n[sat]).max()) + 1e-3
    assert bound < 10.0
    assert float(_angle_deg(r, l[sat]).max()) <= bound
    # an unsaturated pixel away from the highlight points elsewhere: the cue needs the saturation
    far = rgb.amax(-1) < 0.05
    assert float(_angle_deg(hl.mirror_direction(d[far], n[far]), l[far]).median()) > 30.0


def test_an_over_exposed_diffuse_sphere_is_not_a_highlight():
    """A Lambertian sphere under a light strong enough to saturate a broad disc: its mirror
    directions miss the light, and its colour toward other cameras is saturated too, so
    :func:`is_highlight` rejects it; a mirror's point, dark from every other camera, passes."""
    light = torch.tensor([0.0, 3.0, 3.0])
    x, n, d, rgb, l = _sphere_view(light, (0.8, 0.8, 0.8), 1.0, 0.0, 200.0)
    sat = rgb.amin(-1) >= hl.SATURATED
    assert int(sat.sum()) > 0.1 * len(rgb)
    assert float(_angle_deg(hl.mirror_direction(d[sat], n[sat]), l[sat]).median()) > 15.0
    # the same points toward 8 other cameras around them (Lambertian: the colour does not move)
    P, K = int(sat.sum()), 8
    v = _unit(n[sat][:, None, :] + 0.6 * _unit(torch.randn(P, K, 3, generator=torch.Generator().manual_seed(0))))
    e = (200.0 / ((light - x[sat]) ** 2).sum(-1))[:, None, None].expand(P, K, 1)
    rep = lambda t: t[:, None, :].expand(P, K, 3)
    c = bsdf.shade(rep(n[sat]), rep(l[sat]), v, torch.full((P, K, 3), 0.8), torch.ones(P, K, 1),
                   torch.zeros(P, K, 1), e, kind="gltf").clamp(0.0, 1.0)
    valid = torch.ones(P, K, dtype=torch.bool)
    assert not bool(hl.is_highlight(c, valid).any())
    dark = torch.zeros(P, K, 3)
    dark[:, 0] = 1.0                                      # one other camera also catches the lobe
    assert bool(hl.is_highlight(dark, valid).all())
    few = valid.clone()
    few[:, hl.MIN_VIEWS - 1:] = False                     # fewer than MIN_VIEWS views say nothing
    assert not bool(hl.is_highlight(dark, few).any())


class _SDF:
    def __init__(self):
        self.feature = torch.nn.Parameter(torch.zeros(1, 2))

    def sdf(self, x):
        return x.norm(dim=-1) - 0.5

    def __call__(self, x):
        return self.sdf(x), self.feature.expand(x.shape[0], 2)


class _Photon(torch.nn.Module):
    """The light direction ``normalize(w)``: one parameter, the same at every point."""

    def __init__(self):
        super().__init__()
        self.w = torch.nn.Parameter(torch.tensor([1.0, 0.0, 1.0]))

    def forward(self, x, n, f):
        return _unit(self.w).expand(x.shape[0], 3), torch.ones(x.shape[0])


class _MirrorModel:
    """A sphere of radius 0.5 whose radiance is white toward camera 0 and black elsewhere."""

    def __init__(self, cams):
        self.sdf, self.photon, self.cams = _SDF(), _Photon(), cams

    def radiance(self, x, d, n, f, with_logits=False):
        toward_first = _unit(self.cams[0] - x)
        return ((-d * toward_first).sum(-1, keepdim=True) > 0.999).float().expand(-1, 3)


def test_gather_keeps_the_saturated_highlights_and_the_term_moves_only_the_light():
    cams = torch.tensor([[0.0, 0.0, 3.0], [1.0, 0.0, 3.0], [0.0, 1.0, 3.0], [-1.0, 0.0, 3.0], [0.0, -1.0, 3.0]])
    model = _MirrorModel(cams)
    x = torch.tensor([[0.0, 0.0, 0.5], [0.1, 0.0, 0.49], [0.0, 0.0, -0.5]])
    n = _unit(x)
    d = _unit(x - cams[0])
    rgb = torch.tensor([[1.0, 1.0, 1.0], [0.5, 0.5, 0.5], [1.0, 1.0, 1.0]])
    keep = torch.tensor([True, True, True])
    hb = hl.gather_highlights(model, x, n, d, rgb, keep, cams, torch.Generator().manual_seed(0))
    # ray 1 is not saturated; ray 2 (the far side) is seen by no camera: only ray 0 counts
    assert hb.target.shape == (1, 3)
    assert torch.allclose(hb.target, hl.mirror_direction(d[:1], n[:1]))
    assert torch.allclose(hb.light_dir, _unit(model.photon.w).expand(1, 3))

    class Out:
        highlight_light = hb

    class Batch:
        out, zero = Out(), torch.zeros(())

    loss = loss_highlight_light(Batch())
    want = 1.0 - (hb.light_dir * hb.target).sum(-1).mean()
    assert torch.allclose(loss, want)
    loss.backward()
    assert float(loss.detach()) > 0.2 and float(model.photon.w.grad.norm()) > 0.0    # 45 deg off: 1 - cos 45
    assert model.sdf.feature.grad is None                 # the cue moves the light, not the surface
    # nothing saturated: an empty batch and a zero term
    none = hl.gather_highlights(model, x, n, d, rgb * 0.5, keep, cams)
    assert none.target.shape == (0, 3)

    class Empty:
        out, zero = type("O", (), {"highlight_light": none})(), torch.zeros(())

    assert float(loss_highlight_light(Empty())) == 0.0
