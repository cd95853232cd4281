"""Where the light is, read from the highlights in the training images.

A GGX lobe (either kind of material, any roughness) is brightest where the surface normal
bisects the light and the view, ``n = h``, so at a highlight the light lies along the mirror
direction of the ray ``d`` (camera -> point) about the normal:

    r = d - 2 (d . n) n                                                  (unit; r . n = -d . n > 0)

For a near-mirror (roughness ~0) this is the light's direction at ``x*`` itself; for a rough lobe
the saturated patch spreads around that point and ``r`` scatters about the light by about the
lobe's width. A Lambertian surface has no such point (its peak is at ``n = l``, wherever the
view is), so the cue is taken only where the pixel is a highlight:

* the training pixel is saturated in every channel (linear ``>=`` :data:`SATURATED`), and
* the radiance network shows the same surface point much darker toward other training cameras
  that face and see it (the median luminance over at least ``MIN_VIEWS`` of them below
  :data:`HIGHLIGHT_RATIO`): a highlight moves with the view, an over-exposed diffuse region
  (a real capture's) does not.

The term (``loss.w_highlight_light``) pulls the photon network's direction there toward ``r``:

    L_hl = w mean_p (1 - l(x*_p) . r_p)

with the photon network evaluated at the detached point, normal and feature, so the cue moves
the light and not the surface (``r`` itself is detached too).

Why: the photon field may point each surface point's light anywhere, and on the suite the
learned direction is 13-98 degrees from the true one (98 on torus_stiff, a near-mirror whose
images are black but for saturated highlights: with the light misplaced no sharp lobe can put
them where they are, and the roughness went to ~0.9). The highlights pin the light exactly where
the other cues say nothing. Cost: the colours of a few saturated points toward ``K`` cameras
(:func:`nepf_core.render.material_evidence.views_of_points`) and one photon evaluation of them.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from nepf_core.render.material_evidence import MIN_VIEWS, VIEWS_PER_POINT, views_of_points
from nepf_core.view_dependence import LUMA

SATURATED = 0.95
"""A pixel is saturated when every linear channel is at least this (sRGB ~0.98)."""
HIGHLIGHT_RATIO = 0.5
"""A saturated point is a highlight when its median luminance toward other cameras is below this."""
POINTS_PER_STEP = 64
"""Saturated foreground rays per step whose surface point is checked."""


@dataclass
class HighlightBatch:
    """The highlights of one training step: ``light_dir [P, 3]`` the photon network's direction at
    their surface points (grad to its parameters only) and ``target [P, 3]`` the mirror directions."""

    light_dir: Tensor
    target: Tensor


def mirror_direction(d: Tensor, n: Tensor) -> Tensor:
    """``r = d - 2 (d . n) n`` for ray directions ``d [P, 3]`` and unit normals ``n [P, 3]``."""
    return d - 2.0 * (d * n).sum(-1, keepdim=True) * n


def is_highlight(c: Tensor, valid: Tensor) -> Tensor:
    """``[P]`` bool: at least ``MIN_VIEWS`` valid views and a median luminance over them below
    :data:`HIGHLIGHT_RATIO`; ``c [P, K, 3]`` linear colours, ``valid [P, K]``."""
    y = (c @ c.new_tensor(LUMA)).masked_fill(~valid, float("nan"))
    median = torch.nanmedian(y, dim=-1).values
    return (valid.sum(-1) >= MIN_VIEWS) & (median < HIGHLIGHT_RATIO)


def gather_highlights(model, x: Tensor, n: Tensor, d: Tensor, rgb: Tensor, keep: Tensor, cams: Tensor,
                      generator: torch.Generator | None = None, *, points: int = POINTS_PER_STEP,
                      k: int = VIEWS_PER_POINT) -> HighlightBatch:
    """The highlights among up to ``points`` rays drawn from ``keep [R]`` (bool: foreground) whose
    pixel ``rgb [R, 3]`` (linear) is saturated, at their surface points ``x``, unit normals ``n``
    and ray directions ``d`` (``[R, 3]``, detached here); ``cams [C, 3]`` the training cameras'
    centres (normalised frame)."""
    rows = (keep & (rgb.amin(-1) >= SATURATED)).nonzero(as_tuple=True)[0]
    if rows.numel() > points:
        rows = rows[torch.randperm(rows.numel(), generator=generator)[:points].to(rows.device)]
    x, n, d = x.detach()[rows], n.detach()[rows], d.detach()[rows]
    if rows.numel() > 0:
        c, _, valid = views_of_points(model, x, n, cams.to(x), k, generator)
        hl = is_highlight(c, valid)
        x, n, d = x[hl], n[hl], d[hl]
    if x.shape[0] == 0:
        return HighlightBatch(light_dir=x, target=x)
    with torch.no_grad():
        _, feat = model.sdf(x)
    light_dir, _ = model.photon(x, n, feat)
    return HighlightBatch(light_dir=light_dir, target=mirror_direction(d, n))
