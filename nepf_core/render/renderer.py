"""The NePF renderer: one set of samples, the NeuS weights, and three colours per ray.

    L_r    = sum_i w_i R(x_i, d, n_i, F_i)                      + (1 - sum_i w_i) C_bg
    L_vol  = sum_i w_i f_bsdf(l_i, v, n_i; c_i, r_i, m_i) I_i (n_i . l_i)^+   + (1 - sum_i w_i) C_bg
    L_surf = f_bsdf(l, v, n; c, r, m) I (n . l)^+  at the surface point x* (:class:`Surface`)

with ``v = -d``, ``n_i = grad f / |grad f|`` and ``C_bg`` the background volume's colour
(:mod:`nepf_core.fields.background`; 0 without one). :func:`render_rays` runs the stages:

1. samples and weights, one function per alpha mode (:mod:`nepf_core.render.weights`);
2. the heads and the BSDF at the samples whose weight exceeds ``head_weight_threshold``
   (:mod:`nepf_core.render.shading`), composited into ``L_r`` and ``L_vol``;
3. the surface point ``x*`` and the fields there (:mod:`nepf_core.render.surface`): the
   max-weight sample, or its section's SDF zero crossing (``surface_refine``); the material
   next to it for the smoothness priors; the lobe's share of ``L_surf`` when a
   :class:`SurfaceRequest` asks for it.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from nepf_core.rays import RayBatch
from nepf_core.render.sampling import hierarchical_z, object_segment, stratified_z
from nepf_core.render.shading import Shading, selected_samples, shade_points, shade_samples
from nepf_core.render.surface import (LobeSplit, Surface, SurfaceRequest, jittered_material, lobe_split,
                                      refine_surface, surface_at_index)
from nepf_core.render.weights import SampleWeights, weights_midpoint_mode, weights_sample_mode

__all__ = ["RenderConfig", "RenderOutput", "Shading", "Surface", "SurfaceRequest", "LobeSplit", "render_rays",
           "render_background_only"]


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
    received no light carries no information on the albedo; letting its error reach the albedo
    drives the albedo to 0 in shadows (docs/FAST.md, "Albedo in unlit regions")."""
    albedo_smooth_sigma: float = 0.0
    """Training only, > 0: also query the material network at ``x* + N(0, sigma^2 I)`` next
    to each surface point (:attr:`Surface.jitter`) for the smoothness priors
    (``LossConfig.w_albedo_smooth``, ``w_brdf_smooth``: a non-zero weight needs it). Normalised-frame units."""
    surface_refine: bool = False
    """``sample`` alpha mode only: shade L_surf (and place :class:`Surface`) at the SDF zero crossing
    inside the max-weight section (:func:`nepf_core.render.neus.surface_crossing_t`), with its
    own finite-difference normal, instead of at the max-weight sample, which lies up to one
    sample spacing in front of the surface, at an offset that changes with the sample
    placement. Costs one photon + material evaluation and 5 SDF queries per ray. Off in
    ``paper`` (the paper shades the max-weight point)."""
    amp_heads: bool = False
    """bf16 autocast for the radiance / photon / material networks only (CUDA). The SDF, the
    NeuS density and the BSDF stay in fp32: a bf16 SDF near the surface is off by ~1e-3,
    which at inv_s >= 1e3 changes the density a lot."""


@dataclass
class RenderOutput:
    """Per-ray results (``R`` rays) and per-sample regulariser terms."""

    rgb_r: Tensor
    """``[R, 3]`` ``L_r`` (linear)."""
    rgb_vol: Tensor
    """``[R, 3]`` ``L_vol``."""
    rgb_surf: Tensor
    """``[R, 3]`` ``L_surf`` (not composited over the background)."""
    weight_sum: Tensor
    """``[R]`` the opacity ``sum_i w_i``."""
    w_max: Tensor
    """``[R]`` the largest weight ``w_{i*}``."""
    depth: Tensor
    """``[R]`` ``sum_i w_i t_i`` (``t_i``: where the SDF was evaluated)."""
    eikonal: Tensor
    """``| |grad f| - 1 |`` on samples inside the unit sphere, ``[P]``."""
    hessian: Tensor
    """``|H f|_F`` (Frobenius norm of the SDF Hessian) on a subset of samples, ``[Q]`` (may be empty)."""
    surface: Surface
    """The surface point of each ray and the fields there."""
    lobe: LobeSplit | None = None
    """The lobe's part of ``L_surf`` (only when the :class:`SurfaceRequest` asks for it)."""
    background: Tensor | None = None
    """``[R, 3]`` the background volume's colour of each ray (None without one), composited into
    ``rgb_r`` and ``rgb_vol`` behind the object."""
    n_samples: int = 0
    n_head_evals: int = 0
    inv_s: Tensor | float = 0.0
    """NeuS's sharpness ``s`` of this render: a 0-d tensor (detached) so that a training step
    does not sync the host for it; a record reads it with ``float()`` when it writes."""
    eikonal_weight: Tensor | None = None
    """``[P]``: the importance weight ``RayBatch.weight`` of the ray each ``eikonal`` sample
    lies on (None when the batch has no weights): the eikonal mean is then weighted like the
    mask loss, so a batch thinned by :meth:`nepf_core.train.rules.empty_rays.EmptyRayRule.thin` keeps
    its expectation."""
    material_evidence: object | None = None
    """What the radiance field across views says the material is at some surface points
    (:class:`nepf_core.render.material_evidence.EvidenceBatch`); set by the training step when
    ``loss.w_material_evidence > 0`` (it knows the cameras), else None."""
    metal_share: Tensor | None = None
    """``[R]`` in ``[0, 1)``: how firmly the evidence recorded near each ray's surface point says
    metal (:class:`nepf_core.train.metal_record.MetalRecord`), which lifts the unseen-lobe prior
    there; set by the training step beside ``material_evidence``, else None (the prior in full)."""
    colour_logits: Tensor | None = None
    """``[K, 3]`` (training renders): the raw outputs before the sigmoid of every colour this render
    evaluated, the radiance network's at the shaded samples and the background's at its samples,
    for :attr:`nepf_core.losses.LossConfig.w_colour_range`. None when not training."""


def sample_weights(model, rays: RayBatch, cfg: RenderConfig, near: Tensor, far: Tensor, *, train: bool,
                   cos_anneal: float, generator: torch.Generator | None) -> SampleWeights:
    """Stage 1: stratified then NeuS hierarchical depths in ``[near, far]``, and the weights of
    ``cfg.alpha_mode`` (:mod:`nepf_core.render.weights`)."""
    o, d = rays.origins, rays.directions
    z = stratified_z(near, far, cfg.n_samples, perturb=train and cfg.perturb, generator=generator)
    z = hierarchical_z(o, d, z, model.sdf.sdf, cfg.n_importance, cfg.up_sample_steps)
    inv_s = model.deviation()
    if cfg.alpha_mode == "sample":
        return weights_sample_mode(model, o, d, z, inv_s, head_threshold=cfg.head_weight_threshold,
                                   eikonal_fraction=cfg.eikonal_fraction, train=train)
    return weights_midpoint_mode(model, o, d, z, inv_s, normals=cfg.normals, hessian_fraction=cfg.hessian_fraction,
                                 cos_anneal=cos_anneal, train=train)


def render_rays(model, rays: RayBatch, cfg: RenderConfig, *, train: bool, cos_anneal: float = 1.0,
                generator: torch.Generator | None = None, request: SurfaceRequest = SurfaceRequest(),
                shading: Shading | None = None) -> RenderOutput:
    """Render ``rays`` (``R``) with ``model`` (a :class:`nepf_core.model.NePFModel`): the stages of
    the module docstring. ``shading``: the shading model in effect (a trained run's:
    ``RunState.shading()``); None: ``Shading(specular=cfg.specular)``, the configured start.
    ``request``: extra evidence (:class:`SurfaceRequest`). Random numbers: the sample jitter and
    the background's from ``generator``; the eikonal / Hessian subsets and the smoothness priors'
    jitter from torch's global generator."""
    shading = shading if shading is not None else Shading(specular=cfg.specular)
    o, d = rays.origins, rays.directions
    R = o.shape[0]
    near, far, _, cut = object_segment(o, d, model.cfg.object_halfspace)
    sw = sample_weights(model, rays, cfg, near, far, train=train, cos_anneal=cos_anneal, generator=generator)
    P = sw.pts.shape[0]
    weight_sum = sw.weights.sum(-1)
    eik_w = None if rays.weight is None else rays.weight[sw.eikonal_ray].to(sw.eikonal.dtype)
    normals = sw.grad / sw.grad_norm.clamp_min(1e-8)[:, None]
    flat_max = sw.flat_max
    unlit_ray = rays.unlit if (train and rays.unlit is not None) else None
    ray_vis = ray_visibility(model, sw.pts[flat_max].detach(), normals[flat_max].detach(), weight_sum.detach())

    sel = shade_samples(model, cfg, shading, sw, normals, selected_samples(sw.weights, flat_max,
                                                                           cfg.head_weight_threshold),
                        unlit_ray, train=train, ray_visibility=ray_vis)
    rad_full = sw.pts.new_zeros(P, 3).index_copy(0, sel.index, sel.radiance)
    pbr_full = sw.pts.new_zeros(P, 3).index_copy(0, sel.index, sel.pbr)
    w3 = sw.weights[..., None]
    rgb_r = (w3 * rad_full.reshape(R, -1, 3)).sum(1)
    rgb_vol = (w3 * pbr_full.reshape(R, -1, 3)).sum(1)
    rgb_surf = pbr_full[flat_max]
    bg = None
    colour_logits = [sel.radiance_logits] if train else []
    if getattr(model, "background", None) is not None:
        bg, bg_z = model.background(o, d, perturb=train and cfg.perturb, generator=generator, start=cut,
                                    with_logits=True)
        colour_logits += [bg_z] if train else []
        rgb_r = rgb_r + (1.0 - weight_sum)[:, None] * bg
        rgb_vol = rgb_vol + (1.0 - weight_sum)[:, None] * bg

    surface = surface_at_index(sel, flat_max, sw.pts, normals, d)
    jitter_sigma = cfg.albedo_smooth_sigma if train else 0.0
    xj = fj = nj = None
    if cfg.surface_refine and cfg.alpha_mode == "sample":
        xr, nr, fr, xj, fj, nj = refine_surface(model, o, d, sw.z, sw.sdf, sw.idx_max, jitter_sigma=jitter_sigma,
                                                jitter_normals=request.jitter_normals)
        p = shade_points(model, cfg, shading, xr, d, nr, fr, unlit_ray, logits=train, visibility=ray_vis)
        rgb_surf = p.pbr
        surface = Surface(x=xr, normal=nr, direction=d, light_dir=p.light_dir, intensity=p.intensity,
                          albedo=p.albedo, roughness=p.roughness, metallic=p.metallic, material_logits=p.logits,
                          lights=p.lights)
    if jitter_sigma > 0:
        surface.jitter = jittered_material(model, surface, jitter_sigma, amp=cfg.amp_heads, xj=xj, fj=fj, nj=nj)
    lobe = lobe_split(surface, rgb_surf, lambertian=cfg.lambertian, kind=cfg.bsdf_kind) if request.lobe_split else None
    return RenderOutput(rgb_r=rgb_r, rgb_vol=rgb_vol, rgb_surf=rgb_surf, weight_sum=weight_sum, w_max=sw.w_max,
                        depth=(sw.weights * sw.t_eval).sum(-1), eikonal=sw.eikonal, hessian=sw.hessian,
                        surface=surface, lobe=lobe, background=bg, n_samples=int(P),
                        n_head_evals=int(sel.index.shape[0]), inv_s=sw.inv_s.detach(),
                        eikonal_weight=eik_w, colour_logits=torch.cat(colour_logits) if colour_logits else None)


def ray_visibility(model, x: Tensor, n: Tensor, weight_sum: Tensor) -> Tensor | None:
    """``[R, K]`` which global emitters each ray's surface point ``x [R, 3]`` (normal ``n``)
    sees, traced through the SDF (:meth:`nepf_core.fields.emitters.TracedEmitters.trace_visibility`)
    for the rays that meet the surface (``weight_sum > SURFACE_WEIGHT``; the others, whose PBR
    colour is the background's, count as seeing all); None for the photon network."""
    trace = getattr(model.photon, "trace_visibility", None)
    if trace is None:
        return None
    vis = x.new_ones(x.shape[0], model.photon.count)
    hit = (weight_sum > SURFACE_WEIGHT).nonzero(as_tuple=True)[0]
    if hit.numel():
        vis[hit] = trace(model.query_sdf, x[hit], n[hit])
    return vis


SURFACE_WEIGHT = 1e-2
"""A ray whose SDF weights sum to at most this has no surface worth a shadow ray."""


def render_background_only(model, rays: RayBatch, cfg: RenderConfig, *, train: bool,
                           generator: torch.Generator | None = None, with_logits: bool = False):
    """``[B, 3]`` linear colour of rays that meet no occupied cell: ``C = C_bg`` (with
    ``with_logits`` also the background's colour logits, as :attr:`RenderOutput.colour_logits`).

    Such a ray's SDF weights sum to at most ~e^{-k_s} (:mod:`nepf_core.render.occupancy`), so
    ``C = sum_i w_i c_i + (1 - sum_i w_i) C_bg`` is ``C_bg`` up to that bound, for the radiance
    and the PBR colour alike. The background volume starts where the object's region ends on
    the ray (the support plane's cut, else the unit sphere's exit), as in :func:`render_rays`.
    Needs ``model.background``."""
    _, _, _, cut = object_segment(rays.origins, rays.directions, model.cfg.object_halfspace)
    return model.background(rays.origins, rays.directions, perturb=train and cfg.perturb, generator=generator,
                            start=cut, with_logits=with_logits)
