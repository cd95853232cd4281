"""One benchmark run, in its own process: ``python -m bench.run --child SPEC.json``.

:mod:`bench.run` (the parent) writes ``SPEC.json`` and starts this in a subprocess so that its
peak RSS and CPU time are the run's alone. :func:`child_main` trains (synthetic scenes through
``nepf_core.jobs.run_job`` with the scene's own test views; real datasets through
:func:`fit_real` with every K-th view held out), re-evaluates Chamfer on the final model, scores
relighting where the scene has ``gt/relight``, and writes ``RUN/bench_child.json``; a failure
is recorded there, not raised.
"""

from __future__ import annotations

import json
import os
import resource
import sys
import time
import traceback
from pathlib import Path



def _rss_self_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: KiB


def _final_chamfer(run_dir: Path, gt_mesh: str, resolution: int, n_samples: int) -> dict:
    """Chamfer of the final model at ``resolution``³ against ``gt_mesh`` (unit-sphere and world units)."""
    from nepf_core.train import load_model
    from nepf_core.meshing import chamfer_against_gt
    from nepf_core.model import ModelFieldQuery
    import numpy as np

    t0 = time.perf_counter()
    model, _cfg, state = load_model(run_dir, "cpu")
    wfn = np.asarray(state["extra"]["world_from_norm"], dtype=np.float64)
    out = {"chamfer_resolution": resolution, "chamfer_samples": n_samples}
    try:
        import torch
        with torch.no_grad():
            cd_world, cd_unit = chamfer_against_gt(ModelFieldQuery(model), wfn, gt_mesh, resolution=resolution,
                                                   n_samples=n_samples)
        out.update({"chamfer_final": cd_unit, "chamfer_final_world": cd_world})
    except Exception as e:  # no surface (diverged / empty SDF): record, don't fail the benchmark
        out["chamfer_final_error"] = f"{type(e).__name__}: {e}"
    out["chamfer_final_s"] = time.perf_counter() - t0
    return out


def fit_real(spec: dict, run: Path, overrides: dict, callbacks=None) -> dict:
    """Real-data mode: hold out every K-th view of a dataset folder, fit, write the mesh."""
    import numpy as np

    from nepf_core.data.detect import load_scene
    from nepf_core.train import fit, load_model
    from nepf_core.jobs import build_config, held_out_targets

    full = load_scene(spec["data_dir"], downscale=int(spec.get("downscale", 1)), max_side=int(spec.get("max_side", 0)))
    train, targets, split = held_out_targets(full, int(spec["holdout_every"]), has_test_set=False)
    cfg = build_config(spec["preset"], None, overrides)
    res = fit(train, run, cfg, device="cpu", callbacks=callbacks, resume=False, time_budget_s=spec["budget_s"],
              targets=targets, iters_fixed=False, log=print)
    summary = {"status": res.status, "step": res.step, "total": res.total, "wall_s": res.wall_s,
               "manifest": None, "report": res.report, "last_test": res.last_test,
               "nonfinite_steps": res.nonfinite_steps,
               "split": {**split, "downscale": int(spec.get("downscale", 1)), "max_side": int(spec.get("max_side", 0)),
                         "resolution": [full.width, full.height]}}
    (run / "summary.json").write_text(json.dumps(summary, indent=2, default=str))
    t0 = time.perf_counter()
    try:
        from nepf_core.meshing import world_mesh
        from nepf_core.model import ModelFieldQuery
        import torch
        model, _cfg, state = load_model(run, "cpu")
        with torch.no_grad():
            m = world_mesh(ModelFieldQuery(model), np.asarray(state["extra"]["world_from_norm"]),
                           resolution=int(spec.get("mesh_resolution", 256)))
        m.export(run / "mesh.ply")
        summary["mesh"] = {"path": str(run / "mesh.ply"), "faces": int(len(m.faces)),
                           "vertices": int(len(m.vertices)), "seconds": time.perf_counter() - t0}
    except Exception as e:
        summary["mesh"] = {"error": f"{type(e).__name__}: {e}", "seconds": time.perf_counter() - t0}
    return summary


class _EvalClock:
    """How long each held-out evaluation took (``eval_s``: rendering + Chamfer mesh, wall time of
    this process) and the training time at its start.

    ``emit_progress("evaluating")`` at the start of an evaluation carries the training time
    (``train_wall_s``); it is paired with the next test record by step. ``fit()`` stamps the test
    record's ``wall_s`` with the same training time (its clock is paused during evaluations), so
    ``logged_wall_s == train_wall_s``, a check that evaluations are not counted as training.
    """

    def __init__(self) -> None:
        self.pending = None
        self.evals: list[dict] = []

    def on_progress(self, info: dict) -> None:
        if info.get("stage") == "evaluating":
            self.pending = {"step": info.get("step"), "wall_s": info.get("wall_s"), "t0": time.perf_counter()}

    def on_metrics(self, rec: dict) -> None:
        if rec.get("kind") != "test":
            return
        p = self.pending if self.pending and self.pending["step"] == rec.get("step") else None
        self.evals.append({"step": rec.get("step"), "logged_wall_s": rec.get("wall_s"),
                           "train_wall_s": None if p is None else p["wall_s"],
                           "eval_s": None if p is None else time.perf_counter() - p["t0"]})
        self.pending = None

    def callbacks(self):
        from nepf_core.callbacks import FitCallbacks
        return FitCallbacks(on_progress=self.on_progress, on_metrics=self.on_metrics)


def child_main(spec_path: str) -> int:
    spec = json.loads(Path(spec_path).read_text())
    run = Path(spec["run_dir"])
    run.mkdir(parents=True, exist_ok=True)
    import torch
    if spec.get("threads"):
        torch.set_num_threads(int(spec["threads"]))
    result = {"spec": spec, "torch": torch.__version__, "torch_threads": torch.get_num_threads(),
              "loadavg_start": list(os.getloadavg())}
    t0 = time.perf_counter()
    overrides = dict(spec.get("overrides") or {})
    clock = _EvalClock()
    result["evals"] = clock.evals
    code = 0
    try:
        if spec["mode"] == "synthetic":
            from nepf_core.jobs import run_job
            s = spec["scene_dir"]
            summary = run_job(f"{s}/input/dtu", run, preset=spec["preset"], time_budget_s=spec["budget_s"],
                              test_dir=f"{s}/gt/dtu_test",
                              gt_mesh=spec.get("gt_mesh") if spec.get("fit_chamfer", True) else None,
                              gt_albedo=spec.get("gt_albedo"), export=False, overrides=overrides,
                              device="cpu", resume=False, callbacks=clock.callbacks())
        else:
            summary = fit_real(spec, run, overrides, clock.callbacks())
        result["summary"] = summary
        result["status"] = summary.get("status")
        result["rss_after_fit_mb"] = _rss_self_mb()
        result["fit_process_s"] = time.perf_counter() - t0
        if spec.get("gt_mesh") and spec.get("chamfer_resolution", 0) > 0:
            result.update(_final_chamfer(run, spec["gt_mesh"], int(spec["chamfer_resolution"]),
                                         int(spec["chamfer_samples"])))
        if spec["mode"] == "synthetic":
            from bench.relight_eval import has_relight_truth, relight_metrics
            if has_relight_truth(spec["scene_dir"]):
                try:  # relight / material scores and the oracle (bench/relight_eval.py), after training
                    result["relight_eval"] = relight_metrics(run, spec["scene_dir"])
                except Exception as e:
                    result["relight_eval"] = {"error": f"{type(e).__name__}: {e}"}
    except BaseException as e:  # record the failure (diverged, bad data, ...) and go on with the next run
        result["status"] = "failed"
        result["error"] = f"{type(e).__name__}: {e}"
        result["traceback"] = traceback.format_exc()
        result["rss_after_fit_mb"] = _rss_self_mb()
        print(result["traceback"], file=sys.stderr)
        code = 1
    result["process_s"] = time.perf_counter() - t0
    result["loadavg_end"] = list(os.getloadavg())
    (run / "bench_child.json").write_text(json.dumps(result, indent=2, default=str))
    return code
