"""A light model a point light cannot fool: a few global emitters and a smooth visibility.

The paper's photon network gives each surface point its own light direction ``l(x)`` and
intensity ``I(x)``. On a scene lit by one or two lamps every direction should meet at a lamp, but
nothing asks it to: the direction is free per point, so shading (and with it the evidence that
tells a metal from a dark dielectric) moves into the albedo. Here the light is ``K`` point
emitters shared by every point, with learned positions ``p_k`` and radiant intensities
``I_k > 0``, and a per-point visibility ``v_k(x)`` in ``[0, 1]``:

    l_k(x) = (p_k - x) / |p_k - x|                       [N, K, 3]
    E_k(x) = v_k(x) I_k / |p_k - x|^2                      [N, K]   (inverse-square irradiance scale)
    pbr(x) = sum_k f(l_k, v, n) E_k(x) (n . l_k)^+          (nepf_core.render.shading)

``v_k`` is a small MLP of ``x`` alone (positional encoding with ``n_freqs_x`` frequencies, no SDF
feature, no normal): a low-frequency field, so a cast shadow can darken a region but a texture
cannot hide in it and ``n . l`` stays the geometry's. It starts near 1 (``sigmoid(4)``).

Why learned positions and not a per-point field: with the light pinned to a few points the
directions are identified by the whole object's shading at once (diffuse ``n . l`` falls off
across every surface), and the material's cues become identifiable: a metal has no diffuse term
and a tinted highlight, a dielectric a white one. The emitters are placed before training
(:meth:`EmitterLight.place`) at the camera centres farthest apart, pushed out by
``PLACE_FACTOR`` (a lamp beside the camera is the common capture), and move by gradient.

``forward`` keeps the photon network's contract (``light_dir [N, 3]``, ``intensity [N]``: the
emitter that gives the point the most irradiance) for the export's light field, the render
channels and the light-variance loss; :meth:`illuminate` gives all ``K``.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

from nepf_core.mlp import MLPConfig, build_mlp, encoding_dim, positional_encoding

VISIBILITY_INIT_LOGIT = 4.0
"""``v_k`` starts at ``sigmoid(4) ~ 0.98``: every point sees every emitter until the data says not."""
PLACE_FACTOR = 1.5
"""Emitters start at the chosen camera centres times this (outside the cameras' sphere)."""
MIN_DISTANCE = 1e-2
"""``|p_k - x|`` floor: an emitter that wanders onto the surface gives a bounded irradiance."""


class EmitterLight(nn.Module):
    """``K`` global point emitters and a visibility network (module docstring).

    ``cfg``: the :class:`~nepf_core.fields.heads.HeadConfig` of the visibility MLP (``n_freqs_x``,
    width, depth, activation); ``count``: ``K``.
    """

    def __init__(self, cfg, count: int, init_intensity: float = 3.0) -> None:
        super().__init__()
        if count < 1:
            raise ValueError(f"an emitter light needs at least one emitter, got {count}")
        self.cfg, self.count = cfg, count
        self.visibility = build_mlp(MLPConfig(in_dim=encoding_dim(3, cfg.n_freqs_x), out_dim=count,
                                              width=cfg.width, depth=cfg.depth, activation=cfg.activation))
        angles = torch.arange(count, dtype=torch.float32) * (2.0 * math.pi / count)
        start = torch.stack([torch.cos(angles), torch.sin(angles), torch.ones(count)], -1) * 3.0
        self.positions = nn.Parameter(start)
        """``p_k [K, 3]`` in the normalised frame."""
        self.log_intensity = nn.Parameter(torch.zeros(count))
        """``log I_k [K]``: radiant intensity, positive by construction."""
        self.set_init_intensity(init_intensity)

    @torch.no_grad()
    def set_init_intensity(self, value: float) -> None:
        """Set ``I_k`` so that a point at the origin fully visible to all emitters gets irradiance
        scale ``sum_k I_k / |p_k|^2 = value`` (the photon network's starting ``I``)."""
        if not (math.isfinite(value) and value > 0):
            raise ValueError(f"initial light intensity must be finite and > 0, got {value}")
        d2 = (self.positions ** 2).sum(-1).clamp_min(MIN_DISTANCE ** 2)
        self.log_intensity.copy_(torch.log(value * d2 / self.count))

    @torch.no_grad()
    def place(self, camera_centres: Tensor) -> None:
        """Start the emitters at ``K`` camera centres ``[C, 3]`` chosen farthest apart (the first
        is the one nearest the cameras' mean direction), times ``PLACE_FACTOR``; the intensity is
        re-set for the new distances. Fewer cameras than emitters: the cameras repeat."""
        c = camera_centres.to(self.positions).reshape(-1, 3)
        if len(c) == 0:
            return
        mean = c.mean(0)
        chosen = [int(((c - mean) ** 2).sum(-1).argmin())]
        while len(chosen) < self.count:
            d = torch.cdist(c, c[chosen]).min(-1).values
            chosen.append(int(d.argmax()))
        intensity = (self.log_intensity.exp() / (self.positions ** 2).sum(-1).clamp_min(MIN_DISTANCE ** 2)).sum()
        self.positions.copy_(c[chosen] * PLACE_FACTOR)
        self.set_init_intensity(float(intensity))

    def illuminate(self, x: Tensor, n: Tensor, feature: Tensor) -> tuple[Tensor, Tensor]:
        """``(directions [N, K, 3] unit, irradiance scale E [N, K] >= 0)`` at points ``x [N, 3]``
        (``n`` and ``feature`` are not read: the visibility is a function of ``x`` alone)."""
        to = self.positions[None] - x[:, None]                       # [N, K, 3]
        d2 = (to ** 2).sum(-1).clamp_min(MIN_DISTANCE ** 2)          # [N, K]
        dirs = to * torch.rsqrt(d2)[..., None]
        vis = torch.sigmoid(self.visibility(positional_encoding(x, self.cfg.n_freqs_x)) + VISIBILITY_INIT_LOGIT)
        return dirs, vis * self.log_intensity.exp() / d2

    def forward(self, x: Tensor, n: Tensor, feature: Tensor) -> tuple[Tensor, Tensor]:
        """The photon network's contract: ``(light_dir [N, 3], intensity [N])`` of the emitter that
        gives each point the most irradiance ``E_k (n . l_k)^+``."""
        return dominant(*self.illuminate(x, n, feature), n)


def dominant(dirs: Tensor, irradiance: Tensor, n: Tensor) -> tuple[Tensor, Tensor]:
    """``(light_dir [N, 3], intensity [N])`` of the light ``k`` with the most ``E_k (n . l_k)^+``
    among ``dirs [N, K, 3]``, ``irradiance [N, K]`` (``n [N, 3]``); ``K = 1`` returns it as is."""
    if dirs.shape[1] == 1:
        return dirs[:, 0], irradiance[:, 0]
    k = (irradiance * (dirs * n[:, None]).sum(-1).clamp_min(0.0)).argmax(-1)
    rows = torch.arange(len(dirs), device=dirs.device)
    return dirs[rows, k], irradiance[rows, k]
