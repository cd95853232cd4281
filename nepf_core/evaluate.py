"""Rendering whole views and the error metrics (PSNR, SSIM, Chamfer, aligned albedo PSNR).

Conventions (stated wherever the numbers are reported):
* Image PSNR / SSIM compare sRGB-encoded values in [0, 1] (what the PNGs on disk hold).
  "masked" uses only ground-truth foreground pixels; "full" uses every pixel.
* Albedo PSNR: per-channel least-squares scale ``s_c = sum(gt_c p_c) / sum(p_c^2)`` over
  foreground pixels in linear space (albedo and light intensity share a scale), then
  PSNR of ``srgb(clip(s p))`` against ``srgb(gt)`` on the foreground.
* Chamfer: ``(mean_a min_b |a-b| + mean_b min_a |a-b|) / 2`` with area-uniform surface
  samples (100k per mesh by default), in world units and divided by the scene's
  world scale for unit-sphere units.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from nepf_core.bsdf import diffuse_only_material
from nepf_core.rays import PixelSampler
from nepf_core.render.renderer import RenderConfig, render_rays

CHANNELS = ("pbr", "radiance", "albedo", "roughness", "metallic", "normal", "light_dir",
            "light_intensity", "alpha", "depth")


def srgb_np(x: np.ndarray) -> np.ndarray:
    """sRGB OETF for numpy arrays (clamped to [0, 1])."""
    x = np.clip(x, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(np.maximum(x, 0.0031308), 1 / 2.4) - 0.055)


def render_view(model, sampler: PixelSampler, k: int, cfg: RenderConfig, *, stride: int = 1,
                chunk: int = 2048, rotation: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """Render every channel of view ``k``: dict of ``[H', W', C]`` float32 arrays.

    ``pbr`` is the surface PBR at the max-weight sample composited by the opacity
    ``alpha = sum w`` (over the background model when there is one). Normals and light
    directions are rotated by ``rotation`` (3x3, normalised -> world) when given.
    """
    rays = sampler.view_rays(k, stride)
    H = len(range(0, sampler.height, stride))
    W = len(range(0, sampler.width, stride))
    acc: dict[str, list] = {c: [] for c in CHANNELS}
    was_training = model.training
    model.eval()
    for a in range(0, len(rays), chunk):
        rb = rays.slice(a, a + chunk)
        out = render_rays(model, rb, cfg, train=False)
        with torch.no_grad():
            alpha = out.weight_sum.clamp(0, 1)[:, None]
            pbr = out.rgb_surf * alpha
            if getattr(model, "background", None) is not None:
                pbr = pbr + (1 - alpha) * model.background(rb.directions)
            s = out.surf
            albedo, metal = s["albedo"], s["metallic"]
            if not cfg.specular:  # lobe dropped: shaded as a dielectric diffuse (metallic 0)
                albedo, metal = diffuse_only_material(albedo, metal, cfg.diffuse_metal_weight)
            vals = {"pbr": pbr, "radiance": out.rgb_r, "albedo": albedo, "roughness": s["roughness"][:, None],
                    "metallic": metal[:, None], "normal": s["normal"], "light_dir": s["light_dir"],
                    "light_intensity": s["intensity"][:, None], "alpha": alpha, "depth": out.depth[:, None]}
            for c in CHANNELS:
                acc[c].append(vals[c].detach().float().cpu())
    model.train(was_training)
    res = {c: torch.cat(v).reshape(H, W, -1).numpy() for c, v in acc.items()}
    if rotation is not None:
        for c in ("normal", "light_dir"):
            res[c] = (res[c] @ rotation.T).astype(np.float32)
    return res


def psnr(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray | None = None) -> float:
    """``-10 log10(MSE)`` over pixels (``mask`` [H,W] bool selects them); inf-safe (MSE >= 1e-10)."""
    err = (pred.astype(np.float64) - gt.astype(np.float64)) ** 2
    if mask is not None:
        if mask.sum() == 0:
            return float("nan")
        err = err[mask]
    return float(-10.0 * math.log10(max(float(err.mean()), 1e-10)))


def ssim(pred: np.ndarray, gt: np.ndarray) -> float:
    """SSIM of two ``[H, W, 3]`` images in [0, 1] (scikit-image, Gaussian window)."""
    from skimage.metrics import structural_similarity
    return float(structural_similarity(pred, gt, channel_axis=-1, data_range=1.0, gaussian_weights=True,
                                       sigma=1.5, use_sample_covariance=False))


def albedo_psnr_aligned(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray) -> tuple[float, np.ndarray]:
    """Per-channel least-squares scale alignment, then sRGB PSNR on the foreground.

    ``pred, gt [N, H, W, 3]`` linear; ``mask [N, H, W]`` bool. Returns ``(psnr, scale [3])``.
    """
    p = pred[mask].astype(np.float64)
    g = gt[mask].astype(np.float64)
    scale = (p * g).sum(0) / np.maximum((p * p).sum(0), 1e-12)
    aligned = np.clip(pred * scale, 0, 1)
    return psnr(srgb_np(aligned)[mask], srgb_np(gt)[mask]), scale


def chamfer_distance(mesh_a, mesh_b, n_samples: int = 100_000, seed: int = 0) -> float:
    """Symmetric mean Chamfer distance between two trimesh meshes (same units as vertices)."""
    import trimesh
    from scipy.spatial import cKDTree
    pa = trimesh.sample.sample_surface(mesh_a, n_samples, seed=seed)[0]
    pb = trimesh.sample.sample_surface(mesh_b, n_samples, seed=seed + 1)[0]
    da = cKDTree(pb).query(pa, workers=-1)[0]
    db = cKDTree(pa).query(pb, workers=-1)[0]
    return float(0.5 * (da.mean() + db.mean()))
