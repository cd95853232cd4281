"""The geometry terms: the SDF's regularisers, the mask, the normal prior and the sparse points.

    L_eik    = w_eikonal * mean_q | |grad f| - 1 |    (q: the sample's ray weight, 1 unless thinned)
    L_hess   = w_hessian * mean |H f|_F               (fields/gradients.py)
    L_mask   = w_mask * BCE(clip(sum w, 1e-3, 1 - 1e-3), mask)
    L_ns     = w_normal_smooth * mean_surf | n(x* + e) + n(x* - e) - 2 n(x*) |   (e: the render's jitter)
    L_points = w_surface_points * mean_p |f(p)|        (captures without masks, train/surface_points.py)

Each reads a :class:`~nepf_core.losses.batch.LossBatch` and returns a scalar ``[]``.
"""

from __future__ import annotations

import torch.nn.functional as F
from torch import Tensor

from nepf_core.losses.batch import LossBatch, mean_where, weighted_mean


def mask_bce(weight_sum: Tensor, mask: Tensor, ray_weight: Tensor | None = None) -> Tensor:
    """``BCE(clip(sum w, 1e-3, 1 - 1e-3), mask)``, finite for any weight sum: ``[R], [R] -> []``.

    With ``ray_weight`` ``[R]`` (importance weights ``q_r``): ``sum_r q_r BCE_r / sum_r q_r``."""
    bce = F.binary_cross_entropy(weight_sum.clip(1e-3, 1.0 - 1e-3), mask, reduction="none")
    return weighted_mean(bce, ray_weight)


def loss_eikonal(b: LossBatch) -> Tensor:
    return weighted_mean(b.out.eikonal, b.out.eikonal_weight) if b.out.eikonal.numel() else b.zero


def loss_hessian(b: LossBatch) -> Tensor:
    return b.out.hessian.mean() if b.out.hessian.numel() else b.zero


def loss_mask(b: LossBatch) -> Tensor:
    if not b.use_mask or b.rays.mask is None:
        return b.zero
    return mask_bce(b.out.weight_sum, b.rays.mask, b.rays.weight)


def loss_normal_smooth(b: LossBatch) -> Tensor:
    """``mean_surf |n(x* + e) + n(x* - e) - 2 n(x*)|`` (:attr:`LossConfig.w_normal_smooth`): on a
    smoothly curved surface the first-order turn cancels between ``+e`` and ``-e``, so only bumps
    at the jitter's scale pay."""
    s = b.out.surface
    return mean_where((s.jitter.normal + s.jitter.normal_mirror - 2 * s.normal).norm(dim=-1), b.on_surf)


def loss_surface_points(b: LossBatch) -> Tensor:
    return b.surface_points()
