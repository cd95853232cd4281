"""Leaving out what a scene does not need, with every decision recorded in ``report.json``.

Rules (each decision is logged with its step and reason):
* **Masks.** With masks: mask BCE on, no background model, and (with an occupancy grid)
  the grid starts from the masks' visual hull, so no samples fall outside the mask bounds.
  Without masks: no mask loss, a background radiance model B(d) is on.
* **Specular lobe.** Every ``check_every`` steps after a warm-up (``warmup_frac`` of the
  run, at most ``warmup_max_steps``, so that a time-budgeted run with a large nominal
  iteration count still gets to decide) we measure, on up to ``view_points`` foreground
  max-weight points of the batch, how much the learned outgoing radiance changes across the
  training cameras that face each point (:func:`nepf_core.view_dependence.radiance_view_spread`:
  max minus median view over the mean, a ratio of sums). The lobe can only add
  view-dependent light, so when that spread stays under ``view_spread_thr`` (2.5 %) for
  ``patience`` checks in a row the lobe is dropped: the surface is then shaded, and exported,
  as a dielectric diffuse, metallic 0 (:func:`nepf_core.bsdf.diffuse_only_material`), after a
  fade of ``lobe_fade_steps`` over which lobe and metallic dimmer go linearly (the image is the
  same at the drop), and the albedo flatness prior (``LossConfig.w_albedo_flat``) applies: without
  the lobe only the product of albedo and light intensity is seen (docs/FAST.md, "What fixed it").
  While it is off it comes back after ``patience`` checks in a row at which
  the spread exceeds ``2 view_spread_thr``, or the L_vol residual on the brightest 5 % of
  pixels exceeds ``highlight_ratio`` times the median residual while the spread is not flat
  (the running count is logged as ``lobe_return_votes`` while the lobe is off).
  The spread counts only lit pixels' points, and only while the radiance explains them
  (relative L1 error <= ``radiance_fit_max``): torus_stiff, a near-mirror under a grazing light
  with 98 % of its foreground unlit, read 0.44-0.94 % at metallic 1.0 and lost its lobe before
  these two conditions. Where no spread can be measured (fewer than two cameras within 53
  degrees of the normal: sparse captures; or the conditions above), the material decides instead: metallic < ``metal_thr`` and the lobe's
  share of the surface PBR (with and without it, no grad) < ``spec_thr``. Measured spreads
  (fast preset): sphere_diffuse (Lambertian) 1.7 % at step 400 and 0.76-0.85 % at 600 s;
  torus_glossy 4.2-7.4 % over steps 300-900; spot_textured (roughness 0.6 dielectric)
  4.2-5.7 %. The material rule alone never fires on the sphere: metallic stays ~0.5 and the
  lobe takes 9-14 % of L_surf there (the optimiser darkens the diffuse with metallic and
  shapes the shading with the lobe), and that lobe does not generalise: with it, held-out PBR
  PSNR inside the silhouette was 34.6 dB against 56.6 dB for the radiance network on the
  same views (bench/RESULTS.md). A lobe kept to the end is recorded as kept, with the last
  spread, metallic, share and :meth:`Adaptivity.lobe_residual_gain`.
* **Metallic** (only with ``train.adaptive_metallic``, off by default: it cost held-out PBR
  PSNR where it was measured, config docstring). While the lobe is on, the same checks read the colour of the learned
  radiance's highlights (:func:`nepf_core.view_dependence.highlight_chroma`: the dichromatic
  model; a dielectric's highlight has the light's colour, a metal's the surface's). When the
  spread shows a highlight (``>= view_spread_thr``), the body is coloured (saturation ``>=
  dielectric_min_saturation``) and the highlight's chromaticity is at least
  ``dielectric_ratio`` of the body's saturation away from the body's for ``patience`` checks,
  the surface is a dielectric: ``render.metallic_scale`` fades from 1 to 0 over
  ``lobe_fade_steps`` (shaded and exported metallic ``s m``), and comes back (the same fade) if
  the ratio falls under half that for ``patience`` checks. Grey bodies (torus_stiff's
  near-white metal, bunny_dark) leave metallic free.
* **Hessian regulariser.** Only while the eikonal residual (EMA) is above ``eik_thr``.
* **Iterations.** When the user did not fix the iteration count, stop when the held-out
  PSNR (the mean of the last ``plateau_window`` evaluations, 3 in every preset: one evaluation
  is noisy) has not improved by ``min_gain_db`` over ``plateau_patience`` evaluations **and**
  over at least ``plateau_min_frac`` (default 1/2) of the training time so far
  (``t - t_best >= plateau_min_frac * t``), so frequent evaluations cannot stop a run that
  still improves slowly. The stop comes after a cool-down of ``plateau_cooldown_frac`` of
  the training time so far, over which the learning rate is annealed to its floor
  (:meth:`Adaptivity.lr_after_plateau`). With a grid SDF the plateau clock starts only when the
  coarse-to-fine schedule has activated every level (``train.coarse_to_fine_frac`` of the
  run): before that the model is still gaining resolution.
* **Coarse samples.** With the occupancy sampler, every ``check_every`` steps the number of
  coarse samples per ray follows the measured occupied length ``L`` of the rays that hit
  (EMA): one per march step (half a cell) crossed,
  ``clamp(ceil(2 L / h), min_coarse_samples, n_samples)``.
* **Empty rays.** Drawn rays that meet no occupied cell leave the training batch, except a
  random ``miss_keep`` share (:meth:`Adaptivity.thin_empty_rays`; reported as
  ``rays_left_out_fraction``).
* **Empty space.** The occupancy grid skips it; with masks, cells outside the visual hull are
  not even queried at a refresh; we report the fraction of cells culled
  (``occupied_fraction``) and the fraction of samples saved (``samples_saved_fraction``:
  the running mean over training steps of the batch-mean share of each ray's ``[near, far]``
  that the sampler skipped, i.e. at equal sampling density the share of samples not spent there;
  per logged step as ``skipped_fraction`` in ``metrics.jsonl``).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import torch


class Adaptivity:
    """Holds the switches and their history for one run."""

    check_every = 100
    warmup_frac = 0.1
    warmup_max_steps = 300
    metal_thr = 0.05
    spec_thr = 0.02
    view_spread_thr = 0.025
    view_points = 256
    radiance_fit_max = 0.25
    lobe_fade_steps = 500
    patience = 3
    highlight_ratio = 3.0
    eik_thr = 0.05
    min_gain_db = 0.1
    min_coarse_samples = 8
    miss_keep = 0.1
    coarse_spacing_cells = 0.5
    dielectric_ratio = 0.5
    dielectric_min_saturation = 0.05

    def __init__(self, cfg, *, enabled: bool, iters_fixed: bool) -> None:
        self.cfg = cfg
        self.enabled = enabled
        self.iters_fixed = iters_fixed
        self.decisions: list[dict] = []
        self.use_mask_loss = False
        self.plateaued = False
        self.stop_requested = False
        self._cool_start = self._cool_len = self._cool_f0 = None
        self._diffuse_streak = 0
        self._return_streak = 0
        self._highlight_vote = None   # (step, reason) of the last check whose residual asked for the lobe
        self._eik_ema = None
        self._best_psnr = -math.inf
        self._evals_since_best = 0
        self._best_wall = None
        self._recent: list[float] = []
        self._plateau_armed = False
        self._hess_weight = cfg.loss.w_hessian
        self._stats: dict = {}
        self._occ_frac = None
        self._skip_last = None
        self._skip_sum, self._skip_n = 0.0, 0
        self._occ_len = None
        self._lobe_gain = None
        self._drop_last = None
        self._drop_sum, self._drop_n = 0.0, 0
        self._cams = None
        self._view_spread = None
        self._fit_err = None
        self._fade_start = None
        self._chroma = None
        self._metal_streak = 0
        self._metal_fade = None   # [step started, scale at the start, target scale]

    # -- bookkeeping --
    def record(self, decision: str, value, reason: str, step: int = 0) -> None:
        self.decisions.append({"decision": decision, "value": value, "reason": reason, "step": step})

    def state(self) -> dict:
        return {"decisions": self.decisions, "specular": self.cfg.render.specular, "streak": self._diffuse_streak,
                "eik_ema": self._eik_ema, "best": self._best_psnr if math.isfinite(self._best_psnr) else None,
                "since_best": self._evals_since_best, "best_wall": self._best_wall,
                "plateau_armed": self._plateau_armed, "plateaued": self.plateaued, "recent": self._recent,
                "cool": [self._cool_start, self._cool_len, self._cool_f0], "w_hessian": self.cfg.loss.w_hessian,
                "skip_sum": self._skip_sum, "skip_n": self._skip_n, "occ_len": self._occ_len,
                "n_samples_occupied": self.cfg.render.n_samples_occupied,
                "drop_sum": self._drop_sum, "drop_n": self._drop_n, "view_spread": self._view_spread,
                "fade_start": self._fade_start, "diffuse_metal_weight": self.cfg.render.diffuse_metal_weight,
                "metallic_scale": self.cfg.render.metallic_scale, "metal_fade": self._metal_fade,
                "metal_streak": self._metal_streak, "return_streak": self._return_streak}

    def load_state(self, s: dict) -> None:
        if not s:
            return
        self.decisions = s.get("decisions", self.decisions)
        self.cfg.render.specular = s.get("specular", self.cfg.render.specular)
        self._diffuse_streak = s.get("streak", 0)
        self._eik_ema = s.get("eik_ema")
        self._best_psnr = s.get("best") if s.get("best") is not None else -math.inf
        self._evals_since_best = s.get("since_best", 0)
        self._best_wall = s.get("best_wall")
        self._plateau_armed = s.get("plateau_armed", False)
        self._recent = list(s.get("recent", []))
        self.plateaued = s.get("plateaued", False)
        self._cool_start, self._cool_len, self._cool_f0 = s.get("cool", [None, None, None])
        self.cfg.loss.w_hessian = s.get("w_hessian", self.cfg.loss.w_hessian)
        self._skip_sum, self._skip_n = s.get("skip_sum", 0.0), s.get("skip_n", 0)
        self._occ_len = s.get("occ_len")
        self._drop_sum, self._drop_n = s.get("drop_sum", 0.0), s.get("drop_n", 0)
        self._view_spread = s.get("view_spread")
        self._fade_start = s.get("fade_start")
        self.cfg.render.diffuse_metal_weight = s.get("diffuse_metal_weight", self.cfg.render.diffuse_metal_weight)
        self.cfg.render.n_samples_occupied = s.get("n_samples_occupied", self.cfg.render.n_samples_occupied)
        self.cfg.render.metallic_scale = s.get("metallic_scale", self.cfg.render.metallic_scale)
        self._metal_fade = s.get("metal_fade")
        self._return_streak = s.get("return_streak", 0)
        self._metal_streak = s.get("metal_streak", 0)

    # -- before training --
    def decide_before_training(self, scene) -> None:
        c2w = getattr(scene, "c2w", None)
        self._cams = None if c2w is None else torch.as_tensor(np.asarray(c2w)[:, :3, 3], dtype=torch.float32)
        if scene.has_masks:
            self.use_mask_loss = self.cfg.loss.w_mask > 0
            self.cfg.model.background = False
            self.record("mask_loss", self.use_mask_loss, "the dataset has masks: mask BCE supervises the opacity")
            self.record("background_model", False, "masked scene: everything outside the mask is empty")
        else:
            self.use_mask_loss = False
            self.cfg.model.background = True
            self.record("mask_loss", False, "the dataset has no masks: no mask loss")
            self.record("background_model", True, "no masks: a background radiance B(d) explains non-object pixels")
        if self.cfg.model.occupancy_resolution > 0:
            how = ("the occupancy sampler places samples in occupied cells only"
                   if self.cfg.render.sampler == "occupancy" else
                   "rays that meet no occupied cell leave the training batch" if self.enabled else
                   "the grid is maintained but not used (adaptivity off)")
            self.record("empty_space_skipping", self.enabled or self.cfg.render.sampler == "occupancy",
                        f"occupancy grid {self.cfg.model.occupancy_resolution}^3 refreshed from the SDF during "
                        f"training: {how}")
        if not self.enabled:
            self.record("adaptive", False, "adaptivity disabled: every term stays on")

    def init_occupancy(self, model, scene) -> None:
        from nepf_core.render.visual_hull import visual_hull_cells
        if scene.has_masks and not self.enabled:
            self.record("visual_hull", False, "adaptivity disabled: samples may fall outside the mask bounds "
                        "(everything-on baseline)")
        elif scene.has_masks:
            hull = visual_hull_cells(scene, model.occupancy.cfg.resolution, device=model.hull.device)
            if hull.any():
                model.hull.copy_(hull)
                model.occupancy.occ &= hull
                self.record("visual_hull", True, f"no samples outside the mask bounds: cells outside the masks' visual "
                            f"hull are empty ({1 - float(hull.float().mean()):.1%} of the grid culled)")
            else:
                self.record("visual_hull", False, "the masks' visual hull is empty (inconsistent masks/cameras?): not used")

    def update_occupancy(self, model, step: int) -> None:
        occ = model.occupancy
        hull = None if bool(model.hull.all()) else model.hull  # cells outside the hull are never queried
        occ.update(model.sdf.sdf, float(model.deviation().detach()), step, allowed=hull)
        if hasattr(occ, "occupied_fraction"):
            self._occ_frac = float(occ.occupied_fraction())

    def thin_empty_rays(self, model, rays, step: int, generator: torch.Generator | None = None):
        """Leave out of the batch the rays that meet no occupied cell, except a random
        ``miss_keep`` share of them.

        Such a ray crosses only cells where ``|f| > safety (r_h + delta/2) + k_s / s``
        (occupancy rule (1)), so its opacity is ``<= ~e^{-k_s}`` and rendering it spends
        ``n_samples + n_importance`` SDF queries (with gradients) on empty space; the share kept
        lets the mask loss and the eikonal term still see empty space; the kept misses get the
        importance weight ``RayBatch.weight = 1 / miss_keep`` in the mask loss and in the eikonal
        mean (every eikonal sample of a kept miss counts ``1 / miss_keep`` times), so their
        expectations are the means over the drawn batch (hits weigh 1). Before the eikonal was
        weighted, thinning made it a near-surface term: measured on a trained spot_textured model
        (docs/FAST.md), rays that meet an occupied cell held 55 % of the eikonal mean of a full
        drawn batch, 92 % of a thinned one unweighted, 55 % weighted (``bench/eikonal_share.py``).
        ``rays`` (``R``) -> the kept :class:`~nepf_core.rays.RayBatch` (``R' <= R``, unchanged order). Only with
        adaptivity on, an occupancy grid that has been refreshed, the ``neus`` sampler (which
        spreads a kept ray's samples over its whole chord, so a surface outside the occupied
        cells is still found and then makes its cells occupied), and at least 8 rays kept.
        """
        occ = getattr(model, "occupancy", None)
        if not self.enabled or occ is None or int(occ.n_updates) == 0 or self.cfg.render.sampler != "neus":
            # the occupancy sampler puts a hit ray's samples in occupied cells only, so a surface
            # outside them is found through the uniform samples of the rays that miss: thinning
            # those collapsed spot_textured (13 dB at 210 s, mask loss stuck near 0.5)
            return rays
        from nepf_core.render.sampling import near_far_from_sphere
        near, far, _ = near_far_from_sphere(rays.origins, rays.directions)
        hit = occ.ray_hits(rays.origins, rays.directions, near, far)
        u = torch.rand(hit.shape, generator=generator).to(hit.device)
        keep = hit | (u < self.miss_keep)
        thin = int(keep.sum()) >= 8 and not bool(keep.all())
        dropped = 1.0 - float(keep.float().mean()) if thin else 0.0
        self._drop_last = dropped
        self._drop_sum += dropped
        self._drop_n += 1
        if not thin:
            return rays
        if not any(d["decision"] == "empty_rays" for d in self.decisions):
            self.record("empty_rays", {"left_out_fraction": round(dropped, 4), "miss_keep": self.miss_keep},
                        f"{1 - float(hit.float().mean()):.1%} of the drawn rays meet no occupied cell (opacity "
                        f"<= ~e^-{occ.cfg.k_s:g}): they leave the batch except a random {self.miss_keep:.0%}, "
                        "which keep the mask loss and the eikonal term on empty space", step)
        kept = rays.index(keep.nonzero(as_tuple=True)[0])
        # the mask loss stays an unbiased estimate of its mean over the drawn batch: each kept
        # miss stands for 1 / miss_keep misses
        kept.weight = torch.where(hit[keep], 1.0, 1.0 / max(self.miss_keep, 1e-12)).to(rays.origins.dtype)
        return kept

    # -- during training --
    def wants_specular_stats(self, step: int) -> bool:
        return self.enabled and step > 0 and step % self.check_every == 0

    def check_view_spread(self, model, out, rays) -> None:
        """At a specular check (before :meth:`on_step`): how much the learned outgoing radiance
        changes with the viewpoint at the surface (:func:`nepf_core.view_dependence.radiance_view_spread`
        at the max-weight points of up to ``view_points`` foreground rays of the batch whose pixel
        is lit (``rays.unlit`` false, when fit() marked unlit pixels), over the training cameras;
        fewer than 8 such points: no measurement), and only while the radiance explains those
        pixels: relative L1 error ``sum |L_r - I| / sum |I|`` over them (logged as
        ``radiance_fit_error_lit``) at most ``radiance_fit_max`` (0.25); otherwise there is no
        measurement and the material decides (module docstring). Logged as ``radiance_view_spread``."""
        if not self.enabled or self._cams is None or "x" not in out.surf:
            return
        from nepf_core.view_dependence import radiance_view_spread
        fg = out.weight_sum.detach() > 0.5
        if rays.mask is not None:
            fg = fg & (rays.mask > 0.5)
        unlit = getattr(rays, "unlit", None)
        if unlit is not None:
            # a point whose pixel the light does not reach shows no highlight in that view and
            # says nothing about view dependence; on torus_stiff (near-mirror, grazing light,
            # 98 % of the foreground unlit) counting such points dropped the lobe of a mirror
            fg = fg & ~unlit
        x = out.surf["x"].detach()[fg][: self.view_points]
        if x.shape[0] < 8:
            return
        rgb_r = getattr(out, "rgb_r", None)
        if rgb_r is not None and getattr(rays, "rgb", None) is not None:
            # the spread of a radiance that does not yet explain the lit pixels is no evidence:
            # on torus_stiff (tiny saturated highlights) it read 0.44 % at metallic 1.0
            err = float((rgb_r.detach()[fg] - rays.rgb[fg]).abs().sum() / rays.rgb[fg].abs().sum().clamp_min(1e-8))
            self._fit_err = err
            if err > self.radiance_fit_max:
                self._view_spread = self._chroma = None
                return
        r = radiance_view_spread(model, x, self._cams.to(x.device))
        if math.isfinite(r["spread"]):
            self._view_spread = r["spread"]
        gap, sat = r["chroma_gap"], r["body_saturation"]
        self._chroma = (gap, sat) if math.isfinite(gap) and math.isfinite(sat) else None

    def step_stats(self) -> dict:
        s = dict(self._stats)
        if self._occ_frac is not None:
            s["occupied_fraction"] = self._occ_frac
        if self._skip_last is not None:
            s["skipped_fraction"] = self._skip_last
        if self._occ_len is not None:
            s["occupied_length"] = self._occ_len
        if self._drop_last is not None:
            s["rays_left_out"] = self._drop_last
        if self.enabled and not self.cfg.render.specular:
            s["lobe_return_votes"] = self._return_streak   # checks in a row that asked for the lobe back
        return s

    def on_step(self, step: int, out, losses: dict) -> None:
        eik = float(losses["loss_eik"].detach()) if "loss_eik" in losses else 0.0
        self._eik_ema = eik if self._eik_ema is None else 0.95 * self._eik_ema + 0.05 * eik
        occ_len = getattr(out, "occupied_length", None)
        if occ_len is not None and math.isfinite(occ_len):
            self._occ_len = occ_len if self._occ_len is None else 0.9 * self._occ_len + 0.1 * occ_len
        skip = getattr(out, "skip_fraction", None)
        if skip is not None and math.isfinite(skip):
            self._skip_last = skip
            self._skip_sum += skip
            self._skip_n += 1
        if not self.enabled:
            return
        self._fade_metal(step)
        self._fade_metallic_scale(step)
        if step % self.check_every == 0:
            self._decide_coarse_samples(step)
        total = self.cfg.train.iters
        # Hessian only while the surface is rough
        if self._hess_weight > 0 and step % self.check_every == 0:
            want = self._eik_ema > self.eik_thr
            on = self.cfg.loss.w_hessian > 0
            if want != on:
                self.cfg.loss.w_hessian = self._hess_weight if want else 0.0
                self.record("hessian_loss", want, f"eikonal residual EMA {self._eik_ema:.3f} "
                            f"{'>' if want else '<='} {self.eik_thr}", step)
        if "specular" not in out.surf or step < min(self.warmup_frac * total, self.warmup_max_steps):
            return
        surf_w = out.weight_sum.detach() > 0.5
        if surf_w.sum() < 8:
            return
        metal = float(out.surf["metallic"].detach()[surf_w].mean())
        share = float(out.surf["specular"][surf_w].mean())
        spread = self._view_spread
        self._stats = {"surf_metallic": metal, "specular_share": share}
        if self._fit_err is not None:
            self._stats["radiance_fit_error_lit"] = self._fit_err
        if self._lobe_gain is not None:
            self._stats["lobe_residual_gain"] = self._lobe_gain
        if spread is not None:
            self._stats["radiance_view_spread"] = spread
        # the radiance's view spread decides where it can be measured; the material's own
        # numbers only when it cannot (metallic stays ~0.5 on a Lambertian sphere, docstring)
        if self.cfg.render.specular:
            self._decide_dielectric(step, spread)
        flat = spread is not None and spread < self.view_spread_thr
        diffuse = flat if spread is not None else (metal < self.metal_thr and share < self.spec_thr)
        if self.cfg.render.specular:
            if diffuse:
                self._diffuse_streak += 1
                if self._diffuse_streak >= self.patience:
                    why = (f"the learned radiance is view-independent: it changes by {spread:.2%} across the training "
                           f"cameras (< {self.view_spread_thr:.1%})" if flat else
                           f"mean metallic {metal:.3f} < {self.metal_thr}, specular share {share:.3%} < {self.spec_thr:.0%}")
                    self._set_lobe(False, step, f"scene looks diffuse: {why} for {self.patience} checks "
                                   f"(at the drop: metallic {metal:.3f}, lobe share {share:.1%}); the GGX lobe and the metallic "
                                   f"dimmer fade out over {self.lobe_fade_steps} steps, then the lobe is no longer evaluated and "
                                   "the surface is a dielectric diffuse f_d(c) (the asset carries the shaded material, metallic 0)")
            else:
                self._diffuse_streak = 0
        else:
            self._count_return_vote(step, spread, share)

    def _count_return_vote(self, step: int, spread: float | None, share: float) -> None:
        """While the lobe is off, one check votes for its return when the radiance's spread
        exceeds ``2 view_spread_thr``, when no spread is measured and the lobe's share would
        exceed ``2 spec_thr``, or when :meth:`on_highlight_residual` flagged this check. The
        lobe comes back after ``patience`` votes in a row, as it went: a return on a single vote
        made sphere_diffuse seed 0 flap in four rounds of bench/RESULTS.md (dropped, back
        200-300 steps later, dropped again), each flap costing a fade and a restarted average."""
        why = None
        if spread is not None and spread > 2 * self.view_spread_thr:
            why = (f"the learned radiance now changes by {spread:.2%} across the training cameras "
                   f"(> {2 * self.view_spread_thr:.1%})")
        elif spread is None and share > 2 * self.spec_thr:
            why = f"specular share would be {share:.3%} > {2 * self.spec_thr:.0%}"
        elif self._highlight_vote is not None and self._highlight_vote[0] == step:
            why = self._highlight_vote[1]
        self._return_streak = self._return_streak + 1 if why else 0
        if why and self._return_streak >= self.patience:
            self._set_lobe(True, step, f"{why} ({self.patience} checks in a row)")

    def _decide_dielectric(self, step: int, spread: float | None) -> None:
        """The metallic rule (module docstring): from this check's highlight colour
        (``self._chroma``, measured by :meth:`check_view_spread`), count checks that disagree
        with the current state and switch after ``patience`` of them in a row."""
        if self._chroma is None or spread is None or spread < self.view_spread_thr:
            return   # no highlight to read
        gap, sat = self._chroma
        self._stats["highlight_chroma_gap"], self._stats["body_saturation"] = gap, sat
        if not self.cfg.train.adaptive_metallic:
            return   # measured and logged only
        if sat < self.dielectric_min_saturation:
            return   # a grey body: the highlight's colour cannot tell
        ratio = gap / sat
        dielectric = (self._metal_fade[2] if self._metal_fade else self.cfg.render.metallic_scale) == 0.0
        flip = ratio < 0.5 * self.dielectric_ratio if dielectric else ratio > self.dielectric_ratio
        self._metal_streak = self._metal_streak + 1 if flip else 0
        if self._metal_streak < self.patience:
            return
        self._metal_streak = 0
        target = 1.0 if dielectric else 0.0
        self._metal_fade = [step, self.cfg.render.metallic_scale, target]
        if dielectric:
            why = (f"the highlights now take the surface's colour: chromaticity gap {gap:.3f} is {ratio:.2f} of the "
                   f"body saturation {sat:.3f} (< {0.5 * self.dielectric_ratio:g}) for {self.patience} checks: metallic "
                   f"free again (fades back over {self.lobe_fade_steps} steps)")
        else:
            why = (f"the highlights keep the light's colour, not the surface's (dichromatic model): their chromaticity is "
                   f"{gap:.3f} from the body's, {ratio:.2f} of the body saturation {sat:.3f} (> {self.dielectric_ratio:g}) "
                   f"for {self.patience} checks, with view spread {spread:.2%}: a dielectric, metallic faded to 0 over "
                   f"{self.lobe_fade_steps} steps (F0 = 0.04)")
        self.record("dielectric", not dielectric, why, step)
        self._restart_plateau_clock()

    def _metallic_free_reason(self) -> str:
        """Why no dielectric decision was taken (for a kept lobe's report), from the last check's
        highlight colour in ``self._stats``."""
        gap, sat = self._stats.get("highlight_chroma_gap"), self._stats.get("body_saturation")
        if self.cfg.render.metallic_scale != 1.0:
            return f"metallic scaled by {self.cfg.render.metallic_scale:g} as configured"
        if not self.cfg.train.adaptive_metallic:
            why = "the metallic decision is off (train.adaptive_metallic"
            if gap is None:
                return why + ")"
            return (why + "; measured, it cost held-out PBR PSNR on spot_textured); the highlights' colour read "
                    f"{gap:.3f} from the body's, body saturation {sat:.3f}")
        if gap is None:
            return (f"no highlight colour was measured (no view spread above {self.view_spread_thr:.1%}, or the "
                    "radiance did not yet explain the lit pixels)")
        if sat < self.dielectric_min_saturation:
            return (f"the body is grey (saturation {sat:.3f} < {self.dielectric_min_saturation}), so the highlight's "
                    "colour cannot tell a metal from a dielectric")
        return (f"at the last check the highlights' chromaticity was {gap:.3f} from the body's, {gap / sat:.2f} of the "
                f"body saturation {sat:.3f} (a dielectric above {self.dielectric_ratio:g})")

    def _fade_metallic_scale(self, step: int) -> None:
        """``render.metallic_scale`` goes linearly from its value at the decision to the target
        over ``lobe_fade_steps`` (the image changes by a bounded amount per step, as for the lobe)."""
        if self._metal_fade is None:
            return
        t0, s0, target = self._metal_fade
        q = min(1.0, (step - t0) / max(self.lobe_fade_steps, 1))
        self.cfg.render.metallic_scale = s0 + (target - s0) * q
        if q >= 1.0:
            self.cfg.render.metallic_scale = target
            self._metal_fade = None
            self._restart_plateau_clock()

    def _set_lobe(self, on: bool, step: int, reason: str) -> None:
        """Switch the GGX lobe and what goes with it, and record why.

        Off: the shading fades from the full BSDF to a dielectric diffuse over
        ``lobe_fade_steps`` (:meth:`_fade_metal`, :func:`nepf_core.bsdf.shade_fading_lobe`).
        While it is off, the albedo flatness prior (``LossConfig.w_albedo_flat``) applies."""
        r = self.cfg.render
        r.specular = on
        self._diffuse_streak = self._return_streak = 0
        self.record("specular_lobe", on, reason, step)
        if not on:
            r.diffuse_metal_weight = 1.0   # same image at the drop, then fades
            self._fade_start = step
        if self.cfg.loss.w_albedo_flat > 0:
            self.record("albedo_flatness_prior", not on,
                        "specular lobe back on: the images tie the light again" if on else
                        f"specular lobe off: diffuse-only shading sees only albedo x light intensity, so slow "
                        f"luminance variation goes to the light (weight {self.cfg.loss.w_albedo_flat:g})", step)
        self._restart_plateau_clock()

    def _restart_plateau_clock(self) -> None:
        """Forget the evaluations so far: the shading model changed (lobe dropped or back, end
        of the fade), and the held-out PBR PSNR dips while the material adapts. Measured:
        sphere_diffuse seed 1, 400 s, stopped at 300 s on the dip after the drop (means of
        3 evaluations 32.4 dB before the drop, 30.1-31.8 dB after) while still climbing
        (36.4, 38.6, 38.8 dB). Not during the cool-down: a stop already decided stands."""
        if self.plateaued:
            return
        self._recent, self._best_psnr, self._best_wall, self._evals_since_best = [], -math.inf, None, 0

    def _fade_metal(self, step: int) -> None:
        """After a drop, ``render.diffuse_metal_weight = max(0, 1 - (step - t_drop) / lobe_fade_steps)``:
        the shading goes from ``(1 - m) f_d(c) + f_s`` (the image just before the drop) to
        ``f_d(c)`` linearly (:func:`nepf_core.bsdf.shade_fading_lobe`). An immediate switch to
        ``f_d(c)`` doubled the sphere's shading at metallic ~0.5: its held-out PBR fell to 19 dB
        and its albedo PSNR from 45 to 32 dB."""
        r = self.cfg.render
        if r.specular or self._fade_start is None or r.diffuse_metal_weight <= 0.0:
            return
        r.diffuse_metal_weight = max(0.0, 1.0 - (step - self._fade_start) / max(self.lobe_fade_steps, 1))
        if r.diffuse_metal_weight <= 0.0:
            self._restart_plateau_clock()   # the fade is over: the model from here on is the one to judge

    def coarse_samples_for(self, occupied_length: float) -> int:
        """One coarse sample per march step of occupied space crossed:
        ``n = clamp(ceil(L / (h / 2)), n_min, n_samples)`` with ``L`` the mean occupied length of
        the rays that hit and ``h`` the cell size (the grid covers ``[-1, 1]^3``; ``h / 2`` is
        the occupancy march step). Measured: one sample per cell (``L / h``, 16-19 samples on
        sphere_diffuse) lost 2-3 dB against the 24 of the preset at equal steps."""
        n = math.ceil(occupied_length / self._coarse_spacing())
        return int(min(max(n, self.min_coarse_samples), self.cfg.render.n_samples))

    def _coarse_spacing(self) -> float:
        """Target coarse-sample spacing: ``coarse_spacing_cells`` cells of the ``[-1, 1]^3`` grid."""
        return self.coarse_spacing_cells * 2.0 / max(self.cfg.model.occupancy_resolution, 1)

    def _decide_coarse_samples(self, step: int) -> None:
        r = self.cfg.render
        if r.sampler != "occupancy" or self._occ_len is None:
            return
        n = self.coarse_samples_for(self._occ_len)
        cur = r.n_samples_occupied if r.n_samples_occupied > 0 else r.n_samples
        if n != cur and (abs(n - cur) >= 4 or n in (self.min_coarse_samples, r.n_samples)):
            r.n_samples_occupied = n
            h = self._coarse_spacing()
            self.record("coarse_samples", n, f"rays cross {self._occ_len:.3f} of occupied space on average "
                        f"= {self._occ_len / h:.1f} march steps of {h:.4f}: {n} coarse samples per ray in occupied cells "
                        f"(preset {r.n_samples}; the uniform sampler's spacing over the unit sphere would be "
                        f"{2.0 / r.n_samples:.3f})", step)

    @staticmethod
    def lobe_residual_gain(rgb_surf: torch.Tensor, diffuse_only: torch.Tensor, target: torch.Tensor) -> float:
        """What the GGX lobe explains, on surface rays ``[N, 3]``: ``g = E_d / E - 1`` with
        ``E = mean |c_surf - t|^2`` (diffuse + lobe) and ``E_d = min_{k >= 0} mean |k c_d - t|^2``
        (diffuse only, best per-channel gain ``k_c = max(0, <c_d, t>_c / <c_d, c_d>_c)``, which
        stands for what the albedo could absorb). ``g <= 0``: the lobe adds nothing a brighter
        diffuse could not; ``g = 0.3``: without it the surface error would be 30 % higher."""
        k = ((diffuse_only * target).sum(0) / (diffuse_only * diffuse_only).sum(0).clamp_min(1e-12)).clamp_min(0)
        e = ((rgb_surf - target) ** 2).mean()
        e_d = ((k * diffuse_only - target) ** 2).mean()
        return float(e_d / e.clamp_min(1e-12) - 1.0)

    def on_lobe_residual(self, gain: float) -> None:
        """Record this check's :meth:`lobe_residual_gain` (logged as ``lobe_residual_gain``)."""
        if math.isfinite(gain):
            self._lobe_gain = gain

    def on_highlight_residual(self, step: int, ratio: float) -> None:
        """Vote for the lobe's return at this check (counted by :meth:`on_step`, which brings it
        back after ``patience`` votes in a row) when the brightest pixels' L_vol residual is
        ``highlight_ratio`` times the median, unless the learned radiance says the scene is
        still view-independent (a diffuse fit's residual grows with brightness too)."""
        if self._view_spread is not None and self._view_spread < self.view_spread_thr:
            return
        if self.enabled and not self.cfg.render.specular and ratio > self.highlight_ratio:
            self._highlight_vote = (step, f"L_vol residual on the brightest 5% pixels is {ratio:.1f}x the median")

    def plateau_min_progress(self) -> float:
        """Training progress before which no plateau counts: a grid SDF still gains resolution
        until its coarse-to-fine schedule ends (``train.coarse_to_fine_frac``)."""
        return self.cfg.train.coarse_to_fine_frac if self.cfg.model.sdf_kind == "grid" else 0.0

    def on_test_eval(self, step: int, rec: dict, progress: float | None = None) -> None:
        """Plateau bookkeeping on one held-out evaluation. The rule compares the running mean of
        the last ``train.plateau_window`` evaluations (fewer at the start),
        ``m_k = mean(psnr_{k-w+1..k})``, with the best such mean so far: one evaluation still moves
        by up to 1.2 dB on spot_textured late in a run (bench/RESULTS.md), so a single lucky
        evaluation must not become the bar that the next ones fail to clear. The first full
        mean (``w`` evaluations) sets the first bar."""
        v = rec.get("test_psnr")
        if v is None or not math.isfinite(v):
            return
        window = max(int(self.cfg.train.plateau_window), 1)
        self._recent = (self._recent + [float(v)])[-window:]
        v = sum(self._recent) / len(self._recent)
        wall = rec.get("wall_s")
        growing = progress is not None and progress < self.plateau_min_progress()
        if len(self._recent) < window:
            # a mean of fewer evaluations is noisier than the rule assumes: no bar yet (the first
            # full mean sets it)
            self._best_psnr, self._best_wall, self._evals_since_best = -math.inf, wall, 0
            return
        if growing or (progress is not None and not self._plateau_armed):
            # still adding capacity: track the best, but the plateau clock starts only once
            # every level is active (then it restarts from this evaluation)
            self._best_psnr = max(self._best_psnr, v)
            self._evals_since_best = 0
            self._best_wall = wall
            self._plateau_armed = not growing
            return
        if v > self._best_psnr + self.min_gain_db:
            self._best_psnr = v
            self._best_wall = wall
            self._evals_since_best = 0
        else:
            self._evals_since_best += 1
        long_enough = True   # the plateau must also span a share of the training time so far
        if wall is not None and self._best_wall is not None:
            long_enough = (wall - self._best_wall) >= self.cfg.train.plateau_min_frac * wall
        if (self.enabled and not self.iters_fixed and self._evals_since_best >= self.cfg.train.plateau_patience
                and long_enough and not self.plateaued):
            self.plateaued = True
            span = "" if wall is None or self._best_wall is None else \
                f" and {wall - self._best_wall:.0f} s of {wall:.0f} s of training"
            frac = self.cfg.train.plateau_cooldown_frac
            if wall is None or frac <= 0:
                self.stop_requested = True
                then = "stop now"
            else:
                self._cool_start, self._cool_len = wall, frac * wall
                then = (f"anneal the learning rate to its floor over {self._cool_len:.0f} s "
                        f"({frac:.0%} of the training time so far), then stop")
            w = len(self._recent)
            what = "held-out PSNR" if w == 1 else f"mean held-out PSNR of the last {w} evaluations"
            self.record("early_stop", True, f"{what} plateaued: no gain > {self.min_gain_db} dB over "
                        f"{self._evals_since_best} evaluations{span} (best {self._best_psnr:.2f} dB): {then}", step)

    def lr_after_plateau(self, wall: float, f_now: float) -> float:
        """Learning-rate factor once the plateau rule fired: a cosine from the factor at that
        moment ``f0`` to the floor ``alpha`` over the cool-down ``D`` (``plateau_cooldown_frac``
        of the training time at the plateau),
        ``f = alpha + (f0 - alpha) (1 + cos(pi q)) / 2``, ``q = (wall - t_plateau) / D``, never
        above the regular schedule ``f_now``; at ``q >= 1`` the run stops. Before the plateau
        it returns ``f_now`` unchanged. (The regular schedule would anneal only at the end of
        the budget; a run stopped at a plateau would otherwise end at a high learning rate.)"""
        if self._cool_start is None:
            return f_now
        alpha = self.cfg.train.lr_alpha
        if self._cool_f0 is None:
            self._cool_f0 = f_now
        q = (wall - self._cool_start) / max(self._cool_len, 1e-9)
        if q >= 1.0:
            self.stop_requested = True
            return alpha
        return min(f_now, alpha + (self._cool_f0 - alpha) * 0.5 * (1.0 + math.cos(math.pi * max(q, 0.0))))

    def write_report(self, path: Path, *, step: int, status: str, nonfinite: int) -> dict:
        if self.enabled and self.cfg.render.specular and self._stats and \
                not any(d["decision"] == "specular_lobe" for d in self.decisions):
            st = self._stats
            gain = st.get("lobe_residual_gain")
            spread = st.get("radiance_view_spread")
            self.record("specular_lobe", True, "kept: " + (
                        "" if spread is None else f"the learned radiance changes by {spread:.2%} across the training "
                        f"cameras (drop below {self.view_spread_thr:.1%}); ") + "at the last check the mean surface metallic was "
                        f"{st['surf_metallic']:.3f} (drop below {self.metal_thr}), the lobe's share of L_surf "
                        f"{st['specular_share']:.1%} (drop below {self.spec_thr:.0%})"
                        + ("" if gain is None else f", and without it the surface error would be {gain:+.0%}"),
                        step)
        if self.enabled and self.cfg.render.specular and self._stats and \
                not any(d["decision"] == "dielectric" for d in self.decisions):
            self.record("dielectric", False, "metallic left free: " + self._metallic_free_reason(), step)
        rep = {"status": status, "step": step, "nonfinite_steps": nonfinite, "decisions": self.decisions,
               "final_switches": {"specular": self.cfg.render.specular, "mask_loss": self.use_mask_loss,
                                  "background": self.cfg.model.background, "w_hessian": self.cfg.loss.w_hessian,
                                  "metallic_scale": self.cfg.render.metallic_scale}}
        if self._occ_frac is not None:
            rep["occupied_fraction"] = self._occ_frac
        if self._drop_n:
            rep["rays_left_out_fraction"] = self._drop_sum / self._drop_n
            rep["rays_left_out_note"] = ("mean over training steps of the share of drawn rays left out of the batch "
                                         "because they meet no occupied cell (a random miss_keep share of those stays)")
        if self._skip_n:
            rep["samples_saved_fraction"] = self._skip_sum / self._skip_n
            rep["samples_saved_note"] = ("mean over training steps and rays of the share of each ray's [near, far] in "
                                         "the unit sphere that the occupancy grid skipped as empty (no samples there)")
        Path(path).write_text(json.dumps(rep, indent=2))
        return rep
