"""ParamEMA: hand-worked averages, the swap in and out, and fit()/load_model() with an average."""

import json

import pytest
import torch
from torch import nn

from nepf_core.callbacks import FitCallbacks
from nepf_core.config import tiny
from nepf_core.train import fit, load_model
from nepf_core.weight_average import ParamEMA


def test_hand_worked_average_with_warm_up():
    m = nn.Linear(1, 1, bias=False)
    with torch.no_grad():
        m.weight.fill_(0.0)
    ema = ParamEMA(m, decay=0.5)
    # update 0: beta = min(0.5, 1/10) = 0.1 -> 0.1 * 0 + 0.9 * 10 = 9
    with torch.no_grad():
        m.weight.fill_(10.0)
    ema.update(m)
    assert ema.shadow[0].item() == pytest.approx(9.0)
    # update 1: beta = min(0.5, 2/11) = 2/11 -> 2/11 * 9 + 9/11 * 20
    with torch.no_grad():
        m.weight.fill_(20.0)
    ema.update(m)
    assert ema.shadow[0].item() == pytest.approx(2 / 11 * 9 + 9 / 11 * 20)
    # much later the warm-up no longer binds: beta = decay
    ema.updates = 1000
    before = ema.shadow[0].item()
    with torch.no_grad():
        m.weight.fill_(-4.0)
    ema.update(m)
    assert ema.shadow[0].item() == pytest.approx(0.5 * before + 0.5 * -4.0)


def test_applied_swaps_in_the_average_and_restores_the_live_weights():
    torch.manual_seed(0)
    m = nn.Sequential(nn.Linear(3, 4), nn.ReLU(), nn.Linear(4, 2))
    ema = ParamEMA(m, decay=0.9)
    live_before = [p.detach().clone() for p in m.parameters()]
    with torch.no_grad():
        for p in m.parameters():
            p.add_(1.0)
    ema.update(m)
    live = [p.detach().clone() for p in m.parameters()]
    with ema.applied(m):
        for p, s, a in zip(m.parameters(), ema.shadow, live_before):
            assert torch.equal(p, s)
            # beta_0 = 0.1: 0.1 * a + 0.9 * (a + 1)
            assert torch.allclose(p, a + 0.9, atol=1e-6)
    for p, l in zip(m.parameters(), live):
        assert torch.equal(p, l)
    # an exception inside the block still restores the live weights
    with pytest.raises(RuntimeError):
        with ema.applied(m):
            raise RuntimeError("boom")
    for p, l in zip(m.parameters(), live):
        assert torch.equal(p, l)


def test_state_dict_round_trip_and_bad_decay():
    m = nn.Linear(2, 2)
    a = ParamEMA(m, 0.99)
    with torch.no_grad():
        m.weight.add_(3.0)
    a.update(m)
    b = ParamEMA(nn.Linear(2, 2), 0.99)
    b.load_state_dict(a.state_dict())
    assert b.updates == 1
    for x, y in zip(a.shadow, b.shadow):
        assert torch.equal(x, y)
    with pytest.raises(ValueError, match="decay"):
        ParamEMA(m, 1.0)


def _cfg(iters):
    cfg = tiny()
    cfg.train.iters = iters
    cfg.train.sync_every = 0
    cfg.train.checkpoint_every = 3
    cfg.train.batch_rays = 64
    cfg.train.ema_decay = 0.8
    return cfg


def test_fit_saves_the_average_and_load_model_returns_it(small_scene, tmp_path):
    run = tmp_path / "r"
    fit(small_scene, run, _cfg(6), device="cpu")
    state = torch.load(run / "checkpoints" / "latest.pt", weights_only=False)
    avg = state["extra"]["ema"]["params"]
    assert state["extra"]["ema"]["updates"] == 6
    model, _cfg_loaded, _ = load_model(run, "cpu")
    params = dict(model.named_parameters())
    differs = 0
    for name, value in avg.items():
        assert torch.equal(params[name].detach(), value), name
        differs += int(not torch.equal(value, state["model"][name]))
    assert differs > 0  # the average is not the live model after 6 steps


def test_resume_restores_the_average(small_scene, tmp_path):
    a = tmp_path / "a"
    fit(small_scene, a, _cfg(6), device="cpu")
    b = tmp_path / "b"
    n = {"k": 0}

    def stop():
        n["k"] += 1
        return n["k"] > 3

    fit(small_scene, b, _cfg(6), device="cpu", callbacks=FitCallbacks(should_stop=stop))
    fit(small_scene, b, _cfg(6), device="cpu", resume=True)
    ea = torch.load(a / "checkpoints" / "latest.pt", weights_only=False)["extra"]["ema"]
    eb = torch.load(b / "checkpoints" / "latest.pt", weights_only=False)["extra"]["ema"]
    assert ea["updates"] == eb["updates"] == 6
    for name in ea["params"]:
        assert torch.allclose(ea["params"][name], eb["params"][name], rtol=1e-5, atol=1e-7), name
    assert json.loads((b / "config.json").read_text())["train"]["ema_decay"] == 0.8


def test_reset_restarts_at_the_live_weights():
    m = nn.Linear(2, 1)
    ema = ParamEMA(m, 0.99)
    with torch.no_grad():
        m.weight.add_(5.0)
    ema.update(m)
    ema.update(m)
    ema.reset(m)
    assert ema.updates == 0
    for s, p in zip(ema.shadow, m.parameters()):
        assert torch.equal(s, p.detach())


def test_decay_must_be_in_the_open_unit_interval():
    m = nn.Linear(1, 1)
    for bad in (0.0, 1.0, -0.5, 1.5):
        with pytest.raises(ValueError, match="decay"):
            ParamEMA(m, bad)
    assert ParamEMA(m, 0.9).state_dict()["decay"] == 0.9


def test_fit_rejects_a_negative_decay(small_scene, tmp_path):
    cfg = _cfg(2)
    cfg.train.ema_decay = -0.5
    with pytest.raises(ValueError, match="decay"):
        fit(small_scene, tmp_path / "r", cfg, device="cpu")
