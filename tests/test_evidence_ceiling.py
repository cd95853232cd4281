"""bench/evidence_ceiling.py: the true-light shading (inverse square, sum over lights, the BSDF's
own value), the scale-fitted residual and the per-brightness ratio, worked by hand."""

import numpy as np
import pytest
import torch

from bench.evidence_ceiling import ratio_by_brightness, scaled_relative_residual, shade_true_lights
from nepf_core import bsdf


def _setup(metallic: float):
    x = np.zeros((1, 3))
    n = torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64)
    v = torch.nn.functional.normalize(torch.tensor([[[0.3, 0.0, 1.0], [-0.5, 0.2, 1.0]]], dtype=torch.float64), dim=-1)
    albedo = torch.tensor([[0.8, 0.5, 0.2]], dtype=torch.float64)
    return x, n, v, albedo, torch.tensor([0.4], dtype=torch.float64), torch.tensor([metallic], dtype=torch.float64)


@pytest.mark.parametrize("metallic", [0.0, 1.0])
def test_one_light_is_the_bsdf_times_the_inverse_square_irradiance(metallic):
    x, n, v, a, r, m = _setup(metallic)
    pos = np.array([1.0, 0.5, 2.0])
    out = shade_true_lights(x, n, v, a, r, m, [{"position_world": pos.tolist(), "intensity_rgb": [4.0, 4.0, 4.0]}])
    d2 = float((pos ** 2).sum())
    u = torch.tensor(pos / np.sqrt(d2))[None, None].expand(1, 2, 3)
    f = bsdf.bsdf_eval(n[:, None].expand(1, 2, 3), u, v, a[:, None].expand(1, 2, 3), r.reshape(1, 1, 1).expand(1, 2, 1),
                       m.reshape(1, 1, 1).expand(1, 2, 1), kind="gltf")
    assert torch.allclose(out, f * 4.0 * float(u[0, 0, 2]) / d2)


def test_lights_add_and_fall_off_with_the_square_of_the_distance():
    x, n, v, a, r, m = _setup(0.0)
    near = {"position_world": [0.0, 0.0, 2.0], "intensity_rgb": [1.0, 1.0, 1.0]}
    far = {"position_world": [0.0, 0.0, 4.0], "intensity_rgb": [1.0, 1.0, 1.0]}
    below = {"position_world": [0.0, 0.0, -3.0], "intensity_rgb": [9.0, 9.0, 9.0]}
    one = shade_true_lights(x, n, v, a, r, m, [near])
    assert torch.allclose(shade_true_lights(x, n, v, a, r, m, [far]), one / 4.0)
    assert torch.allclose(shade_true_lights(x, n, v, a, r, m, [near, far, below]), one * 1.25)
    assert float(one.min()) > 0.0


def test_the_scaled_residual_by_hand():
    model = torch.tensor([[[1.0, 1.0, 1.0], [0.0, 0.0, 0.0], [5.0, 5.0, 5.0]]])
    c = torch.tensor([[[2.0, 2.0, 2.0], [1.0, 1.0, 1.0], [9.0, 9.0, 9.0]]])
    valid = torch.tensor([[True, True, False]])
    # best scale over the two valid views: s = 2; residual 3 (the second view) of power 12 + 3
    assert float(scaled_relative_residual(model, c, valid)[0]) == pytest.approx(3.0 / 15.0)
    assert float(scaled_relative_residual(model, 3.0 * model, torch.ones(1, 3, dtype=torch.bool))[0]) == pytest.approx(0.0, abs=1e-12)


def test_the_ratio_is_binned_by_the_views_brightness_over_the_points_median():
    model = torch.tensor([[1.0, 1.0, 1.0, 10.0]])[..., None].expand(1, 4, 3)
    pixels = torch.tensor([[1.0, 1.0, 1.0, 5.0]])[..., None].expand(1, 4, 3)
    rows = ratio_by_brightness(model, pixels, torch.ones(1, 4, dtype=torch.bool))
    assert [(r["model_over_median"], r["views"]) for r in rows] == [([1.0, 2.0], 3), ([5.0, float("inf")], 1)]
    assert rows[0]["pixel_over_model_p25_p50_p75"] == [1.0, 1.0, 1.0]
    assert rows[1]["pixel_over_model_p25_p50_p75"] == [0.5, 0.5, 0.5]
