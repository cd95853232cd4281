"""A light a point light cannot fool: ``K`` global point emitters, shadows traced through the SDF.

The paper's photon network gives each surface point its own light direction ``l(x)`` and
intensity ``I(x)``; on a scene lit by one or two lamps nothing makes those directions meet at a
lamp, and texture can hide in them (bench/RESULTS.md v55: spot_svbrdf's black spots drawn by
``n . l``). Here the light is ``K`` emitters shared by every point, with learned positions
``p_k`` and radiant intensities ``I_k > 0``:

    l_k(x) = (p_k - x) / |p_k - x|                          [N, K, 3]
    E_k(x) = V_k(x) I_k / |p_k - x|^2                        [N, K]
    pbr(x) = sum_k f(l_k, v, n) E_k(x) (n . l_k)^+            (nepf_core.render.shading)

``V_k(x)`` in ``{0, 1}`` is not learned: it is a shadow ray from ``x`` to ``p_k`` marched
through the SDF (:func:`nepf_core.relight.tracing.light_visibility`), once per ray at its
surface point and shared by the ray's samples. A learned visibility (v25/v35, docs/TRIED.md)
could carry the cosine shading itself, which the relight then kept in the albedo.

The emitters start at the camera centres farthest apart, pushed out by ``PLACE_FACTOR`` (a lamp
beside the camera is the common capture), and move by gradient (their own parameter group at
``LR_SCALE`` times ``lr``: at the heads' rate an emitter ~5 units away turns 0.06 deg a step).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

PLACE_FACTOR = 1.5
"""Emitters start at the chosen camera centres times this (outside the cameras' sphere)."""
MIN_DISTANCE = 1e-2
"""``|p_k - x|`` floor: an emitter that wanders onto the surface gives a bounded irradiance."""
SECONDARY_SHARE = 0.01
"""The share of the starting irradiance each emitter after the first gets."""
LR_SCALE = 10.0
"""The emitters' positions and log-intensities learn at this times the heads' ``lr``."""


class TracedEmitters(nn.Module):
    """``K`` global point emitters (module docstring); ``count``: ``K``."""

    lr_scale = LR_SCALE
    """The emitters' parameters learn at this times ``lr``."""

    def __init__(self, count: int, init_intensity: float = 3.0) -> None:
        super().__init__()
        if count < 1:
            raise ValueError(f"an emitter light needs at least one emitter, got {count}")
        self.count = count
        angles = torch.arange(count, dtype=torch.float32) * (2.0 * math.pi / count)
        start = torch.stack([torch.cos(angles), torch.sin(angles), torch.ones(count)], -1) * 3.0
        self.positions = nn.Parameter(start)
        """``p_k [K, 3]`` in the normalised frame."""
        self.log_intensity = nn.Parameter(torch.zeros(count))
        """``log I_k [K]``: radiant intensity, positive by construction."""
        self.set_init_intensity(init_intensity)

    @torch.no_grad()
    def set_init_intensity(self, value: float) -> None:
        """``I_k`` such that the origin, seeing every emitter, gets ``sum_k I_k / |p_k|^2 = value``
        (the photon network's starting intensity): the first emitter ``1 - (K - 1) s`` of it, each
        other one ``s = SECONDARY_SHARE``, so that a second light grows only where the data shows
        one (on a one-lamp scene an equal share lights the dark side, and the material, not the
        emitter, took the blame: bench/RESULTS.md v56)."""
        if not (math.isfinite(value) and value > 0):
            raise ValueError(f"initial light intensity must be finite and > 0, got {value}")
        d2 = (self.positions ** 2).sum(-1).clamp_min(MIN_DISTANCE ** 2)
        share = torch.full_like(d2, SECONDARY_SHARE)
        share[0] = 1.0 - SECONDARY_SHARE * (self.count - 1)
        self.log_intensity.copy_(torch.log(value * d2 * share))

    @torch.no_grad()
    def place(self, camera_centres: Tensor) -> None:
        """Start the emitters at ``K`` of the camera centres ``[C, 3]`` chosen farthest apart (the
        first the one nearest the cameras' mean), times ``PLACE_FACTOR``, keeping the origin's
        irradiance. Fewer cameras than emitters: the cameras repeat."""
        c = camera_centres.to(self.positions).reshape(-1, 3)
        if len(c) == 0:
            return
        chosen = [int(((c - c.mean(0)) ** 2).sum(-1).argmin())]
        while len(chosen) < self.count:
            chosen.append(int(torch.cdist(c, c[chosen]).min(-1).values.argmax()))
        at_origin = (self.log_intensity.exp() / (self.positions ** 2).sum(-1).clamp_min(MIN_DISTANCE ** 2)).sum()
        self.positions.copy_(c[chosen] * PLACE_FACTOR)
        self.set_init_intensity(float(at_origin))

    def illuminate(self, x: Tensor, n: Tensor | None = None, feature: Tensor | None = None,
                   visibility: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """``(directions [N, K, 3] unit, irradiance scale E [N, K] >= 0)`` at ``x [N, 3]``;
        ``visibility [N, K]`` in [0, 1] (None: every emitter seen). ``n`` and ``feature`` are
        not read (the photon network's signature)."""
        to = self.positions[None] - x[:, None]
        d2 = (to ** 2).sum(-1).clamp_min(MIN_DISTANCE ** 2)
        irradiance = self.log_intensity.exp() / d2
        if visibility is not None:
            irradiance = irradiance * visibility
        return to * torch.rsqrt(d2)[..., None], irradiance

    def forward(self, x: Tensor, n: Tensor, feature: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """The photon network's contract: ``(light_dir [N, 3], intensity [N])`` of the emitter
        that gives each point the most ``E_k (n . l_k)^+`` (no shadows: the export's light field)."""
        return dominant(*self.illuminate(x, n, feature), n)

    @torch.no_grad()
    def trace_visibility(self, sdf, x: Tensor, n: Tensor) -> Tensor:
        """``[N, K]`` 1 where emitter ``k`` is seen from the surface points ``x [N, 3]`` (unit
        normals ``n``), 0 where the SDF ``sdf: [M, 3] -> [M]`` blocks the segment to it.

        The ``N K`` shadow rays march as one batch: a march step is one SDF call whatever the
        batch, and on a CPU a training batch's call costs mostly its fixed overhead."""
        from nepf_core.relight.tracing import TraceConfig, light_visibility
        cfg = TraceConfig(max_steps=SHADOW_STEPS, min_step=SHADOW_MIN_STEP, shadow_offset=SHADOW_OFFSET)
        K, N = self.count, x.shape[0]
        lights = self.positions.detach().repeat_interleave(N, 0)
        return light_visibility(sdf, x.repeat(K, 1), n.repeat(K, 1), lights, cfg).reshape(K, N).T


SHADOW_STEPS = 48
"""Sphere-tracing steps per shadow ray in training (the relight's 128 are for final images)."""
SHADOW_MIN_STEP = 1e-2
"""Smallest shadow-ray step: a ray creeping through the SDF's far field (where ``f`` is small but
positive and nothing is there) moves a pixel's footprint per step (the 128-pixel image across the
unit ball: ~0.016) instead of the relight's 1e-3; a blocker thinner than this may be crossed."""
SHADOW_OFFSET = 2e-2
"""Shadow rays start this far along the normal: the ray's surface point is its max-weight
sample, up to half a sample spacing off the zero level."""


def received(dirs: Tensor, irradiance: Tensor, n: Tensor) -> Tensor:
    """``[N, K]`` the irradiance each light delivers through the surface, ``E_k (n . l_k)^+``
    (``dirs [N, K, 3]``, ``irradiance [N, K]``, ``n [N, 3]``)."""
    return irradiance * (dirs * n[:, None]).sum(-1).clamp_min(0.0)


def dominant(dirs: Tensor, irradiance: Tensor, n: Tensor) -> tuple[Tensor, Tensor]:
    """``(light_dir [N, 3], intensity [N])`` of the light ``k`` with the most ``E_k (n . l_k)^+``
    among ``dirs [N, K, 3]``, ``irradiance [N, K]`` (``n [N, 3]``); ``K = 1`` returns it as is."""
    if dirs.shape[1] == 1:
        return dirs[:, 0], irradiance[:, 0]
    k = received(dirs, irradiance, n).argmax(-1)
    rows = torch.arange(len(dirs), device=dirs.device)
    return dirs[rows, k], irradiance[rows, k]


DARK_SHARE = 0.02
"""A point is dark under the traced emitters when it receives less than this times the 90th
percentile of what the points around it (one batch) receive."""


def dark_under_emitters(dirs: Tensor, irradiance: Tensor, n: Tensor, among: Tensor | None = None) -> Tensor:
    """``[N]`` bool: ``sum_k E_k (n . l_k)^+ < DARK_SHARE q90`` with the 90th percentile over the
    points ``among [N]`` (bool; None: all), all detached. Where the shadows are traced, a dark
    pixel at a point that is not dark here is a dark *material* under light, not a shadow."""
    e = received(dirs, irradiance, n).sum(-1).detach()
    ref = e if among is None else e[among]
    if ref.numel() == 0:
        return torch.ones_like(e, dtype=torch.bool)
    return e < DARK_SHARE * torch.quantile(ref.float(), 0.9)
