"""The training images' own colour of a 3D point in the views that see it.

A point ``x`` (normalised frame) projects into view ``k`` (pinhole, pixel centres at +0.5 as in
:mod:`nepf_core.rays`) at

    p = R_k^T (x - t_k),   (u, v, w) = K_k p,   column = u / w - 0.5,   row = v / w - 0.5

in pixel-index units (pixel ``(i, j)``'s centre at ``(i, j)``), and its colour there is the
bilinear mix of the 4 pixels around it. Why: the metal evidence
(:mod:`nepf_core.render.material_evidence`) compares how a surface point looks across views; read
through the radiance network it sees that network's fit (16-22 dB on the suite's metals at 1,000
steps), read here it sees what the cameras recorded.

A projection counts only when it lies in front of the camera, inside the image, and (with masks)
all 4 pixels are foreground, so that no background colour mixes in at a silhouette. Whether the
surface hides the point from the camera is the caller's test (``material_evidence.seen_from``).
"""

from __future__ import annotations

from dataclasses import dataclass

import math

import torch
import torch.nn.functional as F
from torch import Tensor

BLUR_PX = 0.0
"""Gaussian blur (pixels) of the images the evidence reads (:func:`blur_within_masks`)."""


@dataclass
class TrainingViews:
    """Images ``[C, H, W, 3]`` (linear), masks ``[C, H, W]`` bool or None, intrinsics ``K [C, 3, 3]``
    and camera-to-world ``c2w [C, 4, 4]`` (or ``[C, 3, 4]``), all on one device."""

    images: Tensor
    masks: Tensor | None
    K: Tensor
    c2w: Tensor

    @classmethod
    def of_sampler(cls, sampler, blur_px: float = BLUR_PX) -> "TrainingViews":
        """The views a :class:`nepf_core.rays.PixelSampler` holds (``K`` from its ``K_inv``), the
        images blurred by a Gaussian of ``blur_px`` pixels (:func:`blur_within_masks`)."""
        images = sampler.images if blur_px <= 0 else blur_within_masks(sampler.images, sampler.masks, blur_px)
        return cls(images, sampler.masks, torch.linalg.inv(sampler.K_inv), sampler.c2w)

    def project(self, x: Tensor, cam: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """``(column, row, depth)`` each ``[P, k]`` of points ``x [P, 3]`` in views ``cam [P, k]``."""
        R, t = self.c2w[cam, :3, :3], self.c2w[cam, :3, 3]                  # [P, k, 3, 3], [P, k, 3]
        p = torch.einsum("pkji,pkj->pki", R, x[:, None, :] - t)             # R^T (x - t)
        uvw = torch.einsum("pkij,pkj->pki", self.K[cam].to(p), p)
        w = uvw[..., 2]
        safe = torch.where(w.abs() > 1e-8, w, torch.ones_like(w))
        return uvw[..., 0] / safe - 0.5, uvw[..., 1] / safe - 0.5, w

    def colours(self, x: Tensor, cam: Tensor) -> tuple[Tensor, Tensor]:
        """``(c [P, k, 3], seen [P, k])``: the bilinear colour of ``x [P, 3]`` in views ``cam [P, k]``
        and whether the projection counts (in front, inside, on foreground pixels)."""
        C, H, W = self.images.shape[:3]
        col, row, depth = self.project(x, cam)
        e = 1e-3   # the outer pixel centres themselves count, whatever the rounding
        inside = (depth > 0) & (col >= -e) & (col <= W - 1 + e) & (row >= -e) & (row <= H - 1 + e)
        col, row = col.clamp(0, W - 1), row.clamp(0, H - 1)
        c0, r0 = col.floor().clamp(max=max(W - 2, 0)).long(), row.floor().clamp(max=max(H - 2, 0)).long()
        fc, fr = (col - c0).unsqueeze(-1), (row - r0).unsqueeze(-1)
        flat = self.images.reshape(C * H * W, 3)
        base = cam * (H * W) + r0 * W + c0
        corners = (base, base + 1, base + W, base + W + 1)
        a, b, c, d = (flat[i].to(x.dtype) for i in corners)
        colour = (a * (1 - fc) + b * fc) * (1 - fr) + (c * (1 - fc) + d * fc) * fr
        if self.masks is not None:
            fg = self.masks.reshape(-1)
            inside = inside & fg[corners[0]] & fg[corners[1]] & fg[corners[2]] & fg[corners[3]]
        return colour, inside


def blur_within_masks(images: Tensor, masks: Tensor | None, sigma: float) -> Tensor:
    """``[C, H, W, 3]`` images blurred by a Gaussian of ``sigma`` pixels, over the foreground only:

        out = (G * (m I)) / (G * m)      (normalised convolution; ``m`` all ones without masks)

    so that no background colour bleeds into the object's edge. Why: a surface point placed a
    pixel off projects onto a neighbouring texel in each view, and at pixel-scale texture that
    reads as a colour that changes with the view, which only a metal's lobe explains; blurring
    by about the geometry's error makes the point's colour agree across views again, while a
    highlight (many pixels wide at the roughness a metal is called at) keeps its shape."""
    r = max(1, int(math.ceil(3 * sigma)))
    t = torch.arange(-r, r + 1, device=images.device, dtype=torch.float32)
    g = torch.exp(-0.5 * (t / sigma) ** 2)
    g = g / g.sum()
    out = torch.empty_like(images)
    for k in range(images.shape[0]):      # one view at a time: a real capture's set is GBs in fp32
        m = torch.ones(images.shape[1:3], device=images.device) if masks is None else masks[k].float()
        x = torch.cat([images[k].float() * m[..., None], m[..., None]], -1).permute(2, 0, 1)[None]   # [1, 4, H, W]
        x = F.conv2d(F.pad(x, (r, r, 0, 0), mode="replicate"), g.view(1, 1, 1, -1).expand(4, 1, 1, -1), groups=4)
        x = F.conv2d(F.pad(x, (0, 0, r, r), mode="replicate"), g.view(1, 1, -1, 1).expand(4, 1, -1, 1), groups=4)
        out[k] = (x[0, :3] / x[0, 3:].clamp_min(1e-6)).permute(1, 2, 0).to(images.dtype)
    return out
