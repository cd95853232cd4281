"""Anti-aliased silhouettes: a silhouette pixel is the mean of ``n x n`` rays through it.

A camera (and every ground truth we score against: Mitsuba, Blender) integrates a pixel over its
area, while one ray through the pixel's centre sees a silhouette pixel as all surface or all
background. A model whose density is sharp at its silhouette then scores worse than a blurry one
on a scene whose error is mostly at its edge (bench/RESULTS.md v64: on sphere_diffuse 80-88 % of
the relight's squared error lay within 2 px of the silhouette).

So a view is rendered in two passes:

1. one ray through each pixel's centre, giving its coverage ``alpha = sum_i w_i``;
2. on the silhouette pixels only (:func:`silhouette_pixels`), ``n x n`` rays through the centres
   of a stratified grid of sub-pixels (:func:`subpixel_points`), and every composited channel
   (``alpha`` itself, ``alpha L``) is replaced by the mean over them:
   ``C = (1/n^2) sum_j C_j``.

A silhouette pixel is one whose centre ray is partly covered (``0.02 < alpha < 0.98``) or whose
3 x 3 neighbourhood holds both covered and uncovered centres. The render then costs ``1 + n^2 f``
rays per pixel for a silhouette share ``f`` (a few per cent), not ``n^2``. Edges inside the
surface (shadows, texture) keep one ray. Channels that are not composited (material maps,
normals, depth) keep the centre ray's value: a mean over rays that miss the surface would mix
in the placeholder material of a miss.

Used by the relight (:mod:`nepf_core.relight.render`) and by the whole-view render
(:func:`nepf_core.evaluate.render_view`: ``nepf render`` and the held-out PBR PSNR).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from nepf_core.rays import PixelSampler, RayBatch

PIXEL_SUBSAMPLES = 2
"""``n``: a silhouette pixel averages ``n x n`` rays through the centres of an ``n x n`` grid of
sub-pixels (module docstring)."""

PARTIAL_COVERAGE = 0.02
"""A centre ray with ``PARTIAL_COVERAGE < alpha < 1 - PARTIAL_COVERAGE`` is partly covered."""


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


def silhouette_subpixel_rays(sampler: PixelSampler, view: int, alpha: Tensor, subsamples: int = PIXEL_SUBSAMPLES,
                             stride: int = 1) -> tuple[Tensor, list[RayBatch]]:
    """The second pass of view ``view``, whose centre rays (every ``stride``-th row and column,
    as :meth:`PixelSampler.view_rays`) gave the coverage ``alpha [H', W']``.

    Returns ``edge [H', W']`` bool (CPU; all False when ``subsamples == 1``) and one RayBatch per
    sub-pixel point, each ``[E]`` long in ``edge``'s row-major order (``E = edge.sum()``): the
    caller renders each, averages the composited channels over them and writes the mean into
    the edge pixels."""
    alpha = alpha.detach().float().cpu()
    points = subpixel_points(subsamples)
    if len(points) == 1:
        return torch.zeros(alpha.shape, dtype=torch.bool), []
    edge = silhouette_pixels(alpha)
    if not edge.any():
        return edge, []
    row, col = (t.to(sampler.device) * stride for t in edge.nonzero(as_tuple=True))
    v = torch.full_like(row, view)
    return edge, [sampler.pixel_rays(v, row, col, at) for at in points]
