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


def displayed_range_scale(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Per-channel scale that minimises the error a display shows: ``pred, gt [..., 3]`` linear,
    ``mask [...]`` bool -> ``[3]``, per channel ``c`` over the masked values ``p_i >= 0, g_i``:

        s_c = argmin_{s >= 0} E(s),   E(s) = sum_i (min(s p_i, 1) - min(g_i, 1))^2

    Why: the PSNR compares clipped images, and a highlight reaches 100-1000x white in linear
    units. An unclipped least-squares fit is decided by those few values, on either side: a GT
    lobe averaged over the pixel against a predicted lobe shaded at its centre halves the scale,
    and a handful of predicted near-mirror highlights (a few pixels in 10^4 over 10x white) took
    the scale to 0.002 and the relight of a whole scene down by 4.5 dB (bench/RESULTS.md v34).
    Clipped, a pixel the scaled prediction saturates costs ``(1 - min(g, 1))^2`` whatever the
    scale. Exact: ``E`` is quadratic between the breakpoints ``s = 1 / p_i`` (where ``p_i``
    saturates); with the breakpoints sorted, the unsaturated pixels of each interval are a suffix,
    so suffix sums give each interval's minimiser ``sum p g / sum p^2`` clamped to it and its cost
    (``O(N log N)``). A channel whose prediction is all 0 gets ``s = 1``."""
    p = np.clip(pred[mask].astype(np.float64), 0.0, None)
    g = np.clip(gt[mask].astype(np.float64), 0.0, 1.0)
    return np.array([_best_clipped_scale(p[:, c], g[:, c]) for c in range(p.shape[-1])])


def _best_clipped_scale(p: np.ndarray, g: np.ndarray) -> float:
    """:func:`displayed_range_scale` for one channel, ``p >= 0`` and ``g in [0, 1]``, ``[N]``."""
    lit = p > 0
    if not lit.any():
        return 1.0
    p, g = p[lit], g[lit]                                     # p = 0 shows 0 at any scale: a constant cost
    t = 1.0 / p                                               # saturation breakpoints
    order = np.argsort(t)
    p, g, t = p[order], g[order], t[order]
    sat = np.concatenate([[0.0], np.cumsum((1.0 - g) ** 2)])  # cost of the first k saturated
    pp = np.concatenate([np.cumsum((p * p)[::-1])[::-1], [0.0]])   # suffix sums: unsaturated
    pg = np.concatenate([np.cumsum((p * g)[::-1])[::-1], [0.0]])
    gg = np.concatenate([np.cumsum((g * g)[::-1])[::-1], [0.0]])
    lo = np.concatenate([[0.0], t])                           # interval k: k values saturated
    hi = np.concatenate([t, [np.inf]])
    s = np.clip(np.where(pp > 0, pg / np.where(pp > 0, pp, 1.0), lo), lo, hi)
    cost = sat + pp * s * s - 2.0 * pg * s + gg
    return float(s[int(np.argmin(cost))])


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
