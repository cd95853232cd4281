"""NePF losses. Each term is a pure function; :class:`LossConfig` weights and switches them.

Colour terms compare display-space values ``srgb(.)`` (see ``docs/ARCHITECTURE.md``):

    L_r     = mean | srgb(L_r) - srgb(L_gt) |
    L_surf  = lambda1 * mean (1 - w_max) | srgb(L_surf) - srgb(sg(L_r)) |     (paper; sg = stop-grad)
              (ablation: supervise by L_gt instead of L_r)
    L_vol   = lambda2 * mean | srgb(L_vol) - srgb(L_gt) |
    L_eik   = w_eik * mean_q | |grad f| - 1 |      (q: the sample's ray weight, 1 unless thinned)
    L_hess  = w_hess * mean |H f|_F      (Frobenius norm of the SDF Hessian, fields/gradients.py)
    L_light = w_light * (l3 |var x - var I| + l4 |var n - var l| + l5 |var x - var l|)
    L_asm   = w_albedo_smooth * mean | c(x*) - c(x* + eps) |   (albedo smoothness prior, off in paper)
    L_flat  = w_albedo_flat * mean_lit | Y(c) / sg(mean_lit Y(c)) - 1 |, Y = channel mean   (lobe off only)
    L_mask  = w_mask * BCE(clip(sum w, 1e-3, 1 - 1e-3), mask)
    L_bsm   = w_brdf_smooth * mean (|r(x*) - r(x* + eps)| + |m(x*) - m(x* + eps)|)   (off in paper)
    L_range = w_material_range * mean_surf mean_k relu(|z_k| - z_max)   (z: material logits; off in paper)
    L_unseen = w_metallic_unseen * mean_lit m (1 - s)   (s: the lobe's share of L_surf, stop-grad; off in paper)
    L_bg    = w_r * mean_{mask = 0} | srgb(L_r) - srgb(L_gt) |   (masks and a background model)

With masks, colour terms average over foreground rays only (NeuS); with masks and a background
volume (``background``), ``L_bg`` trains the colour of the rays outside the masks, averaged
over those rays alone, so that the foreground terms keep their scale; ``L_surf`` and
``L_light`` always use only rays that hit a surface (mask, or ``sum w > 0.5`` without).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from nepf_core.rays import RayBatch


@dataclass
class LossConfig:
    """Loss weights (0 switches a term off). Defaults are the paper's where it gives them."""

    w_r: float = 1.0
    """Outgoing-radiance colour loss."""
    lambda1_surf: float = 3e-4
    """Paper lambda1 (L_surf)."""
    lambda2_vol: float = 1e-4
    """Paper lambda2 (L_vol)."""
    surf_target: str = "radiance"
    """``radiance`` (paper: L_surf supervised by L_r) or ``gt`` (ablation)."""
    surf_one_minus_wmax: bool = True
    """Multiply L_surf by (1 - w_max) (paper's "surface approaching")."""
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
    """Albedo smoothness prior at the max-weight points (needs ``RenderConfig.albedo_smooth_sigma
    > 0``); not in the paper. Unlit regions carry no albedo information, so without a prior
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
    w_metallic_unseen: float = 0.0
    """Metallic only where its lobe is seen: ``mean_lit m (1 - s)`` with ``s`` the specular lobe's
    share of the shaded surface colour (stop-grad, ``surf["lobe_share"]``), over lit surface rays.
    A metal whose lobe the views never see (roughness near 0, so the highlight is a point that no
    pixel catches) only darkens its diffuse by ``(1 - m)``, which the albedo can do as well; the
    images cannot tell the two apart, and without a prior the texture goes into metallic. Where
    the lobe carries the colour (a real metal: ``s ~ 1``) the term vanishes."""
    w_surface_points: float = 0.0
    """Without masks: ``mean |f(p)|`` at the points triangulated from the images in the object
    region (:mod:`nepf_core.train.surface_points`, Geo-NeuS's sparse-point SDF loss). Not in the
    paper (its scenes have masks)."""
    w_mask: float = 0.1
    """Mask BCE weight (NeuS's value); only applied when the scene has masks."""
    color_space: str = "srgb"
    """``srgb`` (display space) or ``linear``."""


def srgb_encode(x: Tensor) -> Tensor:
    """sRGB OETF on linear values clamped to [0, 1]; bounded slope (12.92) near 0."""
    x = x.clamp(0.0, 1.0)
    return torch.where(x <= 0.0031308, 12.92 * x, 1.055 * x.clamp_min(0.0031308) ** (1 / 2.4) - 0.055)


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


def compute_losses(out, rays: RayBatch, cfg: LossConfig, *, use_mask: bool, specular: bool = True,
                   background: bool = False,
                   background_rays: tuple[Tensor, RayBatch] | None = None) -> dict[str, Tensor]:
    """All enabled loss terms plus their weighted sum under ``"loss"``. ``specular``: whether
    the render evaluated the GGX lobe (``RenderConfig.specular``); L_flat applies only without it.
    ``background``: the model has a background volume (L_bg with masks).

    ``background_rays = (C_bg [B, 3], rays [B])``: the misses the empty-ray rule left out of the
    SDF batch, rendered by the background alone (their ``rgb_r = rgb_vol = C_bg``,
    :func:`nepf_core.render.renderer.render_background_only`). The colour terms ``L_r``, ``L_vol``
    and ``L_bg`` are then means over all ``R + B`` rays, each background ray weighing its
    ``rays.weight`` (the misses it stands for, :mod:`nepf_core.train.rules.empty_rays`), and the
    kept misses count once in ``L_bg`` (each stands for itself, no longer for ``1 / miss_keep``
    drawn misses)."""
    enc = srgb_encode if cfg.color_space == "srgb" else (lambda t: t.clamp(0.0, 1.0))
    gt = enc(rays.rgb)
    fg = rays.mask if (use_mask and rays.mask is not None) else None
    L = {}
    zero = out.rgb_r.new_zeros(())
    r_sdf = enc(out.rgb_r)
    r_enc, vol_enc = r_sdf, enc(out.rgb_vol)
    gt_all, fg_all = gt, fg
    colour_q = None          # per-ray weight in the colour means (None: every ray once)
    outside_q = rays.weight  # L_bg: a thinned batch's kept misses stand for 1 / miss_keep misses
    if background_rays is not None:
        bg_rgb, bg_rays = background_rays
        bg_enc = enc(bg_rgb)
        r_enc, vol_enc = torch.cat([r_enc, bg_enc]), torch.cat([vol_enc, bg_enc])
        gt_all = torch.cat([gt, enc(bg_rays.rgb)])
        fg_all = None if fg is None else torch.cat([fg, bg_rays.mask])
        bg_q = bg_rays.weight if bg_rays.weight is not None else torch.ones_like(bg_enc[:, 0])
        colour_q = outside_q = torch.cat([torch.ones_like(gt[:, 0]), bg_q])
    colour_w = fg_all if colour_q is None else (colour_q if fg_all is None else fg_all * colour_q)
    L["loss_r"] = l1_masked(r_enc, gt_all, colour_w) if cfg.w_r > 0 else zero
    L["loss_bg"] = zero
    if background and fg_all is not None and cfg.w_r > 0:
        L["loss_bg"] = l1_masked(r_enc, gt_all, (1.0 - fg_all) * (outside_q if outside_q is not None else 1.0))
    surf_rays = fg if fg is not None else (out.weight_sum.detach() > 0.5).float()
    if cfg.lambda1_surf > 0:
        target = r_sdf.detach() if cfg.surf_target == "radiance" else gt
        wt = surf_rays * ((1.0 - out.w_max.detach()) if cfg.surf_one_minus_wmax else 1.0)
        err = (enc(out.rgb_surf) - target).abs().mean(-1)
        L["loss_surf"] = (err * wt).sum() / surf_rays.sum().clamp_min(1.0)
    else:
        L["loss_surf"] = zero
    L["loss_vol"] = l1_masked(vol_enc, gt_all, colour_w) if cfg.lambda2_vol > 0 else zero
    L["loss_eik"] = (weighted_mean(out.eikonal, out.eikonal_weight)
                     if (cfg.w_eikonal > 0 and out.eikonal.numel()) else zero)
    L["loss_hess"] = out.hessian.mean() if (cfg.w_hessian > 0 and out.hessian.numel()) else zero
    s = out.surf
    on_surf = surf_rays > 0.5
    lit = on_surf & ~rays.unlit if rays.unlit is not None else on_surf
    if cfg.w_light > 0:
        L["loss_light"] = light_variance_loss(s["x"][on_surf], s["normal"][on_surf], s["light_dir"][on_surf],
                                              s["intensity"][on_surf], cfg.lambda3, cfg.lambda4, cfg.lambda5)
    else:
        L["loss_light"] = zero
    L["loss_albedo_smooth"] = zero
    if cfg.w_albedo_smooth > 0 and "albedo_jitter" in s:
        L["loss_albedo_smooth"] = mean_where((s["albedo"] - s["albedo_jitter"]).abs().mean(-1), on_surf)
    L["loss_albedo_flat"] = zero
    if cfg.w_albedo_flat > 0 and not specular and lit.sum() >= 2:
        lum = s["albedo"][lit].mean(-1)
        L["loss_albedo_flat"] = (lum / lum.detach().mean().clamp_min(1e-4) - 1.0).abs().mean()
    L["loss_brdf_smooth"] = zero
    if cfg.w_brdf_smooth > 0 and "roughness_jitter" in s:
        diff = (s["roughness"] - s["roughness_jitter"]).abs() + (s["metallic"] - s["metallic_jitter"]).abs()
        L["loss_brdf_smooth"] = mean_where(diff, on_surf)
    L["loss_material_range"] = zero
    if cfg.w_material_range > 0 and "material_logits" in s:
        over = (s["material_logits"].abs() - cfg.material_logit_max).clamp_min(0.0).mean(-1)
        L["loss_material_range"] = mean_where(over, on_surf)
    L["loss_metallic_unseen"] = zero
    if cfg.w_metallic_unseen > 0 and "lobe_share" in s:
        L["loss_metallic_unseen"] = mean_where(s["metallic"] * (1.0 - s["lobe_share"].detach()), lit)
    L["loss_mask"] = (mask_bce(out.weight_sum, rays.mask, rays.weight)
                      if (use_mask and rays.mask is not None and cfg.w_mask > 0) else zero)
    L["loss"] = (cfg.w_r * (L["loss_r"] + L["loss_bg"]) + cfg.lambda1_surf * L["loss_surf"] + cfg.lambda2_vol * L["loss_vol"]
                 + cfg.w_eikonal * L["loss_eik"] + cfg.w_hessian * L["loss_hess"]
                 + cfg.w_light * L["loss_light"] + cfg.w_mask * L["loss_mask"]
                 + cfg.w_albedo_smooth * L["loss_albedo_smooth"] + cfg.w_albedo_flat * L["loss_albedo_flat"]
                 + cfg.w_brdf_smooth * L["loss_brdf_smooth"] + cfg.w_material_range * L["loss_material_range"]
                 + cfg.w_metallic_unseen * L["loss_metallic_unseen"])
    return L
