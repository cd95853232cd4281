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
(:data:`PIXEL_SUBSAMPLES`): ``rgb = (1/n^2) sum_j alpha_j L_j``, ``alpha = (1/n^2) sum_j alpha_j``.
Why: a camera (and the ground truth a relight is scored against) integrates over the pixel's
area, while one ray through its centre sees a silhouette pixel as all surface or all background;
a model whose density is sharp at its silhouette then scores worse than a blurry one on a scene
whose error is mostly at its edge (bench/RESULTS.md v64, sphere_diffuse). A silhouette pixel is one
whose centre ray is partly covered (``0.02 < alpha < 0.98``) or whose 3 x 3 neighbourhood holds
both covered and uncovered centres (:func:`silhouette_pixels`); the rest keep their centre ray,
so the render costs ``1 + n^2 f`` rays per pixel for a silhouette share ``f`` (a few per cent),
not ``n^2``. Edges inside the surface (shadows, texture) keep one ray.

Everything is in the normalised frame: lights are mapped there with
:func:`.lights.lights_to_normalised`, which keeps the irradiance of the world frame.
"""

from __future__ import annotations

from typing import Callable

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from nepf_core.rays import PixelSampler, RayBatch
from nepf_core.relight.shade import ShadeOptions, SurfaceSamples, shade_under_lights
from nepf_core.relight.tracing import SdfFn, TraceConfig, light_visibility, trace_primary

PIXEL_SUBSAMPLES = 2
"""``n``: a silhouette pixel averages ``n x n`` rays through the centres of an ``n x n`` grid of
sub-pixels (module docstring)."""

PARTIAL_COVERAGE = 0.02
"""A centre ray with ``PARTIAL_COVERAGE < alpha < 1 - PARTIAL_COVERAGE`` is partly covered."""

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


def subpixel_points(n: int) -> list[tuple[float, float]]:
    """The centres ``((i + 0.5) / n, (j + 0.5) / n)`` of an ``n x n`` grid of sub-pixels, in pixel
    units from the pixel's corner (``n = 1``: the pixel's centre)."""
    if n < 1:
        raise ValueError(f"sub-pixel grid must be at least 1 x 1 (got {n})")
    return [((i + 0.5) / n, (j + 0.5) / n) for j in range(n) for i in range(n)]


def silhouette_pixels(alpha: Tensor) -> Tensor:
    """``[H, W]`` bool of a view's centre-ray coverage ``alpha [H, W]``: partly covered, or a 3 x 3
    neighbourhood holding both covered (``alpha > 0.5``) and uncovered centres."""
    covered = (alpha > 0.5).float()[None, None]
    mixed = F.max_pool2d(covered, 3, stride=1, padding=1) > -F.max_pool2d(-covered, 3, stride=1, padding=1)
    partial = (alpha > PARTIAL_COVERAGE) & (alpha < 1.0 - PARTIAL_COVERAGE)
    return mixed[0, 0] | partial


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
    points = subpixel_points(subsamples)
    rgb = np.zeros((K, V, H, W, 3), np.float32)
    alpha = np.zeros((V, H, W), np.float32)
    for v in range(V):
        L, cov = _relight_rays(surfaces, sampler.view_rays(v), P, I, opts, vis, chunk)
        L, cov = L.reshape(K, H, W, 3), cov.reshape(H, W)
        edge = silhouette_pixels(cov) if len(points) > 1 else torch.zeros(H, W, dtype=torch.bool)
        if edge.any():
            row, col = (t.to(dev) for t in edge.nonzero(as_tuple=True))
            view = torch.full_like(row, v)
            L_sum, cov_sum = 0.0, 0.0
            for at in points:
                Lj, cj = _relight_rays(surfaces, sampler.pixel_rays(view, row, col, at), P, I, opts, vis, chunk)
                L_sum, cov_sum = L_sum + Lj, cov_sum + cj
            L[:, edge], cov[edge] = L_sum / len(points), cov_sum / len(points)
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
