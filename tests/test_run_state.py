"""The run state: the switches in effect live there, never in the config; checkpoints carry it;
``paper`` takes no adaptive decision."""

from __future__ import annotations

import json
from types import SimpleNamespace

import torch

from nepf_core.config import fast, paper, tiny
from nepf_core.render.renderer import Shading
from nepf_core.train.adaptivity import Adaptivity
from nepf_core.train.run_state import RunState
from rule_fixtures import fake_out, losses, named


def test_run_state_starts_from_the_config_and_round_trips():
    cfg = tiny()
    rs = RunState.from_config(cfg)
    assert (rs.specular, rs.w_hessian, rs.background, rs.diffuse_metal_weight) == (True, 5e-4, False, 0.0)
    rs.specular, rs.diffuse_metal_weight, rs.w_hessian, rs.background = False, 0.25, 0.0, True
    back = RunState.from_dict(json.loads(json.dumps(rs.to_dict())), RunState())
    assert back == rs
    assert rs.shading() == Shading(specular=False, diffuse_metal_weight=0.25)
    loss = rs.loss_config(cfg.loss)
    assert loss.w_hessian == 0.0 and cfg.loss.w_hessian == 5e-4 and loss.w_r == cfg.loss.w_r
    assert rs.model_config(cfg.model).background is True and cfg.model.background is False


def test_checkpoints_written_before_the_run_state_still_load_their_switches():
    cfg = tiny()
    legacy = {"adaptivity": {"specular": False, "diffuse_metal_weight": 0.4, "w_hessian": 0.0, "streak": 2}}
    rs = RunState.from_checkpoint(legacy, cfg)
    assert (rs.specular, rs.diffuse_metal_weight, rs.w_hessian) == (False, 0.4, 0.0)
    new = {"run_state": {"specular": True, "diffuse_metal_weight": 0.0, "w_hessian": 5e-4, "background": True,
                         "use_mask_loss": False}, "adaptivity": legacy["adaptivity"]}
    assert RunState.from_checkpoint(new, cfg).background is True and RunState.from_checkpoint(new, cfg).specular
    assert RunState.from_checkpoint(None, cfg) == RunState.from_config(cfg)


def test_paper_takes_no_adaptive_decision():
    """``paper`` keeps the lobe, the Hessian term and its iteration count whatever the evidence:
    a diffuse-looking scene, a smooth surface and a flat held-out PSNR change nothing."""
    cfg = paper()
    assert cfg.train.adaptive is False and fast().train.adaptive and tiny().train.adaptive
    rs = RunState.from_config(cfg)
    a = Adaptivity(cfg, rs, iters_fixed=False)
    a.before_training(SimpleNamespace(has_masks=True, images=[torch.zeros(4, 4, 3).numpy()], masks=[torch.ones(4, 4).numpy()]))
    assert not a.request(100).lobe_split
    for step in range(1, 2001):
        a.after_step(step, fake_out(share=0.0, metallic=0.0), losses(eik=0.0), check=True)
    for k in range(1, 20):
        a.on_test_eval(k, {"test_psnr": 20.0, "wall_s": 100.0 * k})
        assert a.lr_factor(100.0 * k, 0.5) == 0.5
    assert rs.specular and rs.w_hessian == cfg.loss.w_hessian > 0 and not a.stop_requested
    assert [d["decision"] for d in a.decisions] == ["mask_loss", "background_model", "adaptive"]
    assert not named(a, "specular_lobe") and not named(a, "hessian_loss") and not named(a, "early_stop")


def test_fit_never_writes_into_the_config(tmp_path):
    """A run whose data switch the background on and whose rules drop the lobe leaves ``cfg`` and
    ``config.json`` exactly as asked; the switches are in the checkpoint and report.json."""
    from nepf_core.data.detect import load_scene
    from nepf_core.data.synth import make_scene
    from nepf_core.train import fit

    make_scene(tmp_path / "s", n_views=16, n_test=0, resolution=16, supersample=1, masks=False, write_mesh=False)
    scene = load_scene(tmp_path / "s" / "dtu")
    cfg = tiny()
    cfg.train.iters, cfg.train.batch_rays, cfg.train.log_every, cfg.train.sync_every = 12, 64, 4, 0
    asked = cfg.to_json()
    fit(scene, tmp_path / "run", cfg, device="cpu",
        rules={"check_every": 5, "patience": 1, "view_spread_thr": 1.0, "radiance_fit_max": float("inf"),
               "metal_thr": 2.0, "spec_thr": 2.0})
    assert cfg.to_json() == asked and (tmp_path / "run" / "config.json").read_text() == asked
    rep = json.loads((tmp_path / "run" / "report.json").read_text())
    ck = torch.load(tmp_path / "run" / "checkpoints" / "latest.pt", weights_only=False)
    assert rep["run_state"] == ck["extra"]["run_state"]
    assert rep["run_state"]["background"] is True and rep["run_state"]["specular"] is False
