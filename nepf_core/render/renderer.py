"""The NePF renderer: one set of samples, the NeuS weights, and three colours per ray.

    L_r    = sum_i w_i R(x_i, d, n_i, f_i)              (+ (1 - sum w) C_bg, fields/background.py)
    L_vol  = sum_i w_i f_bsdf(l_i, v, n_i; c_i, r_i, m_i) I_i (n_i . l_i)^+   (same background)
    L_surf = f_bsdf(...) I (n . l)^+  at i* = argmax_i w_i              (surface PBR)

(``surface_refine``: L_surf at the SDF zero crossing inside the max-weight section instead of
at the sample ``x_{i*}`` itself.)

with ``v = -d`` and ``n_i = grad f / |grad f|``. Heads (radiance, photon, material) are
evaluated only where ``w_i > head_weight_threshold`` (0 evaluates every sample); skipped
samples contribute at most ``threshold`` each to any colour, which is below 8-bit precision
for the default fast threshold.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
from torch import Tensor

from nepf_core import bsdf
from nepf_core.fields.fd_normals import fd_stencil, gradient_from_stencil, sdf_gradient_fd
from nepf_core.fields.gradients import sdf_gradient_autograd, sdf_gradient_central, sdf_hessian_norm
from nepf_core.rays import RayBatch
from nepf_core.render.neus import (alpha_from_sdf, annealed_cos, max_weight_index, surface_crossing_t,
                                   weights_from_alpha)
from nepf_core.render.sampling import hierarchical_z, object_segment, stratified_z


@dataclass
class RenderConfig:
    """How rays are sampled and shaded."""

    n_samples: int = 64
    """Coarse samples per ray (uniform in the paper preset)."""
    n_importance: int = 64
    """NeuS importance samples per ray (added to n_samples)."""
    up_sample_steps: int = 4
    """Rounds of NeuS up-sampling (n_importance / steps samples each)."""
    perturb: bool = True
    """Jitter coarse samples during training."""
    normals: str = "autograd"
    """``autograd`` (double backward) or ``fd`` (central differences, 6 extra SDF calls)."""
    alpha_mode: str = "midpoint"
    """``midpoint``: NeuS's section opacity from the mid-point SDF and the ray-normal
    cosine (needs the gradient at every sample). ``sample``: the same logistic-CDF ratio
    from the SDF at consecutive samples, ``alpha_i = (Phi(s f_i) - Phi(s f_{i+1})) / Phi(s f_i)``,
    which needs no gradient, is exact across skipped gaps, and lets the fast preset take
    finite-difference normals only where a head is evaluated."""
    eikonal_fraction: float = 0.25
    """``sample`` mode: extra random samples (fraction of all) that get the eikonal loss."""
    head_weight_threshold: float = 0.0
    """Evaluate radiance/photon/material only where w_i exceeds this (0: everywhere)."""
    hessian_fraction: float = 0.1
    """Fraction of samples (``midpoint`` alpha mode, training) that get the Hessian regulariser
    ``|H f|_F`` (:func:`nepf_core.fields.gradients.sdf_hessian_norm`: 6 gradient evaluations per
    point, so 0.1 adds 0.6 gradient evaluations per sample)."""
    lambertian: bool = False
    """Use the Lambertian diffuse (paper ablation) instead of Disney + retro-reflection
    (``bsdf_kind="paper"`` only; ``"gltf"`` is always Lambert)."""
    bsdf_kind: str = "paper"
    """The BSDF that shades L_surf / L_vol (:data:`nepf_core.bsdf.BSDF_KINDS`): ``"paper"`` is the
    supplementary's Disney diffuse + GGX (its masking term makes the lobe about a quarter of a
    standard GGX lobe); ``"gltf"`` is the glTF 2.0 metallic-roughness BRDF (Lambert + Smith GGX), the
    one three.js and Blender render the exported GLB with, so the recovered roughness and metallic
    mean the same there as in training."""
    specular: bool = True
    """Start with the GGX specular lobe (fit()'s adaptivity may drop it; the lobe in effect is
    the run state's :class:`Shading`, never written back here)."""
    unlit_albedo_stopgrad: bool = False
    """Training only: on rays whose target colour is unlit (``RayBatch.unlit``, set by fit()
    from the data), the colour error of L_vol / L_surf does not reach the albedo; only the
    photon field (direction, intensity) and geometry may explain the darkness. A pixel that
    received no light carries no information on the albedo, and letting it drive the albedo
    to 0 is what made the recovered albedo black in shadows (docs/FAST.md, "Albedo in
    unlit regions")."""
    albedo_smooth_sigma: float = 0.0
    """Training only, > 0: also query the material network at ``x* + N(0, sigma^2 I)`` next
    to each max-weight point (``surf["albedo_jitter"]``) for the albedo smoothness prior
    (``LossConfig.w_albedo_smooth``). Normalised-frame units."""
    unlit_rel_threshold: float = 0.01
    """A target pixel is unlit when ``max_c L_gt < unlit_rel_threshold * q99(foreground)``
    (:func:`nepf_core.rays.unlit_threshold`)."""
    surface_refine: bool = False
    """``sample`` alpha mode only: shade L_surf (and report ``surf``) at the SDF zero crossing
    inside the max-weight section (:func:`nepf_core.render.neus.surface_crossing_t`), with its
    own finite-difference normal, instead of at the max-weight sample, which lies up to one
    sample spacing in front of the surface, at an offset that changes with the sample
    placement. Costs one photon + material evaluation and 5 SDF queries per ray. Off in
    ``paper`` (the paper shades the max-weight point)."""
    amp_heads: bool = False
    """bf16 autocast for the radiance / photon / material networks only (CUDA). The SDF, the
    NeuS density and the BSDF stay in fp32: a bf16 SDF near the surface is off by ~1e-3,
    which at inv_s >= 1e3 changes the density a lot."""


@dataclass(frozen=True)
class Shading:
    """The shading model in effect (a run's switches, :class:`nepf_core.train.run_state.RunState`).

    ``specular``: evaluate the GGX lobe, ``f = f_d + f_s`` (Disney diffuse, :mod:`nepf_core.bsdf`).
    Without it the surface is shaded as ``(1 - w m) f_d(c) + w f_s`` with
    ``w = diffuse_metal_weight`` (:func:`nepf_core.bsdf.shade_fading_lobe`): 0 is a dielectric
    diffuse (metallic ignored, no lobe evaluated); adaptivity fades ``w`` from 1 to 0 after
    dropping the lobe, so the image does not jump from the full BSDF to ``f_d``."""

    specular: bool = True
    diffuse_metal_weight: float = 0.0


@dataclass
class RenderOutput:
    """Per-ray results (``R`` rays) and per-sample regulariser terms."""

    rgb_r: Tensor
    rgb_vol: Tensor
    rgb_surf: Tensor
    weight_sum: Tensor
    w_max: Tensor
    depth: Tensor
    eikonal: Tensor
    """``| |grad f| - 1 |`` on samples inside the unit sphere, ``[P]``."""
    hessian: Tensor
    """``|H f|_F`` (Frobenius norm of the SDF Hessian) on a subset of samples, ``[Q]`` (may be empty)."""
    surf: dict = field(default_factory=dict)
    """At the max-weight sample: x, normal, light_dir, intensity, albedo, roughness,
    metallic; in training renders ``material_logits``; with ``need_lobe_share`` ``lobe_share``
    (no grad: the specular lobe's share of L_surf); with ``need_surface_extras`` also (no grad) specular (the same share),
    specular_abs and diffuse_only (``[R, 3]``, L_surf without the lobe)."""
    background: Tensor | None = None
    """``[R, 3]`` the background volume's colour of each ray (None without one), composited into
    ``rgb_r`` and ``rgb_vol`` behind the object."""
    n_samples: int = 0
    n_head_evals: int = 0
    inv_s: float = 0.0
    eikonal_weight: Tensor | None = None
    """``[P]``: the importance weight ``RayBatch.weight`` of the ray each ``eikonal`` sample
    lies on (None when the batch has no weights): the eikonal mean is then weighted like the
    mask loss, so a batch thinned by :func:`nepf_core.train.rules.empty_rays.thin_empty_rays` keeps
    its expectation."""


def _shade_points(model, cfg: RenderConfig, shading: Shading, xs: Tensor, vs: Tensor, ns: Tensor, fs: Tensor,
                  unlit: Tensor | None, *, logits: bool = False):
    """Photon + material heads and the BSDF at ``N`` points: ``xs, vs, ns [N, 3]`` (position,
    ray direction, unit normal), ``fs [N, F]`` SDF features, ``unlit [N]`` bool or None (training:
    the colour error of an unlit point does not reach its albedo, ``RenderConfig.unlit_*``).
    Returns ``pbr [N, 3] = f(l, -v; c, r, m) I (n . l)^+`` (the fading lobe when
    ``shading.specular`` is off), ``light_dir [N, 3]``, ``intensity [N]``, ``albedo [N, 3]``,
    ``roughness [N]``, ``metallic [N]`` (all fp32), and with ``logits`` the material network's raw
    outputs ``[N, 5]`` (else None)."""
    with torch.autocast(device_type=xs.device.type, dtype=torch.bfloat16,
                        enabled=cfg.amp_heads and xs.device.type == "cuda"):
        light_dir, intensity = model.photon(xs, ns, fs)
        if logits:
            albedo, rough, metal, z = model.material(xs, ns, fs, with_logits=True)
        else:
            (albedo, rough, metal), z = model.material(xs, ns, fs), None
    light_dir, intensity = light_dir.float(), intensity.float()
    albedo, rough, metal = albedo.float(), rough.float(), metal.float()
    albedo_shade = albedo
    if cfg.unlit_albedo_stopgrad and unlit is not None:
        albedo_shade = torch.where(unlit[:, None], albedo.detach(), albedo)
    if not shading.specular:  # lobe dropped: (1 - w m) f_d(c) + w f_s, w fading to 0 (a dielectric diffuse)
        pbr = bsdf.shade_fading_lobe(ns, light_dir, -vs, albedo_shade, rough[:, None], metal[:, None],
                                     intensity[:, None], shading.diffuse_metal_weight, lambertian=cfg.lambertian,
                                     kind=cfg.bsdf_kind)
    else:
        pbr = bsdf.shade(ns, light_dir, -vs, albedo_shade, rough[:, None], metal[:, None],
                         intensity[:, None], lambertian=cfg.lambertian, specular=True, kind=cfg.bsdf_kind)
    return pbr, light_dir, intensity, albedo, rough, metal, (None if z is None else z.float())


def _expand(t: Tensor, S: int) -> Tensor:
    return t[:, None, :].expand(-1, S, -1).reshape(-1, t.shape[-1])


def render_rays(model, rays: RayBatch, cfg: RenderConfig, *, train: bool, cos_anneal: float = 1.0,
                generator: torch.Generator | None = None, need_surface_extras: bool = False,
                need_lobe_share: bool = False, shading: Shading | None = None) -> RenderOutput:
    """Render ``rays`` with ``model`` (a :class:`nepf_core.model.NePFModel`).

    Shapes: rays of length ``R``; returns :class:`RenderOutput` with ``[R, 3]`` colours.
    ``shading``: the shading model in effect (a trained run's: ``RunState.shading()``); None:
    ``Shading(specular=cfg.specular)``, the configured start. ``need_lobe_share``: also return
    ``surf["lobe_share"]`` (for :attr:`nepf_core.losses.LossConfig.w_metallic_unseen`).
    """
    shading = shading if shading is not None else Shading(specular=cfg.specular)
    o, d = rays.origins, rays.directions
    R = o.shape[0]
    near, far, hit, cut = object_segment(o, d, model.cfg.object_halfspace)
    sdf_only = model.sdf.sdf
    z = stratified_z(near, far, cfg.n_samples, perturb=train and cfg.perturb, generator=generator)
    z = hierarchical_z(o, d, z, sdf_only, cfg.n_importance, cfg.up_sample_steps)
    S = z.shape[1]
    dists = z[:, 1:] - z[:, :-1]
    dists = torch.cat([dists, dists[:, -1:].clamp_min(1e-4)], -1)
    inv_s = model.deviation()
    hess = o.new_zeros(0)
    if cfg.alpha_mode == "sample":
        mid = z
        pts = (o[:, None, :] + d[:, None, :] * z[..., None]).reshape(-1, 3)
        dirs = _expand(d, S)
        sdf, feat = model.sdf(pts)
        f = sdf.reshape(R, S)
        prev_cdf = torch.sigmoid(f[:, :-1] * inv_s)
        next_cdf = torch.sigmoid(f[:, 1:] * inv_s)
        alpha = ((prev_cdf - next_cdf + 1e-5) / (prev_cdf + 1e-5)).clip(0.0, 1.0)
        alpha = torch.cat([alpha, torch.zeros_like(alpha[:, :1])], -1)
        weights = weights_from_alpha(alpha)
        # gradients (FD) only where a head is evaluated, plus a random subset for the eikonal
        w_flat = weights.reshape(-1).detach()
        need = w_flat > cfg.head_weight_threshold
        idx_max = weights.argmax(-1)
        need[torch.arange(R, device=o.device) * S + idx_max] = True
        if train and cfg.eikonal_fraction > 0:
            need |= torch.rand(need.shape, device=o.device) < cfg.eikonal_fraction
        gidx = need.nonzero(as_tuple=True)[0]
        g_sub, _ = sdf_gradient_fd(sdf_only, pts[gidx], model.sdf.fd_step(), scheme="tetra", center="mean")
        grad = pts.new_zeros(pts.shape[0], 3).index_copy(0, gidx, g_sub)
        gnorm_sub = g_sub.norm(dim=-1)
        inside_sub = pts[gidx].norm(dim=-1) < 1.0
        eikonal = (gnorm_sub - 1.0).abs()[inside_sub]
        eik_ray = torch.div(gidx, S, rounding_mode="floor")[inside_sub]
        gnorm = grad.norm(dim=-1)
    else:
        mid = z + dists * 0.5
        pts = (o[:, None, :] + d[:, None, :] * mid[..., None]).reshape(-1, 3)
        dirs = _expand(d, S)
        if cfg.normals == "fd":
            sdf, feat = model.sdf(pts)
            grad, _ = sdf_gradient_central(sdf_only, pts, model.sdf.fd_step())
        else:
            sdf, feat, grad = sdf_gradient_autograd(model.sdf, pts, create_graph=train)
        if train and cfg.hessian_fraction > 0:  # |H f|_F on a random subset (fields/gradients.py)
            q = max(1, int(pts.shape[0] * cfg.hessian_fraction))
            sub = torch.randint(0, pts.shape[0], (q,), device=pts.device)
            hess = sdf_hessian_norm(sdf_only, pts[sub], model.sdf.fd_step(),
                                    gradient="fd" if cfg.normals == "fd" else "autograd")
        true_cos = (dirs * grad).sum(-1)
        cos = annealed_cos(true_cos, cos_anneal if train else 1.0)
        alpha = alpha_from_sdf(sdf.reshape(R, S), cos.reshape(R, S), dists, inv_s)
        weights = weights_from_alpha(alpha)
        inside = pts.norm(dim=-1) < 1.0
        gnorm = grad.norm(dim=-1)
        eikonal = (gnorm - 1.0).abs()[inside]
        eik_ray = torch.div(torch.arange(pts.shape[0], device=o.device), S, rounding_mode="floor")[inside]
    weight_sum = weights.sum(-1)
    eik_w = None if rays.weight is None else rays.weight[eik_ray].to(eikonal.dtype)

    normals = grad / gnorm.clamp_min(1e-8)[:, None]
    w_flat = weights.reshape(-1)
    idx, w_max = max_weight_index(weights)
    flat_max = torch.arange(R, device=o.device) * S + idx
    if cfg.head_weight_threshold > 0:
        sel = w_flat.detach() > cfg.head_weight_threshold
        sel[flat_max] = True  # the surface sample is always shaded
        sel_idx = sel.nonzero(as_tuple=True)[0]
    else:
        sel_idx = torch.arange(pts.shape[0], device=o.device)
    xs, vs, ns, gs, fs = pts[sel_idx], dirs[sel_idx], normals[sel_idx], grad[sel_idx], feat[sel_idx]
    with torch.autocast(device_type=xs.device.type, dtype=torch.bfloat16,
                        enabled=cfg.amp_heads and xs.device.type == "cuda"):
        rad = model.radiance(xs, vs, gs, fs)
    rad = rad.float()
    unlit_sample = rays.unlit[sel_idx // S] if (train and rays.unlit is not None) else None
    pbr, light_dir, intensity, albedo, rough, metal, z_mat = _shade_points(model, cfg, shading, xs, vs, ns, fs,
                                                                          unlit_sample, logits=train)

    P = pts.shape[0]
    rad_full = pts.new_zeros(P, 3).index_copy(0, sel_idx, rad)
    pbr_full = pts.new_zeros(P, 3).index_copy(0, sel_idx, pbr)
    w3 = weights[..., None]
    rgb_r = (w3 * rad_full.reshape(R, S, 3)).sum(1)
    rgb_vol = (w3 * pbr_full.reshape(R, S, 3)).sum(1)
    rgb_surf = pbr_full[flat_max]
    bg = None
    if getattr(model, "background", None) is not None:
        bg = model.background(o, d, perturb=train and cfg.perturb, generator=generator, start=cut)
        rgb_r = rgb_r + (1.0 - weight_sum)[:, None] * bg
        rgb_vol = rgb_vol + (1.0 - weight_sum)[:, None] * bg

    # surface quantities at the max-weight sample, for losses and rendering
    pos = torch.full((P,), -1, dtype=torch.long, device=o.device)
    pos[sel_idx] = torch.arange(sel_idx.shape[0], device=o.device)
    k = pos[flat_max]
    surf = {
        "x": pts[flat_max], "normal": normals[flat_max], "light_dir": light_dir[k],
        "intensity": intensity[k], "albedo": albedo[k], "roughness": rough[k], "metallic": metal[k],
    }
    if z_mat is not None:
        surf["material_logits"] = z_mat[k]
    xj = fj = None   # the albedo prior's jittered points and their SDF features
    if cfg.surface_refine and cfg.alpha_mode == "sample":
        # the same quantities at the zero crossing inside the max-weight section
        xr = o + d * surface_crossing_t(z, f, idx)[:, None]
        queries = [xr]
        if train and cfg.albedo_smooth_sigma > 0:   # the albedo prior's jittered points, in the same SDF call
            xj = xr + cfg.albedo_smooth_sigma * torch.randn(xr.shape, device=o.device, dtype=xr.dtype)
            queries.append(xj)
        stencil, offsets = fd_stencil(xr, model.sdf.fd_step(), scheme="tetra", center="mean")
        f_all, feat_all = model.sdf(torch.cat([stencil] + queries, 0))
        gr, _ = gradient_from_stencil(f_all, R, offsets, model.sdf.fd_step(), scheme="tetra", center="mean")
        fr = feat_all[stencil.shape[0]:stencil.shape[0] + R]
        if xj is not None:
            fj = feat_all[stencil.shape[0] + R:]
        nr = gr / gr.norm(dim=-1, keepdim=True).clamp_min(1e-8)
        unlit_ray = rays.unlit if (train and rays.unlit is not None) else None
        rgb_surf, ld_r, int_r, alb_r, rough_r, metal_r, z_r = _shade_points(model, cfg, shading, xr, d, nr, fr,
                                                                             unlit_ray, logits=train)
        surf = {"x": xr, "normal": nr, "light_dir": ld_r, "intensity": int_r, "albedo": alb_r,
                "roughness": rough_r, "metallic": metal_r}
        if z_r is not None:
            surf["material_logits"] = z_r
    if train and cfg.albedo_smooth_sigma > 0:
        if xj is None:
            xj = surf["x"].detach() + cfg.albedo_smooth_sigma * torch.randn(surf["x"].shape, device=o.device,
                                                                            dtype=surf["x"].dtype)
            _, fj = model.sdf(xj)
        with torch.autocast(device_type=xj.device.type, dtype=torch.bfloat16,
                            enabled=cfg.amp_heads and xj.device.type == "cuda"):
            a_j, r_j, m_j = model.material(xj, surf["normal"].detach(), fj)
            surf["albedo_jitter"], surf["roughness_jitter"], surf["metallic_jitter"] = a_j.float(), r_j.float(), m_j.float()
    if need_surface_extras or need_lobe_share:
        with torch.no_grad():
            diffuse_only = bsdf.shade(surf["normal"], surf["light_dir"], -d, surf["albedo"],
                                      surf["roughness"][:, None], surf["metallic"][:, None],
                                      surf["intensity"][:, None], lambertian=cfg.lambertian, specular=False,
                                      kind=cfg.bsdf_kind)
            total = rgb_surf.detach().sum(-1)
            share = (total - diffuse_only.sum(-1)).clamp_min(0) / total.clamp_min(1e-6)
            if need_lobe_share:
                surf["lobe_share"] = share
            if need_surface_extras:      # the lobe rule's checks only (their cadence is the rule's)
                surf["specular"] = share
                surf["specular_abs"] = (rgb_surf.detach() - diffuse_only).clamp_min(0).mean(-1)
                surf["diffuse_only"] = diffuse_only
    depth = (weights * mid).sum(-1)
    return RenderOutput(rgb_r=rgb_r, rgb_vol=rgb_vol, rgb_surf=rgb_surf, weight_sum=weight_sum, w_max=w_max,
                        depth=depth, eikonal=eikonal, hessian=hess, surf=surf, background=bg, n_samples=int(P),
                        n_head_evals=int(sel_idx.shape[0]), inv_s=float(inv_s.detach()), eikonal_weight=eik_w)


def render_background_only(model, rays: RayBatch, cfg: RenderConfig, *, train: bool,
                           generator: torch.Generator | None = None) -> Tensor:
    """``[B, 3]`` linear colour of rays that meet no occupied cell: ``C = C_bg``.

    Such a ray's SDF weights sum to at most ~e^{-k_s} (:mod:`nepf_core.render.occupancy`), so
    ``C = sum_i w_i c_i + (1 - sum_i w_i) C_bg`` is ``C_bg`` up to that bound, for the radiance
    and the PBR colour alike. The background volume starts where the object's region ends on
    the ray (the support plane's cut, else the unit sphere's exit), as in :func:`render_rays`.
    Needs ``model.background``."""
    _, _, _, cut = object_segment(rays.origins, rays.directions, model.cfg.object_halfspace)
    return model.background(rays.origins, rays.directions, perturb=train and cfg.perturb, generator=generator,
                            start=cut)
