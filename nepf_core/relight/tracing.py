"""Sphere tracing through an SDF (normalised frame): primary hits and shadow rays.

Both march ``x(t) = o + t d`` with steps ``t += max(f(x), min_step)`` (``f`` the SDF), which
never skips a surface when ``f`` underestimates the distance (a trained SDF with ``|grad f| ~ 1``
does, up to its error; ``step_scale < 1`` adds margin for one that overestimates). Every scene
lies inside the unit sphere, so a ray that leaves the ball of radius ``bound`` has hit nothing.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import torch
from torch import Tensor

SdfFn = Callable[[Tensor], Tensor]
"""``[N, 3] -> [N]`` signed distance (normalised frame)."""


@dataclass
class TraceConfig:
    """Sphere-tracing parameters (normalised-frame units; the object fills the unit sphere)."""

    hit_eps: float = 1e-3
    """A point with ``f < hit_eps`` is on the surface (primary rays) / blocks the light (shadow rays)."""
    min_step: float = 1e-3
    """Smallest step: keeps a ray that grazes a surface moving."""
    max_steps: int = 128
    step_scale: float = 0.9
    """Steps are ``step_scale * f``: margin for an SDF that overestimates the distance a little."""
    shadow_offset: float = 1e-2
    """Shadow rays start at ``x + shadow_offset n`` (off the surface they leave, along its normal)."""
    bound: float = 1.0
    """Radius of the ball that holds the scene."""


def _ray_ball(o: Tensor, d: Tensor, radius: float) -> tuple[Tensor, Tensor]:
    """Entry and exit ``t`` of unit-direction rays ``[N, 3]`` through the ball ``|x| <= radius``
    (``t_exit < t_entry`` when the ray misses it); entry clamped to >= 0."""
    b = (o * d).sum(-1)
    c = (o * o).sum(-1) - radius * radius
    disc = b * b - c
    s = disc.clamp_min(0.0).sqrt()
    t0, t1 = -b - s, -b + s
    t1 = torch.where(disc >= 0, t1, torch.full_like(t1, -1.0))
    return t0.clamp_min(0.0), t1


@torch.no_grad()
def march(sdf: SdfFn, o: Tensor, d: Tensor, t_max: Tensor, cfg: TraceConfig) -> tuple[Tensor, Tensor]:
    """March ``[N]`` rays from ``t = 0`` up to ``t_max [N]``; returns ``hit [N]`` bool (some
    ``f < hit_eps`` before ``t_max``) and ``t [N]`` (the hit distance where hit)."""
    t = torch.zeros(o.shape[0], dtype=o.dtype, device=o.device)
    hit = torch.zeros(o.shape[0], dtype=torch.bool, device=o.device)
    active = t_max > 0
    for _ in range(cfg.max_steps):
        idx = active.nonzero(as_tuple=True)[0]
        if idx.numel() == 0:
            break
        f = sdf(o[idx] + t[idx, None] * d[idx]).reshape(-1).to(o.dtype)
        h = f < cfg.hit_eps
        hit[idx[h]] = True
        t[idx] = t[idx] + torch.where(h, torch.zeros_like(f), (cfg.step_scale * f).clamp_min(cfg.min_step))
        active[idx] = ~h & (t[idx] < t_max[idx])
    return hit, t


@torch.no_grad()
def trace_primary(sdf: SdfFn, o: Tensor, d: Tensor, cfg: TraceConfig) -> tuple[Tensor, Tensor]:
    """First surface hit of camera rays (``o, d [N, 3]``, d unit): ``hit [N]`` and the point
    ``x [N, 3]`` (meaningful where hit). Marching starts where the ray enters the bound ball."""
    t0, t1 = _ray_ball(o, d, cfg.bound)
    start = o + t0[:, None] * d
    hit, t = march(sdf, start, d, t1 - t0, cfg)
    return hit, start + t[:, None] * d


@torch.no_grad()
def light_visibility(sdf: SdfFn, x: Tensor, n: Tensor, light_pos: Tensor, cfg: TraceConfig) -> Tensor:
    """``[N]`` float: 1 where the point light at ``light_pos`` (``[3]`` or ``[N, 3]``) is visible
    from the surface points ``x [N, 3]`` (unit normals ``n [N, 3]``), 0 where the SDF goes below
    ``hit_eps`` on the segment from ``x + shadow_offset n`` to the light (or to where it leaves
    the bound ball, if sooner)."""
    o = x + cfg.shadow_offset * n
    to_light = light_pos.expand_as(o) - o
    dist = to_light.norm(dim=-1)
    d = to_light / dist.clamp_min(1e-12)[:, None]
    _, t_exit = _ray_ball(o, d, cfg.bound)
    t_max = torch.minimum(dist, t_exit.clamp_min(0.0))
    hit, _ = march(sdf, o, d, t_max, cfg)
    return (~hit).to(x.dtype)
