"""Rendering whole views and the error metrics (PSNR, SSIM, Chamfer, aligned albedo PSNR).

Conventions (stated wherever the numbers are reported):
* Image PSNR / SSIM compare sRGB-encoded values in [0, 1] (what the PNGs on disk hold).
  "masked" uses only ground-truth foreground pixels; "full" uses every pixel.
* Albedo PSNR: per-channel least-squares scale ``s_c = sum(gt_c p_c) / sum(p_c^2)`` over
  foreground pixels in linear space (albedo and light intensity share a scale), then
  PSNR of ``srgb(clip(s p))`` against ``srgb(gt)`` on the foreground.
* SSIM: scikit-image's (Gaussian window, sigma 1.5); "masked" is the mean of the SSIM map
  over foreground pixels (the images themselves are not masked), see :func:`ssim`.
* Chamfer: point-to-mesh, :func:`nepf_core.meshing.chamfer_distance`.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from nepf_core.bsdf import diffuse_only_material
from nepf_core.color import linear_to_srgb
from nepf_core.rays import PixelSampler, RayBatch
from nepf_core.render.antialias import PIXEL_SUBSAMPLES, silhouette_subpixel_rays
from nepf_core.render.renderer import RenderConfig, Shading, render_rays

CHANNELS = ("pbr", "radiance", "albedo", "roughness", "metallic", "normal", "light_dir",
            "light_intensity", "alpha", "depth")
COMPOSITED = ("pbr", "radiance", "alpha")
"""The channels that are coverage-weighted sums over a ray (``alpha L``, ``alpha``): a silhouette
pixel's value is their mean over its sub-pixel rays (:mod:`nepf_core.render.antialias`)."""


def render_view(model, sampler: PixelSampler, k: int, cfg: RenderConfig, *, stride: int = 1,
                chunk: int = 2048, rotation: np.ndarray | None = None,
                shading: Shading | None = None, subsamples: int = PIXEL_SUBSAMPLES) -> dict[str, np.ndarray]:
    """Render every channel of view ``k``: dict of ``[H', W', C]`` float32 arrays.

    ``pbr`` is the surface PBR at the max-weight sample composited by the opacity
    ``alpha = sum w`` (over the background model when there is one). Normals and light
    directions are rotated by ``rotation`` (3x3, normalised -> world) when given. ``shading``:
    the run's shading model (``RunState.shading()``; None: ``cfg.specular``, no fade).
    The :data:`COMPOSITED` channels of silhouette pixels are the mean over ``subsamples x
    subsamples`` rays in them (:mod:`nepf_core.render.antialias`; 1: every pixel its centre ray).
    """
    shading = shading if shading is not None else Shading(specular=cfg.specular)
    H = len(range(0, sampler.height, stride))
    W = len(range(0, sampler.width, stride))
    was_training = model.training
    model.eval()
    res = _render_channels(model, sampler.view_rays(k, stride), cfg, shading, chunk)
    res = {c: v.reshape(H, W, -1) for c, v in res.items()}
    edge, subrays = silhouette_subpixel_rays(sampler, k, res["alpha"][..., 0], subsamples, stride)
    if subrays:
        sums = {c: 0.0 for c in COMPOSITED}
        for rays in subrays:
            sub = _render_channels(model, rays, cfg, shading, chunk)
            sums = {c: sums[c] + sub[c] for c in COMPOSITED}
        for c in COMPOSITED:
            res[c][edge] = sums[c] / len(subrays)
    model.train(was_training)
    res = {c: v.numpy() for c, v in res.items()}
    if rotation is not None:
        for c in ("normal", "light_dir"):
            res[c] = (res[c] @ rotation.T).astype(np.float32)
    return res


def _render_channels(model, rays: RayBatch, cfg: RenderConfig, shading: Shading,
                     chunk: int) -> dict[str, torch.Tensor]:
    """Every channel of :data:`CHANNELS` of ``R`` rays, ``chunk`` at a time: ``{c: [R, C]}`` float32 (CPU)."""
    acc: dict[str, list] = {c: [] for c in CHANNELS}
    for a in range(0, len(rays), chunk):
        rb = rays.slice(a, a + chunk)
        out = render_rays(model, rb, cfg, train=False, shading=shading)
        with torch.no_grad():
            alpha = out.weight_sum.clamp(0, 1)[:, None]
            pbr = out.rgb_surf * alpha
            if out.background is not None:
                pbr = pbr + (1 - alpha) * out.background
            s = out.surface
            albedo, rough, metal = s.albedo, s.roughness, s.metallic
            if not shading.specular:  # lobe dropped: shaded as a dielectric diffuse (metallic 0, roughness 1)
                albedo, rough, metal = diffuse_only_material(albedo, rough, metal, shading.diffuse_metal_weight)
            vals = {"pbr": pbr, "radiance": out.rgb_r, "albedo": albedo, "roughness": rough[:, None],
                    "metallic": metal[:, None], "normal": s.normal, "light_dir": s.light_dir,
                    "light_intensity": s.intensity[:, None], "alpha": alpha, "depth": out.depth[:, None]}
            for c in CHANNELS:
                acc[c].append(vals[c].detach().float().cpu())
    return {c: torch.cat(v) for c, v in acc.items()}


def psnr(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray | None = None) -> float:
    """``-10 log10(MSE)`` over pixels (``mask`` [H,W] bool selects them); inf-safe (MSE >= 1e-10)."""
    err = (pred.astype(np.float64) - gt.astype(np.float64)) ** 2
    if mask is not None:
        if mask.sum() == 0:
            return float("nan")
        err = err[mask]
    return float(-10.0 * math.log10(max(float(err.mean()), 1e-10)))


SSIM_SIGMA = 1.5
"""Gaussian window of SSIM (Wang et al. 2004): 11 taps, so the map's outer 5 pixels are unreliable."""
SSIM_BORDER = int(3.5 * SSIM_SIGMA + 0.5)


def ssim(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray | None = None) -> float:
    """SSIM of two ``[H, W, 3]`` images in [0, 1] (scikit-image, Gaussian window, sigma 1.5).

    The SSIM map ``S(p) = (2 mu_x mu_y + C1)(2 s_xy + C2) / ((mu_x^2 + mu_y^2 + C1)(s_x^2 + s_y^2 + C2))``
    (``C1 = 0.01^2``, ``C2 = 0.03^2``, local Gaussian-weighted moments per channel) is averaged over
    the pixels at least ``SSIM_BORDER`` from the frame edge (scikit-image's full-frame value)
    and, with ``mask [H, W]`` bool, over those of them in the mask only. The images are not
    multiplied by the mask: their shared black background would score ~1 and pull the mean up,
    the more so the smaller the object. NaN when no pixel is left.
    """
    from skimage.metrics import structural_similarity
    kw = dict(channel_axis=-1, data_range=1.0, gaussian_weights=True, sigma=SSIM_SIGMA,
              use_sample_covariance=False)
    if mask is None:
        return float(structural_similarity(pred, gt, **kw))
    _, smap = structural_similarity(pred, gt, full=True, **kw)  # [H, W, 3]
    b = SSIM_BORDER
    inner = np.zeros(mask.shape, dtype=bool)
    inner[b:mask.shape[0] - b, b:mask.shape[1] - b] = True
    sel = mask.astype(bool) & inner
    if not sel.any():
        return float("nan")
    return float(smap[sel].mean())


def channel_scale(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Per-channel least-squares scale ``s_c = argmin_s sum_i (s p_ic - g_ic)^2 = sum_i g_ic p_ic /
    sum_i p_ic^2`` over ``mask``: ``pred, gt [..., 3]``, ``mask [...]`` bool -> ``[3]`` float64.

    A channel with no signal (``sum p^2 <= 1e-12``) gets 1: any scale fits it equally (``s p = 0``),
    and 1 leaves the prediction as it is. For relit images, whose highlights saturate the
    display, :func:`nepf_core.relight.metrics.displayed_range_scale` fits on the displayed range."""
    p = pred[mask].astype(np.float64)
    g = gt[mask].astype(np.float64)
    den = (p * p).sum(0)
    return np.where(den > 1e-12, (p * g).sum(0) / np.maximum(den, 1e-12), 1.0)


def albedo_psnr_aligned(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray) -> tuple[float, np.ndarray]:
    """Per-channel least-squares scale alignment (:func:`channel_scale`; albedo and light share a
    scale), then sRGB PSNR on the foreground.

    ``pred, gt [N, H, W, 3]`` linear; ``mask [N, H, W]`` bool. Returns ``(psnr, scale [3])``.
    """
    scale = channel_scale(pred, gt, mask)
    aligned = np.clip(pred * scale, 0, 1)
    return psnr(linear_to_srgb(aligned)[mask], linear_to_srgb(gt)[mask]), scale
