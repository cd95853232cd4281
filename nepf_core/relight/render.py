"""Render views of a recovered asset under point lights (``nepf relight``), instead of the learned
photon field.

Per pixel: find the surface, take its normal and material, and shade it under each light with
shadows traced through the SDF (:mod:`.shade`, :mod:`.tracing`). Two ways to find the surface:

* :func:`model_surfaces`, for a trained model: the renderer's own surface (the NeuS weights'
  max-weight sample, its normal and material, as ``nepf render`` shades the ``pbr`` channel), with
  coverage ``alpha = sum_i w_i``. The relit colour is ``alpha L``, on black.
* :func:`query_surfaces`, for any FieldQuery (export previews, analytic test scenes): sphere
  tracing (:func:`.tracing.trace_primary`), coverage 0 or 1.

Silhouette pixels are the mean of ``n x n`` rays through a stratified grid of points in them
(:mod:`nepf_core.render.antialias`): ``rgb = (1/n^2) sum_j alpha_j L_j``, ``alpha = (1/n^2) sum_j
alpha_j``, as a camera and the ground truth integrate a pixel over its area.

Everything is in the normalised frame: lights are mapped there with
:func:`.lights.lights_to_normalised`, which keeps the irradiance of the world frame.
"""

from __future__ import annotations

from typing import Callable

import numpy as np
import torch
from torch import Tensor

from nepf_core.rays import PixelSampler, RayBatch
from nepf_core.render.antialias import PIXEL_SUBSAMPLES, silhouette_subpixel_rays
from nepf_core.relight.shade import ShadeOptions, SurfaceSamples, shade_under_lights
from nepf_core.relight.tracing import SdfFn, TraceConfig, light_visibility, trace_primary

SurfaceFn = Callable[[RayBatch], tuple[SurfaceSamples, Tensor]]
"""``rays -> (surface samples of every ray, coverage alpha [R] in [0, 1])``."""


def model_surfaces(model, render_cfg, shading) -> SurfaceFn:
    """The renderer's surface of a trained model (see the module docstring). ``shading``: the
    run's :class:`~nepf_core.render.renderer.Shading`; with the lobe dropped the material is the
    one the run shades with (:func:`nepf_core.bsdf.diffuse_only_material`)."""
    from nepf_core.bsdf import diffuse_only_material
    from nepf_core.render.renderer import render_rays

    def surfaces(rays: RayBatch) -> tuple[SurfaceSamples, Tensor]:
        out = render_rays(model, rays, render_cfg, train=False, shading=shading)
        s = out.surface
        albedo, rough, metal = s.albedo.detach(), s.roughness.detach(), s.metallic.detach()
        if not shading.specular:
            # relit without a lobe, the roughness reaches only the paper kind's Disney diffuse: keep the run's
            albedo, _, metal = diffuse_only_material(albedo, rough, metal, shading.diffuse_metal_weight)
        return (SurfaceSamples(s.x.detach(), s.normal.detach(), rays.directions, albedo, rough, metal),
                out.weight_sum.detach().clamp(0.0, 1.0))
    return surfaces


def query_surfaces(query, trace: TraceConfig) -> SurfaceFn:
    """Sphere-traced surface of a FieldQuery (``sdf``, ``normal``, ``material``); misses get
    alpha 0 (and harmless placeholder samples)."""
    def surfaces(rays: RayBatch) -> tuple[SurfaceSamples, Tensor]:
        hit, x = trace_primary(query.sdf, rays.origins, rays.directions, trace)
        n = torch.zeros_like(x)
        n[:, 2] = 1.0
        albedo, rough, metal = torch.zeros_like(x), x.new_ones(x.shape[0]), x.new_zeros(x.shape[0])
        if hit.any():
            n[hit] = query.normal(x[hit]).to(x.dtype)
            a, r, m = query.material(x[hit], n[hit])
            albedo[hit], rough[hit], metal[hit] = a.to(x.dtype), r.reshape(-1).to(x.dtype), m.reshape(-1).to(x.dtype)
        return SurfaceSamples(x, n, rays.directions, albedo, rough, metal), hit.to(x.dtype)
    return surfaces


def relight_views(surfaces: SurfaceFn, sdf: SdfFn, sampler: PixelSampler, positions: np.ndarray,
                  intensities: np.ndarray, opts: ShadeOptions, *, trace: TraceConfig | None = None,
                  shadows: bool = True, chunk: int = 4096,
                  subsamples: int = PIXEL_SUBSAMPLES) -> tuple[np.ndarray, np.ndarray]:
    """Every view of ``sampler`` under ``K`` point lights (normalised frame: ``positions [K, 3]``,
    ``intensities [K, 3]``). Returns ``rgb [K, V, H, W, 3]`` float32 linear radiance composited
    on black (``alpha * L``, so 0 where nothing is covered) and ``alpha [V, H, W]`` float32; the
    silhouette pixels are the mean over ``subsamples x subsamples`` rays in them (module docstring;
    1: every pixel its centre ray)."""
    trace = trace or TraceConfig()
    dev = sampler.device
    P = torch.as_tensor(positions, dtype=torch.float32, device=dev)
    I = torch.as_tensor(intensities, dtype=torch.float32, device=dev)

    def visibility(x: Tensor, n: Tensor, p: Tensor) -> Tensor:
        return light_visibility(sdf, x, n, p, trace)

    vis = visibility if shadows else None
    K, V, H, W = P.shape[0], sampler.n_views, sampler.height, sampler.width
    rgb = np.zeros((K, V, H, W, 3), np.float32)
    alpha = np.zeros((V, H, W), np.float32)
    for v in range(V):
        L, cov = _relight_rays(surfaces, sampler.view_rays(v), P, I, opts, vis, chunk)
        L, cov = L.reshape(K, H, W, 3), cov.reshape(H, W)
        edge, subrays = silhouette_subpixel_rays(sampler, v, cov, subsamples)
        if subrays:
            L_sum, cov_sum = 0.0, 0.0
            for rays in subrays:
                Lj, cj = _relight_rays(surfaces, rays, P, I, opts, vis, chunk)
                L_sum, cov_sum = L_sum + Lj, cov_sum + cj
            L[:, edge], cov[edge] = L_sum / len(subrays), cov_sum / len(subrays)
        rgb[:, v], alpha[v] = L.numpy(), cov.numpy()
    return rgb, alpha


def _relight_rays(surfaces: SurfaceFn, rays: RayBatch, P: Tensor, I: Tensor, opts: ShadeOptions, visibility,
                  chunk: int) -> tuple[Tensor, Tensor]:
    """``(alpha L [K, R, 3], alpha [R])`` (CPU) of ``R`` rays under the lights, ``chunk`` rays at a time."""
    cols, alphas = [], []
    for a in range(0, len(rays), chunk):
        rb = rays.slice(a, a + chunk)
        s, cov = surfaces(rb)
        L = torch.zeros(P.shape[0], len(rb), 3, device=P.device)
        keep = cov > 0
        if keep.any():
            sub = SurfaceSamples(*(t[keep] for t in (s.x, s.normal, s.view_dir, s.albedo, s.roughness,
                                                      s.metallic)))
            with torch.no_grad():
                L[:, keep] = shade_under_lights(sub, P, I, opts, visibility) * cov[keep][None, :, None]
        cols.append(L.detach().cpu())
        alphas.append(cov.detach().cpu())
    return torch.cat(cols, 1), torch.cat(alphas)
