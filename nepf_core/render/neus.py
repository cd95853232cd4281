"""NeuS opacity and weights, computed the stable way (Wang et al. 2021).

For a section [t_i, t_{i+1}] with mid-point SDF f_i, ray-normal cosine c_i and length d_i:

    f_prev = f_i - c_i d_i / 2,   f_next = f_i + c_i d_i / 2
    Phi_s(f) = sigmoid(s f)
    alpha_i = clip((Phi_s(f_prev) - Phi_s(f_next) + 1e-5) / (Phi_s(f_prev) + 1e-5), 0, 1)
    T_i = prod_{j<i} (1 - alpha_j + 1e-7),   w_i = alpha_i T_i

``sigmoid`` saturates instead of overflowing, the +1e-5 keeps the ratio finite when both
CDFs are 0 (far outside), and the clip absorbs the +1e-5 bias, so alpha is in [0, 1] for
any finite SDF and any s in [1e-6, 1e6]. Sum of weights <= 1 + n * 1e-7.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor


def annealed_cos(true_cos: Tensor, anneal_ratio: float) -> Tensor:
    """NeuS's cosine annealing: ``-(relu(-c/2 + 1/2)(1 - r) + relu(-c) r)``, ``[...] -> [...]``.

    Early in training (r = 0) every section is treated as "entering" the surface so that
    gradients reach the SDF from both sides.
    """
    return -(F.relu(-true_cos * 0.5 + 0.5) * (1.0 - anneal_ratio) + F.relu(-true_cos) * anneal_ratio)


def alpha_from_sdf(sdf_mid: Tensor, cos: Tensor, dists: Tensor, inv_s: Tensor | float) -> Tensor:
    """NeuS discrete opacity. All ``[R, S]`` (``inv_s`` scalar or broadcastable) -> ``[R, S]``."""
    prev_sdf = sdf_mid - cos * dists * 0.5
    next_sdf = sdf_mid + cos * dists * 0.5
    prev_cdf = torch.sigmoid(prev_sdf * inv_s)
    next_cdf = torch.sigmoid(next_sdf * inv_s)
    return ((prev_cdf - next_cdf + 1e-5) / (prev_cdf + 1e-5)).clip(0.0, 1.0)


def weights_from_alpha(alpha: Tensor) -> Tensor:
    """``w_i = alpha_i prod_{j<i}(1 - alpha_j + 1e-7)``: ``[R, S] -> [R, S]``."""
    ones = torch.ones_like(alpha[..., :1])
    trans = torch.cumprod(torch.cat([ones, 1.0 - alpha + 1e-7], dim=-1), dim=-1)[..., :-1]
    return alpha * trans


def max_weight_index(weights: Tensor) -> tuple[Tensor, Tensor]:
    """Index and value of the largest weight per ray: ``[R, S] -> ([R] long, [R])``.

    Well defined when all weights are 0: argmax returns the first sample (index 0) and
    ``w_max = 0``, so any loss scaled by ``w_max`` or masked by it is inert there.
    """
    w_max, idx = weights.max(dim=-1)
    return idx, w_max


def surface_crossing_t(z: Tensor, f: Tensor, idx: Tensor) -> Tensor:
    """Ray depth of the SDF zero crossing nearest the max-weight sample: ``[R]``.

    ``z, f [R, S]`` sample depths and SDF values, ``idx [R]`` the max-weight sample (in
    ``sample`` alpha mode the weight of sample ``i`` is the opacity of section ``[z_i, z_{i+1}]``).
    Among the sections that enter the surface (``f_j > 0 >= f_{j+1}``) take the one nearest
    ``idx`` in sample order (``idx`` itself when it enters: the usual case; a neighbour when
    a wide section just in front of a narrow importance-sampled one carries more weight), and
    return the crossing of the linear interpolant there,
    ``z* = z_j + (z_{j+1} - z_j) f_j / (f_j - f_{j+1})``. A ray with no entering section (it
    misses, or grazes) keeps ``z_idx``. No gradient: like the samples themselves, the depth is
    a placement; the fields queried there carry the gradients.
    """
    with torch.no_grad():
        R, S = z.shape
        if S < 2:
            return z.gather(1, idx[:, None])[:, 0]
        enters = (f[:, :-1] > 0) & (f[:, 1:] <= 0)                      # [R, S-1]
        j = torch.arange(S - 1, device=z.device)[None]
        dist = torch.where(enters, (j - idx[:, None]).abs(), torch.full_like(j, 2 * S))
        jj = dist.argmin(-1)
        zi, zn = z.gather(1, jj[:, None])[:, 0], z.gather(1, jj[:, None] + 1)[:, 0]
        fi, fn = f.gather(1, jj[:, None])[:, 0], f.gather(1, jj[:, None] + 1)[:, 0]
        frac = (fi / (fi - fn).clamp_min(1e-12)).clamp(0.0, 1.0)
        return torch.where(enters.any(-1), zi + frac * (zn - zi), z.gather(1, idx[:, None])[:, 0])


FOREGROUND_WEIGHT_SUM = 0.5
"""A ray without a mask is on the object when its opacity ``sum_i w_i`` exceeds this."""


def foreground(weight_sum: Tensor) -> Tensor:
    """``[R] -> [R]`` bool: ``sum_i w_i > 0.5``, the ray ends on the object (no grad). Used where no
    mask says so: the surface loss terms (:mod:`nepf_core.losses`), the lobe rule's statistics
    (:mod:`nepf_core.train.rules.lobe_evidence`)."""
    return weight_sum.detach() > FOREGROUND_WEIGHT_SUM
