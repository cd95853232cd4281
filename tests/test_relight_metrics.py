"""Relight and material scores on hand-worked values."""

from __future__ import annotations

import math

import numpy as np
import pytest

from nepf_core.evaluate import channel_scale
from nepf_core.relight.metrics import displayed_range_scale, mae, material_metrics, normal_mae_deg, relight_psnr

SRGB_HALF = 1.055 * 0.5 ** (1 / 2.4) - 0.055       # sRGB of linear 0.5 = 0.735357


def _img(*pixels):
    """K = 1, V = 1, H = 1, W = len(pixels) grey pixels -> [1, 1, 1, W, 3]."""
    return np.asarray(pixels, np.float64)[None, None, None, :, None].repeat(3, -1)


def test_relight_psnr_hand_worked():
    # GT (1, 0), prediction (1, 1): s = (1*1 + 0*1) / (1 + 1) = 1/2; aligned (0.5, 0.5) -> sRGB
    # 0.735357 against (1, 0): MSE = ((1 - 0.735357)^2 + 0.735357^2) / 2 = 0.305393 -> 5.1514 dB.
    # A third pixel with GT alpha 0.4 (background) is ignored however wrong it is.
    gt, pred = _img(1.0, 0.0, 0.0), _img(1.0, 1.0, 50.0)
    alpha = np.array([[[1.0, 1.0, 0.4]]])
    value, scale = relight_psnr(pred, gt, alpha)
    assert scale.tolist() == pytest.approx([0.5] * 3)
    mse = ((1 - SRGB_HALF) ** 2 + SRGB_HALF ** 2) / 2
    assert mse == pytest.approx(0.305393, abs=1e-6)
    assert value == pytest.approx(-10 * math.log10(mse), abs=1e-9)
    assert value == pytest.approx(5.1514, abs=1e-4)


def test_relight_scale_is_fitted_on_the_displayed_range():
    # GT (2, 0) (over-exposed, linear), prediction (1, 1): on the displayed GT (1, 0),
    # s = (1*1 + 0*1) / (1 + 1) = 1/2, and 0.5 * 1 < 1 saturates nothing, so s stays 1/2
    # (the unclipped fit would say 2/2 = 1); aligned (0.5, 0.5) -> MSE 0.305393 as above.
    value, scale = relight_psnr(_img(1.0, 1.0), _img(2.0, 0.0), np.ones((1, 1, 2)))
    assert scale.tolist() == pytest.approx([0.5] * 3)
    assert value == pytest.approx(-10 * math.log10(((1 - SRGB_HALF) ** 2 + SRGB_HALF ** 2) / 2), abs=1e-9)


def test_one_hot_pixel_does_not_decide_the_scale():
    # 99 pixels predicted 1 where GT is 0.5, and one highlight predicted 1000 where GT is 1000.
    # Unclipped least squares: s = (99*0.5 + 1000*1000) / (99 + 1000^2) = 0.99995, so the 99
    # pixels show 1.0 against 0.5. Displayed: at s = 1/2 the highlight shows min(500, 1) = 1
    # against min(1000, 1) = 1 and the 99 pixels 0.5 against 0.5: E = 0, every pixel matches,
    # 100 dB (MSE floored at 1e-10).
    gt, pred = _img(*([0.5] * 99 + [1000.0])), _img(*([1.0] * 99 + [1000.0]))
    alpha = np.ones((1, 1, 100))
    unclipped = channel_scale(pred, gt, np.ones(pred.shape[:-1], bool))
    assert unclipped[0] == pytest.approx((99 * 0.5 + 1e6) / (99 + 1e6))
    value, scale = relight_psnr(pred, gt, alpha)
    assert scale.tolist() == pytest.approx([0.5] * 3)
    assert value == pytest.approx(100.0)


def test_a_predicted_hot_pixel_does_not_decide_the_scale():
    # 99 pixels predicted 1 where GT is 0.5, and one near-mirror highlight predicted 1000 where
    # GT is 0.2 (a highlight the truth does not have). A fit on unclipped predictions against the
    # clipped GT: s = (99*0.5 + 1000*0.2) / (99 + 1000^2) = 2.495e-4 (the highlight then shows
    # 0.2495 and never saturates), so the 99 pixels show 2.5e-4 against 0.5. Displayed: for
    # s >= 1e-3 the highlight shows 1 whatever s (cost (1 - 0.2)^2 = 0.64), and the 99 pixels
    # cost 99 (s - 0.5)^2: s = 1/2, E = 0.64; below 1e-3, E > 99 * 0.499^2. PSNR: one pixel of
    # 100 wrong, 1 against srgb(0.2) = 1.055 * 0.2^(1/2.4) - 0.055 = 0.484529.
    gt, pred = _img(*([0.5] * 99 + [0.2])), _img(*([1.0] * 99 + [1000.0]))
    value, scale = relight_psnr(pred, gt, np.ones((1, 1, 100)))
    assert scale.tolist() == pytest.approx([0.5] * 3)
    srgb_02 = 1.055 * 0.2 ** (1 / 2.4) - 0.055
    assert srgb_02 == pytest.approx(0.484529, abs=1e-6)
    assert value == pytest.approx(-10 * math.log10((1 - srgb_02) ** 2 / 100), abs=1e-9)


def test_the_displayed_scale_is_the_minimum_of_the_displayed_error():
    """Against a brute-force search: no scale on a dense grid shows a smaller clipped error."""
    rng = np.random.default_rng(0)
    for trial in range(20):
        n = int(rng.integers(1, 200))
        p = rng.lognormal(-1.0, 1.5, (n, 3)) * (rng.random((n, 3)) > 0.1)     # some zeros, some hot
        g = rng.lognormal(-1.2, 1.0, (n, 3))
        s = displayed_range_scale(p, g, np.ones(n, bool))
        grid = np.concatenate([np.geomspace(1e-4, 1e4, 4001), s])
        for c in range(3):
            err = lambda k: ((np.minimum(k * p[:, c], 1.0) - np.minimum(g[:, c], 1.0)) ** 2).sum()
            best = min(err(k) for k in grid)
            assert err(s[c]) <= best + 1e-9, (trial, c)
    assert displayed_range_scale(np.zeros((4, 3)), np.ones((4, 3)), np.ones(4, bool)).tolist() == [1.0] * 3


def test_relight_scale_per_channel_over_all_lights_and_views():
    # two lights, one view, one pixel; red predicted at half, green at twice, blue exact:
    # scales 2, 1/2, 1 and a perfect score (MSE floored at 1e-10 -> 100 dB)
    gt = np.array([[0.2, 0.3, 0.1], [0.4, 0.05, 0.6]])[:, None, None, None, :]
    pred = gt * np.array([0.5, 2.0, 1.0])
    value, scale = relight_psnr(pred, gt, np.ones((1, 1, 1)))
    assert scale.tolist() == pytest.approx([2.0, 0.5, 1.0])
    assert value == pytest.approx(100.0)
    with pytest.raises(ValueError, match="differ in shape"):
        relight_psnr(pred[:1], gt, np.ones((1, 1, 1)))


def test_channel_scale_without_signal_is_one():
    s = channel_scale(np.zeros((2, 3)), np.ones((2, 3)), np.ones(2, bool))
    assert s.tolist() == [1.0, 1.0, 1.0]


def test_mae_and_normal_mae_hand_worked():
    mask = np.array([True, True, False])
    assert mae(np.array([0.2, 0.5, 0.9]), np.array([0.3, 0.5, 0.4]), mask) == pytest.approx(0.05)
    pred = np.array([[0.0, 0.0, 2.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])     # not unit: normalised
    gt = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    assert normal_mae_deg(pred, gt, mask) == pytest.approx(45.0)             # (90 + 0) / 2
    assert normal_mae_deg(pred, gt, np.ones(3, bool)) == pytest.approx(90.0)  # (90 + 0 + 180) / 3
    assert math.isnan(mae(pred, gt, np.zeros(3, bool)))


def test_material_metrics_hand_worked():
    # one view, 1 x 3 pixels; the last is background (GT alpha 0)
    gt = {"albedo": np.array([[[[1.0, 1.0, 1.0], [0.0, 0.0, 0.0], [0.3, 0.3, 0.3]]]]),
          "roughness": np.array([[[0.2, 0.6, 0.0]]]), "metallic": np.array([[[0.0, 1.0, 1.0]]]),
          "normal_world": np.array([[[[0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]]]]),
          "alpha": np.array([[[1.0, 1.0, 0.0]]])}
    pred = {"albedo": np.array([[[[0.5, 0.5, 0.5], [0.5, 0.5, 0.5], [0.9, 0.1, 0.1]]]]),
            "roughness": np.array([[[[0.5], [0.5], [1.0]]]]), "metallic": np.array([[[[0.5], [0.0], [0.0]]]]),
            "normal": np.array([[[[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [0.0, 0.0, 1.0]]]])}
    lit = np.array([[[True, False, True]]])
    res = material_metrics(pred, gt, lit)
    # albedo over the foreground: s = (1*0.5 + 0*0.5) / (0.25 + 0.25) = 1 per channel, so
    # (0.5, 0.5) against (1, 0): the relight example again, 5.1514 dB. Over the lit foreground
    # pixel only: s = 1*0.5 / 0.25 = 2, aligned 1 against 1, perfect (100 dB).
    assert res["albedo_scale"] == pytest.approx([1.0] * 3)
    assert res["albedo_psnr"] == pytest.approx(5.1514, abs=1e-4)
    assert res["albedo_psnr_lit"] == pytest.approx(100.0)
    assert res["roughness_mae"] == pytest.approx((0.3 + 0.1) / 2)
    assert res["metallic_mae"] == pytest.approx((0.5 + 1.0) / 2)
    assert res["normal_mae_deg"] == pytest.approx(45.0)
