"""Colour Retinex: telling the light's shading from the albedo's texture by the pixels' colour.

Shading ``c I(x) (n.l) / pi`` sees only the product of the albedo ``c`` and the scalar photon
intensity ``I``, so the images alone cannot say which of the two carries a pattern (with the GGX
lobe on as well: it ties the split only near a highlight). Under one light colour the shading
scales a pixel's ``rgb`` and keeps its chromaticity ``rgb / sum(rgb)``, while a change of albedo
usually changes it (Grosse et al. 2009, "colour Retinex"). :func:`albedo_flat_loss` asks lit
surface points whose pixels share a chromaticity to share an albedo luminance, and leaves the
rest to the images. It is ``loss.w_albedo_flat`` (:mod:`nepf_core.losses`).

A texture that changes only luminance (a grey checker) is flattened into the light: the known
failure of this assumption, and the reason the weight stays small (docs/FAST.md, "Colour Retinex").
"""

from __future__ import annotations

import torch
from torch import Tensor

CHROMA_SIGMA = 0.01
"""Width of the chromaticity kernel of :func:`albedo_flat_loss`: a chromaticity ``rgb / sum(rgb)``
difference of 0.01 is about one just-noticeable step of colour; an 8-bit pixel at linear 0.1
quantises it by ~0.003. On the GT test views of the two textured suite scenes, lit pixel pairs
within 0.01 of each other differ in albedo log-luminance by 0.07-0.08 on average and in pixel
log-luminance by 0.86-1.05 (the shading); pairs 0.05-0.1 apart differ in albedo by 2.1-2.6
(docs/FAST.md, "Colour Retinex")."""


def albedo_flat_loss(lum: Tensor, rgb: Tensor, sigma: float = CHROMA_SIGMA) -> Tensor:
    """Colour Retinex over one batch: ``mean_i g_i |Y_i / sg(Ybar_i) - 1|``.

    ``lum [N]``: the albedo luminance ``Y_i`` of the lit surface rays; ``rgb [N, 3]``: their target
    pixels (linear). ``k_ij = exp(-|h_i - h_j|^2 / 2 sigma^2)`` with ``h = rgb / sum(rgb)`` the pixel
    chromaticity and ``k_ii = 0``; ``Ybar_i = sum_j k_ij Y_j / sum_j k_ij`` the luminance of the
    ray's colour partners; ``g_i = sum_j k_ij / (1 + sum_j k_ij)``, so that a ray with one partner
    counts half (one match may be chance) and a ray with none not at all. With one chromaticity in
    the batch (an untextured object) this is a pull toward the mean of the others.
    """
    h = rgb / rgb.sum(-1, keepdim=True).clamp_min(1e-6)
    k = torch.exp(-torch.cdist(h, h).square() / (2.0 * sigma ** 2))    # [N, N], k_ii = 1 here
    y = lum.detach()
    partners = (k.sum(1) - 1.0).clamp_min(0.0)                          # leave out k_ii
    ref = (k @ y - y) / partners.clamp_min(1e-12)
    g = partners / (1.0 + partners)
    return (g * (lum / ref.clamp_min(1e-4) - 1.0).abs()).mean()
