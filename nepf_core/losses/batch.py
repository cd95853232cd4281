"""What the loss terms read: :class:`LossBatch` (one step's render, its rays and the values several
terms share, built once by :func:`loss_batch`) and the reductions they average with.

Colour terms compare display-space values ``srgb(.)`` (``docs/ARCHITECTURE.md``). With masks the
colour means run over foreground rays only (NeuS); with masks and a background volume, ``L_bg``
trains the rays outside the masks, averaged over those rays alone, so that the foreground terms
keep their scale. The surface terms use only rays that hit a surface (the mask, or
:func:`~nepf_core.render.neus.foreground` without one).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import torch
from torch import Tensor

from nepf_core.color import linear_to_srgb
from nepf_core.losses.config import LossConfig
from nepf_core.rays import RayBatch
from nepf_core.render.neus import foreground


def logit_excess(z: Tensor, z_max: float) -> Tensor:
    """``relu(|z| - z_max)``, elementwise: how far a logit lies past the range a sigmoid still
    trains in (the range priors ``w_material_range`` and ``w_colour_range``)."""
    return (z.abs() - z_max).clamp_min(0.0)


def l1_masked(pred: Tensor, target: Tensor, weight: Tensor | None) -> Tensor:
    """``sum_r w_r |pred_r - target_r|_1 / (3 sum_r w_r)`` (plain mean when weight is None)."""
    err = (pred - target).abs()
    if weight is None:
        return err.mean()
    return (err * weight[:, None]).sum() / (3.0 * weight.sum().clamp_min(1.0))


def weighted_mean(x: Tensor, weight: Tensor | None) -> Tensor:
    """``sum_i q_i x_i / sum_i q_i`` over ``[P]`` values with importance weights ``q [P]``
    (plain mean when ``weight`` is None). With the ray weights of a thinned batch (each kept
    miss stands for ``1 / miss_keep`` drawn misses) this is the mean over the drawn batch in
    expectation, as for the mask loss."""
    if weight is None:
        return x.mean()
    return (x * weight).sum() / weight.sum().clamp_min(1e-12)


def mean_where(x: Tensor, keep: Tensor) -> Tensor:
    """``sum_r x_r keep_r / max(1, sum_r keep_r)``: the mean of ``x [R]`` over the rays ``keep [R]``
    (bool), 0 when none is kept."""
    return (x * keep).sum() / keep.sum().clamp_min(1.0)


@dataclass
class LossBatch:
    """What the loss terms read: one step's render, its rays and the values several terms share."""

    out: object
    """The :class:`~nepf_core.render.renderer.RenderOutput`."""
    rays: RayBatch
    cfg: LossConfig
    use_mask: bool
    specular: bool
    """The render evaluated the GGX lobe (L_flat applies only without it)."""
    background: bool
    """The model has a background volume (L_bg with masks)."""
    zero: Tensor
    gt: Tensor
    """``[R, 3]`` ``srgb(L_gt)``."""
    fg: Tensor | None
    """``[R]`` the mask when the mask loss applies, else None."""
    r_sdf: Tensor
    """``[R, 3]`` ``srgb(L_r)`` of the SDF batch."""
    r_enc: Tensor
    """``[R (+ B), 3]`` ``srgb(L_r)``, with the background-only rays appended."""
    vol_enc: Tensor
    """``[R (+ B), 3]`` ``srgb(L_vol)``, likewise."""
    gt_all: Tensor
    colour_w: Tensor | None
    """``[R (+ B)]`` the per-ray weight of the colour means (mask x importance; None: plain mean)."""
    fg_all: Tensor | None
    outside_q: Tensor | None
    """``[R (+ B)]`` L_bg's per-ray importance (None: 1)."""
    surf_rays: Tensor
    """``[R]`` float: the rays that end on a surface (mask, or :func:`foreground`)."""
    on_surf: Tensor
    """``[R]`` bool, ``surf_rays > 0.5``."""
    lit: Tensor
    """``[R]`` bool: on the surface and the target pixel is lit."""
    surface_points: Callable[[], Tensor] | None = None
    """Without masks: ``mean_p |f(p)|`` at the triangulated object points (draws its own points)."""


def loss_batch(out, rays: RayBatch, cfg: LossConfig, *, use_mask: bool, specular: bool = True,
               background: bool = False, background_rays: tuple[Tensor, RayBatch] | None = None,
               surface_points: Callable[[], Tensor] | None = None) -> LossBatch:
    """The shared values of :class:`LossBatch`. ``background_rays = (C_bg [B, 3], rays [B])``: the
    misses the empty-ray rule left out of the SDF batch, rendered by the background alone (their
    ``rgb_r = rgb_vol = C_bg``, :func:`nepf_core.render.renderer.render_background_only`). The colour
    terms ``L_r``, ``L_vol`` and ``L_bg`` are then means over all ``R + B`` rays, each background ray
    weighing its ``rays.weight`` (the misses it stands for, :mod:`nepf_core.train.rules.empty_rays`),
    and the kept misses count once in ``L_bg``: the other misses, for which a kept one weighs
    ``1 / miss_keep`` in the SDF batch's terms, are among the background rays there."""
    gt = linear_to_srgb(rays.rgb)
    fg = rays.mask if (use_mask and rays.mask is not None) else None
    zero = out.rgb_r.new_zeros(())
    r_sdf = linear_to_srgb(out.rgb_r)
    r_enc, vol_enc = r_sdf, linear_to_srgb(out.rgb_vol)
    gt_all, fg_all = gt, fg
    colour_q = None          # per-ray weight in the colour means (None: every ray once)
    outside_q = rays.weight  # L_bg: a thinned batch's kept misses stand for 1 / miss_keep misses
    if background_rays is not None:
        bg_rgb, bg_rays = background_rays
        bg_enc = linear_to_srgb(bg_rgb)
        r_enc, vol_enc = torch.cat([r_enc, bg_enc]), torch.cat([vol_enc, bg_enc])
        gt_all = torch.cat([gt, linear_to_srgb(bg_rays.rgb)])
        fg_all = None if fg is None else torch.cat([fg, bg_rays.mask])
        bg_q = bg_rays.weight if bg_rays.weight is not None else torch.ones_like(bg_enc[:, 0])
        colour_q = outside_q = torch.cat([torch.ones_like(gt[:, 0]), bg_q])
    colour_w = fg_all if colour_q is None else (colour_q if fg_all is None else fg_all * colour_q)
    surf_rays = fg if fg is not None else foreground(out.weight_sum).float()
    on_surf = surf_rays > 0.5
    lit = on_surf & ~rays.unlit if rays.unlit is not None else on_surf
    return LossBatch(out=out, rays=rays, cfg=cfg, use_mask=use_mask, specular=specular, background=background,
                     zero=zero, gt=gt, fg=fg, r_sdf=r_sdf, r_enc=r_enc, vol_enc=vol_enc, gt_all=gt_all,
                     colour_w=colour_w, fg_all=fg_all, outside_q=outside_q, surf_rays=surf_rays, on_surf=on_surf,
                     lit=lit, surface_points=surface_points)


def needs_input(thing, weight: str, what: str):
    """``thing``, or a ValueError naming the weight that asked for it and what it needs."""
    if thing is None:
        raise ValueError(f"loss.{weight} > 0 needs {what}")
    return thing
