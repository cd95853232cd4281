"""``fit()``: the single-stage NePF training loop, a plain function with callbacks.

Per step: draw rays -> render (L_r, L_vol, L_surf from one set of samples) -> losses ->
Adam step (skipped and counted when the loss or gradient is non-finite). Around it:
NeuS learning-rate schedule (linear warm-up, cosine to ``lr_alpha``), cosine annealing,
coarse-to-fine grid levels and occupancy refreshes (fast preset), sync-PSNR on training
views, held-out evaluation on a wall-clock schedule, checkpoints, a time budget and a
cooperative stop.

``wall_s`` in every record counts training time only: sync and held-out evaluations,
checkpoint writes and mesh extraction for Chamfer are excluded.
"""

from __future__ import annotations

import json
import math
import os
import time
from contextlib import nullcontext
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from nepf_core.adaptivity import Adaptivity
from nepf_core.callbacks import FitCallbacks
from nepf_core.checkpoint import load_checkpoint, prune_checkpoints, save_checkpoint
from nepf_core.config import NePFConfig
from nepf_core.data.scene import Scene
from nepf_core.evaluate import albedo_psnr_aligned, psnr, render_view, srgb_np
from nepf_core.losses import compute_losses, srgb_encode
from nepf_core.model import ModelFieldQuery, NePFModel
from nepf_core.rays import PixelSampler, foreground_peaks, unlit_threshold
from nepf_core.render.renderer import render_rays
from nepf_core.weight_average import ParamEMA


class FitError(RuntimeError):
    """Training cannot continue (for example, too many non-finite steps)."""


@dataclass
class EvalTargets:
    """Optional ground truth for held-out evaluation during fit."""

    test_scene: Scene | None = None
    gt_mesh_path: str | None = None
    gt_albedo: np.ndarray | None = None
    """``[N_test, H, W, 3]`` linear albedo of the test views (for albedo PSNR)."""
    chamfer_resolution: int = 128


@dataclass
class FitResult:
    status: str
    step: int
    total: int
    wall_s: float
    run_dir: str
    nonfinite_steps: int = 0
    last_test: dict = field(default_factory=dict)
    report: dict = field(default_factory=dict)


def resolve_device(device: str) -> torch.device:
    """``auto`` -> CUDA when available, else CPU; ``cuda`` without a GPU is a clear error."""
    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise FitError("--device cuda was requested but no CUDA device is available")
    return torch.device(device)


def lr_factor(progress_warm: float, progress: float, alpha: float) -> float:
    """NeuS schedule: ``w`` during warm-up (``w`` in [0,1]); then
    ``((cos(pi p) + 1) / 2) (1 - alpha) + alpha`` for post-warm-up progress ``p``."""
    if progress_warm < 1.0:
        return max(progress_warm, 1e-3)
    return ((math.cos(math.pi * min(progress, 1.0)) + 1.0) * 0.5) * (1.0 - alpha) + alpha


class MetricsLog:
    """Append-only ``metrics.jsonl`` (one JSON object per line, flushed per record).

    A run killed mid-write can leave a partial last line; on resume it is closed with a newline,
    so the first new record starts a line of its own instead of being glued to the broken one.
    """

    def __init__(self, path: Path, callbacks: FitCallbacks) -> None:
        self.path = path
        self.cb = callbacks
        self.f = open(path, "a", encoding="utf-8")
        if path.stat().st_size and not _ends_with_newline(path):
            self.f.write("\n")

    def write(self, rec: dict) -> None:
        clean = {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in rec.items()}
        self.f.write(json.dumps(clean) + "\n")
        self.f.flush()
        self.cb.metrics(clean)

    def close(self) -> None:
        self.f.close()


def _ends_with_newline(path: Path) -> bool:
    with open(path, "rb") as f:
        f.seek(-1, os.SEEK_END)
        return f.read(1) == b"\n"


def _write_json_atomic(path: Path, obj) -> None:
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json.dumps(obj, indent=2))
    os.replace(tmp, path)


def _param_groups(model: NePFModel, cfg: NePFConfig):
    grid, other = [], []
    for name, p in model.named_parameters():
        (grid if ".grid" in name or name.startswith("sdf.encoding") else other).append(p)
    groups = [{"params": other, "lr": cfg.train.lr, "base_lr": cfg.train.lr}]
    if grid:
        groups.append({"params": grid, "lr": cfg.train.lr_grid, "base_lr": cfg.train.lr_grid})
    return groups


def init_radiance_to_data(model: NePFModel, scene: Scene) -> None:
    """Start the radiance network at the mean foreground colour (linear; all pixels without
    masks) by setting its last bias to the logit of it.

    With masks a ray's colour is ``sum_i w_i c_i`` (no background), so from the default grey
    start (sigmoid(0) = 0.5) on a dark or near-mirror scene the cheapest way down the colour
    loss is to make the object transparent: the surface vanished (EmptyMeshError) within
    150 tiny steps (docs/STABILITY.md). A resumed run overwrites this with its checkpoint.
    """
    last = model.radiance.mlp.layers[-1]
    total, count = np.zeros(3), 0
    for k in range(scene.n_views):  # per view: no copy of the whole image set
        px = scene.images[k][scene.masks[k] > 0.5] if scene.masks is not None else scene.images[k].reshape(-1, 3)
        total += px.sum(0, dtype=np.float64)
        count += len(px)
    if count == 0:
        return
    p = torch.as_tensor(total / count, dtype=torch.float32).clamp(1e-3, 0.999)
    with torch.no_grad():
        last.bias.copy_(torch.log(p / (1.0 - p)).to(last.bias))


def init_light_to_data(model: NePFModel, scene: Scene, albedo: float) -> float:
    """Start the photon intensity at ``I0 = pi * q99(max_c L_gt) / albedo`` and return ``I0``.

    Albedo and intensity share a scale (``L = c/pi * I * cos`` for a diffuse surface), so
    the data fix only their product. From the fixed start ``I0 = 3`` the albedo of a bright
    scene climbs into the flat top of its sigmoid: on spot_textured (q99 = 1.0, clipped) it sat
    at 0.99 in every pixel after 90 s, its gradient vanished, and the texture could not be
    learned (albedo PSNR stayed that of a constant, 12.04 dB). Choosing the scale from the
    data keeps the brightest pixels at albedo ``albedo`` (< 1) for head-on light.
    ``scene.images [N, H, W, 3]`` linear.
    """
    q99 = float(np.quantile(foreground_peaks(scene.images, scene.masks)[::7], 0.99)) if scene.n_views else 0.0
    i0 = math.pi * max(q99, 1e-3) / albedo
    with torch.no_grad():
        model.photon.set_init_intensity(i0)
    return i0


def sync_psnr(model, sampler: PixelSampler, cfg: NePFConfig, views: list[int], n_rays: int, seed: int) -> dict:
    """PSNR (sRGB) of L_r, L_surf and L_vol against the images on fixed pixels of ``views``.

    With masks only foreground pixels count (L_surf is a surface quantity)."""
    g = torch.Generator().manual_seed(seed)
    rays = sampler.sample(n_rays, generator=g, views=torch.tensor(views))
    outs = {"r": [], "surf": [], "vol": []}
    was = model.training
    model.eval()
    for a in range(0, len(rays), 1024):
        rb = rays.slice(a, a + 1024)
        o = render_rays(model, rb, cfg.render, train=False)
        outs["r"].append(o.rgb_r.detach()); outs["surf"].append((o.rgb_surf * o.weight_sum.clamp(0, 1)[:, None]).detach())
        outs["vol"].append(o.rgb_vol.detach())
    model.train(was)
    gt = srgb_encode(rays.rgb).cpu().numpy()
    m = None if rays.mask is None else rays.mask.cpu().numpy() > 0.5
    res = {}
    for k, v in outs.items():
        pred = srgb_encode(torch.cat(v)).cpu().numpy()
        res[f"psnr_{k}"] = psnr(pred, gt, m)
    return res


def evaluate_test(model, cfg: NePFConfig, targets: EvalTargets, device, world_from_norm: np.ndarray,
                  stride: int, with_chamfer: bool) -> dict:
    """Held-out metrics: masked/full PBR PSNR, aligned albedo PSNR, Chamfer (when given).

    ``test_psnr`` / ``test_psnr_full`` score the surface PBR colour (the method's relightable
    output); ``test_psnr_radiance`` / ``test_psnr_radiance_full`` score the outgoing-radiance
    network's volume-rendered colour ``sum_i w_i c_r(x_i, v)`` on the same pixels (the quantity a
    plain NeuS reports, so NePF can be compared with one).

    ``albedo_psnr`` is over every foreground pixel; ``albedo_psnr_lit`` only over foreground
    pixels whose test image is lit (``max_c L_gt >= unlit_rel_threshold * q99``, the training
    rule), with ``lit_fraction`` their share of the foreground.
    """
    ts = targets.test_scene
    sampler = PixelSampler(ts, device)
    preds, rads, albs = [], [], []
    for k in range(ts.n_views):
        r = render_view(model, sampler, k, cfg.render, stride=stride)
        preds.append(r["pbr"]); rads.append(r["radiance"]); albs.append(r["albedo"])
    gt = ts.images[:, ::stride, ::stride]
    gt_srgb = srgb_np(gt)
    m = None if ts.masks is None else ts.masks[:, ::stride, ::stride]
    rec = {}
    for key, colour in (("test_psnr", preds), ("test_psnr_radiance", rads)):
        c = srgb_np(np.stack(colour))
        rec[key + "_full"] = psnr(c, gt_srgb)
        rec[key] = rec[key + "_full"] if m is None else psnr(c, gt_srgb, m)
    if targets.gt_albedo is not None and ts.masks is not None:
        ga = targets.gt_albedo[:, ::stride, ::stride]
        alb = np.stack(albs)
        rec["albedo_psnr"], _ = albedo_psnr_aligned(alb, ga, m)
        # the same metric on the observable pixels only: a pixel the light never reaches carries
        # no albedo information in any view (fixed light), so there any albedo fits the images
        lit = (m > 0.5) & (gt.max(-1) >= unlit_threshold(ts.images, ts.masks, cfg.render.unlit_rel_threshold))
        if lit.any():
            rec["albedo_psnr_lit"], _ = albedo_psnr_aligned(alb, ga, lit)
            rec["lit_fraction"] = float(lit.sum() / max((m > 0.5).sum(), 1))
    if with_chamfer and targets.gt_mesh_path:
        from nepf_core.meshing import chamfer_against_gt
        try:
            cd_world, cd_unit = chamfer_against_gt(ModelFieldQuery(model), world_from_norm, targets.gt_mesh_path,
                                                   resolution=targets.chamfer_resolution)
            rec["chamfer"] = cd_unit
            rec["chamfer_world"] = cd_world
        except ValueError as e:  # no surface yet
            rec["chamfer_error"] = str(e)
    return rec


def fit(scene: Scene, run_dir, cfg: NePFConfig, *, device: str = "auto", callbacks: FitCallbacks | None = None,
        resume: bool = False, time_budget_s: float | None = None, targets: EvalTargets | None = None,
        iters_fixed: bool = True, log=None) -> FitResult:
    """Train NePF on ``scene`` and write ``run_dir`` (see docs/ARCHITECTURE.md "Run folder").

    Args:
        scene: training views (normalised frame).
        cfg: a preset from :mod:`nepf_core.config`, possibly edited.
        device: ``auto | cpu | cuda``.
        resume: continue from ``run_dir/checkpoints/latest.pt`` (exact: same losses as an
            uninterrupted run on the same device).
        time_budget_s: stop after this many seconds of training wall time.
        targets: held-out views / GT mesh / GT albedo for error-against-time records.
        iters_fixed: the user fixed the iteration count (disables plateau early stop).
    Returns:
        :class:`FitResult` (status ``succeeded``, ``cancelled`` or ``stopped_early``).
    """
    cb = callbacks or FitCallbacks()
    log = log or (lambda *a: None)
    run = Path(run_dir)
    (run / "checkpoints").mkdir(parents=True, exist_ok=True)
    dev = resolve_device(device)
    tc = cfg.train
    torch.manual_seed(tc.seed)
    np.random.seed(tc.seed)

    adapt = Adaptivity(cfg, enabled=tc.adaptive, iters_fixed=iters_fixed)
    adapt.decide_before_training(scene)
    (run / "config.json").write_text(cfg.to_json())

    model = NePFModel(cfg.model).to(dev)
    init_radiance_to_data(model, scene)
    if cfg.model.light_init_albedo > 0:
        i0 = init_light_to_data(model, scene, cfg.model.light_init_albedo)
        adapt.record("light_init", {"intensity": round(i0, 4)},
                     f"photon intensity starts at {i0:.3g} = pi * q99 / {cfg.model.light_init_albedo}: the brightest "
                     f"pixels then need albedo ~{cfg.model.light_init_albedo}, away from the saturated end of its sigmoid")
    try:  # fused Adam: one kernel over all tensors (8 ms vs 61 ms for the 4.8M grid values on 2 CPU cores)
        optimizer = torch.optim.Adam(_param_groups(model, cfg), betas=(0.9, 0.99), eps=1e-15, fused=True)
    except (RuntimeError, TypeError):
        optimizer = torch.optim.Adam(_param_groups(model, cfg), betas=(0.9, 0.99), eps=1e-15)
    gen = torch.Generator().manual_seed(tc.seed)
    ema = (ParamEMA(model, tc.ema_decay, tc.ema_half_life_s)
           if tc.ema_decay != 0 or tc.ema_half_life_s != 0 else None)  # a negative one: ParamEMA says so
    sampler = PixelSampler(scene, dev)
    unlit_thr = (unlit_threshold(scene.images, scene.masks, cfg.render.unlit_rel_threshold)
                 if cfg.render.unlit_albedo_stopgrad else None)
    if unlit_thr is not None:
        fg = foreground_peaks(scene.images, scene.masks)
        frac = float((fg < unlit_thr).mean()) if fg.size else 0.0
        adapt.record("unlit_albedo_stopgrad", {"threshold_linear": unlit_thr, "unlit_fraction": round(frac, 4)},
                     f"{100 * frac:.1f}% of the {'foreground ' if scene.masks is not None else ''}training pixels "
                     f"are unlit (max channel < {unlit_thr:.2e}, {cfg.render.unlit_rel_threshold} of the 99th "
                     "percentile): their colour error trains light and geometry, not the albedo")
    if model.occupancy is not None:
        adapt.init_occupancy(model, scene)

    step, wall_prev, nonfinite = 0, 0.0, 0
    latest = run / "checkpoints" / "latest.pt"
    if resume and latest.exists():
        st = load_checkpoint(latest, model=model, optimizer=optimizer, generator=gen, map_location=dev)
        step, wall_prev = int(st["step"]), float(st["wall_s"])
        nonfinite = int(st["extra"].get("nonfinite", 0))
        adapt.load_state(st["extra"].get("adaptivity", {}))
        if ema is not None and "ema" in st["extra"]:
            ema.load_state_dict(st["extra"]["ema"])
        log(f"resumed from step {step}")
    elif not resume:
        for f in ("metrics.jsonl",):
            (run / f).unlink(missing_ok=True)
    mlog = MetricsLog(run / "metrics.jsonl", cb)
    total = tc.iters
    sync_views = list(np.linspace(0, scene.n_views - 1, min(tc.sync_views, scene.n_views)).round().astype(int))
    batch = tc.batch_rays
    t_start = time.perf_counter()
    excluded = 0.0  # evaluation / checkpoint time inside this session
    last_eval_wall = wall_prev
    status = "succeeded"
    last_test: dict = {}
    use_mask = adapt.use_mask_loss
    world_rot = scene.world_from_norm[:3, :3] / scene.world_scale()

    def wall() -> float:
        return wall_prev + (time.perf_counter() - t_start) - excluded

    def progress_frac() -> float:
        p = step / max(total, 1)
        if time_budget_s:
            p = max(p, wall() / time_budget_s)
        return min(p, 1.0)

    def emit_progress(stage: str) -> None:
        w = wall()
        frac = progress_frac()
        eta = (w / frac - w) if frac > 1e-6 else None
        info = {"step": step, "total": total, "fraction": frac, "stage": stage,
                "eta_s": None if eta is None else round(eta, 1), "wall_s": round(w, 3)}
        cb.progress(info)
        if step % 10 == 0 or stage != "training":
            _write_json_atomic(run / "progress.json", info)

    def do_checkpoint() -> None:
        nonlocal excluded
        t0 = time.perf_counter()
        extra = {"nonfinite": nonfinite, "adaptivity": adapt.state(), "config_name": cfg.name,
                 "world_from_norm": np.asarray(scene.world_from_norm, dtype=np.float64).tolist()}
        if ema is not None:
            extra["ema"] = ema.state_dict()
        path = run / "checkpoints" / f"ckpt_{step:07d}.pt"
        save_checkpoint(path, model=model, optimizer=optimizer, step=step, wall_s=wall(), generator=gen, extra=extra)
        save_checkpoint(latest, model=model, optimizer=optimizer, step=step, wall_s=wall(), generator=gen, extra=extra)
        prune_checkpoints(run / "checkpoints", tc.keep_checkpoints)
        cb.checkpoint(step, str(latest))
        excluded += time.perf_counter() - t0

    def do_test_eval(final: bool) -> None:
        nonlocal excluded, last_eval_wall, last_test
        if targets is None or targets.test_scene is None:
            return
        t0 = time.perf_counter()
        w_train = wall()  # training time at the start of this evaluation (the evaluation is excluded)
        emit_progress("evaluating")
        with ema.applied(model) if ema is not None else nullcontext():
            rec = evaluate_test(model, cfg, targets, dev, scene.world_from_norm, tc.eval_stride, with_chamfer=True)
        rec.update({"kind": "test", "step": step, "wall_s": round(w_train, 3), "final": final})
        mlog.write(rec)
        last_test = rec
        adapt.on_test_eval(step, rec, progress=progress_frac())
        excluded += time.perf_counter() - t0
        last_eval_wall = wall()

    model.train()
    emit_progress("training")
    t_log, n_rays_acc, n_samp_acc = time.perf_counter(), 0, 0
    shading_prev = (cfg.render.specular, cfg.render.diffuse_metal_weight, cfg.render.metallic_scale)
    ema_wall = wall()  # training time at the last EMA update (a time-based average weighs by it)
    try:
        while step < total:
            if cb.stop_requested():
                status = "cancelled"
                break
            if time_budget_s is not None and wall() >= time_budget_s:
                break
            p = progress_frac()
            warm = step / max(tc.warmup_steps, 1)
            post = (p * total - tc.warmup_steps) / max(total - tc.warmup_steps, 1) if not time_budget_s else p
            f = lr_factor(warm if not time_budget_s else min(warm, 1.0), post, tc.lr_alpha)
            f = adapt.lr_after_plateau(wall(), f)
            if adapt.stop_requested:  # plateau (at once, or at the end of its cool-down)
                status = "stopped_early"
                break
            for gparam in optimizer.param_groups:
                gparam["lr"] = gparam["base_lr"] * f
            anneal = 1.0 if tc.anneal_end <= 0 else min(1.0, (p * total) / tc.anneal_end)
            if hasattr(model.sdf, "set_progress"):
                model.sdf.set_progress(min(1.0, p / max(tc.coarse_to_fine_frac, 1e-6)))
            if model.occupancy is not None and step % tc.occupancy_every == 0:
                adapt.update_occupancy(model, step)

            rays = sampler.sample(batch, generator=gen)
            if unlit_thr is not None:
                rays.unlit = rays.rgb.amax(-1) < unlit_thr
            rays = adapt.thin_empty_rays(model, rays, step, generator=gen)
            need_extras = adapt.wants_specular_stats(step)
            cfg.render.amp_heads = bool(tc.amp and dev.type == "cuda")
            out = render_rays(model, rays, cfg.render, train=True, cos_anneal=anneal, generator=gen,
                              need_surface_extras=need_extras)
            losses = compute_losses(out, rays, cfg.loss, use_mask=use_mask, specular=cfg.render.specular)
            loss = losses["loss"]
            optimizer.zero_grad(set_to_none=True)
            ok = bool(torch.isfinite(loss))
            if ok:
                loss.backward()
                gn = torch.nn.utils.clip_grad_norm_(model.parameters(), tc.grad_clip if tc.grad_clip > 0 else float("inf"))
                ok = bool(torch.isfinite(gn))
            if ok:
                optimizer.step()
                if ema is not None:
                    w_now = wall()
                    ema.update(model, dt_s=max(w_now - ema_wall, 0.0))
                    ema_wall = w_now
            else:
                nonfinite += 1
                optimizer.zero_grad(set_to_none=True)
                if nonfinite > tc.max_nonfinite_steps:
                    raise FitError(f"training diverged: {nonfinite} steps had a non-finite loss or gradient "
                                   f"(limit {tc.max_nonfinite_steps}); last at step {step}")
            step += 1
            n_rays_acc += len(rays)
            n_samp_acc += out.n_samples
            if need_extras and rays.rgb is not None:
                with torch.no_grad():
                    err = (out.rgb_vol.detach() - rays.rgb).abs().mean(-1)
                    fgm = (rays.mask > 0.5) if rays.mask is not None else (out.weight_sum.detach() > 0.5)
                    on_surf = fgm & (out.weight_sum.detach() > 0.5)
                    if cfg.render.specular and "diffuse_only" in out.surf and int(on_surf.sum()) >= 8:
                        adapt.on_lobe_residual(adapt.lobe_residual_gain(
                            out.rgb_surf.detach()[on_surf], out.surf["diffuse_only"][on_surf], rays.rgb[on_surf]))
                    err, lum = err[fgm], rays.rgb.mean(-1)[fgm]
                    top = lum >= torch.quantile(lum, 0.95) if lum.numel() >= 20 else lum > 1e9
                    if top.sum() > 0:
                        adapt.on_highlight_residual(step, float(err[top].mean() / err.median().clamp_min(1e-4)))
            if need_extras:
                adapt.check_view_spread(model, out, rays)
            adapt.on_step(step, out, losses)   # after the checks above, whose statistics it logs
            shading = (cfg.render.specular, cfg.render.diffuse_metal_weight, cfg.render.metallic_scale)
            if ema is not None and shading != shading_prev:
                ema.reset(model)  # weights averaged across a change of the shading model do not fit it
            shading_prev = shading
            if tc.target_samples > 0 and out.n_head_evals > 0:
                ratio = tc.target_samples / out.n_head_evals
                batch = int(min(max(batch * min(max(ratio, 0.8), 1.25), 128), 8 * tc.batch_rays))

            if step % tc.log_every == 0 or step == total:
                dt = max(time.perf_counter() - t_log, 1e-9)
                rec = {"step": step, "wall_s": round(wall(), 3), "kind": "train"}
                rec.update({k: float(v.detach()) for k, v in losses.items()})
                rec.update({"inv_s": out.inv_s, "lr": optimizer.param_groups[0]["lr"], "batch_rays": len(rays),
                            "rays_per_s": n_rays_acc / dt, "samples_per_s": n_samp_acc / dt,
                            "head_evals": out.n_head_evals, "nonfinite_steps": nonfinite,
                            "specular_on": bool(cfg.render.specular)})
                rec.update(adapt.step_stats())
                mlog.write(rec)
                t_log, n_rays_acc, n_samp_acc = time.perf_counter(), 0, 0
            if tc.sync_every > 0 and step % tc.sync_every == 0:
                t0 = time.perf_counter()
                s = sync_psnr(model, sampler, cfg, sync_views, tc.sync_rays, tc.seed + 1)
                s.update({"kind": "sync", "step": step, "wall_s": round(wall(), 3)})
                excluded += time.perf_counter() - t0
                mlog.write(s)
            if tc.eval_every_s > 0 and wall() - last_eval_wall >= tc.eval_every_s:
                do_test_eval(final=False)
            if step % tc.checkpoint_every == 0:
                do_checkpoint()
            emit_progress("training")
        do_checkpoint()
        do_test_eval(final=True)
    except FitError as e:
        adapt.record("failed", True, str(e), step)
        adapt.write_report(run / "report.json", step=step, status="failed", nonfinite=nonfinite)
        raise
    finally:
        mlog.close()
    report = adapt.write_report(run / "report.json", step=step, status=status, nonfinite=nonfinite)
    emit_progress("finished" if status == "succeeded" else status)
    _plot_error_vs_time(run)
    return FitResult(status=status, step=step, total=total, wall_s=wall(), run_dir=str(run),
                     nonfinite_steps=nonfinite, last_test=last_test, report=report)


def load_model(run_dir, device: str = "auto") -> tuple[NePFModel, NePFConfig, dict]:
    """Rebuild the model of a run from ``config.json`` and ``checkpoints/latest.pt``."""
    run = Path(run_dir)
    cfg_path, ck = run / "config.json", run / "checkpoints" / "latest.pt"
    if not cfg_path.exists() or not ck.exists():
        raise FitError(f"{run} is not a finished or checkpointed NePF run (missing config.json or checkpoints/latest.pt)")
    cfg = NePFConfig.from_dict(json.loads(cfg_path.read_text()))
    dev = resolve_device(device)
    model = NePFModel(cfg.model).to(dev)
    state = torch.load(ck, map_location=dev, weights_only=False)
    model.load_state_dict(state["model"])
    ema = (state.get("extra") or {}).get("ema")
    if ema:  # the averaged weights are the run's model (nepf_core.weight_average); buffers stay
        model.load_state_dict(ema["params"], strict=False)
    # config.json is written before training; a lobe dropped during training stays dropped
    switches = (state.get("extra") or {}).get("adaptivity") or {}
    if "specular" in switches:
        cfg.render.specular = bool(switches["specular"])
    if "diffuse_metal_weight" in switches:
        cfg.render.diffuse_metal_weight = float(switches["diffuse_metal_weight"])
    if "metallic_scale" in switches:
        cfg.render.metallic_scale = float(switches["metallic_scale"])
    model.eval()
    return model, cfg, state


def _plot_error_vs_time(run: Path) -> None:
    """``RUN/error_vs_time.png``: every held-out metric and the training losses against seconds."""
    from nepf_core.plots import plot_error_vs_time
    try:
        plot_error_vs_time(run / "metrics.jsonl", run / "error_vs_time.png")
    except Exception as e:  # a plot must never fail a run
        (run / "error_vs_time.txt").write_text(f"plot failed: {e}\n")
