"""Which weight-average decay? Evaluate several averages and the live weights in **one** run.

``python -m bench.ema_probe SCENE_DIR OUT --budget 600 --decays 0.999,0.9995``

Trains the ``fast`` preset (adaptive, as ``bench run`` does) on a synthetic scene and, at every
held-out evaluation, evaluates besides the preset's average (``train.ema_decay``) one extra
average per ``--decays`` value (same warm-up ``beta_t = min(beta, (1+t)/(10+t))``, restarted
with it when the shading model changes) and the live weights, on the same views and step.
Each evaluation's records go to ``OUT/probe.jsonl`` as ``{"step", "wall_s", "weights",
"test_psnr", "albedo_psnr"}``; a summary (mean PSNR and mean absolute change between
consecutive evaluations over the last half of the run, per weight set) is printed and written
to ``OUT/probe_summary.json``. Comparing inside one run removes the run-to-run noise that a
pair of runs with different decays would carry. The extra evaluations are excluded from the
training clock like the regular one.
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
from contextlib import contextmanager
from pathlib import Path


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m bench.ema_probe", description=__doc__.split("\n")[0])
    p.add_argument("scene_dir", help="a synthetic scene folder (input/dtu, gt/dtu_test)")
    p.add_argument("out", help="run folder to create")
    p.add_argument("--budget", type=float, default=600.0)
    p.add_argument("--decays", default="0.999,0.9995", help="extra averages to evaluate (comma-separated)")
    p.add_argument("--eval-every", type=float, default=30.0)
    p.add_argument("--eval-stride", type=int, default=2)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--seed", type=int, default=0)
    a = p.parse_args(argv)
    scene = Path(a.scene_dir)
    if not (scene / "input" / "dtu").is_dir() or not (scene / "gt" / "dtu_test").is_dir():
        raise SystemExit(f"{scene}: not a synthetic scene folder (needs input/dtu and gt/dtu_test)")
    decays = [float(x) for x in a.decays.split(",") if x.strip()]
    if any(not 0.0 < d < 1.0 for d in decays):
        raise SystemExit(f"--decays must lie in (0, 1): {decays}")

    import torch
    torch.set_num_threads(a.threads)
    import nepf_core.fit as fitmod
    from nepf_core.jobs import run_job
    from nepf_core.weight_average import ParamEMA

    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    log = (out / "probe.jsonl").open("w")
    state: dict = {}

    class ProbeEMA(ParamEMA):
        """The preset's average plus the extra ones, updated and restarted together."""

        def __init__(self, model, decay):
            super().__init__(model, decay)
            self.extra = {d: ParamEMA(model, d) for d in decays}
            state["ema"] = self

        def update(self, model):
            super().update(model)
            for e in self.extra.values():
                e.update(model)

        def reset(self, model):
            super().reset(model)
            for e in self.extra.values():
                e.reset(model)

        @contextmanager
        def applied(self, model):
            state["live"] = [p.detach().clone() for p in self._live(model)]
            with super().applied(model) as m:
                yield m

    regular_eval = fitmod.evaluate_test

    def probe_eval(model, cfg, targets, device, world_from_norm, stride, with_chamfer):
        rec = regular_eval(model, cfg, targets, device, world_from_norm, stride, with_chamfer)
        ema = state["ema"]
        rows = [(f"ema {ema.decay}", rec)]
        for d, e in ema.extra.items():
            with e.applied(model):
                rows.append((f"ema {d}", regular_eval(model, cfg, targets, device, world_from_norm, stride, False)))
        live = ema._live(model)
        held = [p.detach().clone() for p in live]
        with torch.no_grad():
            for p, s in zip(live, state["live"]):
                p.copy_(s)
        rows.append(("live", regular_eval(model, cfg, targets, device, world_from_norm, stride, False)))
        with torch.no_grad():
            for p, s in zip(live, held):
                p.copy_(s)
        state["n"] = state.get("n", 0) + 1
        for name, r in rows:
            log.write(json.dumps({"eval": state["n"], "weights": name, "test_psnr": r.get("test_psnr"),
                                  "albedo_psnr": r.get("albedo_psnr")}) + "\n")
        log.flush()
        return rec

    fitmod.ParamEMA = ProbeEMA
    fitmod.evaluate_test = probe_eval
    run_job(str(scene / "input" / "dtu"), out / "run", preset="fast", time_budget_s=a.budget,
            test_dir=str(scene / "gt" / "dtu_test"), gt_albedo=str(scene / "gt" / "arrays_test.npz") if (scene / "gt" / "arrays_test.npz").exists() else None,
            export=False, overrides={"train.eval_every_s": a.eval_every, "train.eval_stride": a.eval_stride,
                                     "train.seed": a.seed}, device="cpu", resume=False, log=lambda *x: None)
    log.close()
    summary = summarize_probe(out / "probe.jsonl", out / "run" / "metrics.jsonl")
    (out / "probe_summary.json").write_text(json.dumps(summary, indent=2))
    print(json.dumps(summary, indent=2))
    return 0


def summarize_probe(probe_path: Path, metrics_path: Path) -> dict:
    """Per weight set, over the evaluations in the last half of the training time: mean PSNR,
    mean |change| between consecutive evaluations, and the final one."""
    tests = [json.loads(line) for line in metrics_path.read_text().splitlines() if '"kind": "test"' in line]
    walls = {k + 1: t["wall_s"] for k, t in enumerate(tests)}
    rows = [json.loads(line) for line in probe_path.read_text().splitlines()]
    t_end = max(walls.values()) if walls else 0.0
    out = {}
    for name in dict.fromkeys(r["weights"] for r in rows):
        seq = [(walls.get(r["eval"]), r["test_psnr"]) for r in rows if r["weights"] == name]
        late = [v for w, v in seq if w is not None and w >= 0.5 * t_end and v is not None]
        if not late:
            continue
        out[name] = {"n_late": len(late), "mean_late": statistics.fmean(late),
                     "mean_abs_change_late": statistics.fmean(abs(b - c) for b, c in zip(late[1:], late)) if len(late) > 1 else None,
                     "final": seq[-1][1], "curve": seq}
    return out


if __name__ == "__main__":
    sys.exit(main())
