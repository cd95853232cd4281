"""A second radiance network, read only by the metal evidence: highlights as a function of the
reflected ray.

    R_e(x, r, n.v, n, feature) -> rgb in [0, 1]^3,     r = v - 2 (v.n) n   (v: camera to point)

trained at each foreground ray's surface point ``x*`` against the ray's pixel,

    L_e = mean_fg | srgb(R_e(x*, r, n.v, n*, F(x*))) - C_gt |                (weight ``loss.w_r``)

with every input detached: ``L_e`` trains ``R_e`` and nothing else, and ``R_e`` is read only by
:func:`nepf_core.render.material_evidence.views_of_points`.

Why: the evidence fits a metal and a dielectric to the colours one surface point shows toward
several training cameras, so it needs a radiance field whose highlights are where the views put
them. The radiance network of ``L_r`` reads the ray direction ``v``, in which a highlight moves
across the surface with the normal and needs high frequencies; in the reflected direction ``r``
it is the same low-frequency lobe at every point (Ref-NeRF, Verbin et al. 2022). Reading ``r``
in ``L_r`` itself was measured (docs/TRIED.md): coupled to the normal it bent the geometry, and
with the normal detached it helped the one-material scenes and cost the textured ones. Here the
reflected parametrisation serves the evidence only, and ``L_r``, ``L_surf`` and the geometry
are as without it. Cost: one small MLP forward and backward per foreground ray.
"""

from __future__ import annotations

from torch import Tensor, nn

import torch

from nepf_core.fields.heads import HeadConfig
from nepf_core.mlp import MLPConfig, build_mlp, encoding_dim, positional_encoding


def reflected_view(v: Tensor, n: Tensor) -> Tensor:
    """``[N, 4]``: the ray ``v [N, 3]`` (camera to point, unit) reflected about the unit normal of
    ``n [N, 3]`` (any length), and ``n.v``:

        r = v - 2 (v.n) n,        (r, v.n)

    ``v.n`` carries the Fresnel and the grazing darkening that the lobe's direction does not."""
    n = n / n.norm(dim=-1, keepdim=True).clamp_min(1e-8)
    vn = (v * n).sum(-1, keepdim=True)
    return torch.cat([v - 2.0 * vn * n, vn], dim=-1)


class EvidenceRadiance(nn.Module):
    """``(x, v, n, feature) -> rgb [N, 3]`` (linear), the signature of
    :class:`nepf_core.fields.heads.RadianceField`, reading ``(r, v.n)`` in place of ``v``. Every
    input is detached (module docstring)."""

    def __init__(self, cfg: HeadConfig, feature_dim: int) -> None:
        super().__init__()
        self.cfg = cfg
        d_in = encoding_dim(3, cfg.n_freqs_x) + encoding_dim(3, cfg.n_freqs_v) + 1 + 3 + feature_dim
        self.mlp = build_mlp(MLPConfig(in_dim=d_in, out_dim=3, width=cfg.width, depth=cfg.depth,
                                       activation=cfg.activation))

    def forward(self, x: Tensor, v: Tensor, n: Tensor, feature: Tensor) -> Tensor:
        x, v, n, feature = x.detach(), v.detach(), n.detach(), feature.detach()
        rv = reflected_view(v, n)
        h = torch.cat([positional_encoding(x, self.cfg.n_freqs_x), positional_encoding(rv[:, :3], self.cfg.n_freqs_v),
                       rv[:, 3:], n, feature], dim=-1)
        return torch.sigmoid(self.mlp(h))
