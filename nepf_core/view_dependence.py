"""How much the learned outgoing radiance changes with the viewing direction.

The radiance network ``L_r(x, v)`` fits the training views directly (it is the best-fitted
field of the four). On a Lambertian surface under fixed lights, the light leaving a point is
the same in every direction, so ``L_r(x, .)`` is flat across the directions the cameras saw
it from; a specular highlight shows up as some views of a point being brighter than its
typical view. :func:`radiance_view_spread` measures that excess at surface points;
:mod:`nepf_core.train.rules.specular` drops the GGX lobe when it stays small (the lobe can
only add view-dependent light, so a scene whose radiance has none does not need it, and a lobe
fitted anyway overfits the training views, docs/FAST.md).
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
    than a deviation, because a highlight lifts a few views of a point, not all of them, so it
    separates glossy from diffuse scenes more widely. Deterministic: every facing camera is used
    (evenly subsampled to ``max_cams``). Points facing fewer than two cameras are left out.

    Args:
        model: :class:`nepf_core.model.NePFModel` (``sdf``, ``radiance``).
        x: ``[N, 3]`` surface points; cam_centers: ``[C, 3]`` camera centres (normalised frame).
    Returns:
        ``{"spread": float (nan if no point qualifies), "n_points": int}``.
    """
    nan = {"spread": float("nan"), "n_points": 0}
    if x.shape[0] == 0 or cam_centers.shape[0] < 2:
        return nan
    from nepf_core.fields.fd_normals import sdf_gradient_fd
    if cam_centers.shape[0] > max_cams:
        cam_centers = cam_centers[torch.linspace(0, cam_centers.shape[0] - 1, max_cams).round().long()]
    eps = fd_step if fd_step is not None else float(getattr(model.sdf, "fd_step", lambda: 1e-3)())
    g, _ = sdf_gradient_fd(model.sdf.sdf, x, max(eps, 1e-4), scheme="central", center="mean")
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
    ymax = y.masked_fill(~facing, float("-inf")).max(-1).values
    ymed = y.nanmedian(-1).values
    ymean = y.nansum(-1) / facing.sum(-1)
    return {"spread": float((ymax - ymed).sum() / ymean.sum().clamp_min(1e-8)), "n_points": int(x.shape[0])}
