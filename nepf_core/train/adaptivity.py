"""Adaptivity: leaving out what a scene does not need, every decision recorded.

:class:`Adaptivity` holds the rules of one run (:mod:`nepf_core.train.rules`), each a
:class:`~nepf_core.train.rules.callback.RuleCallback`, and is what the training loop calls at
each point of a run: it calls the rules in order, logs the decisions they return (the
``decisions`` of ``report.json``) and gathers their statistics and counters. The rules set the
switches of the :class:`~nepf_core.train.run_state.RunState` themselves; the loop never names one.
"""

from __future__ import annotations

import copy

from nepf_core.train.decisions import Decision, DecisionLog
from nepf_core.train.rules.callback import (DataContext, EvaluationContext, ModelContext, ReportContext,
                                            RuleCallback, StepBatch, StepEnd, StepStart)
from nepf_core.train.rules.empty_rays import EmptyRayRule
from nepf_core.train.rules.hessian import HessianRule
from nepf_core.train.rules.masks import MaskRule
from nepf_core.train.rules.occupancy import OccupancyRule
from nepf_core.train.rules.plateau import PlateauRule
from nepf_core.train.rules.specular import SpecularRule
from nepf_core.train.run_state import RunState


class Adaptivity:
    """The rules of one run, the decisions they took, and the run state they act on."""

    def __init__(self, cfg, run_state: RunState, *, iters_fixed: bool = True) -> None:
        """``cfg``: the run's :class:`~nepf_core.config.NePFConfig` (a private copy is kept, so no
        rule sees a later edit); ``iters_fixed``: the user fixed the iteration count (no plateau stop)."""
        self.cfg = cfg = copy.deepcopy(cfg)
        self.rc = cfg.rules
        self.enabled = bool(cfg.train.adaptive)
        self.run_state = run_state
        self.log = DecisionLog()
        self.masks = MaskRule(cfg, run_state)
        self.hessian = HessianRule(cfg, run_state)
        self.specular = SpecularRule(cfg, run_state)
        self.plateau = PlateauRule(cfg, run_state, iters_fixed)
        self.occupancy = OccupancyRule(cfg)
        self.empty_rays = EmptyRayRule(cfg)
        self.rules: list[RuleCallback] = [self.masks, self.hessian, self.specular, self.plateau, self.occupancy,
                                          self.empty_rays]
        """The order in which each point calls them. It matters where two rules meet: the masks
        may move the scene into the object's frame before the specular rule takes the camera
        centres; the Hessian decision is logged before the lobe's at a shared check; the plateau
        rule sees the lobe switched in the same step, and may end the run before the occupancy
        grid refreshes; the statistics keep the order of the records' keys."""

    @property
    def decisions(self) -> list[dict]:
        return self.log.records

    def log_decision(self, decision: Decision | None) -> None:
        """Log a decision taken outside the rules (the loop's: unlit pixels, a failure)."""
        self.log.add(decision)

    def _call(self, point: str, ctx) -> None:
        """Call ``point`` of every rule in order and log their decisions; a rule that sets
        ``ctx.stop`` (:class:`StepStart`) is the last one called."""
        for rule in self.rules:
            if getattr(ctx, "stop", False):
                return
            for decision in getattr(rule, point)(ctx) or ():
                self.log.add(decision)

    # -- the points of a run (nepf_core.train.rules.callback) --
    def on_data(self, ctx: DataContext) -> DataContext:
        """The data's decisions; returns ``ctx`` (``ctx.scene``: the scene to train on)."""
        self._call("on_data", ctx)
        if not self.enabled:
            self.log.add(Decision("adaptive", False, "adaptivity disabled: every term stays on"))
        return ctx

    def on_model(self, ctx: ModelContext) -> None:
        self._call("on_model", ctx)

    def before_step(self, ctx: StepStart) -> StepStart:
        """Returns ``ctx`` (``ctx.lr_factor`` the factor to train with, ``ctx.stop`` whether to end the run)."""
        self._call("before_step", ctx)
        return ctx

    def on_batch(self, ctx: StepBatch) -> StepBatch:
        """Returns ``ctx`` (``ctx.rays`` to render, ``ctx.left_out`` for the background alone, ``ctx.request``)."""
        self._call("on_batch", ctx)
        return ctx

    def after_step(self, ctx: StepEnd) -> None:
        self._call("after_step", ctx)

    def on_evaluation(self, ctx: EvaluationContext) -> None:
        self._call("on_evaluation", ctx)

    def step_stats(self) -> dict:
        """The rules' statistics for the step's ``metrics.jsonl`` record."""
        stats: dict = {}
        for rule in self.rules:
            stats.update(rule.step_stats())
        return stats

    # -- checkpoint and report --
    def state_dict(self) -> dict:
        """The decisions and every rule's counters (the checkpoint's ``adaptivity`` record)."""
        return {"decisions": self.log.records, **{r.state_key: r.state_dict() for r in self.rules if r.state_key}}

    def load_state_dict(self, s: dict) -> None:
        if not s:
            return
        self.log = DecisionLog(s.get("decisions", []))
        for rule in self.rules:
            if rule.state_key:
                rule.load_state_dict(s.get(rule.state_key, {}))

    def report(self, *, step: int, status: str, nonfinite: int) -> dict:
        """``report.json``: status, decisions, the final switches and the run state, and what the
        rules add (empty-space statistics)."""
        rs = self.run_state
        rep = {"status": status, "step": step, "nonfinite_steps": nonfinite, "decisions": self.log.records,
               "final_switches": {"specular": rs.specular, "mask_loss": rs.use_mask_loss,
                                  "background": rs.background, "w_hessian": rs.w_hessian},
               "run_state": rs.to_dict()}
        self._call("on_report", ReportContext(step=step, report=rep, decided=self.log.has))
        return rep
