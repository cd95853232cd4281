"""Held-out albedo PSNR over every foreground pixel and over the lit (observable) ones only."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

import nepf_core.train.evaluation as evalmod
from nepf_core.config import tiny
from nepf_core.train import EvalTargets, evaluate_test


def test_lit_albedo_psnr_ignores_pixels_the_light_never_reaches(monkeypatch):
    H = W = 8
    rng = np.random.default_rng(0)
    gt_alb = rng.uniform(0.2, 0.9, (1, H, W, 3)).astype(np.float32)
    mask = np.ones((1, H, W), bool)
    mask[:, 0] = False                                   # one background row
    img = np.full((1, H, W, 3), 0.5, np.float32)
    img[:, :, : W // 2] = 0.0                            # the left half is in shadow
    pred = gt_alb.copy()
    pred[:, :, : W // 2] = 0.05                          # wrong albedo where nothing is observable
    test = SimpleNamespace(images=img, masks=mask, n_views=1)

    monkeypatch.setattr(evalmod, "PixelSampler", lambda scene, device: None)
    monkeypatch.setattr(evalmod, "render_view",
                        lambda model, sampler, k, rcfg, stride, shading: {"pbr": img[k], "radiance": img[k],
                                                                 "albedo": pred[k]})
    rec = evaluate_test(None, tiny(), EvalTargets(test_scene=test, gt_albedo=gt_alb), "cpu", np.eye(4),
                        stride=1, with_chamfer=False)

    lit = mask.copy()
    lit[:, :, : W // 2] = False
    assert rec["lit_fraction"] == lit.sum() / mask.sum()
    # the metric written out: per-channel least-squares scale s_c = sum g p / sum p^2 over the
    # foreground, then the PSNR of srgb(clip(s p)) against srgb(g) there
    p, g = pred[mask].astype(np.float64), gt_alb[mask].astype(np.float64)
    s = (p * g).sum(0) / (p * p).sum(0)

    def srgb(x):
        x = np.clip(x, 0.0, 1.0)
        return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.maximum(x, 0.0031308) ** (1 / 2.4) - 0.055)
    want = -10.0 * np.log10(np.mean((srgb(s * p) - srgb(g)) ** 2))
    assert rec["albedo_psnr"] == pytest.approx(want, abs=1e-6)
    # exact on the lit pixels: the only error left there is the sRGB rounding of float32
    assert rec["albedo_psnr_lit"] > 60.0 and rec["albedo_psnr"] < 25.0
