"""SDF gradients (normals) by autograd, and the Hessian regulariser (finite differences of ``f``
itself: :mod:`nepf_core.fields.fd_normals`).

    grad f(x) = d f / d x                                      (autograd, double backward in training)
    grad_i f(x) ~ (f(x + e e_i) - f(x - e e_i)) / (2 e)        (central differences)
    H[:, j]   ~ (g(x + e e_j) - g(x - e e_j)) / (2 e),  H <- (H + H^T) / 2
    |H|_F     = sqrt(sum_ij H_ij^2)

Reading of the paper's ``L_hessian = |nabla^2 f(x)|`` (supplementary, after Zhang et al. 2022,
"critical regularizations"): ``nabla^2 f`` is the Hessian matrix (the text says "minimizing the
Hessian Matrix"), and ``|.|`` on a matrix is read as its Frobenius norm, so the term is
``mean_x |H f(x)|_F`` over a random subset of the samples. It is zero exactly where the SDF is
locally linear (a plane) and ``sqrt(2) / r`` on a sphere of radius ``r``.

How ``H`` is computed: central differences of a *differentiable gradient* ``g``, not second
differences of ``f``. A second difference ``(f(x+e) + f(x-e) - 2 f(x)) / e^2`` divides the
float32 rounding error of ``f`` (~1e-7 relative, more through an 8-layer MLP) by ``e^2 = 1e-6``,
which made ~40 % of a diagonal-only term of second differences noise; a first difference of ``g`` divides by
``2e`` only. With ``e = 1e-3`` the float32 result agrees with float64 autograd's Hessian to
~1e-4 (rounding) plus the O(e^2) truncation (~1e-3 relative on a random small MLP), see
``tests/test_hessian.py``. ``g`` is

* ``gradient="autograd"`` (MLP SDF): autograd with ``create_graph=True``; training then needs a
  double backward, as the eikonal term already does. An exact autograd Hessian (three more
  backward passes, then a triple backward in training) costs ~20 % more and does not work
  for the grid SDF.
* ``gradient="fd"`` (grid SDF: the trilinear lookup has no second derivative in its sampling
  grid): central differences of ``f`` with the same step, so ``H`` is the usual second-
  difference stencil with step ``2e`` on the diagonal (36 SDF evaluations per point). Use a
  step tied to the grid cell (``GridSDF.fd_step``) so that ``e^2`` stays well above the
  rounding error of ``f``.

Both are differentiable with respect to the network parameters.
"""

from __future__ import annotations

from typing import Callable

import torch
from torch import Tensor

from nepf_core.fields.fd_normals import sdf_gradient_fd


def sdf_gradient_autograd(sdf_fn: Callable[[Tensor], tuple[Tensor, Tensor]], x: Tensor,
                          create_graph: bool = True) -> tuple[Tensor, Tensor, Tensor]:
    """``(sdf [N], feature [N,F], grad [N,3])`` with the gradient from autograd.

    ``create_graph=True`` keeps the graph so the eikonal loss can train the network.
    """
    with torch.enable_grad():
        x = x.detach().requires_grad_(True)
        sdf, feat = sdf_fn(x)
        (grad,) = torch.autograd.grad(sdf.sum(), x, create_graph=create_graph)
    return sdf, feat, grad


def _autograd_gradient_fn(sdf_only: Callable[[Tensor], Tensor]) -> Callable[[Tensor], Tensor]:
    """``x [M,3] -> grad f [M,3]`` by autograd, with the graph kept for training."""
    def grad_fn(x: Tensor) -> Tensor:
        with torch.enable_grad():
            x = x.detach().requires_grad_(True)
            (g,) = torch.autograd.grad(sdf_only(x).sum(), x, create_graph=True)
        return g
    return grad_fn


def hessian_central(grad_fn: Callable[[Tensor], Tensor], x: Tensor, eps: float) -> Tensor:
    """Symmetrised central-difference Jacobian of ``grad_fn`` at ``x``: ``[N,3] -> H [N,3,3]``.

    ``H[n, i, j] = (g_i(x_n + eps e_j) - g_i(x_n - eps e_j)) / (2 eps)``, then ``(H + H^T) / 2``
    (the exact Hessian is symmetric; averaging halves the antisymmetric part of the O(eps^2)
    error). One batched call of ``grad_fn`` on ``6N`` points.
    """
    eye = torch.eye(3, dtype=x.dtype, device=x.device) * eps
    offsets = torch.cat([eye, -eye], 0)  # [6, 3]: +e_j (j = 0..2), then -e_j
    g = grad_fn((x[None] + offsets[:, None]).reshape(-1, 3)).reshape(6, x.shape[0], 3)  # [6, N, 3 (i)]
    cols = (g[:3] - g[3:]) / (2.0 * eps)  # [3 (j), N, 3 (i)]
    h = cols.permute(1, 2, 0)  # [N, i, j]
    return 0.5 * (h + h.transpose(-1, -2))


def frobenius_norm(h: Tensor) -> Tensor:
    """``sqrt(sum_ij H_ij^2)``: ``[N,3,3] -> [N]``. The square is clamped at 1e-12 before the root,
    so an exactly zero Hessian (a plane, a ReLU network) has a zero gradient instead of NaN."""
    return h.square().sum((-2, -1)).clamp_min(1e-12).sqrt()


def sdf_hessian_norm(sdf_only: Callable[[Tensor], Tensor], x: Tensor, eps: float,
                     gradient: str = "autograd") -> Tensor:
    """The Hessian regulariser's per-point value ``|H f(x)|_F``: ``[N,3] -> [N]`` (module docstring).

    ``gradient``: ``autograd`` (MLP SDF) or ``fd`` (grid SDF); ``eps``: the difference step in
    normalised units (``sdf.fd_step()``).
    """
    if gradient == "autograd":
        grad_fn = _autograd_gradient_fn(sdf_only)
    elif gradient == "fd":
        def grad_fn(p: Tensor) -> Tensor:
            return sdf_gradient_fd(sdf_only, p, eps, scheme="central", center="mean")[0]
    else:
        raise ValueError(f"unknown Hessian gradient {gradient!r} (autograd | fd)")
    return frobenius_norm(hessian_central(grad_fn, x, eps))
