"""One training job end to end: load -> fit -> export. Used by the worker and ``nepf fit``.

Contract (stable; the worker codes against it):

    run_job(data_dir, run_dir, *, preset="fast", iters=None, time_budget_s=None,
            device="auto", callbacks=None, resume=True, ...) -> dict

* Raises ``nepf_core.data.DatasetError`` for bad input (before any training).
* Resumes from ``run_dir/checkpoints/latest.pt`` when ``resume`` and it exists: the first
  progress report is then ``stage: "resuming"`` at the checkpoint's step, and ``metrics.jsonl``
  is cut back to the checkpoint (``nepf_core/resume.py``), so each step is listed once.
* Returns a summary ``{"status": "succeeded"|"cancelled"|"stopped_early", "step", "total",
  "wall_s", "manifest": "manifest.json" (relative to run_dir, or None), "report": {...},
  "working_size": [W, H] the images were trained at, "split": {"holdout_every", "n_train",
  "n_test", "test_views"}}``; also written to ``run_dir/summary.json``,
  which the service serves, so it holds no absolute path.
* ``holdout_every`` (None: 8 for 16 or more views, else 0; 0 with ``test_dir``): views
  ``0, K, 2K, ...`` are held out of training and evaluated on the preset's wall-clock schedule
  (``train.eval_every_s``) and at the end (``nepf_core.data.split``), every
  ``split["eval_stride"]``-th pixel so that an evaluation renders at most
  ``EVAL_PIXEL_BUDGET`` pixels; the summary's ``split`` (and ``report.json``'s) says which.
* ``max_side`` (0/None: full size) is the working resolution of the training and held-out
  views: larger images are area-resampled at load, intrinsics scaled to match; it is logged with
  the memory the images take. ``max_total_pixels`` (None/0: none) refuses a dataset whose images
  hold more decoded pixels (``too_many_pixels``, before any decoding). ``nepf fit`` passes the
  service's defaults for both (``nepf_core.limits``); a library caller asks for them.
* ``up_axis`` (None / ``"auto"``: detected from the cameras; ``"+x"`` ... ``"-z"``: the user's) is
  the input world's up axis; the export rotates it to glTF's +Y (``nepf_core.up_axis``) and
  records the choice in ``frame.json`` and the manifest.
* When ``callbacks.should_stop()`` turns True, training stops at the next step, a final
  checkpoint and the export of the partial model are still written, and the status is
  ``"cancelled"``.
"""

from __future__ import annotations

import json
from dataclasses import fields, is_dataclass
from pathlib import Path

from nepf_core.callbacks import FitCallbacks
from nepf_core.config import NePFConfig, preset as make_preset


def _coerce(current, value, key: str):
    """``value`` converted to the type of ``current``; a bool accepts ``true/false/1/0/yes/no``
    (``bool("False")`` would be True)."""
    if isinstance(current, bool) and isinstance(value, str):
        v = value.strip().lower()
        if v in ("true", "1", "yes", "on"):
            return True
        if v in ("false", "0", "no", "off"):
            return False
        raise ValueError(f"config field {key!r} is a bool: use true or false, not {value!r}")
    return type(current)(value)


def build_config(preset: str = "fast", iters: int | None = None, overrides: dict | None = None) -> NePFConfig:
    """A preset with the user's iteration count and optional ``{"section.field": value}`` overrides
    (nested fields too: ``{"model.photon.n_freqs_x": 6}``)."""
    cfg = make_preset(preset)
    if iters is not None:
        if int(iters) < 1:
            raise ValueError(f"iters must be >= 1 (got {iters})")
        cfg.train.iters = int(iters)
    for key, value in (overrides or {}).items():
        *path, name = key.split(".")
        obj = cfg
        for part in path:   # "section.field" or deeper, e.g. "model.photon.use_feature"
            obj = getattr(obj, part, None) if is_dataclass(obj) else None
        if not path or not is_dataclass(obj) or name not in {f.name for f in fields(obj)}:
            raise ValueError(f"unknown config field {key!r}")
        setattr(obj, name, _coerce(getattr(obj, name), value, key))
    return cfg


def held_out_targets(scene, holdout_every: int | None, has_test_set: bool, eval_pixels: int | None = None):
    """``(train scene, EvalTargets | None, split record)``: views ``0, K, 2K, ...`` of ``scene``
    held out for evaluation (``nepf_core.data.split``; ``holdout_every=None``: the default
    rule). A separate test set (``--eval-test``) and a held-out split exclude each other.
    ``eval_pixels``: render at most this many held-out pixels per evaluation (a stride,
    ``split["eval_stride"]``; None: the config's ``train.eval_stride`` alone)."""
    from nepf_core.data.split import (check_holdout_every, default_holdout_every, eval_stride_for, split_info,
                                      split_scene)
    from nepf_core.train import EvalTargets

    if holdout_every is None:
        every = default_holdout_every(scene.n_views, has_test_set)
    else:
        every = check_holdout_every(holdout_every, scene.n_views)
    if every and has_test_set:
        raise ValueError(f"holdout_every = {every} and a separate test set (--eval-test) both give held-out "
                         "views; use one of them (--holdout-every 0 with --eval-test)")
    split = split_info(scene.n_views, every)
    train, test = split_scene(scene, every)
    if test is None:
        return train, None, split
    stride = None if eval_pixels is None else eval_stride_for(test.n_views, test.width, test.height, eval_pixels)
    if stride is not None:
        split["eval_stride"] = stride
    return train, EvalTargets(test_scene=test, split=split, stride=stride), split


def working_size_text(scene, max_side: int | None) -> str:
    """One line for the progress output: the views' working size, the rule that set it and the
    memory the images take (``n W H x 12`` bytes of float32 RGB), e.g.
    ``"data: 49 views at 800x600 px (long side at most 800 px; --max-side 0: full size), 0.28 GB of images"``."""
    from nepf_core.limits import BYTES_PER_PIXEL

    rule = f"long side at most {max_side} px; --max-side 0: full size" if max_side else "full resolution"
    gb = scene.n_views * scene.width * scene.height * BYTES_PER_PIXEL / 1e9
    return f"data: {scene.n_views} views at {scene.width}x{scene.height} px ({rule}), {gb:.2f} GB of images"


EXPORT_DEFAULTS = {
    # tiny: seconds, for tests and demos; fast/paper: the defaults (100k faces, 1024^2)
    "tiny": {"texture_size": 256, "max_faces": 5_000, "mesh_resolution": 64},
    "fast": {"texture_size": 1024, "max_faces": 100_000, "mesh_resolution": 256},
    "paper": {"texture_size": 1024, "max_faces": 100_000, "mesh_resolution": 256},
}


def start_progress(run: Path, total: int, resume: bool) -> dict:
    """The first progress report: ``loading`` at step 0, or, when a checkpoint will be resumed,
    ``resuming`` at its step (``checkpoints/latest.json``, ``nepf_core/resume.py``), so that the
    progress a service shows does not drop to 0 while the data loads again."""
    from nepf_core.resume import read_checkpoint_info

    info = read_checkpoint_info(run) if resume and (run / "checkpoints" / "latest.pt").exists() else None
    if info is None:
        return {"step": 0, "total": 0, "fraction": 0.0, "stage": "loading", "eta_s": None, "wall_s": 0.0}
    step = info["step"]
    return {"step": step, "total": total, "fraction": min(1.0, step / max(total, 1)), "stage": "resuming",
            "eta_s": None, "wall_s": float(info.get("wall_s") or 0.0)}


def run_job(data_dir, run_dir, *, preset: str = "fast", iters=None, time_budget_s=None,
            device: str = "auto", callbacks: FitCallbacks | None = None, resume: bool = True,
            export: bool = True, texture_size: int | None = None, max_faces: int | None = None,
            mesh_resolution: int | None = None, test_dir=None, gt_mesh=None, gt_albedo=None,
            overrides: dict | None = None, max_side: int | None = None, holdout_every: int | None = None,
            up_axis: str | None = None, max_total_pixels: int | None = None, log=print) -> dict:
    """Load ``data_dir``, fit, and export into ``run_dir``; see the module docstring."""
    from nepf_core.data.detect import load_scene
    from nepf_core.data.split import EVAL_PIXEL_BUDGET
    from nepf_core.train import EvalTargets, fit
    from nepf_core.up_axis import parse_up_axis

    parse_up_axis(up_axis)   # a bad value fails before the training, not after it
    cb = callbacks or FitCallbacks()
    run = Path(run_dir)
    run.mkdir(parents=True, exist_ok=True)
    cfg = build_config(preset, iters, overrides)
    cb.progress(start_progress(run, cfg.train.iters, resume))
    scene = load_scene(data_dir, split="train", max_side=max_side, max_total_pixels=max_total_pixels)
    log(working_size_text(scene, max_side))
    scene, targets, split = held_out_targets(scene, holdout_every, has_test_set=test_dir is not None,
                                             eval_pixels=EVAL_PIXEL_BUDGET)
    if test_dir is not None:
        import numpy as np
        from nepf_core.reframe import load_held_out
        test_scene = load_held_out(test_dir, scene.world_from_norm, max_side=max_side,
                                   max_total_pixels=max_total_pixels)
        alb = None
        if gt_albedo is not None:
            alb = np.load(gt_albedo)["albedo"].astype("float32") if str(gt_albedo).endswith(".npz") else gt_albedo
        targets = EvalTargets(test_scene=test_scene, gt_mesh_path=gt_mesh, gt_albedo=alb)
    res = fit(scene, run, cfg, device=device, callbacks=cb, resume=resume, time_budget_s=time_budget_s,
              targets=targets, iters_fixed=iters is not None, log=log)
    manifest_path = None
    d = EXPORT_DEFAULTS.get(preset, EXPORT_DEFAULTS["fast"])
    texture_size = texture_size or d["texture_size"]
    max_faces = max_faces or d["max_faces"]
    mesh_resolution = mesh_resolution or d["mesh_resolution"]
    if export:
        cb.progress({"step": res.step, "total": res.total, "fraction": 1.0 if res.status != "cancelled" else res.step / max(res.total, 1),
                     "stage": "exporting", "eta_s": None, "wall_s": res.wall_s})
        manifest_path = export_run(run, device=device, texture_size=texture_size, max_faces=max_faces,
                                   mesh_resolution=mesh_resolution, up_axis=up_axis, log=log)
    summary = {"status": res.status, "step": res.step, "total": res.total, "wall_s": res.wall_s,
               "manifest": None if manifest_path is None else Path(manifest_path).relative_to(run).as_posix(),
               "working_size": [scene.width, scene.height], "split": split, "report": res.report,
               "last_test": res.last_test, "nonfinite_steps": res.nonfinite_steps}
    (run / "summary.json").write_text(json.dumps(summary, indent=2, default=str))
    if manifest_path is not None:
        from nepf_core.export.manifest import write_manifest
        write_manifest(run)
    return summary


def export_frame(run_dir, extra: dict, up_axis: str | None = None):
    """The :class:`~nepf_core.up_axis.UpFrame` of a run's export: ``up_axis`` when it names an
    axis; with None, an earlier export's override (``RUN/frame.json``, ``up_source`` "override":
    ``nepf fit --up`` stays when ``nepf export`` runs again); else (``"auto"`` too) the axis
    nearest the cameras' mean up recorded in the checkpoint (``extra["camera_up"]``), else +z
    (a checkpoint written before the up axis was recorded)."""
    from nepf_core.up_axis import parse_up_axis, resolve_up_frame

    axis = parse_up_axis(up_axis)
    previous = Path(run_dir) / "frame.json"
    if up_axis is None and previous.is_file():
        try:
            rec = json.loads(previous.read_text())
        except (OSError, json.JSONDecodeError):
            rec = {}
        if rec.get("up_source") == "override":
            axis = parse_up_axis(rec.get("world_up"))
    return resolve_up_frame(axis, extra.get("camera_up"))


def export_run(run_dir, *, device: str = "auto", texture_size: int = 1024, max_faces: int = 100_000,
               mesh_resolution: int = 256, previews: bool = True, up_axis: str | None = None, log=print) -> Path:
    """Export the latest checkpoint of ``run_dir`` (GLB, textures, light field, previews, manifest);
    ``up_axis``: see :func:`export_frame`."""
    from nepf_core.export import export_asset
    from nepf_core.model import ModelFieldQuery
    from nepf_core.train import load_model

    model, cfg, state = load_model(run_dir, device)
    world_from_norm = state["extra"].get("world_from_norm")
    if world_from_norm is None:
        raise RuntimeError(f"{run_dir}: checkpoint has no world_from_norm")
    import numpy as np
    dev = next(model.parameters()).device
    # the material as the surface was shaded at the end of the run (a dropped lobe: metallic 0)
    frame = export_frame(run_dir, state["extra"], up_axis)
    log(f"export: world up {frame.world_up} ({frame.source}) -> glTF +Y")
    export_asset(ModelFieldQuery(model, shading=state["run_state"].shading()), np.asarray(world_from_norm), run_dir,
                 texture_size=texture_size, max_faces=max_faces, mesh_resolution=mesh_resolution, device=dev, log=log,
                 previews=previews, relit_bsdf=cfg.render.bsdf_kind, frame=frame)
    return Path(run_dir) / "manifest.json"
