"""Part of each training batch drawn from a band around the masks' silhouettes.

A uniform batch of ``R`` rays puts ``R b / (H W)`` of them within ``r`` pixels of the
silhouette (``b``: the band's pixels per view, ~5 % at 128^2), yet those pixels are the only ones
that tell the mask loss where the surface ends, and a metal's geometry, whose colour is view
dependent, leans on them (bench/RESULTS.md v62: the error map's draws that fell on silhouette
tiles gave bunny_metal its normals and Chamfer; the ones inside the mask did not). This draws
``round(f R)`` of the batch uniformly over the band's pixels of all views and the rest uniformly
over every pixel:

    band = dilate_r(M) & ~erode_r(M),   M = mask > 0.5,   r = BAND_RADIUS (a (2r+1)^2 window)

Half of a band ray misses the object and costs only its empty samples, so a step costs less
than drawing the same share inside the mask. Without masks nothing changes (every pixel
uniform).

The colour terms keep the uniform mean: each ray carries the importance weight of the mixture
(``P`` pixels, ``B`` of them in the band, ``k = round(f R)`` band draws of ``R``)

    q = (1 / P) / p(pixel),   p = (R - k) / (R P) + [pixel in band] k / (R B)

so a band pixel weighs ``1 / ((R - k)/R + k P / (R B))`` (< 1) and any other ``R / (R - k)``
(:func:`nepf_core.losses.batch.loss_batch` multiplies ``L_r``, ``L_vol`` and ``L_surf`` by it).
The mask loss, the eikonal term and the priors see every draw once: only the geometry gets the
extra silhouette rays, and the colour fit is not pulled toward the edge (bench/RESULTS.md v63:
without the weight the sphere lost 2.8 dB inside as well as at its edge).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from nepf_core.train.decisions import Decision

BAND_RADIUS = 2
"""``r`` in pixels: the band is ``2r + 1`` = 5 pixels wide across the silhouette."""


def silhouette_band(masks: Tensor, radius: int = BAND_RADIUS) -> Tensor:
    """``[N, H, W]`` bool: pixels whose ``(2r+1)^2`` window holds both foreground and background
    (``masks [N, H, W]``, foreground where > 0.5)."""
    m = (masks > 0.5).float()[:, None]
    k = 2 * radius + 1
    dilated = F.max_pool2d(m, k, stride=1, padding=radius)
    eroded = -F.max_pool2d(-m, k, stride=1, padding=radius)
    return (dilated > eroded)[:, 0]


class SilhouetteDraws:
    """The band of every view as flat pixel indices, and draws from it."""

    def __init__(self, masks: Tensor, fraction: float, radius: int = BAND_RADIUS) -> None:
        if not 0.0 < fraction <= 1.0:
            raise ValueError(f"train.silhouette_fraction must be in (0, 1] (got {fraction})")
        self.fraction, self.radius = fraction, radius
        self.n_pixels = int(masks.numel())
        self.height, self.width = int(masks.shape[1]), int(masks.shape[2])
        band = torch.cat([silhouette_band(masks[i:i + 1], radius) for i in range(masks.shape[0])])
        self.in_band = band.cpu()
        """``[N, H, W]`` bool: the band."""
        self.pixels = band.reshape(-1).nonzero()[:, 0].cpu()
        """``[B]`` long: flat ``(view, row, col)`` index of each band pixel."""

    def count(self, n: int) -> int:
        """How many of a batch of ``n`` come from the band (0 when the masks show no silhouette)."""
        return 0 if self.pixels.numel() == 0 else int(round(self.fraction * n))

    def draw(self, n: int, generator: torch.Generator | None = None) -> tuple[Tensor, Tensor, Tensor]:
        """``(view, row, col)`` ``[n]`` long (CPU) of ``n`` band pixels, uniform with replacement."""
        i = self.pixels[torch.randint(0, self.pixels.numel(), (n,), generator=generator)]
        hw = self.height * self.width
        return i // hw, (i % hw) // self.width, i % self.width

    def importance(self, view: Tensor, row: Tensor, col: Tensor, n: int) -> Tensor:
        """``[R]`` float (CPU): ``q`` of the module docstring at each drawn pixel of a batch of
        ``n`` (the uniform density over the mixture's density; 1 everywhere when no band draw)."""
        k = self.count(n)
        if k == 0:
            return torch.ones(view.shape[0])
        p_all, p_band = self.n_pixels, self.pixels.numel()
        q_band = 1.0 / ((n - k) / n + k * p_all / (n * p_band))
        q_rest = n / (n - k) if k < n else 0.0
        return torch.where(self.in_band[view, row, col], q_band, q_rest)

    def decision(self) -> Decision:
        """The run's record: the band's share of the training pixels and of each batch."""
        share = self.pixels.numel() / max(1, self.n_pixels)
        drawn = self.fraction if self.pixels.numel() else 0.0
        return Decision("silhouette_draws", {"band_pixel_fraction": round(share, 4), "batch_fraction": drawn},
                        f"{100 * share:.1f}% of the training pixels lie within {self.radius} px of a mask's silhouette; "
                        + (f"{100 * drawn:.0f}% of each batch is drawn there (the mask loss and the geometry learn "
                           "where the surface ends), the rest uniformly" if drawn else
                           "the masks show no silhouette, so every pixel is drawn uniformly"))
