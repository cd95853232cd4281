"""The work a training step does stays level through every phase of a run (no step-rate collapse).

A time would depend on the machine, so the test counts work instead: every grid-SDF lookup
(points x active levels, which includes the occupancy refreshes, the specular checks' view spread
and the sync-PSNR renders) and every head evaluation (radiance, photon, material, background),
summed over windows of ``occupancy_every`` steps (each window then holds one occupancy refresh).
A short ``fast`` run on a small generated scene, without masks and with them, passes through the
coarse-to-fine levels, the occupancy refreshes, the empty-ray thinning, the specular checks after
their warm-up and two sync evaluations; no window may do more than ``MAX_RATIO`` times the median
window's work.
"""

from __future__ import annotations

import numpy as np
import pytest

from nepf_core.train.hooks import TrainHooks

MAX_RATIO = 3.0


class WorkCounter(TrainHooks):
    """Per-step work: ``grid`` (SDF points x active grid levels) and ``heads`` (head-network points)."""

    def __init__(self) -> None:
        self.totals = {"grid": 0, "heads": 0}
        self.seen = dict(self.totals)
        self.per_step: list[dict] = []
        self.hooked = False

    def _hook(self, run) -> None:
        model = run.model
        enc = model.sdf.encoding

        def count_grid(_module, args):
            self.totals["grid"] += args[0].shape[0] * enc.active_levels

        def count_heads(_module, args):
            self.totals["heads"] += args[0].shape[0]

        enc.register_forward_pre_hook(count_grid)
        for head in (model.radiance, model.photon, model.material, model.background):
            if head is not None:
                head.register_forward_pre_hook(count_heads)
        self.hooked = True

    def before_step(self, run, step: int) -> None:
        if not self.hooked:
            self._hook(run)

    def after_step(self, run, step: int, out, losses: dict) -> None:
        self.per_step.append({k: self.totals[k] - self.seen[k] for k in self.totals})
        self.seen = dict(self.totals)


def window_work(per_step: list[dict], key: str, window: int) -> np.ndarray:
    """Work summed over consecutive whole windows of ``window`` steps (the first window, which
    holds the very first refresh over every cell, starts the count)."""
    v = np.array([s[key] for s in per_step], dtype=np.float64)
    n = len(v) // window
    return v[: n * window].reshape(n, window).sum(1)


def test_window_work_sums_whole_windows():
    steps = [{"grid": g} for g in (1, 2, 3, 4, 5, 6, 7)]
    assert window_work(steps, "grid", 3).tolist() == [6.0, 15.0]   # the last partial window is left out


def worst_ratio(windows: np.ndarray) -> float:
    return float(windows.max() / np.median(windows))


def test_worst_ratio_flags_a_heavy_phase():
    steady = np.full(10, 100.0)
    assert worst_ratio(steady) == 1.0
    heavy = steady.copy()
    heavy[6] = 400.0   # one phase doing 4x the steady work
    assert worst_ratio(heavy) == 4.0 > MAX_RATIO


@pytest.mark.parametrize("masks", [False, True])
def test_no_phase_of_a_fast_run_does_a_multiple_of_the_steady_work(tmp_path, masks):
    from nepf_core.config import fast
    from nepf_core.data.detect import load_scene
    from nepf_core.data.synth import make_scene
    from nepf_core.train import fit

    make_scene(tmp_path / "s", n_views=6, n_test=0, resolution=24, supersample=1, masks=masks, write_mesh=False)
    scene = load_scene(tmp_path / "s" / "dtu")
    cfg = fast()
    t = cfg.train
    # sync-PSNR on 256 pixels every 60 steps of 128 rays: about its share in fast (2048 every 500 of 1024)
    t.iters, t.batch_rays, t.log_every, t.sync_every, t.sync_rays = 160, 128, 20, 60, 256
    t.checkpoint_every, t.eval_every_s, t.warmup_steps, t.anneal_end = 1000, 0.0, 20, 100
    counter = WorkCounter()
    fit(scene, tmp_path / "run", cfg, device="cpu", hooks=[counter],
        rules={"check_every": 20, "warmup_max_steps": 40})
    assert len(counter.per_step) == t.iters
    assert cfg.model.sdf_kind == "grid" and counter.per_step[-1]["grid"] > 0
    for key in ("grid", "heads"):
        windows = window_work(counter.per_step, key, t.occupancy_every)
        assert windows.min() > 0
        assert worst_ratio(windows) <= MAX_RATIO, (key, windows.tolist())
