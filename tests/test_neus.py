"""NeuS opacity / weights: a hand-worked ray, invariants, and the stability sweep."""

import math

import torch

from nepf_core.render.neus import alpha_from_sdf, annealed_cos, max_weight_index, weights_from_alpha


def sigmoid(x):
    return 1.0 / (1.0 + math.exp(-x))


def test_alpha_hand_worked_section():
    # One section: mid SDF 0 (the surface), cos = -1 (entering), length 0.2, s = 10.
    # prev_sdf = 0 - (-1)(0.2)/2 = +0.1, next_sdf = -0.1
    # prev_cdf = sigmoid(1) = 0.7310586, next_cdf = sigmoid(-1) = 0.2689414
    # alpha = (0.7310586 - 0.2689414 + 1e-5) / (0.7310586 + 1e-5) = 0.632130...
    a = alpha_from_sdf(torch.tensor([[0.0]]), torch.tensor([[-1.0]]), torch.tensor([[0.2]]), 10.0)
    p, n = sigmoid(1.0), sigmoid(-1.0)
    expected = (p - n + 1e-5) / (p + 1e-5)
    assert abs(float(a) - expected) < 1e-6


def test_weights_hand_worked_ray():
    # alphas 0.5, 0.5, 1.0 -> T = 1, 0.5(+1e-7), 0.25 -> w = 0.5, 0.25, 0.25
    w = weights_from_alpha(torch.tensor([[0.5, 0.5, 1.0]], dtype=torch.float64))
    assert torch.allclose(w, torch.tensor([[0.5, 0.25, 0.25]], dtype=torch.float64), atol=1e-6)


def test_exiting_section_is_transparent_after_annealing():
    # cos > 0 (leaving the surface) with anneal ratio 1 gives cos' = 0 -> alpha ~ 1e-5 / (cdf + 1e-5) ~ 0
    c = annealed_cos(torch.tensor([0.8]), 1.0)
    assert float(c) == 0.0
    a = alpha_from_sdf(torch.tensor([[0.05]]), c[None], torch.tensor([[0.1]]), 50.0)
    assert float(a) < 1e-4


def test_alpha_weights_sweep_finite_and_bounded():
    # inv_s from 1 to 1e6, SDF values up to +-1e4, random cosines and section lengths
    g = torch.Generator().manual_seed(0)
    for inv_s in [1.0, 10.0, 1e3, 1e6]:
        sdf = torch.cat([torch.full((4, 16), 1e4), torch.full((4, 16), -1e4),
                         (torch.rand(56, 16, generator=g) - 0.5) * 2e4 * torch.rand(56, 1, generator=g)])
        sdf = torch.cat([sdf, torch.linspace(1, -1, 16).expand(8, 16)])
        cos = -torch.rand(sdf.shape, generator=g) * 2 + 0.5
        dists = torch.rand(sdf.shape, generator=g) * 0.1
        sdf.requires_grad_(True)
        a = alpha_from_sdf(sdf, cos, dists, torch.tensor(inv_s))
        w = weights_from_alpha(a)
        assert torch.isfinite(a).all() and torch.isfinite(w).all()
        assert (a >= 0).all() and (a <= 1).all()
        assert (w.sum(-1) <= 1.0 + 1e-5).all()
        w.sum().backward()
        assert torch.isfinite(sdf.grad).all()


def test_max_weight_with_all_zero_weights():
    idx, wmax = max_weight_index(torch.zeros(3, 8))
    assert idx.tolist() == [0, 0, 0] and wmax.tolist() == [0.0, 0.0, 0.0]


def test_weights_peak_at_surface_for_sharp_s():
    # A planar surface at t = 1 along the ray: sdf(t) = 1 - t, cos = -1.
    t = torch.linspace(0, 2, 201)[None]
    dist = torch.full_like(t, 0.01)
    sdf_mid = 1 - (t + 0.005)
    w = weights_from_alpha(alpha_from_sdf(sdf_mid, -torch.ones_like(t), dist, 200.0))
    t_peak = float((t + 0.005)[0, w.argmax()])
    assert abs(t_peak - 1.0) < 0.02
    assert float(w.sum()) > 0.99


def test_surface_crossing_hand_values():
    from nepf_core.render.neus import surface_crossing_t
    z = torch.tensor([[0.0, 1.0, 2.0, 3.0]] * 4)
    f = torch.tensor([[0.5, -0.5, -1.0, -2.0],     # crossing in the max-weight section: 0.5
                      [0.9, 0.3, -0.1, -0.5],      # max weight one section early: the crossing of [1, 2], 1.75
                      [1.0, 0.8, 0.6, 0.4],        # no crossing: the max-weight sample itself
                      [0.2, -0.2, 0.2, -0.6]])     # two entering sections: the nearest to idx = 2
    idx = torch.tensor([0, 0, 1, 2])
    t = surface_crossing_t(z, f, idx)
    assert torch.allclose(t, torch.tensor([0.5, 1.75, 1.0, 2.25]))
    # an exiting section (f rising through 0) is not a surface entry
    t2 = surface_crossing_t(torch.tensor([[0.0, 1.0]]), torch.tensor([[-0.5, 0.5]]), torch.tensor([0]))
    assert float(t2) == 0.0
