"""The photon intensity's start from the data (``model.light_init_albedo``, train/setup.py)."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import torch

from nepf_core.fields.heads import HeadConfig, PhotonField
from nepf_core.train.setup import init_light_to_data


def _photon() -> PhotonField:
    return PhotonField(HeadConfig(width=8, depth=1), feature_dim=0)


def _start_intensity(photon: PhotonField) -> float:
    """The intensity a zero raw output gives: ``softplus(bias)``."""
    return float(torch.nn.functional.softplus(photon.intensity_bias))


def _scene(peak: float) -> SimpleNamespace:
    """Two 4x4 views whose foreground pixels all peak at ``peak`` (max channel), with one white
    pixel outside each mask."""
    images = np.zeros((2, 4, 4, 3), np.float32)
    images[..., 1] = peak            # the max channel
    images[..., 0] = 0.5 * peak
    masks = np.ones((2, 4, 4), bool)
    masks[:, 0, 0] = False
    images[:, 0, 0] = 1.0            # outside the masks: must not count
    return SimpleNamespace(images=images, masks=masks)


def test_hand_worked_start():
    # every foreground peak is 0.8, so q99 = 0.8 and I0 = pi * 0.8 / 0.4 = 2 pi
    photon = _photon()
    decision = init_light_to_data(SimpleNamespace(photon=photon), _scene(0.8), albedo=0.4)
    assert math.isclose(_start_intensity(photon), 2.0 * math.pi, rel_tol=1e-5)
    assert math.isclose(decision.value["intensity"], 2.0 * math.pi, rel_tol=1e-4)
    assert decision.value["q99_linear"] == 0.8


def test_brightest_pixel_needs_the_given_albedo():
    # a Lambertian point facing the light at the start: L = a / pi * I0 equals the scene's q99
    rng = np.random.default_rng(0)
    images = rng.uniform(0.0, 0.6, (3, 8, 8, 3)).astype(np.float32)
    photon = _photon()
    init_light_to_data(SimpleNamespace(photon=photon), SimpleNamespace(images=images, masks=None), albedo=0.5)
    q99 = np.quantile(images.max(-1).reshape(-1), 0.99)
    assert math.isclose(0.5 / math.pi * _start_intensity(photon), q99, rel_tol=1e-5)


def test_zero_albedo_keeps_the_fixed_start():
    photon = _photon()
    before = _start_intensity(photon)
    assert init_light_to_data(SimpleNamespace(photon=photon), _scene(0.8), albedo=0.0) is None
    assert _start_intensity(photon) == before
    assert math.isclose(before, 3.0, rel_tol=1e-6)
