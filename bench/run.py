"""The benchmark harness: ``python -m bench run ...`` (see bench/README.md).

For every (scene, config, variant, repeat), one at a time, a **subprocess** runs
``python -m bench.run --child SPEC.json`` (:mod:`bench.child`) which

* synthetic scenes (``<scenes-root>/<name>/input/dtu``, ``gt/dtu_test``, ``gt/mesh.ply``,
  ``gt/arrays_test.npz``): ``nepf_core.jobs.run_job(..., export=False, device="cpu")`` with
  held-out evaluation every ``--eval-every`` training seconds;
* real datasets (``--dataset dtu_scan24``): ``load_scene(path, downscale=D)``, every
  ``--holdout-every``-th view (indices 0, K, 2K, ...) held out (``nepf_core.data.split``,
  the rule ``nepf fit --holdout-every`` and the service use), ``nepf_core.train.fit`` with
  ``EvalTargets(test_scene=...)``, then ``RUN/mesh.ply`` (world coordinates);
* then re-evaluates Chamfer on the final model with a finer mesh (default 256³, 100k
  samples per mesh) when a GT mesh exists, and writes ``RUN/bench_child.json``.

The parent measures each child's peak RSS and CPU time with ``os.wait4`` (exact per child),
and the child also reports its own peak RSS right after training (before the final Chamfer
mesh). After every run the parent rewrites ``results.json``, ``table.md`` and the plots, so an
interrupted benchmark keeps what it finished (``--skip-done`` reuses finished runs whose overrides,
seed included, are the ones asked for).
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import signal
import subprocess
import sys
import time
from datetime import datetime
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
DEFAULT_SCENES_ROOT = "/work/shared/scenes"
DEFAULT_DATASETS_ROOT = "/work/shared/datasets"
VARIANTS = {
    "adaptive": {},                          # the default: fit() leaves out what the scene does not need
    # everything on: no decision is taken, and no empty ray is left out (no occupancy grid to maintain;
    # the NeuS coarse + importance sampler with the preset's sample counts)
    "all_on": {"train.adaptive": False, "model.occupancy_resolution": 0},
    # the brief's naive reference, rebuilt on the NePF model: one dense 96^3 grid level (4 channels),
    # 64-wide heads, finite-difference normals at every sample, 1024 rays x 48 uniform samples (no
    # importance samples, no occupancy grid, no empty rays left out), heads evaluated everywhere,
    # nothing adaptive. The brief measured 0.56 s/step and 21-24 dB held-out radiance PSNR at 300 s
    "naive": {"train.adaptive": False, "model.occupancy_resolution": 0,
              "model.sdf_grid.n_levels": 1, "model.sdf_grid.base_resolution": 96,
              "model.sdf_grid.max_resolution": 96, "model.sdf_grid.features_per_level": 4,
              "model.sdf_grid.start_levels": 1,
              "render.n_samples": 48, "render.n_importance": 0, "render.up_sample_steps": 0,
              "render.alpha_mode": "midpoint", "render.normals": "fd", "render.head_weight_threshold": 0.0,
              "render.surface_refine": False, "loss.w_normal_smooth": 0.0, "train.batch_rays": 1024},
}


def pinned_version(package: str, path: Path = REPO / "constraints.txt") -> str | None:
    """The ``==`` version of ``package`` in the repo's constraints file (the one scripts/install.sh
    installs), or None."""
    try:
        lines = path.read_text().splitlines()
    except OSError:
        return None
    for line in lines:
        name, sep, ver = line.split("#", 1)[0].strip().partition("==")
        if sep and name.strip().lower() == package:
            return ver.strip()
    return None


def machine_info(threads: int | None) -> dict:
    import platform
    info = {"hostname": platform.node(), "platform": platform.platform(), "python": platform.python_version(),
            "cpu_count": os.cpu_count(), "threads": threads}
    try:
        info["cpus_allowed"] = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        pass
    try:
        txt = Path("/proc/cpuinfo").read_text()
        models = [ln.split(":", 1)[1].strip() for ln in txt.splitlines() if ln.startswith("model name")]
        info["cpu_model"] = models[0] if models else None
        flags = next((ln for ln in txt.splitlines() if ln.startswith("flags")), "")
        info["avx512"] = "avx512f" in flags
        info["avx2"] = "avx2" in flags
    except OSError:
        info["cpu_model"] = None
    try:
        mem = next(ln for ln in Path("/proc/meminfo").read_text().splitlines() if ln.startswith("MemTotal"))
        info["mem_total_mb"] = round(int(mem.split()[1]) / 1024.0)
    except (OSError, StopIteration):
        pass
    try:
        from importlib.metadata import version
        info["torch"] = version("torch")
    except Exception:
        info["torch"] = None
    info["torch_pinned"] = pinned_version("torch")
    if info["torch"] and info["torch_pinned"] and info["torch"].split("+")[0] != info["torch_pinned"]:
        print(f"warning: torch {info['torch']} is installed, constraints.txt pins {info['torch_pinned']}: "
              "these numbers are not comparable with bench/RESULTS.md (pip install -c constraints.txt torch)",
              file=sys.stderr)
    try:
        cg = Path("/sys/fs/cgroup/cpu.max").read_text().split()
        info["cgroup_cpu_max"] = " ".join(cg)
    except OSError:
        pass
    info["loadavg"] = list(os.getloadavg())
    return info


def _parse_per_config(items: list[str], flag: str) -> dict[str, float]:
    """``["paper=1800,fast=600"]`` -> ``{"paper": 1800.0, "fast": 600.0}``."""
    out = {}
    for item in items:
        for part in item.split(","):
            part = part.strip()
            if not part:
                continue
            name, sep, val = part.partition("=")
            if not sep:
                raise SystemExit(f"{flag} expects CONFIG=SECONDS, got {part!r}")
            out[name.strip()] = float(val)
    return out


def _parse_overrides(items: list[str]) -> dict:
    out = {}
    for item in items:
        key, sep, val = item.partition("=")
        if not sep:
            raise SystemExit(f"--override expects section.field=VALUE, got {item!r}")
        try:
            out[key.strip()] = json.loads(val)
        except json.JSONDecodeError:
            out[key.strip()] = val
    return out


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m bench run", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scenes", default=None,
                   help="comma-separated synthetic scenes under --scenes-root (default sphere_diffuse,torus_glossy "
                        "unless --dataset is given)")
    p.add_argument("--scenes-root", default=DEFAULT_SCENES_ROOT,
                   help="folder with <scene>/input/dtu, gt/dtu_test, gt/mesh.ply, gt/arrays_test.npz")
    p.add_argument("--dataset", default=None,
                   help="comma-separated real datasets (a name under --datasets-root, or a path), e.g. dtu_scan24")
    p.add_argument("--datasets-root", default=DEFAULT_DATASETS_ROOT)
    p.add_argument("--downscale", type=int, default=4, help="real data: integer downscale (default 4)")
    p.add_argument("--max-side", type=int, default=0,
                   help="real data: working resolution, longest image side in pixels (exact area resampling, any "
                        "factor; use with --downscale 1; 0: off)")
    p.add_argument("--holdout-every", type=int, default=8,
                   help="real data: views 0, K, 2K, ... are held out for testing (default 8)")
    p.add_argument("--configs", default="fast,paper", help="comma-separated presets (paper, fast, tiny)")
    p.add_argument("--variants", default="adaptive", help="comma-separated: adaptive (default), all_on (everything on, no "
                   "empty ray left out), naive (the brief's dense-grid reference rebuilt on the NePF model)")
    p.add_argument("--budget", type=float, default=600.0, help="training seconds per run (default 600)")
    p.add_argument("--budget-for", action="append", default=[], metavar="CONFIG=S",
                   help="per-config budget, e.g. paper=1800 (repeatable or comma-separated)")
    p.add_argument("--eval-every", type=float, default=60.0, help="held-out evaluation period, training seconds")
    p.add_argument("--eval-every-for", action="append", default=[], metavar="CONFIG=S",
                   help="per-config evaluation period, e.g. paper=180 (a paper evaluation costs minutes)")
    p.add_argument("--eval-stride", type=int, default=1, help="render held-out views every N-th pixel")
    p.add_argument("--repeats", type=int, default=1, help="runs per configuration; tables report medians; with N > 1 repeat r of every variant uses train.seed = r (matched pairs) unless --override sets it")
    p.add_argument("--seeds", default=None, help="comma-separated train seeds, one run of every variant per seed (matched pairs); replaces --repeats and an --override of train.seed")
    p.add_argument("--threads", type=int, default=None, help="torch threads in each run (and OMP_NUM_THREADS)")
    p.add_argument("--chamfer-resolution", type=int, default=256,
                   help="marching-cubes resolution of the final Chamfer (0: skip; default 256)")
    p.add_argument("--chamfer-samples", type=int, default=100_000, help="surface samples per mesh (default 100k)")
    p.add_argument("--no-fit-chamfer", dest="fit_chamfer", action="store_false",
                   help="no Chamfer during training (it costs a 128³ mesh + 100k samples per evaluation); "
                        "the final Chamfer is still computed")
    p.add_argument("--mesh-resolution", type=int, default=256, help="real data: resolution of RUN/mesh.ply")
    p.add_argument("--target-psnr", type=float, default=None,
                   help="'time to reach X' target in dB (default per scene: the lowest final test PSNR)")
    p.add_argument("--override", action="append", default=[], metavar="section.field=VALUE",
                   help="extra config override for every run (JSON value), e.g. train.batch_rays=512")
    p.add_argument("--out", default=None, help="results folder (default bench/results/<timestamp>)")
    p.add_argument("--skip-done", action="store_true",
                   help="reuse runs in --out that already have bench_child.json (resume an interrupted benchmark)")
    p.add_argument("--timeout-factor", type=float, default=3.0,
                   help="kill a run after factor * budget + 900 s of process time (hang guard)")
    p.add_argument("--dry-run", action="store_true", help="print the runs and exit")
    return p


def run_seeds(text: str | None, repeats: int, overrides: dict) -> list[int | None]:
    """The training seed of each repeat of every variant (matched pairs): those of ``--seeds
    "a,b,..."``; without it ``0..N-1`` for ``--repeats N > 1`` (unless an ``--override train.seed``
    sets one for all), else ``[None]`` (the config's seed). SystemExit where the seeds are not
    distinct integers, or where ``--repeats`` or an ``--override train.seed`` asks for seeds too:
    two sources of seeds would silently disagree."""
    if text is None:
        n = max(1, repeats)
        return list(range(n)) if n > 1 and "train.seed" not in overrides else [None] * n
    try:
        seeds = [int(s) for s in text.split(",") if s.strip()]
    except ValueError:
        raise SystemExit(f"--seeds takes comma-separated integers, got {text!r}") from None
    if not seeds or len(set(seeds)) != len(seeds):
        raise SystemExit(f"--seeds needs distinct seeds, got {text!r}")
    if repeats > 1 or "train.seed" in overrides:
        raise SystemExit("give the seeds once: --seeds, or --repeats / --override train.seed=N, not both")
    return seeds


def plan_runs(args) -> list[dict]:
    configs = [c.strip() for c in args.configs.split(",") if c.strip()]
    variants = [v.strip() for v in args.variants.split(",") if v.strip()]
    for v in variants:
        if v not in VARIANTS:
            raise SystemExit(f"unknown variant {v!r}: choose from {', '.join(VARIANTS)}")
    from nepf_core.config import PRESETS
    for c in configs:
        if c not in PRESETS:
            raise SystemExit(f"unknown config {c!r}: choose from {', '.join(PRESETS)}")
    budget_for = _parse_per_config(args.budget_for, "--budget-for")
    eval_every_for = _parse_per_config(args.eval_every_for, "--eval-every-for")
    extra = _parse_overrides(args.override)
    scenes = args.scenes
    if scenes is None:
        scenes = "" if args.dataset else "sphere_diffuse,torus_glossy"
    targets: list[dict] = []
    for name in [s.strip() for s in scenes.split(",") if s.strip()]:
        d = Path(args.scenes_root) / name
        for sub in ("input/dtu", "gt/dtu_test"):
            if not (d / sub).is_dir():
                raise SystemExit(f"scene {name!r}: {d / sub} not found (layout: <scenes-root>/<name>/input/dtu, gt/...)")
        gt_mesh = d / "gt" / "mesh.ply"
        gt_alb = d / "gt" / "arrays_test.npz"
        targets.append({"mode": "synthetic", "scene": name, "scene_dir": str(d.resolve()),
                        "gt_mesh": str(gt_mesh.resolve()) if gt_mesh.exists() else None,
                        "gt_albedo": str(gt_alb.resolve()) if gt_alb.exists() else None})
    for name in [s.strip() for s in (args.dataset or "").split(",") if s.strip()]:
        d = Path(name) if (os.sep in name or Path(name).is_dir()) else Path(args.datasets_root) / name
        if not d.is_dir():
            raise SystemExit(f"dataset {name!r}: {d} not found")
        targets.append({"mode": "real", "scene": d.name, "data_dir": str(d.resolve()), "gt_mesh": None,
                        "gt_albedo": None, "downscale": args.downscale, "max_side": args.max_side,
                        "holdout_every": args.holdout_every,
                        "mesh_resolution": args.mesh_resolution})
    if not targets:
        raise SystemExit("nothing to run: give --scenes and/or --dataset")
    seeds = run_seeds(args.seeds, args.repeats, extra)
    runs = []
    for t in targets:
        for c in configs:
            for v in variants:
                for r, seed in enumerate(seeds):
                    ov = {"train.eval_every_s": float(eval_every_for.get(c, args.eval_every)), "train.eval_stride": int(args.eval_stride)}
                    ov.update(extra)
                    ov.update(VARIANTS[v])
                    if seed is not None:
                        ov["train.seed"] = seed
                    rid = f"{t['scene']}__{c}__{v}__r{r}"
                    runs.append({**t, "preset": c, "variant": v, "repeat": r, "id": rid,
                                 "budget_s": float(budget_for.get(c, args.budget)), "overrides": ov,
                                 "threads": args.threads, "chamfer_resolution": args.chamfer_resolution,
                                 "chamfer_samples": args.chamfer_samples, "fit_chamfer": args.fit_chamfer})
    return runs


def _metrics_summary(run_dir: Path, evals: list[dict] | None = None) -> dict:
    """Curves and counters from ``RUN/metrics.jsonl``; each test record gets its evaluation's
    duration ``eval_s`` from the eval clock (:class:`bench.child._EvalClock`)."""
    from nepf_core.plots import read_metrics
    path = run_dir / "metrics.jsonl"
    recs = read_metrics(path) if path.exists() else []
    keys = ("step", "wall_s", "test_psnr", "test_psnr_full", "test_psnr_radiance", "test_psnr_radiance_full", "albedo_psnr", "albedo_psnr_lit", "lit_fraction", "chamfer", "chamfer_world", "final")
    tests = [{k: r.get(k) for k in keys if k in r} for r in recs if r.get("kind") == "test"]
    clock = {e["step"]: e for e in evals or [] if e.get("train_wall_s") is not None}
    for t in tests:
        e = clock.get(t.get("step"))
        if e is not None:
            t["eval_s"] = e.get("eval_s")
    train = [r for r in recs if r.get("kind", "train") == "train"]
    out = {"test_curve": tests, "n_train_records": len(train)}
    if train:
        last = train[-1]
        out["last_train"] = {k: last.get(k) for k in ("step", "wall_s", "loss", "nonfinite_steps", "batch_rays",
                                                      "rays_per_s", "samples_per_s")}
        out["nonfinite_steps_max"] = max(int(r.get("nonfinite_steps") or 0) for r in train)
        out["loss_nonfinite_records"] = sum(1 for r in train if r.get("loss") is None)
    return out


def run_one(spec: dict, out_dir: Path, timeout_s: float, log=print) -> dict:
    run_dir = out_dir / "runs" / spec["id"]
    run_dir.mkdir(parents=True, exist_ok=True)
    for stale in ("bench_child.json", "metrics.jsonl"):
        (run_dir / stale).unlink(missing_ok=True)
    spec = {**spec, "run_dir": str(run_dir)}
    spec_path = run_dir / "bench_spec.json"
    spec_path.write_text(json.dumps(spec, indent=2))
    env = dict(os.environ)
    env["PYTHONPATH"] = str(REPO) + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    if spec.get("threads"):
        env["OMP_NUM_THREADS"] = env["MKL_NUM_THREADS"] = str(spec["threads"])
    cmd = [sys.executable, "-m", "bench.run", "--child", str(spec_path)]
    t0 = time.perf_counter()
    with open(run_dir / "bench_log.txt", "w") as logf:
        proc = subprocess.Popen(cmd, cwd=str(REPO), env=env, stdout=logf, stderr=subprocess.STDOUT,
                                start_new_session=True)
        killed = False
        while True:
            pid, status, ru = os.wait4(proc.pid, os.WNOHANG)
            if pid == proc.pid:
                break
            if not killed and time.perf_counter() - t0 > timeout_s:
                log(f"  ! {spec['id']}: over {timeout_s:.0f} s, killing pid {proc.pid}")
                try:
                    os.killpg(proc.pid, signal.SIGKILL)
                except ProcessLookupError:
                    pass
                killed = True
            time.sleep(0.5)
        proc.returncode = os.waitstatus_to_exitcode(status)
    elapsed = time.perf_counter() - t0
    rec = {"id": spec["id"], "scene": spec["scene"], "mode": spec["mode"], "config": spec["preset"],
           "variant": spec["variant"], "repeat": spec["repeat"], "budget_s": spec["budget_s"],
           "run_dir": str(run_dir), "returncode": proc.returncode, "killed_timeout": killed,
           "process_wall_s": elapsed, "peak_rss_mb_process": ru.ru_maxrss / 1024.0,
           "cpu_user_s": ru.ru_utime, "cpu_sys_s": ru.ru_stime, "overrides": spec["overrides"]}
    child_path = run_dir / "bench_child.json"
    child = json.loads(child_path.read_text()) if child_path.exists() else {"status": "failed",
                                                                            "error": "child wrote no result"}
    rec.update(_collect(child, run_dir))
    if killed:
        rec["status"] = "killed_timeout"
    return rec


def _collect(child: dict, run_dir: Path) -> dict:
    summ = child.get("summary") or {}
    rec = {"status": child.get("status"), "error": child.get("error"),
           "steps": summ.get("step"), "train_wall_s": summ.get("wall_s"),
           "nonfinite_steps": summ.get("nonfinite_steps"),
           "peak_rss_mb_fit": child.get("rss_after_fit_mb"), "torch_threads": child.get("torch_threads"),
           "loadavg_start": child.get("loadavg_start"), "loadavg_end": child.get("loadavg_end"),
           "report": summ.get("report"), "split": summ.get("split"), "mesh": summ.get("mesh")}
    for k in ("chamfer_final", "chamfer_final_world", "chamfer_final_s", "chamfer_final_error",
              "chamfer_resolution", "chamfer_samples", "fit_process_s"):
        if k in child:
            rec[k] = child[k]
    rec.update(_metrics_summary(run_dir, child.get("evals")))
    rec["relight_eval"] = child.get("relight_eval")
    ev = [e["eval_s"] for e in child.get("evals") or [] if e.get("eval_s") is not None]
    rec["eval_s_median"] = sorted(ev)[len(ev) // 2] if ev else None
    rec["n_evals"] = len(child.get("evals") or [])
    if rec.get("nonfinite_steps") is None:
        rec["nonfinite_steps"] = rec.get("nonfinite_steps_max")
    if rec.get("steps") is None and rec.get("last_train"):
        rec["steps"], rec["train_wall_s"] = rec["last_train"]["step"], rec["last_train"]["wall_s"]
    # fit()'s summary wall_s is taken after the final checkpoint/evaluation/report/plot and so also
    # counts writing report.json and error_vs_time.png; the final evaluation's (corrected) stamp is
    # the training time at the end of training.
    rec["summary_wall_s"] = rec.get("train_wall_s")
    fin = [t for t in rec.get("test_curve") or [] if t.get("final") and t.get("wall_s") is not None]
    if fin and fin[-1].get("step") == rec.get("steps"):
        rec["train_wall_s"] = fin[-1]["wall_s"]
    return rec


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["--child"]:
        from bench.child import child_main
        return child_main(argv[1])
    args = build_parser().parse_args(argv)
    runs = plan_runs(args)
    stamp = datetime.now().strftime("%Y%m%d-%H%M%S")
    out = Path(args.out or REPO / "bench" / "results" / stamp)
    command = "python -m bench run " + " ".join(shlex.quote(a) for a in argv)
    total_budget = sum(r["budget_s"] for r in runs)
    print(f"bench: {len(runs)} runs, {total_budget / 60:.1f} min of training budget -> {out}")
    for r in runs:
        print(f"  {r['id']}: budget {r['budget_s']:.0f} s, overrides {r['overrides']}")
    if args.dry_run:
        return 0
    out.mkdir(parents=True, exist_ok=True)
    from bench import report
    results = {"command": command, "argv": argv, "cwd": os.getcwd(), "started": datetime.now().isoformat(timespec="seconds"),
               "machine": machine_info(args.threads), "settings": {k: v for k, v in vars(args).items()},
               "runs": []}
    prev = {}
    if args.skip_done and (out / "results.json").exists():
        prev = {r["id"]: r for r in json.loads((out / "results.json").read_text()).get("runs", [])}
    for i, spec in enumerate(runs, 1):
        done = out / "runs" / spec["id"] / "bench_child.json"
        if args.skip_done and spec["id"] in prev and done.exists() \
                and prev[spec["id"]].get("overrides") == spec["overrides"]:   # same run, not just the same id
            print(f"[{i}/{len(runs)}] {spec['id']}: done before, reused")
            results["runs"].append(prev[spec["id"]])
            continue
        print(f"[{i}/{len(runs)}] {spec['id']}: training {spec['budget_s']:.0f} s ...", flush=True)
        rec = run_one(spec, out, timeout_s=args.timeout_factor * spec["budget_s"] + 900.0)
        results["runs"].append(rec)
        fin = report.final_test(rec)
        print(f"[{i}/{len(runs)}] {spec['id']}: {rec['status']} steps={rec.get('steps')} "
              f"train={_f(rec.get('train_wall_s'))}s process={rec['process_wall_s']:.0f}s "
              f"psnr={_f(fin.get('test_psnr'), 2)} albedo={_f(fin.get('albedo_psnr'), 2)} albedo_lit={_f(fin.get('albedo_psnr_lit'), 2)} "
              f"chamfer256={_f(rec.get('chamfer_final'), 5)} rss={rec['peak_rss_mb_process']:.0f}MB"
              + (f" error={rec['error']}" if rec.get("error") else ""), flush=True)
        results["finished"] = datetime.now().isoformat(timespec="seconds")
        results["machine"]["loadavg_end"] = list(os.getloadavg())
        report.write_all(results, out)
    print(f"bench: wrote {out / 'results.json'}, {out / 'table.md'}")
    return 0


def _f(x, nd: int = 1) -> str:
    return "n/a" if x is None else f"{x:.{nd}f}"


if __name__ == "__main__":
    sys.exit(main())
