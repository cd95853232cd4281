"""The Hessian term only while the surface is rough.

The eikonal residual ``e_t = mean | |grad f| - 1 |`` of each step feeds an EMA
``E_t = 0.95 E_{t-1} + 0.05 e_t``. Every ``check_every`` steps the Hessian term is on (the
configured weight) iff ``E_t > eik_thr``: once the SDF is close to a distance field its
curvature penalty mostly costs time, and it comes back if the field degrades.
"""

from __future__ import annotations

from nepf_core.train.decisions import Decision


class HessianRule:
    def __init__(self, cfg) -> None:
        """``cfg``: the run's :class:`~nepf_core.config.NePFConfig` (``rules``, ``train.adaptive``,
        ``loss.w_hessian``)."""
        self.cfg, self.rc = cfg, cfg.rules
        self.eik_ema: float | None = None

    def observe(self, eikonal: float) -> None:
        """Fold this step's eikonal residual into the EMA (every step, adaptivity on or off)."""
        self.eik_ema = eikonal if self.eik_ema is None else 0.95 * self.eik_ema + 0.05 * eikonal

    def decide(self, step: int, w_in_effect: float) -> Decision | None:
        """At a check: a decision when the wanted state differs from ``w_in_effect > 0``."""
        rc = self.rc
        if not self.cfg.train.adaptive or self.cfg.loss.w_hessian <= 0 or step % rc.check_every != 0 \
                or self.eik_ema is None:
            return None
        want = self.eik_ema > rc.eik_thr
        if want == (w_in_effect > 0):
            return None
        return Decision("hessian_loss", want, f"eikonal residual EMA {self.eik_ema:.3f} "
                        f"{'>' if want else '<='} {rc.eik_thr}", step)

    def state(self) -> dict:
        return {"eik_ema": self.eik_ema}

    def load_state(self, s: dict) -> None:
        self.eik_ema = s.get("eik_ema")
