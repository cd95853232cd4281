"""The networks that read the SDF feature vector: radiance, photon, material.

    radiance  R(x, v, n, feature) -> rgb in [0,1]^3                  (NeuS/IDR input layout)
    photon    P(x, n, feature)    -> (rho, phi, I): l = (sin rho cos phi, sin rho sin phi, cos rho)
    material  M(x, n, feature)    -> albedo in [0,1]^3, roughness in [0,1], metallic in [0,1]

Shapes: x, v, n ``[N, 3]``, feature ``[N, F]``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor, nn

from nepf_core.mlp import MLPConfig, build_mlp, encoding_dim, positional_encoding


@dataclass
class HeadConfig:
    """Settings of one head network."""

    width: int = 256
    """Hidden width."""
    depth: int = 8
    """Hidden layers."""
    activation: str = "relu"
    """relu | softplus | siren."""
    n_freqs_x: int = 0
    """Positional-encoding frequencies for x (0: raw x)."""
    n_freqs_v: int = 4
    """Positional-encoding frequencies for the view direction (radiance only; NeuS: 4)."""
    use_feature: bool = True
    """Read the SDF feature vector (paper: yes). The fast preset's photon network sets this
    False so the light field is a smooth function of (x, n) and cannot copy surface texture
    into the intensity (texture then has to go to the albedo)."""


class RadianceField(nn.Module):
    """Outgoing radiance ``L(x, v)``: ``(x, v, n, feature) -> rgb [N, 3]`` (linear)."""

    def __init__(self, cfg: HeadConfig, feature_dim: int) -> None:
        super().__init__()
        self.cfg = cfg
        d_in = encoding_dim(3, cfg.n_freqs_x) + encoding_dim(3, cfg.n_freqs_v) + 3 + feature_dim
        self.mlp = build_mlp(MLPConfig(in_dim=d_in, out_dim=3, width=cfg.width, depth=cfg.depth,
                                       activation=cfg.activation))

    def forward(self, x: Tensor, v: Tensor, n: Tensor, feature: Tensor, *, with_logits: bool = False):
        """``rgb [N, 3]``; with ``with_logits`` also ``z [N, 3]`` before the sigmoid (for
        :attr:`nepf_core.losses.LossConfig.w_colour_range`)."""
        h = torch.cat([positional_encoding(x, self.cfg.n_freqs_x),
                       positional_encoding(v, self.cfg.n_freqs_v), n, feature], dim=-1)
        z = self.mlp(h)
        return (torch.sigmoid(z), z) if with_logits else torch.sigmoid(z)


def direction_from_angles(rho: Tensor, phi: Tensor) -> Tensor:
    """Unit vector ``(sin rho cos phi, sin rho sin phi, cos rho)``: ``[N], [N] -> [N, 3]``."""
    s = torch.sin(rho)
    return torch.stack([s * torch.cos(phi), s * torch.sin(phi), torch.cos(rho)], dim=-1)


class PhotonField(nn.Module):
    """Photon network ``P(x, n, feature) -> (light_dir [N,3] unit, intensity [N])``.

    Raw outputs map to ``rho = pi * sigmoid(a)`` (polar, [0, pi]), ``phi = pi * tanh(b)``
    (azimuth, (-pi, pi)), and ``I = softplus(c + init_bias)`` (radiant intensity, >= 0).
    """

    def __init__(self, cfg: HeadConfig, feature_dim: int, init_intensity: float = 3.0) -> None:
        super().__init__()
        self.cfg = cfg
        d_in = encoding_dim(3, cfg.n_freqs_x) + 3 + (feature_dim if cfg.use_feature else 0)
        self.mlp = build_mlp(MLPConfig(in_dim=d_in, out_dim=3, width=cfg.width, depth=cfg.depth,
                                       activation=cfg.activation))
        # softplus^-1(init_intensity): start with a plausible light level
        self.register_buffer("intensity_bias", torch.tensor(math.log(math.expm1(init_intensity))))

    def set_init_intensity(self, value: float) -> None:
        """Shift the intensity so that a zero raw output gives ``I = value`` (> 0):
        ``bias = softplus^-1(value) = value + log(-expm1(-value))`` (stable for any value > 0)."""
        if not (math.isfinite(value) and value > 0):
            raise ValueError(f"initial light intensity must be finite and > 0, got {value}")
        self.intensity_bias.fill_(value + math.log(-math.expm1(-value)))

    def forward(self, x: Tensor, n: Tensor, feature: Tensor) -> tuple[Tensor, Tensor]:
        parts = [positional_encoding(x, self.cfg.n_freqs_x), n] + ([feature] if self.cfg.use_feature else [])
        raw = self.mlp(torch.cat(parts, dim=-1))
        rho = math.pi * torch.sigmoid(raw[..., 0])
        phi = math.pi * torch.tanh(raw[..., 1])
        intensity = nn.functional.softplus(raw[..., 2] + self.intensity_bias)
        return direction_from_angles(rho, phi), intensity


class MaterialField(nn.Module):
    """Material network ``M(x, n, feature) -> (albedo [N,3], roughness [N], metallic [N])``,
    all through a sigmoid into [0, 1]."""

    def __init__(self, cfg: HeadConfig, feature_dim: int) -> None:
        super().__init__()
        self.cfg = cfg
        d_in = encoding_dim(3, cfg.n_freqs_x) + 3 + feature_dim
        self.mlp = build_mlp(MLPConfig(in_dim=d_in, out_dim=5, width=cfg.width, depth=cfg.depth,
                                       activation=cfg.activation))
        with torch.no_grad():  # start dielectric: metallic = sigmoid(-3) ~ 0.05
            self.mlp.layers[-1].bias[4] = self.METALLIC_INIT_LOGIT

    METALLIC_INIT_LOGIT = -3.0
    """A surface starts dielectric (metallic = sigmoid(-3) ~ 0.05) and turns metallic only if the
    data asks for it: from metallic 0.5 a rough metal lobe can explain a diffuse surface as well
    as a diffuse albedo does, and the fit drifts into that ambiguity (docs/FAST.md)."""

    def forward(self, x: Tensor, n: Tensor, feature: Tensor, *, with_logits: bool = False):
        """``(albedo [N,3], roughness [N], metallic [N])``; with ``with_logits`` also the raw outputs
        ``z [N, 5]`` before the sigmoid (for :attr:`nepf_core.losses.LossConfig.w_material_range`)."""
        z = self.mlp(torch.cat([positional_encoding(x, self.cfg.n_freqs_x), n, feature], dim=-1))
        out = torch.sigmoid(z)
        if with_logits:
            return out[..., :3], out[..., 3], out[..., 4], z
        return out[..., :3], out[..., 3], out[..., 4]


class Deviation(nn.Module):
    """NeuS's learnable sharpness: ``inv_s = exp(clip(10 v, log 1e-6, log 1e6))``.

    Clipping the exponent (not the result) keeps the gradient finite for any v: outside
    the range it is exactly zero instead of ``0 * inf``."""

    def __init__(self, init_val: float = 0.3) -> None:
        super().__init__()
        self.variance = nn.Parameter(torch.tensor(float(init_val)))

    def forward(self) -> Tensor:
        return torch.exp((self.variance * 10.0).clamp(math.log(1e-6), math.log(1e6)))
