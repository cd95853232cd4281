"""NePF losses. Each term is a pure function; :class:`LossConfig` weights and switches them.

Colour terms compare display-space values ``srgb(.)`` (see ``docs/ARCHITECTURE.md``):

    L_r     = mean | srgb(L_r) - srgb(L_gt) |
    L_surf  = lambda1 * mean (1 - w_max) | srgb(L_surf) - srgb(sg(L_r)) |     (paper; sg = stop-grad)
    L_vol   = lambda2 * mean | srgb(L_vol) - srgb(L_gt) |
    L_eik   = w_eik * mean_q | |grad f| - 1 |      (q: the sample's ray weight, 1 unless thinned)
    L_hess  = w_hess * mean |H f|_F      (Frobenius norm of the SDF Hessian, fields/gradients.py)
    L_light = w_light * (l3 |var x - var I| + l4 |var n - var l| + l5 |var x - var l|)
    L_asm   = w_albedo_smooth * mean | c(x*) - c(x* + eps) |   (albedo smoothness prior, off in paper)
    L_flat  = w_albedo_flat * mean_lit | Y(c) / sg(mean_lit Y(c)) - 1 |, Y = channel mean   (lobe off only)
    L_mask  = w_mask * BCE(clip(sum w, 1e-3, 1 - 1e-3), mask)
    L_bsm   = w_brdf_smooth * mean (|r(x*) - r(x* + eps)| + |m(x*) - m(x* + eps)|)   (off in paper)
    L_range = w_material_range * mean_surf mean_k relu(|z_k| - z_max)   (z: material logits; off in paper)
    L_crange = w_colour_range * mean relu(|z| - z_c)   (z: radiance / background colour logits; off in paper)
    L_unseen = w_metallic_unseen * mean_lit m (1 - s) (1 - share)   (s: the lobe's share of L_surf, stop-grad;
              share: the metal evidence recorded near x*, train/metal_record.py; off in paper)
    L_evid  = w_material_evidence * mean_p q_m |m(x*) - m*|
              (targets from the radiance field across views, render/material_evidence.py; off in paper)
    L_bg    = w_r * mean_{mask = 0} | srgb(L_r) - srgb(L_gt) |   (masks and a background model)
    L_points = w_surface_points * mean_p |f(p)|   (captures without masks, train/surface_points.py)

With masks, colour terms average over foreground rays only (NeuS); with masks and a background
volume (``background``), ``L_bg`` trains the colour of the rays outside the masks, averaged
over those rays alone, so that the foreground terms keep their scale; ``L_surf`` and
``L_light`` always use only rays that hit a surface (mask, or :func:`foreground` without).

Each term is a :class:`LossTerm` of :data:`LOSS_TERMS` (name, weight field, function of a
:class:`LossBatch`); :func:`compute_losses` returns every term by name and
:func:`total_loss` their weighted sum, ``sum_k w_k L_k`` in the registry's order.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import torch
import torch.nn.functional as F
from torch import Tensor

from nepf_core.color import linear_to_srgb
from nepf_core.rays import RayBatch
from nepf_core.render.neus import foreground


@dataclass
class LossConfig:
    """Loss weights (0 switches a term off). Defaults are the paper's where it gives them."""

    w_r: float = 1.0
    """Outgoing-radiance colour loss."""
    lambda1_surf: float = 3e-4
    """Paper lambda1 (L_surf)."""
    lambda2_vol: float = 1e-4
    """Paper lambda2 (L_vol)."""
    w_eikonal: float = 0.1
    """Eikonal weight (NeuS's value; the paper gives none)."""
    w_hessian: float = 5e-4
    """Hessian weight (the paper gives none)."""
    w_light: float = 1e-4
    """Overall light-variance weight (paper: 1e-4)."""
    lambda3: float = 1.0
    """``|var x - var I|``: the light intensity varies across the batch about as much as the
    surface points do, no more; this is what keeps a texture out of the intensity (without it,
    spot_textured's spots went into the light: docs/TRIED.md, ``w_light = 0``)."""
    lambda4: float = 1.0
    """``|var n - var l|``: the light directions spread as much as the normals. For one distant or
    point light the true spread is far smaller, so this tilts ``l`` toward ``n``, raises ``n.l`` at
    grazing points and moves the shading into the albedo (0 in ``fast``; docs/FAST.md, "The light
    field's direction terms")."""
    lambda5: float = 0.1
    """``|var x - var l|``: the directions spread as much as the points (0 in ``fast``, as ``lambda4``)."""
    w_albedo_smooth: float = 0.0
    """Albedo smoothness prior at the surface points; > 0 needs ``RenderConfig.albedo_smooth_sigma
    > 0`` (an error otherwise: :meth:`nepf_core.config.NePFConfig.check`); not in the paper. Unlit regions carry no albedo information, so without a prior
    their albedo is whatever the network extrapolates; this lets neighbouring lit albedo fill it."""
    w_albedo_flat: float = 0.0
    """Lobe off only (``compute_losses(..., specular=False)``): lit surface rays pull the
    luminance of their albedo toward the batch's mean (stop-grad), relative L1. Diffuse-only
    shading ``c I(x) (n.l) / pi`` sees only the product of the albedo and the scalar photon
    intensity, so any pattern ``s(x)`` the photon network can represent moves freely between
    them; this term gives it to the light (slow variation is illumination: the Retinex
    assumption). Both this and the colour terms are L1, so texture stays in the albedo only where
    the colour terms' gradient on the albedo is larger, and that gradient carries the shading
    ``I (n.l) / pi`` and the sRGB slope: the weight must stay well under ``lambda2_vol`` times
    that slope, or the texture moves into the light (docs/FAST.md, "What fixed it")."""
    w_brdf_smooth: float = 0.0
    """The smoothness prior of ``w_albedo_smooth`` for roughness and metallic:
    ``mean (|r(x*) - r(x* + eps)| + |m(x*) - m(x* + eps)|)``. With a smoothness prior on the albedo
    alone, a texture is cheaper to carry in metallic (a ``(1 - m)`` dimmer) than in the albedo."""
    w_material_range: float = 0.0
    """Keep the material network's raw outputs (albedo, roughness, metallic logits ``z``) within
    ``|z| <= material_logit_max``: ``mean relu(|z| - z_max)`` over surface rays. A sigmoid past
    ``|z| ~ 5`` passes almost no gradient (``sigma' < 0.007``), and for roughness ``d alpha / d r =
    2 r`` vanishes at 0 as well, so a material channel that saturates early stays there whatever
    the images say later: spot_textured's roughness sat at exactly 0 and torus_glossy's at 1 and
    its blue albedo at 1 (docs/FAST.md, "Materials: saturation and the unseen lobe")."""
    material_logit_max: float = 3.0
    """``z_max`` of ``w_material_range``: sigmoid(3) = 0.953, so every channel keeps a slope of at
    least 0.045; roughness >= 0.047 still gives a near-mirror glTF lobe (alpha = 3e-3)."""
    w_colour_range: float = 0.0
    """Keep the colour logits (the radiance network's and the background's, every value a training
    render evaluated, :attr:`RenderOutput.colour_logits`) within ``|z| <= colour_logit_max``:
    ``mean relu(|z| - z_c)``. A pixel that is exactly black (a rendered background without masks) or
    white is reached by the sigmoid only at ``z = -/+ inf``, and the L1 colour loss pushes toward
    it with the same force however close it is. Adam then carries the shared network's logits far
    past any finite value (to ~-55 in 300 steps in tests/test_colour_range.py), where
    ``sigmoid' ~ e^-55``: every colour of the network is black, no pixel's error reaches it any
    more, and NeuS, trained by colour alone, lets the surface go to fog (bench/RESULTS.md
    v28). Past ``z_c`` this term's gradient is constant, so Adam brings the logits
    back at full speed. A plain sigmoid with a wider range (mip-NeRF) was tried and does not stop
    the overshoot (docs/TRIED.md)."""
    colour_logit_max: float = 9.0
    """``z_c`` of ``w_colour_range``: sigmoid(-9) = 1.2e-4 linear is sRGB 0.0016, under half of one
    8-bit level, so any colour an image can show lies inside."""
    w_metallic_unseen: float = 0.0
    """Metallic only where its lobe is seen: ``mean_lit m (1 - s)`` with ``s`` the specular lobe's
    share of the shaded surface colour (stop-grad, :attr:`RenderOutput.lobe`), over lit surface rays.
    A metal whose lobe the views never see (roughness near 0, so the highlight is a point that no
    pixel catches) only darkens its diffuse by ``(1 - m)``, which the albedo can do as well; the
    images cannot tell the two apart, and without a prior the texture goes into metallic. Where
    the lobe carries the colour (a real metal: ``s ~ 1``) the term vanishes. With the metal
    evidence on, the term is scaled by ``1 - share`` (:attr:`RenderOutput.metal_share`): it is
    lifted where the evidence recorded in the region says metal (a metal seen away from its
    highlight has ``s ~ 0`` too, and the prior alone turned every metal dielectric)."""
    w_material_evidence: float = 0.0
    """Pull the metallic at a few lit surface points per step toward what the radiance network's
    colours from other training cameras say the point is (:mod:`nepf_core.render.material_evidence`:
    the glTF BSDF fitted as a dielectric and as a metal at several roughnesses and light
    directions, each at its own best albedo), weighted by how clearly one kind fits better. Not
    in the paper (0 in ``paper``)."""
    w_surface_points: float = 0.0
    """Without masks: ``mean |f(p)|`` at the points triangulated from the images in the object
    region (:mod:`nepf_core.train.surface_points`, Geo-NeuS's sparse-point SDF loss). Not in the
    paper (its scenes have masks)."""
    w_mask: float = 0.1
    """Mask BCE weight (NeuS's value); only applied when the scene has masks."""
    w_normal_smooth: float = 0.0
    """``w mean_surf |n(x* + e) + n(x* - e) - 2 n(x*)|``, ``e ~ N(0, sigma^2 I)`` (the albedo prior's
    jitter): a second difference of the normal across the surface, which vanishes to first order on
    any smoothly curved surface (a sphere's costs ``O(sigma^2 / r^2)``) and not on bumps at the
    jitter's scale, so it smooths the grid's cell-scale noise without flattening true curvature."""


def l1_masked(pred: Tensor, target: Tensor, weight: Tensor | None) -> Tensor:
    """``sum_r w_r |pred_r - target_r|_1 / (3 sum_r w_r)`` (plain mean when weight is None)."""
    err = (pred - target).abs()
    if weight is None:
        return err.mean()
    return (err * weight[:, None]).sum() / (3.0 * weight.sum().clamp_min(1.0))


def batch_variance(x: Tensor) -> Tensor:
    """Total variance over a batch, ``sum_c Var(x[:, c])``: ``[N, C] -> []`` (0 for N < 2)."""
    if x.shape[0] < 2:
        return x.new_zeros(())
    return x.var(dim=0, unbiased=False).sum()


def light_variance_loss(x: Tensor, n: Tensor, l: Tensor, I: Tensor, l3: float, l4: float, l5: float) -> Tensor:
    """``l3 |var x - var I| + l4 |var n - var l| + l5 |var x - var l|`` over surface points."""
    vx, vn, vl, vI = batch_variance(x), batch_variance(n), batch_variance(l), batch_variance(I[:, None])
    return l3 * (vx - vI).abs() + l4 * (vn - vl).abs() + l5 * (vx - vl).abs()


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


def mask_bce(weight_sum: Tensor, mask: Tensor, ray_weight: Tensor | None = None) -> Tensor:
    """``BCE(clip(sum w, 1e-3, 1 - 1e-3), mask)``, finite for any weight sum: ``[R], [R] -> []``.

    With ``ray_weight`` ``[R]`` (importance weights ``q_r``): ``sum_r q_r BCE_r / sum_r q_r``."""
    bce = F.binary_cross_entropy(weight_sum.clip(1e-3, 1.0 - 1e-3), mask, reduction="none")
    return weighted_mean(bce, ray_weight)




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


def _needs(thing, weight: str, what: str):
    if thing is None:
        raise ValueError(f"loss.{weight} > 0 needs {what}")
    return thing


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


def loss_eikonal(b: LossBatch) -> Tensor:
    return weighted_mean(b.out.eikonal, b.out.eikonal_weight) if b.out.eikonal.numel() else b.zero


def loss_hessian(b: LossBatch) -> Tensor:
    return b.out.hessian.mean() if b.out.hessian.numel() else b.zero


def loss_light(b: LossBatch) -> Tensor:
    s, m, c = b.out.surface, b.on_surf, b.cfg
    return light_variance_loss(s.x[m], s.normal[m], s.light_dir[m], s.intensity[m], c.lambda3, c.lambda4, c.lambda5)


def loss_mask(b: LossBatch) -> Tensor:
    if not b.use_mask or b.rays.mask is None:
        return b.zero
    return mask_bce(b.out.weight_sum, b.rays.mask, b.rays.weight)


def loss_albedo_smooth(b: LossBatch) -> Tensor:
    s = b.out.surface
    j = _needs(s.jitter, "w_albedo_smooth", "render.albedo_smooth_sigma > 0 (a training render's Surface.jitter)")
    return mean_where((s.albedo - j.albedo).abs().mean(-1), b.on_surf)


def loss_albedo_flat(b: LossBatch) -> Tensor:
    if b.specular or b.lit.sum() < 2:
        return b.zero
    lum = b.out.surface.albedo[b.lit].mean(-1)
    return (lum / lum.detach().mean().clamp_min(1e-4) - 1.0).abs().mean()


def loss_brdf_smooth(b: LossBatch) -> Tensor:
    s = b.out.surface
    j = _needs(s.jitter, "w_brdf_smooth", "render.albedo_smooth_sigma > 0 (a training render's Surface.jitter)")
    return mean_where((s.roughness - j.roughness).abs() + (s.metallic - j.metallic).abs(), b.on_surf)


def loss_normal_smooth(b: LossBatch) -> Tensor:
    """``mean_surf |n(x* + e) + n(x* - e) - 2 n(x*)|`` (:attr:`LossConfig.w_normal_smooth`)."""
    s = b.out.surface
    return mean_where((s.jitter.normal + s.jitter.normal_mirror - 2 * s.normal).norm(dim=-1), b.on_surf)


def logit_excess(z: Tensor, z_max: float) -> Tensor:
    """``relu(|z| - z_max)``, elementwise: how far a logit lies past the range a sigmoid still
    trains in (the range priors ``w_material_range`` and ``w_colour_range``)."""
    return (z.abs() - z_max).clamp_min(0.0)


def loss_material_range(b: LossBatch) -> Tensor:
    z = _needs(b.out.surface.material_logits, "w_material_range", "a training render (material logits)")
    return mean_where(logit_excess(z, b.cfg.material_logit_max).mean(-1), b.on_surf)


def loss_colour_range(b: LossBatch) -> Tensor:
    z = _needs(b.out.colour_logits, "w_colour_range", "a training render (colour logits)")
    return logit_excess(z, b.cfg.colour_logit_max).mean() if z.numel() else b.zero


def loss_metallic_unseen(b: LossBatch) -> Tensor:
    lobe = _needs(b.out.lobe, "w_metallic_unseen", "a render with SurfaceRequest(lobe_split=True)")
    unseen = b.out.surface.metallic * (1.0 - lobe.share.detach())
    if b.out.metal_share is not None:
        unseen = unseen * (1.0 - b.out.metal_share)
    return mean_where(unseen, b.lit)


def loss_material_evidence(b: LossBatch) -> Tensor:
    eb = b.out.material_evidence
    if eb.rays.numel() == 0:
        return b.zero
    s, ev = b.out.surface, eb.evidence
    return (ev.metallic_confidence * (s.metallic[eb.rays] - ev.metallic).abs()).mean()


def loss_surface_points(b: LossBatch) -> Tensor:
    return b.surface_points()


@dataclass(frozen=True)
class LossTerm:
    """One named loss term: its record key, the :class:`LossConfig` field holding its weight, and
    ``fn(LossBatch) -> []``. A term whose weight is 0 is not computed (its value is 0)."""

    name: str
    weight: str
    fn: Callable[[LossBatch], Tensor]
    lobe_split: bool = False
    """The term reads :attr:`RenderOutput.lobe` (the render must be asked for it)."""
    jitter_normals: bool = False
    """The term reads the jittered points' normals (the render must be asked for them)."""
    present: Callable[[LossBatch], bool] | None = None
    """For a term whose input only some renders carry: whether this batch has it (the term is left
    out otherwise). None: always present."""


LOSS_TERMS: tuple[LossTerm, ...] = (
    LossTerm("loss_r", "w_r", loss_radiance),
    LossTerm("loss_bg", "w_r", loss_background),
    LossTerm("loss_surf", "lambda1_surf", loss_surface),
    LossTerm("loss_vol", "lambda2_vol", loss_volume),
    LossTerm("loss_eik", "w_eikonal", loss_eikonal),
    LossTerm("loss_hess", "w_hessian", loss_hessian),
    LossTerm("loss_light", "w_light", loss_light),
    LossTerm("loss_mask", "w_mask", loss_mask),
    LossTerm("loss_albedo_smooth", "w_albedo_smooth", loss_albedo_smooth),
    LossTerm("loss_albedo_flat", "w_albedo_flat", loss_albedo_flat),
    LossTerm("loss_brdf_smooth", "w_brdf_smooth", loss_brdf_smooth),
    LossTerm("loss_normal_smooth", "w_normal_smooth", loss_normal_smooth, jitter_normals=True,
             present=lambda b: b.out.surface.jitter is not None and b.out.surface.jitter.normal is not None),
    LossTerm("loss_material_range", "w_material_range", loss_material_range),
    LossTerm("loss_colour_range", "w_colour_range", loss_colour_range),
    LossTerm("loss_metallic_unseen", "w_metallic_unseen", loss_metallic_unseen, lobe_split=True),
    LossTerm("loss_material_evidence", "w_material_evidence", loss_material_evidence,
             present=lambda b: b.out.material_evidence is not None),   # only the training step gathers it
    LossTerm("loss_surface_points", "w_surface_points", loss_surface_points,
             present=lambda b: b.surface_points is not None),
)
"""Every term, in the order they are computed and summed."""


def needs_lobe_split(cfg: LossConfig) -> bool:
    """Whether a term with a non-zero weight reads :attr:`RenderOutput.lobe`."""
    return any(t.lobe_split and getattr(cfg, t.weight) > 0 for t in LOSS_TERMS)


def needs_jitter_normals(cfg: LossConfig) -> bool:
    """Whether a term with a non-zero weight reads the jittered points' normals."""
    return any(t.jitter_normals and getattr(cfg, t.weight) > 0 for t in LOSS_TERMS)


def compute_losses(out, rays: RayBatch, cfg: LossConfig, *, use_mask: bool, specular: bool = True,
                   background: bool = False, background_rays: tuple[Tensor, RayBatch] | None = None,
                   surface_points: Callable[[], Tensor] | None = None) -> dict[str, Tensor]:
    """Every term of :data:`LOSS_TERMS` by name (unweighted; 0 where its weight is 0), for one
    render ``out`` of ``rays``; arguments as :func:`loss_batch`. ``loss_surface_points`` is
    present only with ``surface_points``, ``loss_material_evidence`` only when ``out`` carries the
    evidence (the training step gathers it; a plain render does not). :func:`total_loss` sums them."""
    b = loss_batch(out, rays, cfg, use_mask=use_mask, specular=specular, background=background,
                   background_rays=background_rays, surface_points=surface_points)
    terms = {}
    for t in LOSS_TERMS:
        if t.present is not None and not t.present(b):
            continue
        terms[t.name] = t.fn(b) if getattr(cfg, t.weight) > 0 else b.zero
    return terms


def total_loss(terms: dict[str, Tensor], cfg: LossConfig) -> Tensor:
    """``sum_k w_k L_k`` over the terms present, in :data:`LOSS_TERMS` order."""
    total = None
    for t in LOSS_TERMS:
        if t.name in terms:
            v = getattr(cfg, t.weight) * terms[t.name]
            total = v if total is None else total + v
    return total
