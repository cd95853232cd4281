"""Colour Retinex (``nepf_core.albedo_retinex``): lit points whose pixels share a chromaticity share
an albedo luminance; the shading goes to the light and a change of colour stays in the albedo."""

from __future__ import annotations

import math

import numpy as np
import torch

from nepf_core.albedo_retinex import CHROMA_SIGMA, albedo_flat_loss


def _reference(lum: np.ndarray, rgb: np.ndarray, sigma: float) -> float:
    """The formula of the docstring, one pair at a time (float64)."""
    h = rgb / rgb.sum(1, keepdims=True)
    total = 0.0
    for i in range(len(lum)):
        k = np.array([0.0 if j == i else math.exp(-np.sum((h[i] - h[j]) ** 2) / (2 * sigma ** 2))
                      for j in range(len(lum))])
        if k.sum() == 0.0:
            continue
        ref = (k * lum).sum() / k.sum()
        total += k.sum() / (1 + k.sum()) * abs(lum[i] / ref - 1)
    return total / len(lum)


def _batch(n: int, seed: int):
    """Pixels of three colours under random shading (chromaticity noise ~0.3 sigma), random albedo."""
    g = np.random.default_rng(seed)
    colours = np.array([[0.8, 0.5, 0.3], [0.3, 0.4, 0.8], [0.5, 0.5, 0.5]])
    pick = g.integers(0, 3, n)
    rgb = colours[pick] * g.uniform(0.05, 1.0, (n, 1)) * (1 + 0.003 * g.standard_normal((n, 3)))
    return g.uniform(0.1, 0.9, n), rgb, pick


def test_matches_the_pairwise_reference():
    for seed in range(3):
        lum, rgb, _ = _batch(40, seed)
        got = albedo_flat_loss(torch.tensor(lum), torch.tensor(rgb)).item()
        assert abs(got - _reference(lum, rgb, CHROMA_SIGMA)) < 1e-10


def test_shading_a_pixel_does_not_change_the_loss():
    """Chromaticity is invariant to the pixel's scale: any shading field gives the same term."""
    lum, rgb, _ = _batch(60, 3)
    shade = np.random.default_rng(4).uniform(0.02, 3.0, (60, 1))
    a = albedo_flat_loss(torch.tensor(lum), torch.tensor(rgb)).item()
    b = albedo_flat_loss(torch.tensor(lum), torch.tensor(rgb * shade)).item()
    assert a > 0.05 and abs(a - b) < 1e-12


def test_the_split_it_picks_puts_shading_in_the_light_and_colour_in_the_albedo():
    """Diffuse pixels ``p = a(x) s(x)`` of a two-colour texture (luminance 0.6 and 0.25) under a
    random shading ``s`` in [0.1, 1]. Fitting per-point albedo ``a`` and intensity ``I`` to ``a I = p``
    is ambiguous up to any ``(a t, I / t)``; with the Retinex term the albedo luminance becomes
    one value per colour (the shading went to ``I``) and the two colours keep their own
    chromaticity. Without it the albedo keeps the shading it was started with."""
    g = torch.Generator().manual_seed(0)
    n = 120
    colour = torch.tensor([[0.9, 0.6, 0.3], [0.2, 0.25, 0.3]])
    pick = torch.arange(n) % 2
    shade = 0.1 + 0.9 * torch.rand(n, 1, generator=g)
    pixels = colour[pick] * shade

    def fit(w: float):
        za = torch.logit(pixels.clamp(0.02, 0.98)).clone().requires_grad_(True)   # the albedo starts as the pixel
        zi = torch.zeros(n, 1, requires_grad=True)
        opt = torch.optim.Adam([za, zi], lr=0.03)
        for _ in range(800):
            a, intensity = torch.sigmoid(za), torch.exp(zi)
            loss = (a * intensity - pixels).abs().mean() + w * albedo_flat_loss(a.mean(-1), pixels)
            opt.zero_grad()
            loss.backward()
            opt.step()
        return torch.sigmoid(za).detach()

    def spread(a):   # relative spread of the albedo luminance within each colour
        y = a.mean(-1)
        return max((y[pick == c].std() / y[pick == c].mean()).item() for c in (0, 1))

    free, retinex = fit(0.0), fit(0.1)
    assert spread(free) > 0.3                      # the shading stayed in the albedo
    assert spread(retinex) < 0.05                  # one albedo per colour: the shading went to the light
    chroma = retinex / retinex.sum(-1, keepdim=True)
    truth = colour / colour.sum(-1, keepdim=True)
    assert (chroma - truth[pick]).abs().max() < 0.02   # each point kept its own colour
    y = retinex.mean(-1)
    assert y[pick == 0].mean() / y[pick == 1].mean() > 1.8   # and its own brightness (true ratio 2.4):
    # a flatness pull over the whole batch would have taken both colours to one luminance


def test_a_batch_without_partners_costs_nothing():
    rgb = torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    lum = torch.tensor([0.1, 0.5, 0.9], requires_grad=True)
    loss = albedo_flat_loss(lum, rgb)
    loss.backward()
    assert loss.item() == 0.0 and torch.all(lum.grad == 0)
