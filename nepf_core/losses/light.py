"""The light-variance term of the paper: the photon field's spread matched to the surface's.

    L_light = w_light * (l3 |var x - var I| + l4 |var n - var l| + l5 |var x - var l|)

over the batch's surface points ``x [S, 3]``, normals ``n [S, 3]``, light directions ``l [S, 3]``
and intensities ``I [S]``. ``var`` is the total variance over the batch, ``sum_c Var(x[:, c])``.
Why each part (and why ``fast`` sets ``l4 = l5 = 0``): :class:`~nepf_core.losses.config.LossConfig`.
"""

from __future__ import annotations

from torch import Tensor

from nepf_core.losses.batch import LossBatch


def batch_variance(x: Tensor) -> Tensor:
    """Total variance over a batch, ``sum_c Var(x[:, c])``: ``[N, C] -> []`` (0 for N < 2)."""
    if x.shape[0] < 2:
        return x.new_zeros(())
    return x.var(dim=0, unbiased=False).sum()


def light_variance_loss(x: Tensor, n: Tensor, l: Tensor, I: Tensor, l3: float, l4: float, l5: float) -> Tensor:
    """``l3 |var x - var I| + l4 |var n - var l| + l5 |var x - var l|`` over surface points."""
    vx, vn, vl, vI = batch_variance(x), batch_variance(n), batch_variance(l), batch_variance(I[:, None])
    return l3 * (vx - vI).abs() + l4 * (vn - vl).abs() + l5 * (vx - vl).abs()


def loss_light(b: LossBatch) -> Tensor:
    s, m, c = b.out.surface, b.on_surf, b.cfg
    return light_variance_loss(s.x[m], s.normal[m], s.light_dir[m], s.intensity[m], c.lambda3, c.lambda4, c.lambda5)
