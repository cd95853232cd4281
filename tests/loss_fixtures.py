"""A minimal :class:`RenderOutput` for loss tests that set their own colours and surface values."""

from __future__ import annotations

import torch

from nepf_core.render.renderer import RenderOutput


def render_output(R: int, *, rgb: torch.Tensor | None = None, surf: dict | None = None) -> RenderOutput:
    """``R`` rays, every colour (``rgb_r``, ``rgb_vol``, ``rgb_surf``) ``rgb`` (default 0), on the
    surface (``weight_sum = w_max = 1``), no eikonal or Hessian samples, ``surf`` (default empty)."""
    rgb = torch.zeros(R, 3) if rgb is None else rgb
    return RenderOutput(rgb_r=rgb, rgb_vol=rgb, rgb_surf=rgb, weight_sum=torch.ones(R), w_max=torch.ones(R),
                        depth=torch.zeros(R), eikonal=torch.zeros(0), hessian=torch.zeros(0),
                        surf={} if surf is None else surf)
