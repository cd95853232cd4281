"""Shade surface points under point lights, with shadows.

For a surface point ``x`` (unit normal ``n``, seen along the ray direction ``d``, so ``v = -d``)
and a point light at ``p`` with radiant intensity ``I`` (both in the frame of ``x``):

    l = (p - x) / |p - x|,   E = I max(n.l, 0) / |p - x|^2,   L = f(l, v; c, r, m) E V(x, p)

with ``f`` the project's BSDF (:func:`nepf_core.bsdf.bsdf_eval`, kind ``"paper"`` or ``"gltf"``)
and ``V`` the visibility of the light (1 lit, 0 shadowed; :mod:`.tracing` or a mesh ray cast).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import torch
from torch import Tensor

from nepf_core import bsdf

VisibilityFn = Callable[[Tensor, Tensor, Tensor], Tensor]
"""``(x [N, 3], n [N, 3], light_pos [3]) -> [N]`` visibility in [0, 1]."""


@dataclass
class SurfaceSamples:
    """What shading needs at ``N`` surface points (one frame, float32 tensors on one device)."""

    x: Tensor
    """``[N, 3]`` positions."""
    normal: Tensor
    """``[N, 3]`` unit normals."""
    view_dir: Tensor
    """``[N, 3]`` unit ray directions (camera -> surface)."""
    albedo: Tensor
    """``[N, 3]`` linear base colour."""
    roughness: Tensor
    """``[N]``."""
    metallic: Tensor
    """``[N]``."""


@dataclass(frozen=True)
class ShadeOptions:
    """The BSDF used: its ``kind`` (:data:`nepf_core.bsdf.BSDF_KINDS`), the paper kind's
    ``lambertian`` ablation and whether the specular lobe is on (a run that dropped it)."""

    kind: str = "paper"
    lambertian: bool = False
    specular: bool = True


def shade_under_lights(s: SurfaceSamples, positions: Tensor, intensities: Tensor, opts: ShadeOptions,
                       visibility: VisibilityFn | None = None) -> Tensor:
    """Radiance ``[K, N, 3]`` of the points under each of ``K`` lights (``positions [K, 3]``,
    ``intensities [K, 3]``, same frame as ``s.x``); ``visibility`` None: no shadows."""
    out = []
    for k in range(positions.shape[0]):
        to_light = positions[k] - s.x
        d2 = (to_light * to_light).sum(-1, keepdim=True).clamp_min(1e-12)
        l = to_light / d2.sqrt()
        L = bsdf.shade(s.normal, l, -s.view_dir, s.albedo, s.roughness[:, None], s.metallic[:, None],
                       intensities[k] / d2, lambertian=opts.lambertian, specular=opts.specular, kind=opts.kind)
        if visibility is not None:
            L = L * visibility(s.x, s.normal, positions[k])[:, None]
        out.append(L)
    return torch.stack(out)
