"""The colour terms: the paper's three radiance losses, the background's, and the colour logits' range.

    L_r      = w_r * mean | srgb(L_r) - srgb(L_gt) |
    L_surf   = lambda1 * mean_surf (1 - w_max) | srgb(L_surf) - srgb(sg(L_r)) |     (sg = stop-grad)
    L_vol    = lambda2 * mean | srgb(L_vol) - srgb(L_gt) |
    L_bg     = w_r * mean_{mask = 0} | srgb(L_r) - srgb(L_gt) |   (masks and a background volume)
    L_crange = w_colour_range * mean relu(|z| - z_c)   (z: radiance / background colour logits)

Each reads a :class:`~nepf_core.losses.batch.LossBatch` and returns a scalar ``[]``. ``L_surf``
compares the BSDF's shading at the max-weight point to the radiance network's colour, not to the
image: the outgoing radiance field is the surface's pseudo ground truth, which is what ties the
two fields to one density (paper, "Synchronization"; the ``1 - w_max`` factor is its "surface
approaching").
"""

from __future__ import annotations

from torch import Tensor

from nepf_core.color import linear_to_srgb
from nepf_core.losses.batch import LossBatch, l1_masked, logit_excess, needs_input


def loss_radiance(b: LossBatch) -> Tensor:
    return l1_masked(b.r_enc, b.gt_all, b.colour_w)


def loss_background(b: LossBatch) -> Tensor:
    if not b.background or b.fg_all is None:
        return b.zero
    return l1_masked(b.r_enc, b.gt_all, (1.0 - b.fg_all) * (b.outside_q if b.outside_q is not None else 1.0))


def loss_surface(b: LossBatch) -> Tensor:
    wt = b.surf_rays * (1.0 - b.out.w_max.detach())
    err = (linear_to_srgb(b.out.rgb_surf) - b.r_sdf.detach()).abs().mean(-1)
    return (err * wt).sum() / b.surf_rays.sum().clamp_min(1.0)


def loss_volume(b: LossBatch) -> Tensor:
    return l1_masked(b.vol_enc, b.gt_all, b.colour_w)


def loss_colour_range(b: LossBatch) -> Tensor:
    z = needs_input(b.out.colour_logits, "w_colour_range", "a training render (colour logits)")
    return logit_excess(z, b.cfg.colour_logit_max).mean() if z.numel() else b.zero
