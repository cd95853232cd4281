"""L_surf from other views: the surface point shaded toward other training cameras, against the
radiance network in those directions (the ``fast`` preset's ``loss.w_surf_views``).

The paper's ``L_surf`` compares the PBR at a ray's surface point ``x*`` with the radiance
network's ``L_r`` in that ray's direction only. From one direction the material and the light
are not identifiable: a dark dielectric under a free per-point light explains a metal's pixel as
well as the metal does, and a broad lobe explains a misplaced highlight. The radiance network
``R(x, v)`` has fitted every training view, so it also says how ``x*`` looks from the other
cameras. This term asks the shading to match it there too:

    L_views = mean_{r, k} | srgb(pbr(x*_r, v_rk)) - srgb(sg R(x*_r, v_rk)) |

    pbr(x, v) = f_bsdf(l, -v, n; c, r, m) I (n . l)^+        (the heads at x*, as L_surf)
    v_rk = (x*_r - o_k) / |x*_r - o_k|                       (camera k's ray direction to x*)

over the lit foreground rays ``r`` and ``K`` (:data:`VIEWS_PER_POINT`) cameras ``o_k`` drawn per
point among those that face it (``n . (-v) > MIN_FACING_COS``) and lie within
``MAX_VIEW_ANGLE_DEG`` of the ray's own direction (nearby views: the radiance network has been
trained on that cone), and that see it: a pair is dropped when the SDF is negative at any of
:data:`OCCLUSION_POINTS` points on the segment from ``x*`` toward the camera, up to where it leaves
the unit sphere (the radiance network is trained only where a point is visible; behind another
part of the object its colour is extrapolation). A view-dependent radiance (a highlight that
moves, a metal's missing diffuse floor) can then only be matched by a lobe of the right
roughness and colour under a light in the right direction; a view-independent one says the
opposite. The geometry is detached (``x*``, ``n``, the SDF features): the term trains the
material and the photon networks only, and the radiance network (the target) not at all.

Cost: the radiance head and the photon, material and BSDF heads at ``K`` extra points per lit
foreground ray, ``K`` x :data:`OCCLUSION_POINTS` SDF lookups without gradient, and one SDF lookup at
``x*`` for its features.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from nepf_core.render.shading import Shading, shade_points

VIEWS_PER_POINT = 2
"""``K``: other cameras per surface point and step."""
MIN_FACING_COS = 0.2
"""A camera sees ``x*`` when ``n . (o - x*) / |o - x*|`` exceeds this (not grazing)."""
MAX_VIEW_ANGLE_DEG = 40.0
"""The other camera's direction to ``x*`` lies within this angle of the ray's own direction."""
OCCLUSION_POINTS = 12
"""SDF lookups on the segment from ``x*`` to the camera that decide whether the camera sees it."""
OCCLUSION_START = 0.03
"""The first lookup's distance from ``x*`` (normalised units): past the surface's own band."""


@dataclass
class SurfaceViews:
    """``M`` (point, camera) pairs: ``pbr [M, 3]`` (differentiable in the material and photon
    networks), ``target [M, 3]`` the radiance network's colour (no grad), ``ray [M]`` long."""

    pbr: Tensor
    target: Tensor
    ray: Tensor


def pick_view_cameras(x: Tensor, n: Tensor, d: Tensor, cams: Tensor, k: int,
                      generator: torch.Generator | None) -> tuple[Tensor, Tensor]:
    """``(ray [M] long, v [M, 3])``: for each point ``x [R, 3]`` (unit normal ``n``, own ray
    direction ``d [R, 3]``) up to ``k`` cameras of ``cams [C, 3]`` drawn uniformly among those that
    face it and lie within :data:`MAX_VIEW_ANGLE_DEG` of ``d``; ``v`` the ray direction from the
    camera to the point (unit). A camera at ``x`` itself is never drawn."""
    to_cam = cams[None, :, :] - x[:, None, :]                                   # [R, C, 3]
    dist = to_cam.norm(dim=-1, keepdim=True).clamp_min(1e-8)
    v = -to_cam / dist                                                          # camera -> point
    facing = (-(v * n[:, None, :]).sum(-1)) > MIN_FACING_COS
    near = (v * d[:, None, :]).sum(-1) > math.cos(math.radians(MAX_VIEW_ANGLE_DEG))
    ok = facing & near & (dist[..., 0] > 1e-6)
    score = torch.rand(ok.shape, generator=generator, device="cpu" if generator is not None else x.device)
    score = score.to(x.device).masked_fill(~ok, -1.0)
    top, cam = score.topk(min(k, cams.shape[0]), dim=-1)                       # [R, k]
    ray, slot = (top >= 0.0).nonzero(as_tuple=True)
    return ray, v[ray, cam[ray, slot]]


@torch.no_grad()
def seen_from(sdf_fn, x: Tensor, v: Tensor) -> Tensor:
    """``[M]`` bool: no SDF value ``< 0`` at :data:`OCCLUSION_POINTS` points evenly spaced on the
    segment from ``x + OCCLUSION_START u`` to where the ray ``x + t u`` (``u = -v``, toward the
    camera) leaves the unit sphere; ``x, v [M, 3]``, ``sdf_fn: [P, 3] -> [P]``."""
    u = -v
    b = (x * u).sum(-1)
    far = -b + (b * b - (x * x).sum(-1) + 1.0).clamp_min(0.0).sqrt()             # exit of |p| = 1
    far = far.clamp_min(OCCLUSION_START)
    s = torch.linspace(0.0, 1.0, OCCLUSION_POINTS, device=x.device, dtype=x.dtype)
    t = OCCLUSION_START + (far[:, None] - OCCLUSION_START) * s[None, :]              # [M, T]
    pts = x[:, None, :] + t[..., None] * u[:, None, :]
    return (sdf_fn(pts.reshape(-1, 3)).reshape(t.shape) >= 0.0).all(-1)


def shade_surface_views(model, cfg, shading: Shading, x: Tensor, n: Tensor, d: Tensor, keep: Tensor,
                        cams: Tensor, generator: torch.Generator | None = None,
                        k: int = VIEWS_PER_POINT) -> SurfaceViews:
    """The pairs of the module docstring at the surface points ``x, n, d [R, 3]`` of the rays
    ``keep [R]`` (bool: lit foreground), cameras ``cams [C, 3]`` (normalised frame); no pairs
    (``M = 0``) when no camera qualifies. ``cfg``: the :class:`~nepf_core.config.RenderConfig`
    (BSDF kind, heads' autocast)."""
    x, n, d = x.detach(), n.detach(), d.detach()
    rows = keep.nonzero(as_tuple=True)[0]
    ray, v = pick_view_cameras(x[rows], n[rows], d[rows], cams.to(x), k, generator)
    if ray.numel():
        seen = seen_from(model.sdf.sdf, x[rows][ray], v)
        ray, v = ray[seen], v[seen]
    if ray.numel() == 0:
        empty = x.new_zeros(0, 3)
        return SurfaceViews(pbr=empty, target=empty, ray=ray)
    with torch.no_grad():
        _, feat = model.sdf(x[rows])
        xs, ns, fs = x[rows][ray], n[rows][ray], feat[ray]
        target = model.radiance(xs, v, ns, fs).float()
    pbr = shade_points(model, cfg, shading, xs, v, ns, fs, None).pbr
    return SurfaceViews(pbr=pbr, target=target, ray=rows[ray])
