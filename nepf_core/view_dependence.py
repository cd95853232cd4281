"""How much the learned outgoing radiance changes with the viewing direction.

The radiance network ``L_r(x, v)`` fits the training views directly (it is the best-fitted
field of the four). On a Lambertian surface under fixed lights, the light leaving a point is
the same in every direction, so ``L_r(x, .)`` is flat across the directions the cameras saw
it from; a specular highlight shows up as some views of a point being brighter than its
typical view. :func:`radiance_view_spread` measures that excess at surface points;
:class:`nepf_core.adaptivity.Adaptivity` drops the GGX lobe when it stays small (the lobe can
only add view-dependent light, so a scene whose radiance has none does not need it, and a lobe
fitted anyway overfits the training views: measured on sphere_diffuse, docs/FAST.md).
"""

from __future__ import annotations

import torch
from torch import Tensor

LUMA = (0.2126, 0.7152, 0.0722)


@torch.no_grad()
def radiance_view_spread(model, x: Tensor, cam_centers: Tensor, *, min_cos: float = 0.6, max_cams: int = 64,
                         fd_step: float | None = None) -> dict:
    """Highlight excess of the learned radiance over the training cameras that face each point.

    For each surface point ``x_i`` (``[N, 3]``, normalised frame) with normal ``n_i`` (SDF
    central differences), let ``C_i`` be the cameras ``c`` with
    ``n_i . (c - x_i) / |c - x_i| > min_cos`` (facing it, not grazing: the radiance is poorly
    constrained at grazing views), and ``Y_ic = luma(L_r(x_i, (x_i - c) / |x_i - c|))`` (the
    network's input is the ray direction, camera to point). Then

        spread = sum_i (max_{c in C_i} Y_ic - median_{c in C_i} Y_ic)  /  sum_i mean_{c in C_i} Y_ic

    (a ratio of sums, so dark points weigh little): how much brighter the brightest view of a
    point is than its typical view. 0 for a view-independent radiance. Max minus median rather
    than a deviation, because a highlight lifts a few views of a point, not all of them (16
    random facing cameras per point: on torus_glossy at steps 600-900 the mean absolute
    deviation was 1.5-1.7 % against 0.38-0.39 % on sphere_diffuse at 600 s and 0.86 % at step
    400; max minus median 3.8-4.5 % against 0.74-0.80 % and 1.65 %). Deterministic: every facing camera is used
    (evenly subsampled to ``max_cams``). Points facing fewer than two cameras are left out.

    The same pass measures the colour of the highlights (:func:`highlight_chroma`), from
    ``c_max_i`` (the RGB of point ``i``'s brightest facing view) and ``c_med_i`` (its per-channel
    median over the facing views).

    Args:
        model: :class:`nepf_core.model.NePFModel` (``sdf``, ``radiance``).
        x: ``[N, 3]`` surface points; cam_centers: ``[C, 3]`` camera centres (normalised frame).
    Returns:
        ``{"spread": float (nan if no point qualifies), "n_points": int,
        "chroma_gap", "body_saturation": float}`` (the last two as :func:`highlight_chroma`).
    """
    nan = {"spread": float("nan"), "n_points": 0, "chroma_gap": float("nan"), "body_saturation": float("nan")}
    if x.shape[0] == 0 or cam_centers.shape[0] < 2:
        return nan
    from nepf_core.fields.gradients import sdf_gradient_central
    if cam_centers.shape[0] > max_cams:
        cam_centers = cam_centers[torch.linspace(0, cam_centers.shape[0] - 1, max_cams).round().long()]
    eps = fd_step if fd_step is not None else float(getattr(model.sdf, "fd_step", lambda: 1e-3)())
    g, _ = sdf_gradient_central(model.sdf.sdf, x, max(eps, 1e-4))
    n = g / g.norm(dim=-1, keepdim=True).clamp_min(1e-8)
    to_cam = cam_centers[None, :, :].to(x) - x[:, None, :]                    # [N, C, 3]
    to_cam = to_cam / to_cam.norm(dim=-1, keepdim=True).clamp_min(1e-8)
    facing = (to_cam * n[:, None, :]).sum(-1) > min_cos                        # [N, C]
    ok = facing.sum(-1) >= 2
    if not bool(ok.any()):
        return nan
    x, g, to_cam, facing = x[ok], g[ok], to_cam[ok], facing[ok]
    _, feat = model.sdf(x)
    ii, cc = facing.nonzero(as_tuple=True)                                     # facing pairs
    rgb = model.radiance(x[ii], -to_cam[ii, cc], g[ii], feat[ii]).float()
    c = x.new_full(facing.shape + (3,), float("nan"))                            # [N, C, 3], nan: not facing
    c[ii, cc] = rgb
    y = (c * c.new_tensor(LUMA)).sum(-1)                                       # [N, C] luma
    ymax, imax = y.masked_fill(~facing, float("-inf")).max(-1)
    ymed = y.nanmedian(-1).values
    ymean = y.nansum(-1) / facing.sum(-1)
    c_max = c[torch.arange(c.shape[0], device=c.device), imax]                 # [N, 3]
    c_med = c.nanmedian(1).values                                              # [N, 3]
    chroma = highlight_chroma(c_max, c_med)
    return {"spread": float((ymax - ymed).sum() / ymean.sum().clamp_min(1e-8)), "n_points": int(x.shape[0]),
            **chroma}


def chromaticity(c: Tensor) -> Tensor:
    """``c / (r + g + b)``: ``[..., 3]`` non-negative RGB -> ``[..., 3]`` summing to 1 (grey:
    ``(1/3, 1/3, 1/3)``; black maps to 0)."""
    return c / c.sum(-1, keepdim=True).clamp_min(1e-8)


def highlight_chroma(c_max: Tensor, c_med: Tensor) -> dict:
    """Is the view-dependent light coloured like the surface (a metal) or like the light (a
    dielectric)? The dichromatic reflection model: a dielectric's specular reflection keeps the
    light's colour (Fresnel F0 = 0.04 for every channel) while its body reflection is tinted by the
    albedo; a metal's specular is tinted by its albedo (F0 = base colour) and it has no body
    reflection. With the highlight ``h_i = max(c_max_i - c_med_i, 0)`` (``[N, 3]``, the light
    added in the brightest view) and the chromaticity ``chi(c) = c / (r + g + b)``:

        chroma_gap      = sum_i w_i |chi(h_i) - chi(c_med_i)|_1 / sum_i w_i
        body_saturation = sum_i w_i |chi(c_med_i) - (1/3, 1/3, 1/3)|_1 / sum_i w_i

    weighted by the highlight's luma ``w_i = luma(h_i)`` (points without a highlight say nothing).
    Under a white light a dielectric's highlight is grey, so ``chroma_gap = body_saturation``
    (ratio 1); a metal's highlight has the body's chromaticity, ``chroma_gap = 0``. Under a
    coloured light ``L`` the dielectric's highlight is ``chi(L)`` and its body ``chi(a L)``, still
    apart unless the albedo ``a`` is grey; on a grey body (saturation ~0) the test says nothing.
    Returns ``{"chroma_gap", "body_saturation"}`` (floats; nan when no point has a highlight)."""
    h = (c_max - c_med).clamp_min(0.0)
    w = (h * h.new_tensor(LUMA)).sum(-1)
    ws = w.sum()
    if not bool(ws > 1e-12):
        return {"chroma_gap": float("nan"), "body_saturation": float("nan")}
    body = chromaticity(c_med.clamp_min(0.0))
    gap = (chromaticity(h) - body).abs().sum(-1)
    sat = (body - 1.0 / 3.0).abs().sum(-1)
    return {"chroma_gap": float((w * gap).sum() / ws), "body_saturation": float((w * sat).sum() / ws)}
