"""SDF gradients (normals) by autograd or central differences, and the Hessian diagonal.

    grad f(x) = d f / d x                          (autograd, double-backward in training)
    grad_i f(x) ~ (f(x + e e_i) - f(x - e e_i)) / (2 e)       (central differences)
    H_ii f(x)  ~ (f(x + e e_i) + f(x - e e_i) - 2 f(x)) / e^2
"""

from __future__ import annotations

from typing import Callable

import torch
from torch import Tensor


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


_OFFSETS = torch.tensor([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]],
                        dtype=torch.float32)


def sdf_gradient_central(sdf_only: Callable[[Tensor], Tensor], x: Tensor, eps: float) -> tuple[Tensor, Tensor]:
    """Central-difference gradient and Hessian diagonal: ``[N,3] -> (grad [N,3], hdiag [N,3])``.

    Needs ``f(x)`` for the Hessian diagonal, so it returns ``f(x +- eps e_i)`` combined with
    one extra evaluation at x. Differentiable with respect to the network parameters.
    """
    off = _OFFSETS.to(x) * eps  # [6, 3]
    pts = (x[:, None, :] + off[None]).reshape(-1, 3)
    f = sdf_only(pts).reshape(-1, 3, 2)  # [N, 3, (+,-)]
    grad = (f[..., 0] - f[..., 1]) / (2.0 * eps)
    return grad, f


def hessian_diag_from_pairs(f_pairs: Tensor, f_center: Tensor, eps: float) -> Tensor:
    """``H_ii ~ (f(x+e e_i) + f(x-e e_i) - 2 f(x)) / e^2``: ``[N,3,2], [N] -> [N,3]``."""
    return (f_pairs[..., 0] + f_pairs[..., 1] - 2.0 * f_center[:, None]) / (eps * eps)
