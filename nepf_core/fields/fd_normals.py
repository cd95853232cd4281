"""Finite-difference SDF gradients (normals / eikonal), the one home of the stencils: central
(6 points) and tetrahedral (4 points). Used for grid SDFs, the Hessian's ``gradient="fd"``
(:mod:`nepf_core.fields.gradients`) and the lobe rule's view spread.

Grid SDFs are looked up trilinearly (:mod:`nepf_core.fields.trilinear`), whose table gradient
is scattered outside autograd: an eikonal loss through ``autograd.grad(create_graph=True)``
would not reach the table (with ``grid_sample`` it did, at ~12x a plain SDF pass on CPU).
Finite differences are ordinary forward passes, so the
gradient estimate is differentiable w.r.t. all parameters at 1.6x (4-point) to 3.7x
(7-point) of a plain pass. A step tied to the active
cell size (Neuralangelo) also lets the gradient see neighbouring cells (smoother normals
early in coarse-to-fine training). Measured costs: ``docs/FAST.md``.
"""
from __future__ import annotations

from typing import Callable

import torch
from torch import Tensor

__all__ = ["sdf_gradient_fd", "TETRA_DIRS"]

# Regular tetrahedron vertices (unnormalised, |k| = sqrt(3)); sum k k^T = 4 I, sum k = 0.
TETRA_DIRS = ((1.0, -1.0, -1.0), (-1.0, -1.0, 1.0), (-1.0, 1.0, -1.0), (1.0, 1.0, 1.0))


def sdf_gradient_fd(
    sdf_fn: Callable[[Tensor], Tensor],
    x: Tensor,
    eps: float,
    scheme: str = "central",
    center: str = "eval",
) -> tuple[Tensor, Tensor]:
    """SDF gradient by finite differences, differentiable w.r.t. the SDF's parameters.

    ``sdf_fn``: ``[M,3] -> [M]`` (one batched call is made). ``x``: ``[N,3]``.
    Returns ``(grad [N,3], sdf [N])``.

    * ``scheme="central"`` (6 stencil points, error ``O(eps^2)``):
      ``g_a = (f(x + eps e_a) - f(x - eps e_a)) / (2 eps)``.
      ``center="eval"`` adds ``x`` itself to the batch (7N evaluations) and returns
      ``f(x)`` exactly; ``center="mean"`` returns the stencil mean
      ``(1/6) sum f = f(x) + eps^2 lap f / 6 + O(eps^4)`` (6N evaluations).
    * ``scheme="tetra"`` (4 stencil points ``x + eps k_i``, ``k_i`` = :data:`TETRA_DIRS`):
      ``g = sum_i k_i f(x + eps k_i) / (4 eps)``. Only first-order accurate in general:
      ``g_c - df/dx_c = eps * d2f/dx_a dx_b`` ({a,b,c} distinct) + O(eps^2).
      ``center="mean"`` gives ``(1/4) sum f = f(x) + eps^2 lap f / 2 + ...``;
      ``center="eval"`` adds ``x`` (5N evaluations).

    For a grid SDF use ``eps`` ~ ``0.5 * grid.active_cell_size()`` (see docs/FAST.md).
    """
    pts, offsets = fd_stencil(x, eps, scheme, center)
    return gradient_from_stencil(sdf_fn(pts).reshape(-1), x.shape[0], offsets, eps, scheme, center)


def fd_stencil(x: Tensor, eps: float, scheme: str = "central", center: str = "eval") -> tuple[Tensor, Tensor]:
    """The points :func:`sdf_gradient_fd` evaluates: ``x [N, 3]`` -> ``(pts [k N (+ N), 3],
    offsets [k, 3])``, offset-major (``pts[i N + n] = x[n] + offsets[i]``), ``x`` itself
    appended when ``center="eval"``. Callers that evaluate the SDF at other points too can
    batch them with these in one call and hand the values to :func:`gradient_from_stencil`."""
    if scheme == "central":
        e = torch.eye(3, dtype=x.dtype, device=x.device) * eps
        offsets = torch.cat([e, -e], 0)  # [6,3]: +x,+y,+z,-x,-y,-z
    elif scheme == "tetra":
        offsets = torch.tensor(TETRA_DIRS, dtype=x.dtype, device=x.device) * eps  # [4,3]
    else:
        raise ValueError(f"unknown scheme {scheme!r} (central | tetra)")
    if center not in ("eval", "mean"):
        raise ValueError(f"unknown center {center!r} (eval | mean)")
    pts = (x.unsqueeze(0) + offsets.unsqueeze(1)).reshape(-1, 3)
    if center == "eval":
        pts = torch.cat([pts, x], 0)
    return pts, offsets


def gradient_from_stencil(f: Tensor, n: int, offsets: Tensor, eps: float, scheme: str = "central",
                          center: str = "eval") -> tuple[Tensor, Tensor]:
    """``(grad [N, 3], sdf [N])`` from the SDF values ``f`` at :func:`fd_stencil`'s points
    (the formulas of :func:`sdf_gradient_fd`)."""
    k = offsets.shape[0]
    fs = f[: k * n].view(k, n)
    if scheme == "central":
        grad = (fs[:3] - fs[3:]).t() / (2.0 * eps)
    else:
        grad = (fs.t() @ offsets) / (4.0 * eps * eps)  # sum_i f_i k_i eps / (4 eps^2)
    sdf = f[k * n : (k + 1) * n] if center == "eval" else fs.mean(0)
    return grad, sdf
