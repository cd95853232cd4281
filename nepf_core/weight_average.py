"""Exponential moving average of the model's parameters, used for evaluation and export.

    theta_ema <- theta_ema + (1 - beta_t) (theta - theta_ema),   beta_t = min(beta, (1 + t) / (10 + t))

after every optimiser step ``t`` (``t`` counts updates). The warm-up ``(1 + t) / (10 + t)``
keeps the first averages from being dominated by the initial weights. With ``beta = 0.995``
the average spans ~200 steps (``1 / (1 - beta)``).

Why: late in a `fast` run the held-out PBR PSNR of the live weights swings between
evaluations a few tens of seconds apart, at a learning rate already on its floor. Adam's
normalised steps keep every parameter moving by ~lr per step; the average of the last ~200
steps sits nearer the minimum than any one of them. Training itself always uses
the live weights; only held-out evaluation, the saved model (``load_model``: render, export,
eval) and the final Chamfer see the average. Buffers (occupancy grid) are not averaged.
While adaptivity changes the shading model (lobe dropped, then fading out), fit()
restarts the average every step, so it equals the live weights until the model is fixed again:
weights averaged across a change of the shading model do not fit the new one.
"""

from __future__ import annotations

from contextlib import contextmanager

import torch
from torch import nn

__all__ = ["ParamEMA"]


class ParamEMA:
    """EMA of ``model``'s floating-point parameters (a detached copy on the same device).

    ``decay``: the per-update ``beta``, in (0, 1)."""

    def __init__(self, model: nn.Module, decay: float) -> None:
        if not 0.0 < decay < 1.0:
            raise ValueError(f"EMA decay must be in (0, 1), got {decay}")
        self.decay = float(decay)
        self.names = [n for n, p in model.named_parameters() if p.is_floating_point()]
        params = dict(model.named_parameters())
        self.shadow = [params[n].detach().clone() for n in self.names]
        self.updates = 0

    def _live(self, model: nn.Module) -> list[torch.Tensor]:
        params = dict(model.named_parameters())
        return [params[n] for n in self.names]

    def beta(self) -> float:
        """``beta_t = min(beta, (1 + t) / (10 + t))`` for the next update."""
        t = self.updates
        return min(self.decay, (1.0 + t) / (10.0 + t))

    @torch.no_grad()
    def update(self, model: nn.Module) -> None:
        """``shadow += (1 - beta_t) (theta - shadow)`` for every parameter (one fused call)."""
        w = 1.0 - self.beta()
        torch._foreach_lerp_(self.shadow, [p.detach() for p in self._live(model)], w)
        self.updates += 1

    @torch.no_grad()
    def reset(self, model: nn.Module) -> None:
        """Restart the average at the live weights (``t = 0``): fit() calls it while the
        shading model changes (the specular lobe dropped or brought back, the lobe fading),
        since weights from before such a change do not fit the new one."""
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
        """``{"decay", "updates", "params": {name: tensor}}`` (for checkpoints)."""
        return {"decay": self.decay, "updates": self.updates, "params": dict(zip(self.names, self.shadow))}

    def load_state_dict(self, state: dict) -> None:
        """Restore :meth:`state_dict`; a parameter missing from ``state`` keeps its copy."""
        self.updates = int(state.get("updates", 0))
        saved = state.get("params", {})
        with torch.no_grad():
            for n, s in zip(self.names, self.shadow):
                if n in saved:
                    s.copy_(saved[n].to(s.device, s.dtype))
