"""Exponential moving average of the model's parameters, used for evaluation and export.

    theta_ema <- theta_ema + (1 - beta_t) (theta - theta_ema),   beta_t = min(beta, (1 + t) / (10 + t))

after every optimiser step ``t`` (``t`` counts updates). The warm-up ``(1 + t) / (10 + t)``
keeps the first averages from being dominated by the initial weights. With ``beta = 0.995``
the average spans ~200 steps (``1 / (1 - beta)``).

With a half-life ``h`` seconds instead, each update's decay is ``beta = 0.5 ** (dt / h)``, ``dt``
the training wall time of that step: a weight's share halves every ``h`` seconds of training,
whatever the step rate. Why: fit()'s adaptivity makes a run's steps cheaper (lobe dropped, empty
rays thinned: spot_textured 0.073-0.080 s/step against 0.153-0.163 for all_on, bench v12), so a
per-step decay averaged the adaptive run over half the time of the all_on one. Measured on
spot_textured seed 1 (600 s, docs/FAST.md "The late fall"): the per-step 0.995 run fell 2 dB
over its last 150 s; with 0.9975 (the all_on averaging time at its step rate) it did not.
With ``h = 22 s`` for both variants (bench/RESULTS.md, v14) no adaptive run fell late, but the
adaptive-vs-all_on time savings were no better than with the per-step 0.995, so the `fast` preset
keeps 0.995 and the half-life is an option (``TrainConfig.ema_half_life_s``).

Why: at the end of a `fast` run the held-out PBR PSNR of the live weights swings by up to
~1.2 dB between evaluations 30 s apart (bench/RESULTS.md), at a learning rate already on its
floor. Adam's normalised steps keep every parameter moving by ~lr per step; the average of
the last ~200 steps sits nearer the minimum than any one of them. Training itself always uses
the live weights; only held-out evaluation, the saved model (``load_model``: render, export,
eval) and the final Chamfer see the average. Buffers (occupancy grid) are not averaged.
While adaptivity changes the shading model (lobe dropped, metallic dimmer fading), fit()
restarts the average every step, so it equals the live weights until the model is fixed again
(measured on sphere_diffuse: an average spanning the fade lagged the live weights by 1-6 dB).
"""

from __future__ import annotations

from contextlib import contextmanager

import torch
from torch import nn

__all__ = ["ParamEMA"]


class ParamEMA:
    """EMA of ``model``'s floating-point parameters (a detached copy on the same device).

    ``decay``: the per-update ``beta``; ``half_life_s > 0`` replaces it by ``0.5 ** (dt / h)``
    with ``dt`` passed to :meth:`update` (seconds of training since the previous update)."""

    def __init__(self, model: nn.Module, decay: float = 0.0, half_life_s: float = 0.0) -> None:
        if not half_life_s >= 0.0 or half_life_s == float("inf"):
            raise ValueError(f"EMA half-life must be a finite number of seconds >= 0, got {half_life_s}")
        if half_life_s == 0.0 and not 0.0 < decay < 1.0:
            raise ValueError(f"EMA decay must be in (0, 1), got {decay}")
        self.decay = float(decay)
        self.half_life_s = float(half_life_s)
        self.names = [n for n, p in model.named_parameters() if p.is_floating_point()]
        params = dict(model.named_parameters())
        self.shadow = [params[n].detach().clone() for n in self.names]
        self.updates = 0

    def _live(self, model: nn.Module) -> list[torch.Tensor]:
        params = dict(model.named_parameters())
        return [params[n] for n in self.names]

    def beta(self, dt_s: float | None = None) -> float:
        """``beta_t = min(beta, (1 + t) / (10 + t))`` for the next update, with
        ``beta = 0.5 ** (dt_s / half_life_s)`` when a half-life is set (``dt_s`` then required, >= 0)."""
        t = self.updates
        if self.half_life_s > 0.0:
            if dt_s is None or not dt_s >= 0.0:
                raise ValueError(f"a time-based EMA needs the step's duration dt_s >= 0, got {dt_s}")
            base = 0.5 ** (dt_s / self.half_life_s)
        else:
            base = self.decay
        return min(base, (1.0 + t) / (10.0 + t))

    @torch.no_grad()
    def update(self, model: nn.Module, dt_s: float | None = None) -> None:
        """``shadow += (1 - beta_t) (theta - shadow)`` for every parameter (one fused call);
        ``dt_s``: seconds of training since the previous update (used with a half-life)."""
        w = 1.0 - self.beta(dt_s)
        torch._foreach_lerp_(self.shadow, [p.detach() for p in self._live(model)], w)
        self.updates += 1

    @torch.no_grad()
    def reset(self, model: nn.Module) -> None:
        """Restart the average at the live weights (``t = 0``): fit() calls it while the
        shading model changes (the specular lobe dropped or brought back, the metallic
        dimmer fading), since weights from before such a change do not fit the new one."""
        for s, p in zip(self.shadow, self._live(model)):
            s.copy_(p.detach())
        self.updates = 0

    @contextmanager
    def applied(self, model: nn.Module):
        """Inside the block ``model`` holds the averaged weights; the live ones come back after."""
        live = self._live(model)
        saved = [p.detach().clone() for p in live]
        with torch.no_grad():
            for p, s in zip(live, self.shadow):
                p.copy_(s)
        try:
            yield model
        finally:
            with torch.no_grad():
                for p, s in zip(live, saved):
                    p.copy_(s)

    def state_dict(self) -> dict:
        """``{"decay", "half_life_s", "updates", "params": {name: tensor}}`` (for checkpoints)."""
        return {"decay": self.decay, "half_life_s": self.half_life_s, "updates": self.updates,
                "params": dict(zip(self.names, self.shadow))}

    def load_state_dict(self, state: dict) -> None:
        """Restore :meth:`state_dict`; a parameter missing from ``state`` keeps its copy."""
        self.updates = int(state.get("updates", 0))
        saved = state.get("params", {})
        with torch.no_grad():
            for n, s in zip(self.names, self.shadow):
                if n in saved:
                    s.copy_(saved[n].to(s.device, s.dtype))
