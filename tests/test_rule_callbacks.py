"""The rules as step callbacks: each keeps its own cadence, the coordinator calls them in order,
a rule that ends the run is the last one called, and a resumed run's clock is not restarted by
the run state it restores."""

from __future__ import annotations

from types import SimpleNamespace

import pytest

from rule_fixtures import (batch, check, end_step, evaluate, fake_out, losses, make_adapt, named, resumed,
                           start_step)


@pytest.fixture
def refreshes(monkeypatch):
    """The steps at which the occupancy rule refreshes the grid (the refresh itself stubbed)."""
    seen = []

    def refresh(model, step):
        seen.append(step)
        return 0.5

    monkeypatch.setattr("nepf_core.train.rules.occupancy.refresh_occupancy", refresh)
    return seen


def test_the_occupancy_grid_refreshes_every_occupancy_every_steps(refreshes):
    a, _ = make_adapt()
    every = a.cfg.train.occupancy_every
    model = SimpleNamespace(occupancy=object())
    for step in range(0, 3 * every + 1):
        start_step(a, wall=float(step), lr_factor=1.0, step=step, model=model)
    assert refreshes == [0, every, 2 * every, 3 * every]
    assert a.step_stats()["occupied_fraction"] == 0.5
    assert a.report(step=3 * every, status="succeeded", nonfinite=0)["occupied_fraction"] == 0.5
    start_step(make_adapt()[0], wall=0.0, lr_factor=1.0, step=0, model=SimpleNamespace(occupancy=None))
    assert len(refreshes) == 4   # no grid, no refresh


def test_a_rule_that_ends_the_run_is_the_last_one_called(refreshes):
    """The plateau rule's stop at the end of its cool-down comes before the occupancy rule in the
    order: the grid is not refreshed for a step that is not taken."""
    a, _ = make_adapt(iters_fixed=False, plateau_cooldown_frac=0.0)
    for step, t in ((1, 80.0), (2, 100.0), (3, 120.0), (4, 160.0)):
        evaluate(a, step, {"test_psnr": 23.9, "wall_s": t})
    assert a.plateau.stop_requested
    start = start_step(a, wall=170.0, lr_factor=0.3, step=0, model=SimpleNamespace(occupancy=object()))
    assert start.stop and refreshes == []


def test_the_specular_rule_reads_evidence_only_from_the_renders_it_asked_for():
    """The lobe split is asked for at every ``check_every``-th batch; the decision that follows
    is taken after that step (step count + 1), and a render it did not ask for (the losses may
    ask for the split at every step) counts as no check."""
    a, _ = make_adapt()
    every = a.rc.check_every
    for k in (1, 2, 3):
        assert batch(a, None, None, step=k * every).request.lobe_split
        end_step(a, k * every + 1, fake_out(share=0.0), losses())
        assert a.specular.diffuse_streak == k or not a.run_state.specular
    assert not a.run_state.specular
    assert named(a, "specular_lobe")[0]["step"] == 3 * every + 1
    b, _ = make_adapt()
    for k in (1, 2, 3):
        assert not batch(b, None, None, step=k * every + 1).request.lobe_split
        end_step(b, k * every + 2, fake_out(share=0.0), losses())
    assert b.run_state.specular and b.specular.diffuse_streak == 0


def test_a_resumed_run_keeps_its_plateau_clock():
    """The plateau clock restarts when the shading model changes in a step, not when a resumed
    run's restored run state differs from the one the rules were built with."""
    a, rs = make_adapt(iters_fixed=False)
    for step in (100, 200, 300):
        check(a, step, fake_out(share=0.0), losses())
    assert not rs.specular and rs.diffuse_metal_weight == 1.0
    evaluate(a, 1, {"test_psnr": 30.0, "wall_s": 10.0})
    b, rs_b = resumed(a, rs, iters_fixed=False)   # rules built on the config's state, then restored
    assert b.plateau.best == 30.0 and not rs_b.specular
    start_step(b, wall=11.0, lr_factor=1.0, step=301)
    end_step(b, 302, fake_out(), losses())        # mid-fade: the shading model is the one restored
    assert b.plateau.best == 30.0
    end_step(b, 300 + b.rc.lobe_fade_steps, fake_out(), losses())   # the fade ends: a new model
    assert rs_b.diffuse_metal_weight == 0.0 and b.plateau.best == float("-inf")
