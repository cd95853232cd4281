"""The whole-view render's anti-aliased silhouettes (``render_view``: ``nepf render`` and the
held-out PBR PSNR), on an analytic half plane seen from above: the renderer is replaced by a ray
-> plane intersection so that every expected value is worked by hand."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import torch

from nepf_core import evaluate
from nepf_core.rays import PixelSampler
from nepf_core.render.renderer import RenderConfig
from tests.test_relight_shading import top_camera

EDGE = 0.005
"""The plane z = 0 is covered for x <= EDGE."""


def half_plane_render(calls):
    """A stand-in for ``render_rays``: each ray meets z = 0 at ``p``; it is covered (weight sum 1)
    when ``p_x <= EDGE``; its surface colour and albedo are ``(p_x + 1, p_y + 1, 0.5)``."""
    def render(model, rays, cfg, train, shading):
        calls.append(len(rays))
        t = -rays.origins[:, 2] / rays.directions[:, 2]
        p = rays.origins + t[:, None] * rays.directions
        w = (p[:, 0] <= EDGE).float()
        colour = torch.stack([p[:, 0] + 1, p[:, 1] + 1, torch.full_like(t, 0.5)], -1)
        ones = torch.ones_like(t)
        surface = SimpleNamespace(albedo=colour, roughness=ones * 0.3, metallic=ones * 0.2,
                                  normal=torch.zeros_like(p), light_dir=torch.zeros_like(p), intensity=ones)
        return SimpleNamespace(weight_sum=w, rgb_surf=colour, rgb_r=colour * w[:, None], background=None,
                               surface=surface, depth=t)
    return render


@pytest.fixture
def calls(monkeypatch):
    seen = []
    monkeypatch.setattr(evaluate, "render_rays", half_plane_render(seen))
    return seen


def render(stride=1, subsamples=2):
    return evaluate.render_view(torch.nn.Module(), PixelSampler(top_camera(), "cpu"), 0,
                                RenderConfig(), stride=stride, subsamples=subsamples)


def test_a_silhouette_pixel_is_the_mean_of_its_subpixel_rays(calls):
    """The top camera's centre pixel spans x in [-0.02, 0.02]; its 2 x 2 sub-pixel rays meet the
    plane at x = -0.01 (covered) and +0.01 (not), y = +-0.01. So alpha = 2/4 and
    pbr = (1/4) sum_j alpha_j c_j = ((0.99 + 0.99) / 4, (0.99 + 1.01) / 4, (0.5 + 0.5) / 4). The
    centre ray (x = 0) is covered: one ray calls the pixel whole. The albedo (not composited)
    keeps the centre ray's value."""
    r = render()
    assert r["alpha"][2, 2, 0] == pytest.approx(0.5)
    np.testing.assert_allclose(r["pbr"][2, 2], [0.495, 0.5, 0.25], atol=1e-6)
    np.testing.assert_allclose(r["radiance"][2, 2], r["pbr"][2, 2], atol=1e-6)
    np.testing.assert_allclose(r["albedo"][2, 2], [1.0, 1.0, 0.5], atol=1e-6)
    assert r["alpha"][2, 3, 0] == 0.0 and r["alpha"][2, 1, 0] == 1.0
    one = render(subsamples=1)
    assert one["alpha"][2, 2, 0] == 1.0
    np.testing.assert_allclose(one["pbr"][2, 2], [1.0, 1.0, 0.5], atol=1e-6)


def test_only_the_silhouette_pixels_take_the_subpixel_rays(calls):
    """Centre rays of columns 0-2 hit (x = -0.08, -0.04, 0), of 3-4 miss: columns 2 and 3 (10
    pixels) have both in their 3 x 3 neighbourhood. So 25 centre rays and 4 x 10 sub-pixel rays,
    and columns 0-1 keep their centre ray."""
    r = render()
    assert sum(calls) == 25 + 4 * 10
    one = render(subsamples=1)
    np.testing.assert_array_equal(r["pbr"][:, :2], one["pbr"][:, :2])


def test_a_strided_render_subsamples_the_full_resolution_pixel(calls):
    """With stride 2 the render's pixel (1, 1) is the camera's pixel (2, 2): the same half-covered
    pixel as above, and the same mean."""
    r = render(stride=2)
    assert r["pbr"].shape == (3, 3, 3)
    assert r["alpha"][1, 1, 0] == pytest.approx(0.5)
    np.testing.assert_allclose(r["pbr"][1, 1], [0.495, 0.5, 0.25], atol=1e-6)
