"""Evaluations during a run: sync-PSNR on training views, held-out metrics on test views."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from nepf_core.data.scene import Scene
from nepf_core.color import linear_to_srgb
from nepf_core.evaluate import SSIM_BORDER, albedo_psnr_aligned, psnr, render_view, ssim
from nepf_core.holdout_preview import write_holdout_preview
from nepf_core.model import ModelFieldQuery
from nepf_core.rays import PixelSampler, unlit_threshold
from nepf_core.render.renderer import Shading, render_rays


@dataclass
class EvalTargets:
    """Optional ground truth for held-out evaluation during fit."""

    test_scene: Scene | None = None
    gt_mesh_path: str | None = None
    gt_albedo: np.ndarray | None = None
    """``[N_test, H, W, 3]`` linear albedo of the test views (for albedo PSNR)."""
    chamfer_resolution: int = 128
    split: dict | None = None
    """When ``test_scene`` was held out of the training set: ``nepf_core.data.split.split_info``
    (written to ``report.json``)."""
    stride: int | None = None
    """Render every N-th pixel of these views at least (the larger of it and ``train.eval_stride``
    applies; None: the config's alone)."""


def sync_psnr(model, sampler: PixelSampler, cfg, views: list[int], n_rays: int, seed: int,
              shading: Shading | None = None) -> dict:
    """PSNR (sRGB) of L_r, L_surf and L_vol against the images on fixed pixels of ``views``.

    L_surf is composited as L_vol is: ``w L_surf + (1 - w) C_bg`` with ``w`` the ray's opacity
    (``weight_sum`` clipped to [0, 1]) and ``C_bg`` the background volume's colour (black without
    one). Why: without masks most sampled pixels show the wall behind the object, which no
    surface point explains; scored bare, L_surf sat at ~6 dB on the fox for a whole run while
    L_r and L_vol reached ~20. With masks only foreground pixels count."""
    g = torch.Generator().manual_seed(seed)
    rays = sampler.sample(n_rays, generator=g, views=torch.tensor(views))
    outs = {"r": [], "surf": [], "vol": []}
    was = model.training
    model.eval()
    for a in range(0, len(rays), 1024):
        rb = rays.slice(a, a + 1024)
        o = render_rays(model, rb, cfg.render, train=False, shading=shading)
        opacity = o.weight_sum.clamp(0, 1)[:, None]
        surf = o.rgb_surf * opacity if o.background is None else o.rgb_surf * opacity + (1 - opacity) * o.background
        outs["r"].append(o.rgb_r.detach())
        outs["surf"].append(surf.detach())
        outs["vol"].append(o.rgb_vol.detach())
    model.train(was)
    gt = linear_to_srgb(rays.rgb).cpu().numpy()
    m = None if rays.mask is None else rays.mask.cpu().numpy() > 0.5
    res = {}
    for k, v in outs.items():
        pred = linear_to_srgb(torch.cat(v)).cpu().numpy()
        res[f"psnr_{k}"] = psnr(pred, gt, m)
    return res


def mean_ssim(pred: np.ndarray, gt: np.ndarray, masks: np.ndarray | None) -> dict:
    """``{"test_ssim_full", "test_ssim"}`` of ``pred, gt [N, H, W, 3]`` sRGB in [0, 1]: the mean
    over views of :func:`nepf_core.evaluate.ssim`, full-image, and with ``masks [N, H, W]`` over
    each view's foreground (views with no foreground pixel left out); without masks
    ``test_ssim`` is the full-image value, as ``test_psnr`` is. Empty for images smaller than
    SSIM's 11-pixel Gaussian window."""
    if min(gt.shape[1:3]) < 2 * SSIM_BORDER + 1:
        return {}
    full = float(np.mean([ssim(pred[i], gt[i]) for i in range(len(gt))]))
    if masks is None:
        return {"test_ssim_full": full, "test_ssim": full}
    fg = [ssim(pred[i], gt[i], masks[i] > 0.5) for i in range(len(gt))]
    fg = [v for v in fg if v == v]
    return {"test_ssim_full": full, "test_ssim": float(np.mean(fg)) if fg else float("nan")}


def evaluate_test(model, cfg, targets: EvalTargets, device, world_from_norm: np.ndarray,
                  stride: int, with_chamfer: bool, shading: Shading | None = None, preview_dir=None) -> dict:
    """Held-out metrics: masked/full PBR PSNR and SSIM, aligned albedo PSNR, Chamfer (when given).

    ``test_psnr`` / ``test_psnr_full`` score the surface PBR colour (the method's relightable
    output); ``test_psnr_radiance`` / ``test_psnr_radiance_full`` score the outgoing-radiance
    network's volume-rendered colour ``sum_i w_i c_r(x_i, v)`` on the same pixels (the quantity a
    plain NeuS reports, so NePF can be compared with one). ``test_ssim`` / ``test_ssim_full``:
    the PBR colour's SSIM, the same way (:func:`mean_ssim`); ``test_views``: how many views.

    ``albedo_psnr`` is over every foreground pixel; ``albedo_psnr_lit`` only over foreground
    pixels whose test image is lit (``max_c L_gt >= unlit_rel_threshold * q99``, the training
    rule), with ``lit_fraction`` their share of the foreground. ``shading``: the run state's.
    ``preview_dir``: a run folder; view 0's render | ground truth | error picture is written there
    (:func:`nepf_core.holdout_preview.write_holdout_preview`) and named in ``preview``.
    """
    ts = targets.test_scene
    sampler = PixelSampler(ts, device)
    preds, rads, albs = [], [], []
    for k in range(ts.n_views):
        r = render_view(model, sampler, k, cfg.render, stride=stride, shading=shading)
        preds.append(r["pbr"]); rads.append(r["radiance"]); albs.append(r["albedo"])
    gt = ts.images[:, ::stride, ::stride]
    gt_srgb = linear_to_srgb(gt)
    m = None if ts.masks is None else ts.masks[:, ::stride, ::stride]
    rec = {"test_views": ts.n_views}
    for key, colour in (("test_psnr", preds), ("test_psnr_radiance", rads)):
        c = linear_to_srgb(np.stack(colour))
        rec[key + "_full"] = psnr(c, gt_srgb)
        rec[key] = rec[key + "_full"] if m is None else psnr(c, gt_srgb, m)
        if key == "test_psnr":
            rec.update(mean_ssim(c, gt_srgb, m))
            if preview_dir is not None:
                rec["preview"] = write_holdout_preview(preview_dir, c[0], gt_srgb[0])
    if targets.gt_albedo is not None and ts.masks is not None:
        ga = targets.gt_albedo[:, ::stride, ::stride]
        alb = np.stack(albs)
        rec["albedo_psnr"], _ = albedo_psnr_aligned(alb, ga, m)
        # the same metric on the observable pixels only: a pixel the light never reaches carries
        # no albedo information in any view (fixed light), so there any albedo fits the images
        lit = (m > 0.5) & (gt.max(-1) >= unlit_threshold(ts.images, ts.masks, cfg.train.unlit_rel_threshold))
        if lit.any():
            rec["albedo_psnr_lit"], _ = albedo_psnr_aligned(alb, ga, lit)
            rec["lit_fraction"] = float(lit.sum() / max((m > 0.5).sum(), 1))
    if with_chamfer and targets.gt_mesh_path:
        from nepf_core.meshing import chamfer_against_gt
        try:
            cd_world, cd_unit = chamfer_against_gt(ModelFieldQuery(model), world_from_norm, targets.gt_mesh_path,
                                                   resolution=targets.chamfer_resolution)
            rec["chamfer"] = cd_unit
            rec["chamfer_world"] = cd_world
        except ValueError as e:  # no surface yet
            rec["chamfer_error"] = str(e)
    return rec
