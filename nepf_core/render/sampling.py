"""Ray-sphere bounds, stratified samples, inverse-CDF sampling and NeuS up-sampling.

Shapes: ``R`` rays, ``S`` samples per ray; ``z`` are distances along unit directions.
"""

from __future__ import annotations

from typing import Callable

import torch
from torch import Tensor

from nepf_core.render.neus import weights_from_alpha


def near_far_from_sphere(rays_o: Tensor, rays_d: Tensor, radius: float = 1.0,
                         min_near: float = 1e-3) -> tuple[Tensor, Tensor, Tensor]:
    """Segment of each ray inside the sphere |x| <= radius.

    With ``mid = -o.d / (d.d)`` and ``h^2 = radius^2 - |o + mid d|^2 / ...``, the chord is
    ``[mid - h, mid + h]``. Rays that miss (h^2 < 0) get ``[mid - radius, mid + radius]``
    (NeuS's choice, so they still see the background) and ``hit = False``. Rays that start
    inside get ``near = min_near``.

    Returns ``near [R], far [R], hit [R] bool``.
    """
    dd = (rays_d * rays_d).sum(-1).clamp_min(1e-12)
    mid = -(rays_o * rays_d).sum(-1) / dd
    closest = rays_o + rays_d * mid[:, None]
    h2 = (radius * radius - (closest * closest).sum(-1)) / dd
    hit = h2 > 0
    h = torch.where(hit, h2.clamp_min(0).sqrt(), torch.full_like(h2, radius))
    near = (mid - h).clamp_min(min_near)
    far = torch.maximum(mid + h, near + 1e-3)
    return near, far, hit


def halfspace_exit(rays_o: Tensor, rays_d: Tensor, halfspace) -> Tensor:
    """Distance along each ray where it leaves the half-space ``n . x + c > 0``: ``[R]``.

    ``halfspace = (n_x, n_y, n_z, c)``. With ``s0 = n . o + c`` and ``sd = n . d``, the ray leaves
    at ``t = -s0 / sd`` when it moves out of it (``sd < 0``), never (``inf``) otherwise; a ray that
    starts outside and moves further out leaves at 0.
    """
    n = torch.as_tensor(halfspace[:3], dtype=rays_o.dtype, device=rays_o.device)
    s0 = rays_o @ n + float(halfspace[3])
    sd = rays_d @ n
    leaving = sd < 0
    t = torch.where(leaving, -s0 / torch.where(leaving, sd, -torch.ones_like(sd)), torch.full_like(s0, float("inf")))
    return t.clamp_min(0.0)


def object_segment(rays_o: Tensor, rays_d: Tensor, halfspace=None
                   ) -> tuple[Tensor, Tensor, Tensor, Tensor | None]:
    """The part of each ray the SDF models: ``near [R], far [R], hit [R], cut [R] | None``.

    The unit-sphere chord (:func:`near_far_from_sphere`), ended where the ray leaves the object's
    half-space when the run found a support plane (``nepf_core.data.object_region``); ``cut`` is
    that exit distance (None without a half-space), where the background volume takes over.
    """
    near, far, hit = near_far_from_sphere(rays_o, rays_d)
    if halfspace is None:
        return near, far, hit, None
    cut = halfspace_exit(rays_o, rays_d, halfspace)
    far = torch.maximum(torch.minimum(far, cut), near + 1e-3)
    return near, far, hit, cut


def stratified_z(near: Tensor, far: Tensor, n: int, perturb: bool,
                 generator: torch.Generator | None = None) -> Tensor:
    """``n`` samples in ``[near, far]``, jittered within strata when ``perturb``: ``[R] -> [R, n]``."""
    t = torch.linspace(0.0, 1.0, n + 1, device=near.device, dtype=near.dtype)[:-1]
    if perturb:
        u = torch.rand(near.shape[0], n, device=near.device, dtype=near.dtype, generator=generator)
    else:
        u = torch.full((near.shape[0], n), 0.5, device=near.device, dtype=near.dtype)
    t = t[None, :] + u / n
    return near[:, None] + (far - near)[:, None] * t


def sample_pdf(bins: Tensor, weights: Tensor, n: int, deterministic: bool = True,
               generator: torch.Generator | None = None) -> Tensor:
    """Inverse-CDF samples from the piecewise-constant pdf ``weights`` on ``bins``.

    ``bins [R, S+1]``, ``weights [R, S]`` -> ``[R, n]``; a ray with all-zero weights gets
    samples spread uniformly over its bins (the +1e-5 floor).
    """
    w = weights + 1e-5
    pdf = w / w.sum(-1, keepdim=True)
    cdf = torch.cat([torch.zeros_like(pdf[..., :1]), torch.cumsum(pdf, -1)], -1)
    if deterministic:
        u = torch.linspace(0.5 / n, 1.0 - 0.5 / n, n, device=bins.device, dtype=bins.dtype)
        u = u.expand(cdf.shape[0], n).contiguous()
    else:
        u = torch.rand(cdf.shape[0], n, device=bins.device, dtype=bins.dtype, generator=generator)
    inds = torch.searchsorted(cdf.contiguous(), u, right=True)
    below = (inds - 1).clamp_min(0)
    above = inds.clamp_max(cdf.shape[-1] - 1)
    cdf_b, cdf_a = torch.gather(cdf, 1, below), torch.gather(cdf, 1, above)
    bin_b, bin_a = torch.gather(bins, 1, below), torch.gather(bins, 1, above)
    denom = torch.where(cdf_a - cdf_b < 1e-5, torch.ones_like(cdf_a), cdf_a - cdf_b)
    return bin_b + (u - cdf_b) / denom * (bin_a - bin_b)


def neus_upsample_step(rays_o: Tensor, rays_d: Tensor, z: Tensor, sdf: Tensor, n: int,
                       inv_s: float) -> Tensor:
    """One NeuS importance step with a fixed sharpness ``inv_s``: ``[R, S] -> new z [R, n]``.

    The slope between consecutive samples estimates the SDF-ray cosine (clamped to
    [-1e3, 0] so only surface-entering sections count), giving section opacities
    ``alpha_i`` as in :func:`alpha_from_sdf`; new samples follow the weights' pdf.
    """
    pts = rays_o[:, None, :] + rays_d[:, None, :] * z[..., None]
    radius = pts.norm(dim=-1)
    inside = ((radius[:, :-1] < 1.0) | (radius[:, 1:] < 1.0)).to(z.dtype)
    prev_sdf, next_sdf = sdf[:, :-1], sdf[:, 1:]
    prev_z, next_z = z[:, :-1], z[:, 1:]
    mid_sdf = (prev_sdf + next_sdf) * 0.5
    cos = (next_sdf - prev_sdf) / (next_z - prev_z + 1e-5)
    prev_cos = torch.cat([torch.zeros_like(cos[:, :1]), cos[:, :-1]], -1)
    cos = torch.minimum(prev_cos, cos).clip(-1e3, 0.0) * inside
    dist = next_z - prev_z
    prev_cdf = torch.sigmoid((mid_sdf - cos * dist * 0.5) * inv_s)
    next_cdf = torch.sigmoid((mid_sdf + cos * dist * 0.5) * inv_s)
    alpha = ((prev_cdf - next_cdf + 1e-5) / (prev_cdf + 1e-5)).clip(0.0, 1.0)
    weights = weights_from_alpha(alpha)
    return sample_pdf(z, weights, n, deterministic=True).detach()


def hierarchical_z(rays_o: Tensor, rays_d: Tensor, z: Tensor, sdf_fn: Callable[[Tensor], Tensor],
                   n_importance: int, steps: int, base_inv_s: float = 64.0) -> Tensor:
    """NeuS up-sampling: ``steps`` rounds of ``n_importance/steps`` samples with
    ``inv_s = base * 2^i``. SDF is queried without gradients. ``[R, S] -> [R, S + n_importance]``.
    """
    if n_importance <= 0 or steps <= 0:
        return z
    with torch.no_grad():
        pts = rays_o[:, None, :] + rays_d[:, None, :] * z[..., None]
        sdf = sdf_fn(pts.reshape(-1, 3)).reshape(z.shape)
        per = n_importance // steps
        for i in range(steps):
            new_z = neus_upsample_step(rays_o, rays_d, z, sdf, per, base_inv_s * 2 ** i)
            z, order = torch.sort(torch.cat([z, new_z], -1), -1)
            if i + 1 < steps:
                new_pts = rays_o[:, None, :] + rays_d[:, None, :] * new_z[..., None]
                new_sdf = sdf_fn(new_pts.reshape(-1, 3)).reshape(new_z.shape)
                sdf = torch.gather(torch.cat([sdf, new_sdf], -1), 1, order)
    return z
