"""Adaptivity: leaving out what a scene does not need, every decision recorded.

:class:`Adaptivity` runs the rules of :mod:`nepf_core.train.rules` (each reads the frozen
:class:`~nepf_core.train.rules.config.RuleConfig`, the config's ``rules`` section, and returns decisions) and applies their
decisions to the :class:`~nepf_core.train.run_state.RunState`, the only place where the
switches in effect live. It also keeps the statistics that go to ``metrics.jsonl`` and
``report.json``.
"""

from __future__ import annotations

import copy

import numpy as np
import torch

from nepf_core.reframe import object_world_from_norm, reframe_scene
from nepf_core.render.surface import SurfaceRequest
from nepf_core.train.decisions import Decision, DecisionLog
from nepf_core.train.rules.empty_rays import EmptyRayRule
from nepf_core.train.rules.hessian import HessianRule
from nepf_core.train.rules.masks import decide_masks, decide_object_region, lit_outside_masks
from nepf_core.train.rules.occupancy import carve_visual_hull, empty_space_decision, refresh_occupancy
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
        self.specular = SpecularRule(cfg)
        self.hessian = HessianRule(cfg)
        self.plateau = PlateauRule(cfg, iters_fixed)
        self.empty_rays = EmptyRayRule(cfg)
        self.occupied_fraction: float | None = None
        self.cams: torch.Tensor | None = None
        self._check = False   # the render of this step is a specular check (request -> after_step)

    @property
    def decisions(self) -> list[dict]:
        return self.log.records

    @property
    def stop_requested(self) -> bool:
        return self.plateau.stop_requested

    def record(self, decision: Decision | None) -> None:
        """Log ``decision`` and apply it to the run state."""
        if decision is None:
            return
        self.log.add(decision)
        rs = self.run_state
        if decision.name == "specular_lobe":
            rs.specular = bool(decision.value)
            if not rs.specular:
                rs.diffuse_metal_weight = 1.0   # the same image at the drop, then the fade
            self.plateau.restart()              # the shading model changed
        elif decision.name == "hessian_loss":
            rs.w_hessian = self.cfg.loss.w_hessian if decision.value else 0.0

    # -- before training --
    def before_training(self, scene):
        """Decisions from the data: mask loss, background model, the object region without masks,
        what the occupancy grid is for. Returns the scene to train on: ``scene`` itself, or, when a
        capture without masks has a support plane, ``scene`` in the frame whose unit sphere
        encloses the object (:func:`nepf_core.train.rules.masks.decide_object_region`); held-out
        views must then be expressed in it too (``reframe_scene(test, scene.world_from_norm)``)."""
        self.surface_points = None
        """Without masks: the points triangulated in the object region ``[P, 3]`` (or None)."""
        lit = lit_outside_masks(scene.images, scene.masks) if scene.has_masks else 0.0
        use, background, decisions = decide_masks(scene.has_masks, self.cfg.loss.w_mask, lit)
        self.run_state.use_mask_loss, self.run_state.background = use, background
        if background and not scene.has_masks:
            self.run_state.object_halfspace, region, self.surface_points, frame = decide_object_region(scene)
            decisions.extend(region)
            if frame is not None:
                scene = reframe_scene(scene, object_world_from_norm(scene.world_from_norm, *frame))
        c2w = getattr(scene, "c2w", None)
        self.cams = None if c2w is None else torch.as_tensor(np.asarray(c2w)[:, :3, 3], dtype=torch.float32)
        for d in decisions:
            self.record(d)
        self.record(empty_space_decision(self.cfg))
        if not self.enabled:
            self.record(Decision("adaptive", False, "adaptivity disabled: every term stays on"))
        return scene

    def start_occupancy(self, model, scene) -> None:
        self.record(carve_visual_hull(model, scene, self.cfg))

    # -- during training --
    def refresh_occupancy(self, model, step: int) -> None:
        self.occupied_fraction = refresh_occupancy(model, step)

    def thin_empty_rays(self, model, rays, step: int, generator: torch.Generator | None = None):
        """``(kept, left_out)``: the rays to render with the SDF and the misses left out (None when
        none was); see :class:`nepf_core.train.rules.empty_rays.EmptyRayRule`."""
        kept, left_out, decision = self.empty_rays.thin(model, rays, step, generator,
                                                        first=not self.log.has("empty_rays"))
        self.record(decision)
        return kept, left_out

    def request(self, step: int) -> SurfaceRequest:
        """What the rules read from the render of step ``step`` (before it): the lobe split at the
        specular rule's checks (every ``check_every`` steps)."""
        self._check = self.specular.wants_evidence(step)
        return SurfaceRequest(lobe_split=self._check)

    def after_step(self, step: int, out, losses: dict, *, model=None, rays=None, check: bool | None = None) -> None:
        """The per-step rules once the optimiser step has made the step count ``step``, in order: the
        check's lobe evidence (from ``model``, ``out`` and its ``rays``, when given), eikonal EMA, the
        lobe's fade, Hessian, lobe decision. ``check``: whether ``out`` is a specular check's render
        (None: whether :meth:`request` asked for one)."""
        check = self._check if check is None else check
        self._check = False
        if check and rays is not None:
            self.specular.observe(step, model, out, rays, self.cams, self.run_state.specular)
        eik = float(losses["loss_eik"].detach()) if "loss_eik" in losses else 0.0
        self.hessian.observe(eik)
        if not self.enabled:
            return
        rs = self.run_state
        w = self.specular.fade_weight(step, rs.specular, rs.diffuse_metal_weight)
        if w is not None:
            rs.diffuse_metal_weight = w
            if w <= 0.0:
                self.plateau.restart()   # the fade is over: the model from here on is the one to judge
        self.record(self.hessian.decide(step, rs.w_hessian))
        if check:
            for d in self.specular.decide(step, out, rs.specular):
                self.record(d)

    def on_test_eval(self, step: int, rec: dict, progress: float | None = None) -> None:
        self.record(self.plateau.on_test_eval(step, rec, progress))

    def lr_factor(self, wall: float, f_now: float) -> float:
        return self.plateau.lr_factor(wall, f_now)

    def step_stats(self) -> dict:
        """Statistics for the step's ``metrics.jsonl`` record."""
        s = self.specular.step_stats(self.run_state.specular)
        if self.occupied_fraction is not None:
            s["occupied_fraction"] = self.occupied_fraction
        if self.empty_rays.last is not None:
            s["rays_left_out"] = self.empty_rays.last
        return s

    # -- checkpoint and report --
    def state(self) -> dict:
        return {"decisions": self.log.records, "specular_rule": self.specular.state(),
                "hessian_rule": self.hessian.state(), "plateau_rule": self.plateau.state(),
                "empty_rays_rule": self.empty_rays.state()}

    def load_state(self, s: dict) -> None:
        if not s:
            return
        self.log = DecisionLog(s.get("decisions", []))
        self.specular.load_state(s.get("specular_rule", {}))
        self.hessian.load_state(s.get("hessian_rule", {}))
        self.plateau.load_state(s.get("plateau_rule", {}))
        self.empty_rays.load_state(s.get("empty_rays_rule", {}))

    def report(self, *, step: int, status: str, nonfinite: int) -> dict:
        """``report.json``: status, decisions, the final switches and the run state, empty-space
        statistics."""
        rs = self.run_state
        if self.enabled and rs.specular and self.specular.stats and not self.log.has("specular_lobe"):
            self.log.add(self.specular.kept_report(step))   # a record only: nothing changes
        rep = {"status": status, "step": step, "nonfinite_steps": nonfinite, "decisions": self.log.records,
               "final_switches": {"specular": rs.specular, "mask_loss": rs.use_mask_loss,
                                  "background": rs.background, "w_hessian": rs.w_hessian},
               "run_state": rs.to_dict()}
        if self.occupied_fraction is not None:
            rep["occupied_fraction"] = self.occupied_fraction
        left_out = self.empty_rays.mean_left_out()
        if left_out is not None:
            rep["rays_left_out_fraction"] = left_out
            rep["rays_left_out_note"] = ("mean over training steps of the share of drawn rays left out of the batch "
                                         "because they meet no occupied cell (a random miss_keep share of those stays)")
        return rep
