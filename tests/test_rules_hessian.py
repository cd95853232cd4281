"""The Hessian rule: on while the eikonal residual's EMA is above its threshold."""

from __future__ import annotations

from rule_fixtures import end_step, fake_out, losses, make_adapt, named, tiny


def test_hessian_follows_the_eikonal_ema():
    a, rs = make_adapt()
    # smooth surface: EMA of 0.01 stays below eik_thr = 0.05 -> off at the next check
    for step in range(1, 101):
        end_step(a, step, fake_out(), losses(eik=0.01))
    assert rs.w_hessian == 0.0
    assert rs.loss_config(tiny().loss).w_hessian == 0.0 and tiny().loss.w_hessian == 5e-4   # a copy, not the config
    (d,) = named(a, "hessian_loss")
    assert d["value"] is False and d["step"] == 100 and "<=" in d["reason"]
    # rough again: 100 steps of 0.5 lift the EMA to 0.5 - 0.49 * 0.95^100 = 0.497 > 0.05 -> on at step 200
    for step in range(101, 201):
        end_step(a, step, fake_out(), losses(eik=0.5))
    assert a.hessian.eik_ema > a.rc.eik_thr and rs.w_hessian == 5e-4
    d = named(a, "hessian_loss")[-1]
    assert d["value"] is True and d["step"] == 200
    for step in range(201, 300):   # decisions only at check steps
        end_step(a, step, fake_out(), losses(eik=0.0))
    assert rs.w_hessian == 5e-4


def test_hessian_ema_hand_value():
    a, _ = make_adapt()
    for e in (1.0, 0.0, 0.0):
        a.hessian.observe(e)
    assert a.hessian.eik_ema == 0.95 * 0.95 * 1.0


def test_hessian_never_switched_on_when_the_preset_has_none():
    a, rs = make_adapt(w_hessian=0.0)
    for step in range(1, 301):
        end_step(a, step, fake_out(), losses(eik=1.0))
    assert rs.w_hessian == 0.0 and not named(a, "hessian_loss")
