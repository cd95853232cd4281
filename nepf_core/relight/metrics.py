"""Relighting and material scores against ground truth (``nepf eval --relight --gt-maps``).

* **relight PSNR**: one scale per colour channel (albedo and light intensity share a scale, as
  in TensoIR), fitted on the *displayed* range (:func:`displayed_range_scale`) over all lights,
  views and pixels with GT alpha > 0.5; then ``PSNR(srgb(clip(s p, 0, 1)), srgb(clip(g, 0, 1)))``
  over the same pixels (all three channels of each).
* **albedo PSNR**: a per-channel least-squares alignment (:func:`nepf_core.evaluate.channel_scale`; an albedo has no
  highlights, so nothing saturates) and PSNR on the albedo maps
  (:func:`nepf_core.evaluate.albedo_psnr_aligned`), over the GT foreground and over its lit
  pixels (those of the test image with ``max_c L >= rel * q99``, the training rule
  :func:`nepf_core.rays.unlit_threshold`).
* **roughness / metallic MAE**: ``mean |p - g|`` over the GT foreground.
* **normal MAE**: ``mean acos(clip(n_p . n_g, -1, 1))`` in degrees over the GT foreground, both
  normals unit (world frame).
"""

from __future__ import annotations

import math

import numpy as np

from nepf_core.color import linear_to_srgb
from nepf_core.evaluate import albedo_psnr_aligned, channel_scale, psnr

FOREGROUND_ALPHA = 0.5
"""A pixel is foreground when the GT alpha exceeds this."""


def displayed_range_scale(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray, rounds: int = 5) -> np.ndarray:
    """Per-channel scale fitted on what a display shows: ``pred, gt [..., 3]`` linear, ``mask
    [...]`` bool -> ``[3]``.

        s_c = sum_{i in K_c} clip(g_ic, 0, 1) p_ic / sum_{i in K_c} p_ic^2,
        K_c = {i in mask : not (s_c p_ic >= 1 and g_ic >= 1)}

    starting from all of ``mask`` and repeated ``rounds`` times (the scale moves which values
    saturate). Why: a glossy highlight reaches 100-1000x white in linear units; an unclipped
    least-squares fit is then decided by those few values (a lobe shaded at the pixel centre
    against a ground truth that averages it over the pixel gave half the right scale), while the
    PSNR compares the clipped images, where a value saturated on both sides agrees whatever the
    scale."""
    p = pred[mask].astype(np.float64)
    g = gt[mask].astype(np.float64)
    g_shown = np.clip(g, 0.0, 1.0)
    keep = np.ones_like(p, dtype=bool)
    s = np.ones(p.shape[-1])
    for _ in range(max(1, rounds)):
        den = np.where(keep, p * p, 0.0).sum(0)
        s = np.where(den > 1e-12, np.where(keep, p * g_shown, 0.0).sum(0) / np.maximum(den, 1e-12), 1.0)
        new_keep = ~((p * s >= 1.0) & (g >= 1.0))
        if np.array_equal(new_keep, keep):
            break
        keep = new_keep
    return s


def relight_psnr(pred: np.ndarray, gt: np.ndarray, gt_alpha: np.ndarray) -> tuple[float, np.ndarray]:
    """Relight PSNR (module docstring): ``pred, gt [K, V, H, W, 3]`` linear, ``gt_alpha [V, H, W]``.
    Returns ``(psnr_db, scale [3])``."""
    if pred.shape != gt.shape:
        raise ValueError(f"relit images {tuple(pred.shape)} and ground truth {tuple(gt.shape)} differ in shape "
                         "(lights, views or resolution)")
    mask = np.broadcast_to(gt_alpha > FOREGROUND_ALPHA, pred.shape[:-1])
    s = displayed_range_scale(pred, gt, mask)
    a = linear_to_srgb(np.clip(pred.astype(np.float64) * s, 0.0, 1.0))
    return psnr(a[mask], linear_to_srgb(gt.astype(np.float64))[mask]), s


def mae(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray) -> float:
    """``mean |p - g|`` over ``mask`` (NaN when empty)."""
    if not mask.any():
        return float("nan")
    return float(np.abs(pred.astype(np.float64) - gt.astype(np.float64))[mask].mean())


def normal_mae_deg(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray) -> float:
    """Mean angle (degrees) between unit normals ``[..., 3]`` over ``mask`` (each normalised first)."""
    if not mask.any():
        return float("nan")
    p = pred[mask].astype(np.float64)
    g = gt[mask].astype(np.float64)
    p /= np.maximum(np.linalg.norm(p, axis=-1, keepdims=True), 1e-12)
    g /= np.maximum(np.linalg.norm(g, axis=-1, keepdims=True), 1e-12)
    return float(np.degrees(np.arccos(np.clip((p * g).sum(-1), -1.0, 1.0))).mean())


def _scalar_map(a: np.ndarray) -> np.ndarray:
    return a[..., 0] if a.ndim == 4 else a


def material_metrics(pred: dict, gt: dict, lit: np.ndarray | None = None) -> dict:
    """Material and normal scores of predicted maps against GT maps.

    ``pred``: ``albedo [V, H, W, 3]``, ``roughness``, ``metallic`` (``[V, H, W]`` or ``[V, H, W, 1]``),
    ``normal [V, H, W, 3]`` (world); ``gt``: the same keys with ``normal_world`` and ``alpha [V, H, W]``
    (``gt/arrays_test.npz``); ``lit [V, H, W]`` bool (optional): the lit pixels.
    Returns ``albedo_psnr``, ``albedo_scale`` (list), ``albedo_psnr_lit`` (when ``lit`` is given and
    has foreground pixels), ``roughness_mae``, ``metallic_mae``, ``normal_mae_deg``.
    """
    fg = np.asarray(gt["alpha"]) > FOREGROUND_ALPHA
    if pred["albedo"].shape != gt["albedo"].shape:
        raise ValueError(f"predicted maps {tuple(pred['albedo'].shape)} and ground-truth maps "
                         f"{tuple(gt['albedo'].shape)} differ in shape (views or resolution)")
    res: dict = {}
    p_alb, g_alb = pred["albedo"].astype(np.float64), gt["albedo"].astype(np.float64)
    res["albedo_psnr"], scale = albedo_psnr_aligned(p_alb, g_alb, fg)
    res["albedo_scale"] = [float(c) for c in scale]
    if lit is not None and (fg & lit).any():
        res["albedo_psnr_lit"], _ = albedo_psnr_aligned(p_alb, g_alb, fg & lit)
    res["roughness_mae"] = mae(_scalar_map(pred["roughness"]), _scalar_map(gt["roughness"]), fg)
    res["metallic_mae"] = mae(_scalar_map(pred["metallic"]), _scalar_map(gt["metallic"]), fg)
    res["normal_mae_deg"] = normal_mae_deg(pred["normal"], gt["normal_world"], fg)
    return {k: (v if isinstance(v, list) or not isinstance(v, float) or math.isfinite(v) else None)
            for k, v in res.items()}
