"""Config sections: old runs' config.json still load, and contradictory settings are refused."""

from __future__ import annotations

import json

import pytest

from nepf_core.config import NePFConfig, fast, paper
from nepf_core.fields.sdf_grid import GridSDFConfig
from nepf_core.train.rules.config import RuleConfig


def test_round_trip_keeps_every_section():
    cfg = fast()
    back = NePFConfig.from_dict(json.loads(cfg.to_json()))
    assert back == cfg
    assert isinstance(back.model.sdf_grid, GridSDFConfig) and isinstance(back.rules, RuleConfig)


def test_old_config_json_loads():
    """A config.json written before this layout: removed loss fields, the unlit threshold under
    ``render``, the plateau constants under ``train`` and the grid SDF as a plain dict."""
    old = json.loads(fast().to_json())
    del old["rules"], old["train"]["unlit_rel_threshold"]
    old["loss"].update({"surf_target": "radiance", "surf_one_minus_wmax": True, "color_space": "srgb"})
    old["render"]["unlit_rel_threshold"] = 0.02
    old["train"].update({"plateau_patience": 7, "plateau_window": 1, "plateau_min_frac": 0.4,
                         "plateau_cooldown_frac": 0.0})
    old["model"]["sdf_grid"] = {"base_resolution": 8, "max_resolution": 32}
    cfg = NePFConfig.from_dict(old)
    assert cfg.train.unlit_rel_threshold == 0.02
    assert (cfg.rules.plateau_patience, cfg.rules.plateau_window, cfg.rules.plateau_min_frac,
            cfg.rules.plateau_cooldown_frac) == (7, 1, 0.4, 0.0)
    assert cfg.model.sdf_grid == GridSDFConfig(base_resolution=8, max_resolution=32)
    assert not hasattr(cfg.loss, "color_space") and not hasattr(cfg.render, "unlit_rel_threshold")


def test_smoothness_priors_without_jitter_are_refused():
    """``w_albedo_smooth`` (or ``w_brdf_smooth``) > 0 reads the material next to the surface point,
    which the renderer queries only with ``render.albedo_smooth_sigma > 0``: an error, not a 0 term."""
    fast().check()
    paper().check()
    cfg = fast()
    cfg.render.albedo_smooth_sigma = 0.0
    with pytest.raises(ValueError, match="albedo_smooth_sigma"):
        cfg.check()
    cfg.loss.w_albedo_smooth = cfg.loss.w_brdf_smooth = 0.0
    with pytest.raises(ValueError, match="w_normal_smooth"):
        cfg.check()                      # the normal prior reads the same jittered points
    cfg.loss.w_normal_smooth = 0.0
    cfg.check()


def test_the_normal_prior_without_a_refined_surface_is_refused():
    """``w_normal_smooth`` > 0 reads the normals at the refined surface point and its jittered
    points, which the renderer computes only with ``render.surface_refine`` in sample mode: an
    error, not a term that silently never applies."""
    cfg = fast()
    cfg.render.surface_refine = False
    with pytest.raises(ValueError, match="surface_refine"):
        cfg.check()
    cfg.loss.w_normal_smooth = 0.0
    cfg.check()
