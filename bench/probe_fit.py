"""What the one-run probes (``bench.ema_probe``, ``bench.fall_probe``) share: their common
command-line options, the scene check, and the ``fast`` fit whose held-out evaluations they hook.

A probe replaces ``nepf_core.fit.evaluate_test`` with a function that calls the original and
renders more (its extra rows go to ``OUT/probe.jsonl``); :func:`fit_and_summarize` then trains,
summarises ``probe.jsonl`` against the run's ``metrics.jsonl``, and writes ``OUT/probe_summary.json``.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Callable


def probe_parser(prog: str, doc: str) -> argparse.ArgumentParser:
    """Parser with the probes' shared options: ``scene_dir out --budget --eval-every --eval-stride
    --threads --seed`` (defaults 600 s, 30 s, 2, 1 thread, seed 0)."""
    p = argparse.ArgumentParser(prog=prog, description=doc.split("\n")[0])
    p.add_argument("scene_dir", help="a synthetic scene folder (input/dtu, gt/dtu_test)")
    p.add_argument("out", help="run folder to create")
    p.add_argument("--budget", type=float, default=600.0)
    p.add_argument("--eval-every", type=float, default=30.0)
    p.add_argument("--eval-stride", type=int, default=2)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--seed", type=int, default=0)
    return p


def synthetic_scene(path: str) -> Path:
    """``path`` as a Path; SystemExit unless it holds ``input/dtu`` and ``gt/dtu_test``."""
    scene = Path(path)
    if not (scene / "input" / "dtu").is_dir() or not (scene / "gt" / "dtu_test").is_dir():
        raise SystemExit(f"{scene}: not a synthetic scene folder (needs input/dtu and gt/dtu_test)")
    return scene


def fit_and_summarize(scene: Path, out: Path, a: argparse.Namespace, summarize: Callable[[Path, Path], dict], *,
                      extra_overrides: dict | None = None, gt_albedo: bool = False) -> dict:
    """Train ``fast`` on ``scene`` into ``out/run`` (CPU, no export, no resume) with the parsed
    budget / evaluation schedule / seed, then ``summarize(out/probe.jsonl, out/run/metrics.jsonl)``,
    write it to ``out/probe_summary.json``, print it and return it. ``gt_albedo``: also evaluate
    the albedo against ``gt/arrays_test.npz`` when the scene has it."""
    from nepf_core.jobs import run_job

    overrides = {"train.eval_every_s": a.eval_every, "train.eval_stride": a.eval_stride, "train.seed": a.seed}
    overrides.update(extra_overrides or {})
    albedo = scene / "gt" / "arrays_test.npz"
    run_job(str(scene / "input" / "dtu"), out / "run", preset="fast", time_budget_s=a.budget,
            test_dir=str(scene / "gt" / "dtu_test"), gt_albedo=str(albedo) if gt_albedo and albedo.exists() else None,
            export=False, overrides=overrides, device="cpu", resume=False, log=lambda *x: None)
    summary = summarize(out / "probe.jsonl", out / "run" / "metrics.jsonl")
    (out / "probe_summary.json").write_text(json.dumps(summary, indent=2))
    print(json.dumps(summary, indent=2))
    return summary
