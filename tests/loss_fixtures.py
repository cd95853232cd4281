"""A minimal :class:`RenderOutput` for loss tests that set their own colours and surface values."""

from __future__ import annotations

import torch

from nepf_core.render.renderer import RenderOutput
from nepf_core.render.surface import LobeSplit, Surface


def render_output(R: int, *, rgb: torch.Tensor | None = None, surface: dict | None = None,
                  lobe_share: torch.Tensor | None = None) -> RenderOutput:
    """``R`` rays, every colour (``rgb_r``, ``rgb_vol``, ``rgb_surf``) ``rgb`` (default 0), on the
    surface (``weight_sum = w_max = 1``), no eikonal or Hessian samples; a :class:`Surface` of zeros
    with the fields in ``surface`` replaced; with ``lobe_share [R]`` a :class:`LobeSplit` of that share."""
    rgb = torch.zeros(R, 3) if rgb is None else rgb
    v3, v1 = torch.zeros(R, 3), torch.zeros(R)
    fields = dict(x=v3, normal=v3, direction=v3, light_dir=v3, intensity=v1, albedo=v3, roughness=v1, metallic=v1)
    fields.update(surface or {})
    lobe = None if lobe_share is None else LobeSplit(diffuse_only=v3, share=lobe_share, absolute=v1)
    return RenderOutput(rgb_r=rgb, rgb_vol=rgb, rgb_surf=rgb, weight_sum=torch.ones(R), w_max=torch.ones(R),
                        depth=torch.zeros(R), eikonal=torch.zeros(0), hessian=torch.zeros(0),
                        surface=Surface(**fields), lobe=lobe)
