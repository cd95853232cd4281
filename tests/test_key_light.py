"""nepf_core/train/key_light.py: the key light fitted to the pixels, points and normals, on
generated shading, its gate on scenes the diffuse model does not explain, and the training term
by hand."""

import math

import pytest
import torch

from nepf_core import bsdf
from nepf_core.losses import LossConfig, loss_key_light
from nepf_core.train.key_light import (CAPACITY, MIN_EXPLAINED, KeyLightEstimate, fibonacci_directions,
                                       fit_key_light)


def _angle_deg(a, b):
    cos = (a * b).sum(-1) / (a.norm(dim=-1) * b.norm(dim=-1))
    return torch.rad2deg(torch.acos(cos.clamp(-1.0, 1.0)))


def _sphere(count, seed, radius=0.8):
    g = torch.Generator().manual_seed(seed)
    n = torch.nn.functional.normalize(torch.randn(count, 3, generator=g), dim=-1)
    return radius * n, n, g


def _seen_from_cameras(n, g):
    v = torch.nn.functional.normalize(torch.randn(n.shape[0], 3, generator=g), dim=-1)
    return torch.where((v * n).sum(-1, keepdim=True) < 0.2, torch.nn.functional.normalize(v + 2 * n, dim=-1), v)


def test_a_point_lit_textured_lambertian_sphere_gives_its_light_within_three_degrees_at_most_points():
    """A sphere of radius 0.8 lit by a point light 4.5 units away (its direction spreads by ~20 deg
    over the sphere), albedo a checker of 0.6-0.85 with noise, every foreground pixel: a point light
    is fitted, and the direction toward it is within 3 deg of the truth at 90 % of the lit points."""
    x, n, g = _sphere(4000, 0)
    light = torch.tensor([2.0, -2.5, 3.0])
    to_light = light - x
    d = to_light.norm(dim=-1)
    cos = ((n * to_light).sum(-1) / d).clamp_min(0.0)
    checker = (((x + 1.0) * 3).floor().long().sum(-1) % 2).float()
    albedo = 0.6 + 0.2 * checker + 0.05 * torch.rand(4000, generator=g)
    y = (albedo * 40.0 * cos / d ** 2 / math.pi).clamp(max=1.0)
    key = fit_key_light(x, n, y)
    assert key.position is not None and key.explained > 0.9
    lit = cos > 0
    err = _angle_deg(key.toward(x[lit]), to_light[lit])
    assert float(err.quantile(0.9)) < 3.0


def test_a_distant_light_on_a_lambertian_sphere_is_fitted_as_one():
    """Parallel light: a distant key (a near point would not explain the pixels 10 % better),
    within 1 deg."""
    x, n, g = _sphere(4000, 1)
    u = torch.nn.functional.normalize(torch.tensor([-0.3, 0.5, 0.8]), dim=0)
    y = (0.5 * (n @ u).clamp_min(0.0) + 0.02 * torch.rand(4000, generator=g)).clamp(max=1.0)
    key = fit_key_light(x, n, y)
    assert key.position is None
    assert float(_angle_deg(key.direction, u)) < 1.0


def test_a_gold_metal_sphere_is_not_explained_so_its_key_is_not_used():
    """A GGX gold metal (roughness 0.3) has no diffuse: its pixels do not fix the light, and the
    fit explains too little of them to be used (the estimate gives no key)."""
    x, n, g = _sphere(4000, 2)
    v = _seen_from_cameras(n, g)
    u = torch.nn.functional.normalize(torch.tensor([0.3, -0.4, 0.9]), dim=0)
    y = bsdf.shade(n, u.expand_as(n), v, torch.tensor([1.0, 0.78, 0.34]).expand(4000, 3), torch.full((4000, 1), 0.3),
                   torch.ones(4000, 1), torch.full((4000, 1), 3.0), kind="gltf").mean(-1).clamp(max=1.0)
    assert fit_key_light(x, n, y).explained < MIN_EXPLAINED
    est = KeyLightEstimate("cpu")
    est.add(x, n, y)
    assert est.maybe_refit(100) and est.key is None and est.last_fit is not None


def test_the_estimate_waits_for_its_first_fit_and_keeps_the_latest_rays():
    est = KeyLightEstimate("cpu")
    x, n, _ = _sphere(5000, 3)
    u = torch.nn.functional.normalize(torch.tensor([0.0, 0.5, 1.0]), dim=0)
    est.add(x, n, (n @ u).clamp_min(0.0) * 0.7)
    assert not est.maybe_refit(99) and est.key is None
    assert est.maybe_refit(100)
    assert float(_angle_deg(est.key.toward(x[:1])[0], u)) < 1.0
    assert est.x.shape[0] == CAPACITY


def test_fibonacci_directions_are_unit_and_balanced():
    u = fibonacci_directions(1024)
    assert torch.allclose(u.norm(dim=-1), torch.ones(1024), atol=1e-6)
    assert float(u.mean(0).norm()) < 1e-2


class _Batch:
    def __init__(self, normal, light_dir, key, lit):
        surface = type("S", (), {"normal": normal, "light_dir": light_dir})()
        self.out = type("O", (), {"surface": surface, "key_light": key})()
        self.lit, self.zero, self.cfg = lit, torch.zeros(()), LossConfig()


def test_the_key_light_term_by_hand():
    """Two lit rays facing the key, their photon directions at 0 and 60 deg from it, one lit ray
    facing away and one unlit: the mean over the first two of (1 - cos) = (0 + 0.5) / 2."""
    u = (torch.tensor([0.0, 0.0, 1.0]).expand(4, 3), torch.zeros(4))
    normal = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.6, 0.8], [0.0, 0.0, -1.0], [0.0, 0.0, 1.0]])
    l = torch.tensor([[0.0, 0.0, 1.0], [0.0, math.sin(math.pi / 3), 0.5], [1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    lit = torch.tensor([True, True, True, False])
    assert float(loss_key_light(_Batch(normal, l, u, lit))) == pytest.approx(0.25, abs=1e-6)
    assert float(loss_key_light(_Batch(normal, l, None, lit))) == 0.0
