"""What a run is built from: the device, the optimiser, the radiance start, unlit pixels."""

from __future__ import annotations

import numpy as np
import torch

from nepf_core.fields.grid_encoding import MultiResGrid

from nepf_core.data.scene import Scene
from nepf_core.model import NePFModel
from nepf_core.rays import foreground_peaks, unlit_threshold
from nepf_core.train.decisions import Decision
from nepf_core.train.result import FitError


def resolve_device(device: str) -> torch.device:
    """``auto`` -> CUDA when available, else CPU; ``cuda`` without a GPU is a clear error."""
    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise FitError("--device cuda was requested but no CUDA device is available")
    return torch.device(device)


def param_groups(model: NePFModel, lr: float, lr_grid: float) -> list[dict]:
    """Two groups: grid-encoding tables (``lr_grid``) and everything else (``lr``); each keeps its
    ``base_lr`` for the schedule."""
    tables = {id(m.table) for m in model.modules() if isinstance(m, MultiResGrid)}
    scaled = [m for m in model.modules() if getattr(m, "lr_scale", None)]
    own = {id(p) for m in scaled for p in m.parameters(recurse=False)}
    grid, other = [], []
    for p in model.parameters():
        if id(p) not in own:
            (grid if id(p) in tables else other).append(p)
    groups = [{"params": other, "lr": lr, "base_lr": lr}]
    if grid:
        groups.append({"params": grid, "lr": lr_grid, "base_lr": lr_grid})
    for m in scaled:   # a module that names an lr_scale (global emitters) learns at that times lr
        groups.append({"params": list(m.parameters(recurse=False)), "lr": lr * m.lr_scale,
                       "base_lr": lr * m.lr_scale})
    return groups


def make_optimizer(model: NePFModel, lr: float, lr_grid: float) -> torch.optim.Adam:
    """Adam with ``betas = (0.9, 0.99)``, ``eps = 1e-15``, fused where the build supports it.

    The paper gives only the learning rate; these are the instant-NGP settings (Mueller et al.
    2022) for grid encodings, used for every preset. Why: a grid cell gets a gradient only from
    the rays that cross it, so its gradients are sparse and often tiny. ``eps = 1e-15`` keeps the
    step ``m / (sqrt(v) + eps)`` normalised for such parameters, where torch's default 1e-8 would
    exceed ``sqrt(v)`` and shrink their steps to nearly nothing; ``beta2 = 0.99`` (instead of
    0.999) lets ``v`` follow a gradient scale that changes within ~100 steps (cells entering and
    leaving the occupied band, the NeuS sharpness ``inv_s`` growing by orders of magnitude).
    ``fused=True`` updates all tensors in one kernel (several times faster than the per-tensor
    loop for millions of grid values, same update rule); builds without it use the loop."""
    groups = param_groups(model, lr, lr_grid)
    try:
        return torch.optim.Adam(groups, betas=(0.9, 0.99), eps=1e-15, fused=True)
    except (RuntimeError, TypeError):
        return torch.optim.Adam(param_groups(model, lr, lr_grid), betas=(0.9, 0.99), eps=1e-15)


def init_radiance_to_data(model: NePFModel, scene: Scene) -> None:
    """Start the radiance network at the mean foreground colour (linear; all pixels without
    masks) by setting its last bias to the logit of it.

    With masks a ray's colour is ``sum_i w_i c_i`` (no background), so from the default grey
    start (sigmoid(0) = 0.5) on a dark or near-mirror scene the cheapest way down the colour
    loss is to make the object transparent, and the surface vanishes (docs/STABILITY.md). A
    resumed run overwrites this with its checkpoint.
    """
    last = model.radiance.mlp.layers[-1]
    total, count = np.zeros(3), 0
    for k in range(scene.n_views):  # per view: no copy of the whole image set
        px = scene.images[k][scene.masks[k] > 0.5] if scene.masks is not None else scene.images[k].reshape(-1, 3)
        total += px.sum(0, dtype=np.float64)
        count += len(px)
    if count == 0:
        return
    p = torch.as_tensor(total / count, dtype=torch.float32).clamp(1e-3, 0.999)
    with torch.no_grad():
        last.bias.copy_(torch.log(p / (1.0 - p)).to(last.bias))


def place_lights(model: NePFModel, scene: Scene) -> None:
    """Start global emitters at the scene's camera centres
    (:meth:`nepf_core.fields.emitters.TracedEmitters.place`) and at the irradiance the images ask
    for: ``E0 = pi q99(max_c L_gt) / EMITTER_START_ALBEDO`` at the origin, so the brightest
    foreground pixels need that albedo under head-on light. The photon network needs no placing.
    A resumed run overwrites this with its checkpoint.

    Why from the data: the images fix only albedo x irradiance. The photon network's ``I(x)`` is
    free per point and climbs where a surface needs more light; a global emitter started too dim
    sends every albedo into the top of its sigmoid in the first steps, and from there the texture
    cannot come back (spot_textured at 1,000 steps: albedo 0.94 on its black spots, v56)."""
    place = getattr(model.photon, "place", None)
    if place is None:
        return
    place(torch.as_tensor(np.asarray(scene.c2w)[:, :3, 3], dtype=torch.float32))
    peaks = foreground_peaks(scene.images, scene.masks)
    step = max(1, peaks.size // 2_000_000)  # a subsample is plenty for a quantile
    q99 = float(np.quantile(peaks[::step], 0.99)) if peaks.size else 0.0
    model.photon.set_init_intensity(float(np.pi * max(q99, 1e-3) / EMITTER_START_ALBEDO))


EMITTER_START_ALBEDO = 0.5
"""The albedo the brightest foreground pixels need under the emitters' starting light."""


def unlit_pixels(scene: Scene, stopgrad: bool, rel_threshold: float) -> tuple[float | None, Decision | None]:
    """``(threshold, decision)`` for ``render.unlit_albedo_stopgrad`` (``stopgrad``): a training
    pixel is unlit when ``max_c L_gt < rel_threshold * q99`` (:func:`nepf_core.rays.unlit_threshold`);
    ``(None, None)`` when the switch is off."""
    if not stopgrad:
        return None, None
    thr = unlit_threshold(scene.images, scene.masks, rel_threshold)
    fg = foreground_peaks(scene.images, scene.masks)
    frac = float((fg < thr).mean()) if fg.size else 0.0
    return thr, Decision("unlit_albedo_stopgrad", {"threshold_linear": thr, "unlit_fraction": round(frac, 4)},
                         f"{100 * frac:.1f}% of the {'foreground ' if scene.masks is not None else ''}training pixels "
                         f"are unlit (max channel < {thr:.2e}, {rel_threshold} of the 99th "
                         "percentile): their colour error trains light and geometry, not the albedo")
