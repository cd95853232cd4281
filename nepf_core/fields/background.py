"""The background: a volume for everything outside the unit sphere (NeRF++ / mip-NeRF 360).

The SDF models the object inside the unit sphere. A photo also shows what lies around it (the
wall behind a mounted head, the table under a DTU scan, the room). Those surfaces are at a
finite distance, so from cameras that move they show parallax: a radiance that depends on the
direction alone, ``B(d)``, cannot explain them, and the SDF then fills its sphere to paint them
(the mesh becomes the bounding sphere). NeuS models the outside with NeRF++ for the same reason.

Space outside the sphere is contracted into the shell ``1 < |c| < 2`` (mip-NeRF 360):

    c(x) = x                      for |x| <= 1
    c(x) = (2 - 1/|x|) x / |x|    for |x| >  1

and a multi-resolution dense grid on ``[-2, 2]^3`` (:class:`MultiResGrid`) with a small MLP
gives a density ``sigma = softplus(s)`` and a colour ``rgb = sigmoid(g(feature, PE(d)))``.
Each ray takes ``n_samples`` stratified samples uniform in disparity between where it leaves
the unit sphere, ``t0``, and ``far``: ``t_i = 1 / ((1 - u_i) / t0 + u_i / far)``, and is
composited with the standard volume rendering over the *contracted* spacing
``delta_i = |c(x_{i+1}) - c(x_i)|`` (bounded, so the density is in contracted units); the last
sample's ``delta`` is infinite, so the background is opaque:

    C_bg = sum_i T_i a_i rgb_i,   a_i = 1 - exp(-sigma_i delta_i),   T_i = prod_{j<i} (1 - a_j)

The renderer adds it behind the object: ``C = sum_i w_i c_i + (1 - sum_i w_i) C_bg``.
Shapes: rays ``o, d [R, 3]`` (normalised frame, ``d`` unit), ``t0 [R]``; output ``[R, 3]``.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from nepf_core.fields.grid_encoding import GridConfig, MultiResGrid
from nepf_core.mlp import MLPConfig, build_mlp, encoding_dim, positional_encoding
from nepf_core.render.neus import weights_from_alpha


@dataclass
class BackgroundConfig:
    """Settings of :class:`BackgroundVolume`."""

    n_samples: int = 24
    """Samples per ray outside the unit sphere (uniform in disparity)."""
    far: float = 100.0
    """Last sample distance along the ray (normalised units; the sphere has radius 1)."""
    resolutions: tuple[int, int] = (16, 128)
    """Coarsest and finest grid resolution over the contracted cube ``[-2, 2]^3``."""
    n_levels: int = 4
    features_per_level: int = 2
    width: int = 64
    """Hidden width of the density/colour MLP (two hidden layers)."""
    n_freqs_d: int = 2
    """Positional-encoding frequencies of the view direction for the colour."""


def contract(x: Tensor) -> Tensor:
    """``c(x) = x`` inside the unit ball, ``(2 - 1/|x|) x/|x|`` outside: ``[..., 3] -> [..., 3]``, ``|c| < 2``."""
    r = torch.linalg.vector_norm(x, dim=-1, keepdim=True).clamp_min(1e-9)
    return torch.where(r <= 1.0, x, (2.0 - 1.0 / r) * x / r)


def sphere_exit(o: Tensor, d: Tensor) -> Tensor:
    """Distance along each ray where it leaves the unit sphere, or the distance of its closest
    approach to the origin when it misses (never below 1e-3): ``[R, 3], [R, 3] -> [R]`` (``d`` unit)."""
    mid = -(o * d).sum(-1)
    h2 = 1.0 - (o + mid[:, None] * d).square().sum(-1)
    return (mid + h2.clamp_min(0.0).sqrt()).clamp_min(1e-3)


class BackgroundVolume(nn.Module):
    """Density and colour outside the unit sphere, volume-rendered per ray (module docstring)."""

    def __init__(self, cfg: BackgroundConfig | None = None) -> None:
        super().__init__()
        self.cfg = cfg = cfg or BackgroundConfig()
        lo, hi = cfg.resolutions
        self.encoding = MultiResGrid(GridConfig(n_levels=cfg.n_levels, base_resolution=lo, max_resolution=hi,
                                                features_per_level=cfg.features_per_level, init_std=1e-2,
                                                bound=2.0, start_levels=cfg.n_levels))
        feat = self.encoding.n_output_dims
        self.density = build_mlp(MLPConfig(in_dim=feat, out_dim=1 + 15, width=cfg.width, depth=1))
        self.color = build_mlp(MLPConfig(in_dim=15 + encoding_dim(3, cfg.n_freqs_d), out_dim=3,
                                         width=cfg.width, depth=1))

    def sample_distances(self, t0: Tensor, *, perturb: bool, generator: torch.Generator | None = None) -> Tensor:
        """``[R] -> [R, n]`` distances uniform in disparity from ``t0`` to ``far`` (stratified when ``perturb``)."""
        n = self.cfg.n_samples
        u = (torch.arange(n, device=t0.device, dtype=t0.dtype) + 0.5) / n
        u = u.expand(t0.shape[0], n)
        if perturb:
            u = u + (torch.rand(u.shape, device=t0.device, dtype=t0.dtype, generator=generator) - 0.5) / n
        far = torch.maximum(torch.full_like(t0, self.cfg.far), t0 * 1.01)
        return 1.0 / ((1.0 - u) / t0[:, None] + u / far[:, None])

    def forward(self, o: Tensor, d: Tensor, *, perturb: bool = False,
                generator: torch.Generator | None = None, start: Tensor | None = None,
                with_logits: bool = False):
        """Background colour of each ray ``[R, 3]`` (linear, in [0, 1]): ``sum_j w_j c_j`` of
        :meth:`weights_and_colours`. ``start [R]``: where the object's region ends before the
        sphere does (its support plane, :func:`nepf_core.render.sampling.object_segment`); the
        volume begins there. With ``with_logits`` also the colour logits of every sample,
        ``z [R * n, 3]`` (for :attr:`nepf_core.losses.LossConfig.w_colour_range`)."""
        w, rgb, z = self.weights_and_colours(o, d, perturb=perturb, generator=generator, start=start,
                                             with_logits=True)
        c = (w[..., None] * rgb).sum(1)
        return (c, z) if with_logits else c

    def weights_and_colours(self, o: Tensor, d: Tensor, *, perturb: bool = False,
                            generator: torch.Generator | None = None,
                            start: Tensor | None = None, with_logits: bool = False):
        """``(w [R, n], c [R, n, 3])``: each sample's volume-rendering weight
        ``w_j = T_j (1 - exp(-sigma_j delta_j))`` (``delta`` measured in the contracted space) and
        colour, for :meth:`forward` and for measuring which samples carry weight
        (``bench/ray_samples.py``); with ``with_logits`` also the colours' logits ``z [R * n, 3]``."""
        R, n = o.shape[0], self.cfg.n_samples
        t0 = sphere_exit(o, d) if start is None else torch.minimum(sphere_exit(o, d), start).clamp_min(1e-3)
        t = self.sample_distances(t0, perturb=perturb, generator=generator)   # [R, n]
        c = contract(o[:, None, :] + t[..., None] * d[:, None, :])                           # [R, n, 3]
        h = self.density(self.encoding(c.reshape(-1, 3)))
        sigma = F.softplus(h[:, 0]).reshape(R, n)
        d_enc = positional_encoding(d, self.cfg.n_freqs_d)[:, None, :].expand(R, n, -1).reshape(R * n, -1)
        z = self.color(torch.cat([h[:, 1:], d_enc], -1))
        rgb = torch.sigmoid(z).reshape(R, n, 3)
        delta = (c[:, 1:] - c[:, :-1]).norm(dim=-1)
        delta = torch.cat([delta, torch.full_like(delta[:, :1], 1e10)], -1)
        alpha = 1.0 - torch.exp(-sigma * delta)
        return (weights_from_alpha(alpha), rgb, z) if with_logits else (weights_from_alpha(alpha), rgb)
