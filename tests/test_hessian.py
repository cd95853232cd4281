"""The Hessian regulariser ``|H f|_F`` (nepf_core/fields/gradients.py) against references.

* a small softplus MLP SDF: float32 central differences of the autograd gradient against
  ``torch.autograd.functional.hessian`` of the same network in float64;
* float32 rounding noise: the same formula in float32 and float64 (same step);
* the analytic sphere ``f = |x| - r`` (``|H|_F = sqrt(2) / |x|``) for both gradient modes and
  the grid SDF at initialisation (a sphere prior);
* the parameter gradient of the loss against float64 double-backward of the exact Hessian;
* the renderer: ``tiny`` (paper code path) returns the term, ``fast`` never computes it.
"""

from __future__ import annotations

import copy
import math

import pytest
import torch
from torch import nn

from nepf_core.fields.gradients import frobenius_norm, hessian_central, sdf_hessian_norm
from nepf_core.fields.sdf_grid import GridSDF, GridSDFConfig
from nepf_core.fields.sdf_mlp import MLPSDF, MLPSDFConfig

EPS = 1e-3  # MLPSDF.fd_step()


def _small_mlp(seed: int = 0) -> MLPSDF:
    """A small softplus SDF whose weights are moved off the geometric init so that its
    Hessian is far from the sphere's (median |H|_F ~ 5 at |x| ~ 0.4)."""
    torch.manual_seed(seed)
    m = MLPSDF(MLPSDFConfig(width=64, depth=3, feature_dim=8, n_freqs=4, skips=(), weight_norm=False))
    with torch.no_grad():
        for p in m.parameters():
            p.add_(0.02 * torch.randn_like(p))
    return m


def _points(n: int = 48, seed: int = 1) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return 0.4 * torch.randn(n, 3, generator=g)


def _reference_hessian(m64: nn.Module, x: torch.Tensor) -> torch.Tensor:
    return torch.stack([torch.autograd.functional.hessian(lambda p: m64.sdf(p[None])[0], xi.double())
                        for xi in x])


def test_matches_float64_autograd_hessian_on_a_small_mlp():
    m = _small_mlp()
    x = _points()
    ref = _reference_hessian(copy.deepcopy(m).double(), x)  # [N, 3, 3]
    got = hessian_central(lambda p: _grad(m, p), x, EPS).double()
    ref_norm = frobenius_norm(ref)
    rel = (got - ref).square().sum((-2, -1)).sqrt() / ref_norm
    # tolerance: every point within 0.2 % of |H|_F (measured max ~4e-4: O(eps^2) truncation)
    assert float(rel.max().detach()) < 2e-3
    assert float(ref_norm.median()) > 1.0  # the reference is not trivially small
    norm = sdf_hessian_norm(m.sdf, x, EPS, gradient="autograd").double()
    assert torch.allclose(norm, ref_norm, rtol=2e-3)


def _grad(m: nn.Module, p: torch.Tensor) -> torch.Tensor:
    p = p.detach().requires_grad_(True)
    return torch.autograd.grad(m.sdf(p).sum(), p, create_graph=True)[0]


def test_float32_rounding_noise_is_small():
    """Same formula, same step, float32 vs float64: what is left is rounding. The old term (second
    differences of f, step 1e-3) is checked the same way to show what the new one avoids."""
    m = _small_mlp(2)
    m64 = copy.deepcopy(m).double()
    x = _points(64, 3)
    h32 = sdf_hessian_norm(m.sdf, x, EPS).detach().double()
    h64 = sdf_hessian_norm(m64.sdf, x.double(), EPS).detach()
    rel = (h32 - h64).abs() / h64
    noise = rel.median()
    assert float(noise) < 1e-4 and float(rel.max()) < 1e-3  # measured ~1e-5 / ~8e-5

    def second_diff_trace(f, xs):  # sum_i (f(x+e e_i) + f(x-e e_i) - 2 f(x)) / e^2
        e = torch.eye(3, dtype=xs.dtype) * EPS
        return sum((f(xs + e[i]) + f(xs - e[i]) - 2 * f(xs)) / EPS ** 2 for i in range(3))
    with torch.no_grad():
        old_noise = ((second_diff_trace(m.sdf, x).double() - second_diff_trace(m64.sdf, x.double())).abs()
                     / h64).median()
    assert float(old_noise) > 10 * float(noise)


class _SphereSDF(nn.Module):
    def __init__(self, r: float) -> None:
        super().__init__()
        self.r = nn.Parameter(torch.tensor(r))

    def sdf(self, x):
        return x.norm(dim=-1) - self.r


@pytest.mark.parametrize("gradient", ["autograd", "fd"])
def test_sphere_has_sqrt2_over_radius(gradient):
    """``f = |x| - r``: ``H = (I - x x^T / |x|^2) / |x|``, two eigenvalues ``1/|x|``, so
    ``|H|_F = sqrt(2) / |x|`` (independent of r)."""
    x = torch.tensor([[0.5, 0.0, 0.0], [0.0, -0.3, 0.4], [0.2, 0.2, 0.2]])
    got = sdf_hessian_norm(_SphereSDF(0.5).sdf, x, 1e-2, gradient=gradient)
    want = math.sqrt(2.0) / x.norm(dim=-1)
    assert torch.allclose(got, want, rtol=1e-3)


def test_plane_has_zero_value_and_finite_zero_gradient():
    lin = nn.Linear(3, 1)
    x = _points(8)
    h = sdf_hessian_norm(lambda p: lin(p)[:, 0], x, EPS)
    assert float(h.detach().max()) < 1e-5
    h.mean().backward()
    g = lin.weight.grad  # (the bias does not reach the gradient of f at all)
    assert g is not None and torch.isfinite(g).all() and float(g.abs().max()) == 0.0


def test_parameter_gradient_matches_exact_double_backward():
    """d/dtheta mean |H|_F: float32 central differences vs the exact Hessian by float64 autograd."""
    m = _small_mlp(4)
    m64 = copy.deepcopy(m).double()
    x = _points(32, 5)
    sdf_hessian_norm(m.sdf, x, EPS).mean().backward()
    xx = x.double().requires_grad_(True)
    g = torch.autograd.grad(m64.sdf(xx).sum(), xx, create_graph=True)[0]
    h = torch.stack([torch.autograd.grad(g[:, j].sum(), xx, create_graph=True)[0] for j in range(3)], -1)
    frobenius_norm(h).mean().backward()
    got = _flat_grad(m).double()
    want = _flat_grad(m64)
    assert float(want.norm()) > 0
    assert float((got - want).norm() / want.norm()) < 1e-2


def _flat_grad(m: nn.Module) -> torch.Tensor:
    """All parameter gradients in one vector (0 for those that do not reach grad f, e.g. the
    last bias and the feature rows)."""
    return torch.cat([(p.grad if p.grad is not None else torch.zeros_like(p)).reshape(-1) for p in m.parameters()])


def test_grid_sdf_fd_mode_sphere_prior_and_gradient_reaches_the_grid():
    """The grid SDF starts as ``|x| - r`` exactly (zero SDF row), so fd mode must give ``sqrt(2)/|x|``;
    after a random perturbation of the grid its parameters receive a finite, non-zero gradient."""
    torch.manual_seed(0)
    grid = GridSDF(GridSDFConfig(n_levels=2, base_resolution=8, max_resolution=16, start_levels=2))
    x = torch.tensor([[0.45, 0.1, 0.0], [0.0, -0.3, 0.4]])
    eps = grid.fd_step()
    got = sdf_hessian_norm(grid.sdf, x, eps, gradient="fd")
    assert torch.allclose(got, math.sqrt(2.0) / x.norm(dim=-1), rtol=2e-2)
    with torch.no_grad():
        grid.head.layers[-1].weight[0].normal_(0.0, 0.1)
        for p in grid.encoding.parameters():
            p.normal_(0.0, 0.1)
    sdf_hessian_norm(grid.sdf, x, eps, gradient="fd").mean().backward()
    grads = [p.grad for p in grid.encoding.parameters()]
    assert all(g is not None and torch.isfinite(g).all() for g in grads)
    assert sum(float(g.abs().sum()) for g in grads) > 0


def test_unknown_gradient_mode_is_rejected():
    with pytest.raises(ValueError, match="autograd | fd"):
        sdf_hessian_norm(_SphereSDF(0.5).sdf, _points(2), EPS, gradient="exact")


def _rays(n: int = 16):
    from nepf_core.rays import RayBatch
    g = torch.Generator().manual_seed(7)
    o = torch.tensor([0.0, 0.0, -2.5]).expand(n, 3).clone()
    d = torch.nn.functional.normalize(torch.tensor([0.0, 0.0, 1.0]) + 0.15 * torch.randn(n, 3, generator=g), dim=-1)
    return RayBatch(o, d, rgb=torch.rand(n, 3, generator=g), mask=torch.ones(n))


def test_renderer_tiny_gets_the_term_and_fast_never_computes_it(monkeypatch):
    from nepf_core.config import fast, tiny
    from nepf_core.model import NePFModel
    from nepf_core.render import renderer as renderer_mod
    from nepf_core.render import weights as weights_mod

    torch.manual_seed(0)
    cfg = tiny()
    model = NePFModel(cfg.model)
    out = renderer_mod.render_rays(model, _rays(), cfg.render, train=True)
    n_samples = out.n_samples
    assert out.hessian.shape == (max(1, int(n_samples * cfg.render.hessian_fraction)),)
    # the sphere init: |H|_F ~ sqrt(2)/|x| > sqrt(2) inside the unit ball, so a real value, > 0
    assert float(out.hessian.detach().min()) > 0 and torch.isfinite(out.hessian).all()
    out.hessian.mean().backward()
    assert any(p.grad is not None and float(p.grad.abs().sum()) > 0 for p in model.sdf.parameters())

    def forbidden(*a, **k):
        raise AssertionError("fast must not compute the Hessian")
    monkeypatch.setattr(weights_mod, "sdf_hessian_norm", forbidden)
    fcfg = fast()
    assert fcfg.loss.w_hessian == 0.0
    fcfg.model.occupancy_resolution = 0  # no occupancy grid to fill: every ray is rendered
    fout = renderer_mod.render_rays(NePFModel(fcfg.model), _rays(), fcfg.render, train=True)
    assert fout.hessian.numel() == 0


def test_renderer_grid_sdf_in_midpoint_mode_uses_the_fd_hessian(monkeypatch):
    from nepf_core.config import fast
    from nepf_core.model import NePFModel
    from nepf_core.render import renderer as renderer_mod
    from nepf_core.render import weights as weights_mod

    calls = []
    real = weights_mod.sdf_hessian_norm

    def spy(*a, **k):
        calls.append(k.get("gradient"))
        return real(*a, **k)
    monkeypatch.setattr(weights_mod, "sdf_hessian_norm", spy)
    cfg = fast()
    cfg.model.occupancy_resolution = 0
    cfg.render.alpha_mode, cfg.render.head_weight_threshold = "midpoint", 0.0
    torch.manual_seed(0)
    model = NePFModel(cfg.model)
    out = renderer_mod.render_rays(model, _rays(8), cfg.render, train=True)
    assert calls == ["fd"]
    assert out.hessian.numel() == max(1, int(out.n_samples * cfg.render.hessian_fraction))
    # the grid SDF starts as the sphere |x| - 0.5, whose Hessian is nowhere zero
    assert torch.isfinite(out.hessian).all() and float(out.hessian.detach().min()) > 0
