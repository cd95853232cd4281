"""The frozen constants every adaptivity rule reads."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass


@dataclass(frozen=True)
class RuleConfig:
    """Thresholds and periods of the rules, plus what they need from the run's config.

    Built once per run by :meth:`from_config`; frozen, so no rule can change what another one
    reads. The library constants below are the ones ``fast`` was tuned with (docs/FAST.md)."""

    enabled: bool = True
    """``train.adaptive``: off, the rules decide nothing (the masks still pick the mask loss and
    the background model: that is the data, not a trade-off)."""
    iters_fixed: bool = True
    """The user fixed the iteration count: no plateau stop."""
    iters: int = 250_000
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
    patience: int = 3
    """Checks in a row before the lobe is dropped or brought back."""
    highlight_ratio: float = 3.0
    """Lobe off: the brightest 5 % pixels' L_vol residual over the median one that votes for its return."""
    eik_thr: float = 0.05
    """The Hessian term applies while the eikonal residual (EMA) is above this."""
    w_hessian: float = 0.0
    """The configured Hessian weight (``loss.w_hessian``; 0: the rule never switches it on)."""
    w_albedo_flat: float = 0.0
    """``loss.w_albedo_flat``: recorded as on while the lobe is off."""
    min_gain_db: float = 0.1
    plateau_patience: int = 3
    plateau_window: int = 3
    plateau_min_frac: float = 0.5
    plateau_cooldown_frac: float = 0.25
    plateau_min_progress: float = 0.0
    """No plateau counts before this training progress (a grid SDF's coarse-to-fine schedule)."""
    lr_alpha: float = 0.05
    miss_keep: float = 0.1
    """Share of the rays that meet no occupied cell kept in the batch (importance weight 1/miss_keep)."""
    w_mask: float = 0.1
    occupancy_resolution: int = 0

    @classmethod
    def from_config(cls, cfg, *, iters_fixed: bool, **overrides) -> "RuleConfig":
        """The rules of a run of ``cfg`` (a :class:`nepf_core.config.NePFConfig`); ``overrides``
        replace library constants (tests, probes)."""
        t = cfg.train
        base = cls(enabled=bool(t.adaptive), iters_fixed=bool(iters_fixed), iters=int(t.iters),
                   w_hessian=float(cfg.loss.w_hessian), w_albedo_flat=float(cfg.loss.w_albedo_flat),
                   plateau_patience=int(t.plateau_patience), plateau_window=int(t.plateau_window),
                   plateau_min_frac=float(t.plateau_min_frac), plateau_cooldown_frac=float(t.plateau_cooldown_frac),
                   plateau_min_progress=float(t.coarse_to_fine_frac) if cfg.model.sdf_kind == "grid" else 0.0,
                   lr_alpha=float(t.lr_alpha), w_mask=float(cfg.loss.w_mask),
                   occupancy_resolution=int(cfg.model.occupancy_resolution))
        return dataclasses.replace(base, **overrides)
