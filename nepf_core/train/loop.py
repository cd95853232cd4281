"""``fit()``: the single-stage NePF training loop.

Per step: the schedule (NeuS cosine annealing, coarse-to-fine grid levels, the learning rate
after the rules' ``before_step``: cool-down, stop, occupancy refresh) -> draw rays -> the rules'
``on_batch`` (rays that meet no occupied cell mostly left out, evidence asked of the render) ->
render (L_r, L_vol, L_surf from one set of samples) -> losses -> Adam step (skipped and counted
when the loss or gradient is non-finite) -> the rules' ``after_step`` -> records. The rules are
step callbacks (:mod:`nepf_core.train.rules.callback`) that :class:`Adaptivity` calls in order;
the loop never names one. Around the steps: sync-PSNR on training views, held-out evaluation on
a wall-clock schedule, checkpoints, a time budget and a cooperative stop. Hooks
(:class:`nepf_core.train.hooks.TrainHooks`) observe the steps, evaluations and checkpoints.

Optimiser: Adam, ``betas = (0.9, 0.99)``, ``eps = 1e-15``, fused where available, two parameter
groups (grid tables at ``train.lr_grid``, the rest at ``train.lr``);
:func:`nepf_core.train.setup.make_optimizer` says why.

``wall_s`` in every record counts training time only (:mod:`nepf_core.train.clock`).
"""

from __future__ import annotations

import dataclasses
from contextlib import nullcontext
from pathlib import Path
from typing import Sequence

import numpy as np
import torch

from nepf_core.callbacks import FitCallbacks
from nepf_core.checkpoint import load_checkpoint, prune_checkpoints, save_checkpoint
from nepf_core.config import NePFConfig
from nepf_core.data.scene import Scene
from nepf_core.losses import compute_losses, needs_jitter_normals, needs_lobe_split, total_loss
from nepf_core.model import NePFModel
from nepf_core.rays import PixelSampler
from nepf_core.render.material_evidence import gather_evidence
from nepf_core.render.neus import foreground
from nepf_core.render.renderer import SurfaceRequest, render_background_only, render_rays
from nepf_core.reframe import reframe_scene
from nepf_core.resume import cut_metrics_to_checkpoint, write_checkpoint_info
from nepf_core.train.adaptivity import Adaptivity
from nepf_core.train.decisions import Decision
from nepf_core.train.clock import TrainClock
from nepf_core.train.evaluation import EvalTargets, evaluate_test, sync_psnr
from nepf_core.train.hooks import TrainHooks
from nepf_core.train.metal_record import MetalRecord
from nepf_core.train.metrics_log import MetricsLog, plot_error_vs_time, write_json_atomic
from nepf_core.train.result import FitError, FitResult
from nepf_core.train.rules.callback import DataContext, EvaluationContext, ModelContext, StepBatch, StepEnd, StepStart
from nepf_core.train.run_state import RunState
from nepf_core.train.schedule import (coarse_to_fine, cos_anneal_ratio, progress_fraction, run_eta,
                                     scheduled_lr_factor)
from nepf_core.train.setup import init_radiance_to_data, make_optimizer, place_lights, resolve_device, unlit_pixels
from nepf_core.train.surface_points import SurfacePointPrior
from nepf_core.up_axis import camera_up_world
from nepf_core.weight_average import ParamEMA


def fit(scene: Scene, run_dir, cfg: NePFConfig, *, device: str = "auto", callbacks: FitCallbacks | None = None,
        resume: bool = False, time_budget_s: float | None = None, targets: EvalTargets | None = None,
        iters_fixed: bool = True, log=None, hooks: Sequence[TrainHooks] = (), rules: dict | None = None) -> FitResult:
    """Train NePF on ``scene`` and write ``run_dir`` (see docs/ARCHITECTURE.md "Run folder").

    Args:
        scene: training views (normalised frame).
        cfg: a preset from :mod:`nepf_core.config`, possibly edited; never written to.
        device: ``auto | cpu | cuda``.
        resume: continue from ``run_dir/checkpoints/latest.pt`` (exact: same losses as an
            uninterrupted run on the same device).
        time_budget_s: stop after this many seconds of training wall time.
        targets: held-out views / GT mesh / GT albedo for error-against-time records.
        iters_fixed: the user fixed the iteration count (disables plateau early stop).
        hooks: observers of steps, evaluations and checkpoints.
        rules: overrides of the ``rules`` section (:class:`~nepf_core.train.rules.config.RuleConfig`
            field names; tests and probes).
    Returns:
        :class:`FitResult` (status ``succeeded``, ``cancelled`` or ``stopped_early``).
    """
    run = TrainingRun(scene, run_dir, cfg, device=device, callbacks=callbacks, resume=resume,
                      time_budget_s=time_budget_s, targets=targets, iters_fixed=iters_fixed, log=log,
                      hooks=hooks, rules=rules)
    return run.train()


class TrainingRun:
    """One run's model, optimiser, run state, clock and counters; hooks receive it."""

    def __init__(self, scene: Scene, run_dir, cfg: NePFConfig, *, device: str, callbacks: FitCallbacks | None,
                 resume: bool, time_budget_s: float | None, targets: EvalTargets | None, iters_fixed: bool,
                 log, hooks: Sequence[TrainHooks], rules: dict | None) -> None:
        self.scene, self.cfg, self.targets = scene, cfg, targets
        self.callbacks = callbacks or FitCallbacks()
        self.hooks = list(hooks)
        self.say = log or (lambda *a: None)
        self.time_budget_s = time_budget_s
        self.dir = Path(run_dir)
        (self.dir / "checkpoints").mkdir(parents=True, exist_ok=True)
        self.device = dev = resolve_device(device)
        tc = cfg.train
        torch.manual_seed(tc.seed)
        np.random.seed(tc.seed)

        cfg.check()
        self.run_state = RunState.from_config(cfg)
        rule_cfg = dataclasses.replace(cfg, rules=dataclasses.replace(cfg.rules, **(rules or {})))
        self.adaptivity = Adaptivity(rule_cfg, self.run_state, iters_fixed=iters_fixed)
        data = self.adaptivity.on_data(DataContext(scene))
        scene = self.scene = data.scene   # maybe in the object's frame
        # the cameras' mean up vector in the input's world: the export's up axis (nepf_core.up_axis)
        self.camera_up = camera_up_world(scene.c2w, scene.world_from_norm)
        if targets is not None and targets.test_scene is not None:
            self.targets = targets = dataclasses.replace(
                targets, test_scene=reframe_scene(targets.test_scene, scene.world_from_norm))
        (self.dir / "config.json").write_text(cfg.to_json())   # what the user asked for, never updated

        self.model = NePFModel(self.run_state.model_config(cfg.model)).to(dev)
        init_radiance_to_data(self.model, scene)
        place_lights(self.model, scene)
        self.optimizer = make_optimizer(self.model, tc.lr, tc.lr_grid)
        self.gen = torch.Generator().manual_seed(tc.seed)
        self.ema = ParamEMA(self.model, tc.ema_decay) if tc.ema_decay != 0 else None   # a negative one: ParamEMA says so
        self.sampler = PixelSampler(scene, dev)
        self.camera_centres = torch.as_tensor(np.asarray(scene.c2w)[:, :3, 3], dtype=torch.float32, device=dev)
        points = data.surface_points   # without masks: where the images saw a surface
        self.surface_points = (SurfacePointPrior(points, dev) if cfg.loss.w_surface_points > 0 and points is not None
                               and len(points) else None)
        # where the metal evidence said metal, the unseen-lobe prior is lifted (train/metal_record.py)
        self.metal_record = (MetalRecord(dev) if cfg.loss.w_material_evidence > 0 and cfg.loss.w_metallic_unseen > 0
                             else None)
        self.unlit_thr, decision = unlit_pixels(scene, cfg.render.unlit_albedo_stopgrad, tc.unlit_rel_threshold)
        self.adaptivity.log_decision(decision)
        self.adaptivity.on_model(ModelContext(self.model, scene))
        # the render settings in effect (bf16 heads only on CUDA); evaluations use the same
        self.run_cfg = dataclasses.replace(cfg, render=dataclasses.replace(cfg.render, amp_heads=bool(tc.amp and dev.type == "cuda")))

        self.step, self.nonfinite, wall_before = 0, 0, 0.0
        self.latest = self.dir / "checkpoints" / "latest.pt"
        if resume and self.latest.exists():
            wall_before = self._restore()
            # the steps after the checkpoint are trained again: their old records go (resume.py)
            cut_metrics_to_checkpoint(self.dir, self.step)
        elif not resume:
            (self.dir / "metrics.jsonl").unlink(missing_ok=True)
        self.mlog = MetricsLog(self.dir / "metrics.jsonl", self.callbacks)
        self.total = tc.iters
        self.sync_views = list(np.linspace(0, scene.n_views - 1, min(tc.sync_views, scene.n_views)).round().astype(int))
        self.clock = TrainClock(wall_before)
        self.last_eval_wall = wall_before
        self.last_test: dict = {}
        self.anneal = 1.0
        self._shading_seen = (self.run_state.specular, self.run_state.diffuse_metal_weight)

    def _restore(self) -> float:
        st = load_checkpoint(self.latest, model=self.model, optimizer=self.optimizer, generator=self.gen,
                             map_location=self.device)
        extra = st["extra"]
        self.step, self.nonfinite = int(st["step"]), int(extra.get("nonfinite", 0))
        self.adaptivity.load_state_dict(extra.get("adaptivity", {}))
        restored = RunState.from_checkpoint(extra, self.cfg)
        for k, v in restored.to_dict().items():   # in place: the rules act on this object
            setattr(self.run_state, k, v)
        if self.ema is not None and "ema" in extra:
            self.ema.load_state_dict(extra["ema"])
        if self.metal_record is not None and "metal_record" in extra:
            self.metal_record.load_state_dict(extra["metal_record"])
        self.say(f"resumed from step {self.step}")
        return float(st["wall_s"])

    # -- clocks --
    def progress(self) -> float:
        return progress_fraction(self.step, self.total, self.clock.wall(), self.time_budget_s)

    def emit_progress(self, stage: str) -> None:
        w = self.clock.wall()
        frac = self.progress()
        eta, ends_by = run_eta(self.step, self.total, w, self.time_budget_s)
        info = {"step": self.step, "total": self.total, "fraction": frac, "stage": stage,
                "eta_s": None if eta is None else round(eta, 1), "ends_by": ends_by, "wall_s": round(w, 3)}
        self.callbacks.progress(info)
        if self.step % 10 == 0 or stage != "training":
            write_json_atomic(self.dir / "progress.json", info)

    # -- the loop --
    def train(self) -> FitResult:
        status = "succeeded"
        self.model.train()
        self.emit_progress("training")
        self._t_log, self._n_rays, self._n_samples, self._n_background_rays = self.clock.wall(), 0, 0, 0
        try:
            while self.step < self.total:
                if self.callbacks.stop_requested():
                    status = "cancelled"
                    break
                if self.time_budget_s is not None and self.clock.wall() >= self.time_budget_s:
                    break
                if not self._set_schedule():   # plateau: at once, or at the end of its cool-down
                    status = "stopped_early"
                    break
                for h in self.hooks:
                    h.before_step(self, self.step)
                rays, out, losses = self._train_step()
                self._after_step(rays, out, losses)
            self.checkpoint()
            self.evaluate(final=True)
        except FitError as e:
            self.adaptivity.log_decision(Decision("failed", True, str(e), self.step))
            self._write_report("failed")
            raise
        finally:
            self.mlog.close()
        report = self._write_report(status)
        self.emit_progress("finished" if status == "succeeded" else status)
        plot_error_vs_time(self.dir)
        return FitResult(status=status, step=self.step, total=self.total, wall_s=self.clock.wall(),
                         run_dir=str(self.dir), nonfinite_steps=self.nonfinite, last_test=self.last_test, report=report)

    def _set_schedule(self) -> bool:
        """Annealing, grid levels, then the rules' step start (a lower learning-rate factor, the
        occupancy refresh), then the learning rate; False when a rule ends the run."""
        tc, p = self.cfg.train, self.progress()
        self.anneal = cos_anneal_ratio(p, self.total, tc.anneal_end)
        if hasattr(self.model.sdf, "set_progress"):
            self.model.sdf.set_progress(coarse_to_fine(p, tc.coarse_to_fine_frac))
        start = self.adaptivity.before_step(StepStart(
            step=self.step, wall=self.clock.wall(), progress=p, model=self.model,
            lr_factor=scheduled_lr_factor(self.step, p, self.total, tc, budgeted=bool(self.time_budget_s))))
        if start.stop:
            return False
        for group in self.optimizer.param_groups:
            group["lr"] = group["base_lr"] * start.lr_factor
        return True

    def _train_step(self):
        """Draw, render, take the losses and the optimiser step; returns ``(rays, out, losses)``."""
        tc, rs, model = self.cfg.train, self.run_state, self.model
        rays = self.sampler.sample(tc.batch_rays, generator=self.gen)
        if self.unlit_thr is not None:
            rays.unlit = rays.rgb.amax(-1) < self.unlit_thr
        loss_cfg = rs.loss_config(self.cfg.loss)
        batch = self.adaptivity.on_batch(StepBatch(step=self.step, model=model, rays=rays, generator=self.gen,
                                                   request=SurfaceRequest(lobe_split=needs_lobe_split(loss_cfg),
                                                                          jitter_normals=needs_jitter_normals(loss_cfg))))
        rays, left_out = batch.rays, batch.left_out
        out = render_rays(model, rays, self.run_cfg.render, train=True, cos_anneal=self.anneal, generator=self.gen,
                          request=batch.request, shading=rs.shading())
        background_rays = None   # the misses left out still show the background: it alone renders them
        if left_out is not None:
            c_bg, z_bg = render_background_only(model, left_out, self.run_cfg.render, train=True, generator=self.gen,
                                                with_logits=True)
            background_rays = (c_bg, left_out)
            out.colour_logits = torch.cat([out.colour_logits, z_bg])
        self._n_background_rays = 0 if background_rays is None else len(left_out)
        if loss_cfg.w_material_evidence > 0:
            out.material_evidence = self._material_evidence(rays, out, rs.specular)
            if self.metal_record is not None:
                ev, x = out.material_evidence.evidence, out.surface.x
                self.metal_record.update(x[out.material_evidence.rays], ev.metallic, ev.metallic_confidence)
                out.metal_share = self.metal_record.metal_share(x)
        points = None if self.surface_points is None else (lambda: self.surface_points.loss(model, self.gen))
        losses = compute_losses(out, rays, loss_cfg, use_mask=rs.use_mask_loss, specular=rs.specular,
                                background=rs.background, background_rays=background_rays, surface_points=points)
        loss = losses["loss"] = total_loss(losses, loss_cfg)
        for h in self.hooks:
            h.before_backward(self, self.step + 1, losses, loss_cfg)
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        gn = torch.nn.utils.clip_grad_norm_(model.parameters(), tc.grad_clip if tc.grad_clip > 0 else float("inf"))
        if bool(torch.isfinite(loss.detach()) & torch.isfinite(gn)):
            self.optimizer.step()
            if self.ema is not None:
                self.ema.update(model)
        else:
            self.nonfinite += 1
            self.optimizer.zero_grad(set_to_none=True)
            if self.nonfinite > tc.max_nonfinite_steps:
                raise FitError(f"training diverged: {self.nonfinite} steps had a non-finite loss or gradient "
                               f"(limit {tc.max_nonfinite_steps}); last at step {self.step}")
        self.step += 1
        return rays, out, losses

    def _material_evidence(self, rays, out, specular: bool):
        """The material evidence (:mod:`nepf_core.render.material_evidence`) at some lit foreground
        rays' surface points, for ``loss.w_material_evidence``; none once the lobe is dropped (the
        shading then ignores the metallic, and the evidence is about the lobe)."""
        keep = foreground(out.weight_sum) & specular
        if rays.mask is not None:
            keep = keep & (rays.mask > 0.5)
        if rays.unlit is not None:
            keep = keep & ~rays.unlit
        s = out.surface
        return gather_evidence(self.model, s.x, s.normal, s.light_dir, keep, self.camera_centres, self.gen)

    def _after_step(self, rays, out, losses) -> None:
        """The rules, the weight average's restart, records, sync/held-out evaluations, checkpoints."""
        tc, step = self.cfg.train, self.step
        self._n_rays += len(rays)
        self._n_samples += out.n_samples
        self.adaptivity.after_step(StepEnd(step=step, model=self.model, rays=rays, out=out, losses=losses))
        shading = (self.run_state.specular, self.run_state.diffuse_metal_weight)
        if self.ema is not None and shading != self._shading_seen:
            self.ema.reset(self.model)   # weights averaged across a change of the shading model do not fit it
        self._shading_seen = shading
        for h in self.hooks:
            h.after_step(self, step, out, losses)
        if step % tc.log_every == 0 or step == self.total:
            self._log_train(rays, out, losses)
        if tc.sync_every > 0 and step % tc.sync_every == 0:
            with self.clock.paused():
                s = sync_psnr(self.model, self.sampler, self.run_cfg, self.sync_views, tc.sync_rays, tc.seed + 1,
                              shading=self.run_state.shading())
                s.update({"kind": "sync", "step": step, "wall_s": round(self.clock.wall(), 3)})
            self.mlog.write(s)
        if tc.eval_every_s > 0 and self.clock.wall() - self.last_eval_wall >= tc.eval_every_s:
            self.evaluate(final=False)
        if step % tc.checkpoint_every == 0:
            self.checkpoint()
        self.emit_progress("training")

    def _log_train(self, rays, out, losses) -> None:
        dt = max(self.clock.wall() - self._t_log, 1e-9)   # training time: evaluations and checkpoints are not steps
        rec = {"step": self.step, "wall_s": round(self.clock.wall(), 3), "kind": "train"}
        rec.update({k: float(v.detach()) for k, v in losses.items()})
        rec.update({"inv_s": float(out.inv_s), "lr": self.optimizer.param_groups[0]["lr"], "batch_rays": len(rays),
                    "background_only_rays": self._n_background_rays, "rays_per_s": self._n_rays / dt,
                    "samples_per_s": self._n_samples / dt,
                    "head_evals": out.n_head_evals, "nonfinite_steps": self.nonfinite,
                    "specular_on": bool(self.run_state.specular)})
        rec.update(self.adaptivity.step_stats())
        self.mlog.write(rec)
        self._t_log, self._n_rays, self._n_samples = self.clock.wall(), 0, 0

    # -- evaluation, checkpoints, report --
    def evaluate(self, final: bool) -> None:
        """Held-out metrics (with the weight average applied), one ``kind == "test"`` record."""
        if self.targets is None or self.targets.test_scene is None:
            return
        with self.clock.paused():
            w_train = self.clock.wall()   # training time at the start of this evaluation
            self.emit_progress("evaluating")
            with self.ema.applied(self.model) if self.ema is not None else nullcontext():
                stride = max(self.cfg.train.eval_stride, self.targets.stride or 1)
                rec = evaluate_test(self.model, self.run_cfg, self.targets, self.device, self.scene.world_from_norm,
                                    stride, with_chamfer=True, shading=self.run_state.shading(), preview_dir=self.dir)
            rec.update({"kind": "test", "step": self.step, "wall_s": round(w_train, 3), "final": final,
                        "eval_stride": stride})
            for h in self.hooks:
                h.on_evaluation(self, rec)
            self.mlog.write(rec)
            self.last_test = rec
            self.adaptivity.on_evaluation(EvaluationContext(self.step, rec, progress=self.progress()))
        self.last_eval_wall = self.clock.wall()

    def checkpoint(self) -> None:
        """``ckpt_<step>.pt`` and ``latest.pt``: weights, optimiser, RNG, run state, rule counters."""
        with self.clock.paused():
            extra = {"nonfinite": self.nonfinite, "adaptivity": self.adaptivity.state_dict(),
                     "run_state": self.run_state.to_dict(), "config_name": self.cfg.name,
                     "world_from_norm": np.asarray(self.scene.world_from_norm, dtype=np.float64).tolist(),
                     "camera_up": [float(c) for c in self.camera_up]}
            if self.ema is not None:
                extra["ema"] = self.ema.state_dict()
            if self.metal_record is not None:
                extra["metal_record"] = self.metal_record.state_dict()
            kw = dict(model=self.model, optimizer=self.optimizer, step=self.step, wall_s=self.clock.wall(),
                      generator=self.gen, extra=extra)
            save_checkpoint(self.dir / "checkpoints" / f"ckpt_{self.step:07d}.pt", **kw)
            save_checkpoint(self.latest, **kw)
            write_checkpoint_info(self.dir, self.step, kw["wall_s"], self.mlog.size())   # after latest.pt
            prune_checkpoints(self.dir / "checkpoints", self.cfg.train.keep_checkpoints)
            self.callbacks.checkpoint(self.step, str(self.latest))
            for h in self.hooks:
                h.on_checkpoint(self, self.step, str(self.latest))

    def _write_report(self, status: str) -> dict:
        rep = self.adaptivity.report(step=self.step, status=status, nonfinite=self.nonfinite)
        if self.targets is not None and self.targets.split is not None:
            rep["split"] = self.targets.split   # which views were held out of training
        write_json_atomic(self.dir / "report.json", rep)
        return rep
