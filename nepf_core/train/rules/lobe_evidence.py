"""What a training batch says about the GGX lobe (measured at specular checks, no grad).

* :func:`lobe_residual_gain`: how much of the surface error the lobe explains;
* :func:`highlight_residual_ratio`: the brightest pixels' L_vol residual against the median one
  (a diffuse-only fit misses highlights);
* :func:`lit_view_spread`: how much the learned radiance changes across the training cameras
  at lit surface points (:func:`nepf_core.view_dependence.radiance_view_spread`).
"""

from __future__ import annotations

import math

import torch

from nepf_core.render.neus import foreground


def lobe_residual_gain(rgb_surf: torch.Tensor, diffuse_only: torch.Tensor, target: torch.Tensor) -> float:
    """What the GGX lobe explains, on surface rays ``[N, 3]``: ``g = E_d / E - 1`` with
    ``E = mean |c_surf - t|^2`` (diffuse + lobe) and ``E_d = min_{k >= 0} mean |k c_d - t|^2``
    (diffuse only, best per-channel gain ``k_c = max(0, <c_d, t>_c / <c_d, c_d>_c)``, which
    stands for what the albedo could absorb). ``g <= 0``: the lobe adds nothing a brighter
    diffuse could not; ``g = 0.3``: without it the surface error would be 30 % higher."""
    k = ((diffuse_only * target).sum(0) / (diffuse_only * diffuse_only).sum(0).clamp_min(1e-12)).clamp_min(0)
    e = ((rgb_surf - target) ** 2).mean()
    e_d = ((k * diffuse_only - target) ** 2).mean()
    return float(e_d / e.clamp_min(1e-12) - 1.0)


@torch.no_grad()
def batch_lobe_evidence(out, rays, specular_on: bool) -> tuple[float | None, float | None]:
    """``(lobe residual gain or None, highlight residual ratio or None)`` of one rendered batch.

    The gain (lobe on, ``out.lobe`` present, >= 8 foreground rays on the surface)
    is :func:`lobe_residual_gain` on those rays. The ratio is ``mean_top |L_vol - I| / median
    |L_vol - I|`` over foreground pixels (mask, or :func:`~nepf_core.render.neus.foreground` without one), ``top`` the
    brightest 5 % by mean channel (at least 20 foreground pixels)."""
    if rays.rgb is None:
        return None, None
    err = (out.rgb_vol.detach() - rays.rgb).abs().mean(-1)
    fgm = (rays.mask > 0.5) if rays.mask is not None else foreground(out.weight_sum)
    on_surf = fgm & foreground(out.weight_sum)
    gain = None
    if specular_on and out.lobe is not None and int(on_surf.sum()) >= 8:
        gain = lobe_residual_gain(out.rgb_surf.detach()[on_surf], out.lobe.diffuse_only[on_surf], rays.rgb[on_surf])
    err, lum = err[fgm], rays.rgb.mean(-1)[fgm]
    top = lum >= torch.quantile(lum, 0.95) if lum.numel() >= 20 else lum > 1e9
    ratio = float(err[top].mean() / err.median().clamp_min(1e-4)) if top.sum() > 0 else None
    return gain, ratio


@torch.no_grad()
def lit_view_spread(model, out, rays, cams: torch.Tensor, view_points: int,
                    radiance_fit_max: float) -> tuple[str, float | None, float | None]:
    """``(status, spread, fit_error)`` at the max-weight points of up to ``view_points`` foreground
    rays whose pixel is lit (``rays.unlit`` false: a point the light does not reach shows no
    highlight in that view and says nothing about view dependence).

    ``fit_error = sum |L_r - I| / sum |I|`` over those pixels: the spread of a radiance that does
    not yet explain them is no evidence. ``status``: ``"none"`` (fewer than 8 points: nothing
    measured, keep the last spread), ``"unfit"`` (``fit_error > radiance_fit_max``: no spread
    now), ``"measured"`` (``spread`` is finite, or None when no point faces two cameras)."""
    from nepf_core.view_dependence import radiance_view_spread
    fg = foreground(out.weight_sum)
    if rays.mask is not None:
        fg = fg & (rays.mask > 0.5)
    unlit = getattr(rays, "unlit", None)
    if unlit is not None:
        fg = fg & ~unlit
    x = out.surface.x.detach()[fg][:view_points]
    if x.shape[0] < 8:
        return "none", None, None
    fit_err = None
    rgb_r = getattr(out, "rgb_r", None)
    if rgb_r is not None and getattr(rays, "rgb", None) is not None:
        fit_err = float((rgb_r.detach()[fg] - rays.rgb[fg]).abs().sum() / rays.rgb[fg].abs().sum().clamp_min(1e-8))
        if fit_err > radiance_fit_max:
            return "unfit", None, fit_err
    spread = radiance_view_spread(model, x, cams.to(x.device))["spread"]
    return "measured", (spread if math.isfinite(spread) else None), fit_err
