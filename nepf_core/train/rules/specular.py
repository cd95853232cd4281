"""Drop the GGX lobe when the scene does not need it; bring it back when it does.

Every ``check_every`` steps after a warm-up (``warmup_frac`` of the run, at most
``warmup_max_steps``) the rule reads the evidence of the batch (:mod:`.lobe_evidence`):

* the spread of the learned outgoing radiance across the training cameras that face each lit
  surface point (only while the radiance explains those pixels). The lobe can only add
  view-dependent light, so when the spread stays under ``view_spread_thr`` for ``patience``
  checks in a row the lobe is dropped;
* where no spread can be measured (sparse captures, or a radiance that does not fit yet), the
  material decides: mean surface metallic < ``metal_thr`` and the lobe's share of L_surf <
  ``spec_thr``. (Where the spread is measured the material's own numbers do not decide: on a
  Lambertian sphere the optimiser darkens the diffuse with metallic and shapes the shading with
  a lobe that does not generalise.)

A drop fades the shading from the full BSDF to a dielectric diffuse over ``lobe_fade_steps``:
``(1 - w m) f_d(c) + w f_s`` with ``w = max(0, 1 - (step - t_drop) / lobe_fade_steps)``
(:func:`nepf_core.bsdf.shade_fading_lobe`; the image is the same at the drop, an immediate
switch to ``f_d`` would double the shading of a surface at metallic ~0.5). While the lobe is
off the albedo flatness prior (``loss.w_albedo_flat``) applies, because diffuse-only shading
sees only albedo x light intensity.

While it is off, a check votes for its return when the spread exceeds ``2 view_spread_thr``,
when no spread is measured and the lobe's share would exceed ``2 spec_thr``, or when the
brightest 5 % pixels' L_vol residual is ``highlight_ratio`` times the median one while the
radiance is not flat. The lobe comes back after ``patience`` votes in a row (as it went: a
single vote made it flap). A lobe kept to the end is reported with its last numbers.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from nepf_core.render.neus import foreground
from nepf_core.render.surface import SurfaceRequest
from nepf_core.train.decisions import Decision
from nepf_core.train.rules.callback import (DataContext, Decisions, ReportContext, RuleCallback, StepBatch,
                                            StepEnd)
from nepf_core.train.rules.lobe_evidence import batch_lobe_evidence, lit_view_spread


class SpecularRule(RuleCallback):
    state_key = "specular_rule"

    def __init__(self, cfg, run_state) -> None:
        """``cfg``: the run's :class:`~nepf_core.config.NePFConfig` (``rules``, ``train.adaptive``,
        ``train.iters``, ``loss.w_albedo_flat``); ``run_state``: the run's, whose lobe switch
        (``specular``) and fade weight (``diffuse_metal_weight``) the rule sets."""
        self.cfg, self.rc, self.run_state = cfg, cfg.rules, run_state
        self.enabled = bool(cfg.train.adaptive)
        self.cams: torch.Tensor | None = None
        """``[C, 3]`` the training cameras' centres (for the view spread), or None."""
        self.checking = False
        """The render of the step under way carries this rule's evidence (its request at :meth:`on_batch`)."""
        self.diffuse_streak = 0
        self.return_streak = 0
        self.highlight_vote: tuple[int, str] | None = None   # (step, reason) of the last residual vote
        self.view_spread: float | None = None
        self.fit_err: float | None = None
        self.lobe_gain: float | None = None
        self.fade_start: int | None = None
        self.stats: dict = {}

    # -- callbacks --
    def on_data(self, ctx: DataContext) -> Decisions:
        c2w = getattr(ctx.scene, "c2w", None)   # the cameras of the frame the run trains in
        self.cams = None if c2w is None else torch.as_tensor(np.asarray(c2w)[:, :3, 3], dtype=torch.float32)
        return ()

    def on_batch(self, ctx: StepBatch) -> Decisions:
        """At a check (every ``check_every`` steps), ask the render for the lobe split."""
        self.checking = self.wants_evidence(ctx.step)
        if self.checking:
            ctx.request = ctx.request | SurfaceRequest(lobe_split=True)
        return ()

    def after_step(self, ctx: StepEnd) -> Decisions:
        """After a check's step: read its evidence (:meth:`observe`); every step: the fade;
        after a check: the lobe decision (:meth:`decide`)."""
        check, self.checking = self.checking, False
        rs = self.run_state
        if check and ctx.rays is not None:
            self.observe(ctx.step, ctx.model, ctx.out, ctx.rays, self.cams, rs.specular)
        if not self.enabled:
            return ()
        w = self.fade_weight(ctx.step, rs.specular, rs.diffuse_metal_weight)
        if w is not None:
            rs.diffuse_metal_weight = w
        return self.decide(ctx.step, ctx.out, rs.specular) if check else ()

    def on_report(self, ctx: ReportContext) -> Decisions:
        """A lobe kept to the end gets a record of its last check's numbers."""
        if self.enabled and self.run_state.specular and self.stats and not ctx.decided("specular_lobe"):
            return [self.kept_report(ctx.step)]
        return ()

    def wants_evidence(self, step: int) -> bool:
        return self.enabled and step > 0 and step % self.rc.check_every == 0

    # -- evidence (at check steps, before decide) --
    def observe(self, step: int, model, out, rays, cams, specular_on: bool) -> None:
        """Read this check's batch: lobe gain, highlight vote (judged with the previous check's
        spread), then the new view spread (``cams [C, 3]`` camera centres or None)."""
        gain, ratio = batch_lobe_evidence(out, rays, specular_on)
        if gain is not None and math.isfinite(gain):
            self.lobe_gain = gain
        if ratio is not None:
            self.vote_on_highlight(step, ratio, specular_on)
        if cams is None:
            return
        status, spread, err = lit_view_spread(model, out, rays, cams, self.rc.view_points, self.rc.radiance_fit_max)
        if err is not None:
            self.fit_err = err
        if status == "unfit":
            self.view_spread = None
        elif status == "measured" and spread is not None:
            self.view_spread = spread

    def vote_on_highlight(self, step: int, ratio: float, specular_on: bool) -> None:
        """Vote for the lobe's return at this check (counted by :meth:`decide`) when the brightest
        pixels' L_vol residual is ``highlight_ratio`` times the median, unless the last measured
        spread says the radiance is view-independent."""
        if self.view_spread is not None and self.view_spread < self.rc.view_spread_thr:
            return   # a diffuse fit's residual grows with brightness too
        if self.enabled and not specular_on and ratio > self.rc.highlight_ratio:
            self.highlight_vote = (step, f"L_vol residual on the brightest 5% pixels is {ratio:.1f}x the median")

    # -- decisions --
    def fade_weight(self, step: int, specular_on: bool, weight_now: float) -> float | None:
        """The fade weight ``w`` after a drop (None: no fade under way)."""
        if specular_on or self.fade_start is None or weight_now <= 0.0:
            return None
        return max(0.0, 1.0 - (step - self.fade_start) / max(self.rc.lobe_fade_steps, 1))

    def decide(self, step: int, out, specular_on: bool) -> list[Decision]:
        """At a check (``out.lobe``: the render's :class:`~nepf_core.render.surface.LobeSplit`): the
        lobe decision (and the albedo flatness record that goes with it), or nothing."""
        rc = self.rc
        if out.lobe is None or step < min(rc.warmup_frac * self.cfg.train.iters, rc.warmup_max_steps):
            return []
        surf_w = foreground(out.weight_sum)
        if surf_w.sum() < 8:
            return []
        metal = float(out.surface.metallic.detach()[surf_w].mean())
        share = float(out.lobe.share[surf_w].mean())
        spread = self.view_spread
        self.stats = {"surf_metallic": metal, "specular_share": share}
        if self.fit_err is not None:
            self.stats["radiance_fit_error_lit"] = self.fit_err
        if self.lobe_gain is not None:
            self.stats["lobe_residual_gain"] = self.lobe_gain
        if spread is not None:
            self.stats["radiance_view_spread"] = spread
        if not specular_on:
            return self._count_return_vote(step, spread, share)
        flat = spread is not None and spread < rc.view_spread_thr
        diffuse = flat if spread is not None else (metal < rc.metal_thr and share < rc.spec_thr)
        if not diffuse:
            self.diffuse_streak = 0
            return []
        self.diffuse_streak += 1
        if self.diffuse_streak < rc.patience:
            return []
        why = (f"the learned radiance is view-independent: it changes by {spread:.2%} across the training "
               f"cameras (< {rc.view_spread_thr:.1%})" if flat else
               f"mean metallic {metal:.3f} < {rc.metal_thr}, specular share {share:.3%} < {rc.spec_thr:.0%}")
        return self._switch(False, step, f"scene looks diffuse: {why} for {rc.patience} checks "
                            f"(at the drop: metallic {metal:.3f}, lobe share {share:.1%}); the GGX lobe and the metallic "
                            f"dimmer fade out over {rc.lobe_fade_steps} steps, then the lobe is no longer evaluated and "
                            "the surface is a dielectric diffuse f_d(c) (the asset carries the shaded material, metallic 0)")

    def _count_return_vote(self, step: int, spread: float | None, share: float) -> list[Decision]:
        rc = self.rc
        why = None
        if spread is not None and spread > 2 * rc.view_spread_thr:
            why = (f"the learned radiance now changes by {spread:.2%} across the training cameras "
                   f"(> {2 * rc.view_spread_thr:.1%})")
        elif spread is None and share > 2 * rc.spec_thr:
            why = f"specular share would be {share:.3%} > {2 * rc.spec_thr:.0%}"
        elif self.highlight_vote is not None and self.highlight_vote[0] == step:
            why = self.highlight_vote[1]
        self.return_streak = self.return_streak + 1 if why else 0
        if why and self.return_streak >= rc.patience:
            return self._switch(True, step, f"{why} ({rc.patience} checks in a row)")
        return []

    def _switch(self, on: bool, step: int, reason: str) -> list[Decision]:
        """Switch the lobe in the run state; off: the fade starts at weight 1 (the same image)."""
        self.diffuse_streak = self.return_streak = 0
        self.run_state.specular = on
        if not on:
            self.fade_start = step
            self.run_state.diffuse_metal_weight = 1.0
        out = [Decision("specular_lobe", on, reason, step)]
        if self.cfg.loss.w_albedo_flat > 0:
            out.append(Decision("albedo_flatness_prior", not on,
                                "specular lobe back on: the images tie the light again" if on else
                                f"specular lobe off: diffuse-only shading sees only albedo x light intensity, so slow "
                                f"luminance variation goes to the light (weight {self.cfg.loss.w_albedo_flat:g})", step))
        return out

    def kept_report(self, step: int) -> Decision:
        """The record of a lobe kept to the end of the run (from the last check's numbers)."""
        st, rc = self.stats, self.rc
        gain, spread = st.get("lobe_residual_gain"), st.get("radiance_view_spread")
        return Decision("specular_lobe", True, "kept: " + (
            "" if spread is None else f"the learned radiance changes by {spread:.2%} across the training "
            f"cameras (drop below {rc.view_spread_thr:.1%}); ") + "at the last check the mean surface metallic was "
            f"{st['surf_metallic']:.3f} (drop below {rc.metal_thr}), the lobe's share of L_surf "
            f"{st['specular_share']:.1%} (drop below {rc.spec_thr:.0%})"
            + ("" if gain is None else f", and without it the surface error would be {gain:+.0%}"), step)

    def step_stats(self) -> dict:
        s = dict(self.stats)
        if self.enabled and not self.run_state.specular:
            s["lobe_return_votes"] = self.return_streak   # checks in a row that asked for the lobe back
        return s

    def state_dict(self) -> dict:
        return {"streak": self.diffuse_streak, "return_streak": self.return_streak,
                "view_spread": self.view_spread, "fade_start": self.fade_start}

    def load_state_dict(self, s: dict) -> None:
        self.diffuse_streak = s.get("streak", 0)
        self.return_streak = s.get("return_streak", 0)
        self.view_spread = s.get("view_spread")
        self.fade_start = s.get("fade_start")
