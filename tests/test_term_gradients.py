"""bench.term_gradients: the per-term pulls on a head are right by hand, and over a real fit's step
they add up to the gradient that step's backward leaves on the head."""

from __future__ import annotations

import math

import pytest
import torch

from bench.term_gradients import TermGradients, format_rows, head_parameters, term_gradients
from nepf_core.losses import LossConfig
from nepf_core.train.hooks import TrainHooks


def test_term_gradients_by_hand():
    # L_r = (W x + b)^2 at W = [1, 1], b = 0, x = [1, 2]: W x + b = 3,
    #   d/dW = 2 * 3 * x = [6, 12] (norm sqrt(180)), d/db = 6.
    # L_vol = 3 b, weight 0.5: no path to W (norm 0), d/db = 1.5.
    # L_eik has weight 0: left out, whatever its value.
    W = torch.tensor([1.0, 1.0], requires_grad=True)
    b = torch.tensor([0.0], requires_grad=True)
    x = torch.tensor([1.0, 2.0])
    losses = {"loss_r": (W @ x + b[0]) ** 2, "loss_vol": 3.0 * b[0], "loss_eik": (W ** 2).sum()}
    cfg = LossConfig(w_r=1.0, lambda2_vol=0.5, w_eikonal=0.0)
    rows = term_gradients(losses, cfg, [W], b)
    assert set(rows) == {"loss_r", "loss_vol"}
    assert rows["loss_r"]["norm"] == pytest.approx(math.sqrt(180.0))
    assert rows["loss_r"]["bias"] == pytest.approx([6.0])
    assert rows["loss_vol"]["norm"] == 0.0 and rows["loss_vol"]["bias"] == pytest.approx([1.5])
    assert W.grad is None and b.grad is None   # the probe leaves .grad alone
    table = format_rows([{"step": 3, "terms": rows}], "none")
    assert table.splitlines()[2].startswith("| 3 | loss_r | 1.34e+01 | 6.0e+00 |")   # the strongest first


class BiasGradAfterBackward(TrainHooks):
    """The material head's last-layer bias gradient each step's backward left (``.grad``)."""

    def __init__(self):
        self.by_step = {}

    def after_step(self, run, step, out, losses):
        self.by_step[step] = head_parameters(run.model, "material")[1].grad.detach().clone()


def test_term_pulls_add_up_to_the_steps_gradient(tmp_path):
    from nepf_core.config import fast
    from nepf_core.data.detect import load_scene
    from nepf_core.data.synth import make_scene
    from nepf_core.train import fit

    make_scene(tmp_path / "s", n_views=6, n_test=0, resolution=24, supersample=1, write_mesh=False)
    cfg = fast()
    t = cfg.train
    t.iters, t.batch_rays, t.warmup_steps, t.eval_every_s, t.sync_every, t.checkpoint_every = 6, 256, 2, 0.0, 0, 1000
    probe, after = TermGradients("material", steps=[2, 6]), BiasGradAfterBackward()
    fit(load_scene(tmp_path / "s" / "dtu"), tmp_path / "run", cfg, device="cpu", hooks=[probe, after])
    assert [r["step"] for r in probe.rows] == [2, 6]
    for r in probe.rows:
        terms = r["terms"]
        assert terms["loss_surf"]["norm"] > 0 and terms["loss_vol"]["norm"] > 0   # the images reach the head
        assert "loss_r" not in terms   # the radiance loss has no path to the material network
        total = torch.tensor([t["bias"] for t in terms.values()], dtype=torch.float64).sum(0)
        assert torch.allclose(total, after.by_step[r["step"]].double(), rtol=1e-4, atol=1e-10)
