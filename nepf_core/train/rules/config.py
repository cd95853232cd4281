"""The adaptivity rules' constants: the ``rules`` section of :class:`nepf_core.config.NePFConfig`.

The rules read these and, for what belongs to other sections, the config itself
(``train.adaptive``, ``train.iters``, ``loss.w_hessian``, ...): no value is copied here. The
defaults are the ones ``fast`` was tuned with (docs/FAST.md).
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass
class RuleConfig:
    """Thresholds and periods of the rules (:mod:`nepf_core.train.rules`); they act only with
    ``train.adaptive`` (the masks still pick the mask loss and the background model: that is the
    data, not a trade-off)."""

    check_every: int = 100
    """Steps between the specular and Hessian checks."""
    warmup_frac: float = 0.1
    warmup_max_steps: int = 300
    """No lobe decision before ``min(warmup_frac iters, warmup_max_steps)`` steps (a time-budgeted
    run with a large nominal iteration count still gets to decide)."""
    metal_thr: float = 0.05
    spec_thr: float = 0.02
    """Where no view spread can be measured: the scene looks diffuse when the mean surface metallic
    is under ``metal_thr`` and the lobe's share of L_surf under ``spec_thr``."""
    view_spread_thr: float = 0.025
    """The learned radiance is view-independent below this spread
    (:func:`nepf_core.view_dependence.radiance_view_spread`)."""
    view_points: int = 256
    """Max-weight points per check for the spread."""
    radiance_fit_max: float = 0.25
    """The spread counts only while the radiance explains the lit pixels (relative L1 error)."""
    lobe_fade_steps: int = 500
    """Steps over which the dropped lobe fades out (``RunState.diffuse_metal_weight`` 1 -> 0)."""
    patience: int = 3
    """Checks in a row before the lobe is dropped or brought back."""
    highlight_ratio: float = 3.0
    """Lobe off: the brightest 5 % pixels' L_vol residual over the median one that votes for its return."""
    eik_thr: float = 0.05
    """The Hessian term applies while the eikonal residual (EMA) is above this."""
    min_gain_db: float = 0.1
    """A held-out evaluation gains when its PSNR beats the best by more than this."""
    plateau_patience: int = 3
    """Early stop after this many held-out evaluations without ``min_gain_db`` gain (only when the
    iteration count was not fixed by the user)..."""
    plateau_window: int = 3
    """The plateau rule compares the mean of the last this-many evaluations (1: single ones)."""
    plateau_min_frac: float = 0.5
    """...and only when those evaluations also span this share of the training time so far
    (``t - t_best >= plateau_min_frac * t``)."""
    plateau_cooldown_frac: float = 0.25
    """After the plateau rule fires, anneal the learning rate to ``train.lr_alpha`` over this share
    of the training time so far, then stop (0: stop at once)."""
    miss_keep: float = 0.1
    """Share of the rays that meet no occupied cell kept in the batch (importance weight 1/miss_keep)."""
