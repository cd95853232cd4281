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

import json
import statistics
import sys
from contextlib import contextmanager
from pathlib import Path

from bench.probe_fit import fit_and_summarize, probe_parser, synthetic_scene


def main(argv: list[str] | None = None) -> int:
    p = probe_parser("python -m bench.ema_probe", __doc__)
    p.add_argument("--decays", default="0.999,0.9995", help="extra averages to evaluate (comma-separated)")
    a = p.parse_args(argv)
    scene = synthetic_scene(a.scene_dir)
    decays = [float(x) for x in a.decays.split(",") if x.strip()]
    if any(not 0.0 < d < 1.0 for d in decays):
        raise SystemExit(f"--decays must lie in (0, 1): {decays}")

    import torch
    torch.set_num_threads(a.threads)
    import nepf_core.fit as fitmod
    from nepf_core.weight_average import ParamEMA

    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    log = (out / "probe.jsonl").open("w")
    state: dict = {}

    class ProbeEMA(ParamEMA):
        """The preset's average plus the extra ones, updated and restarted together."""

        def __init__(self, model, decay, half_life_s=0.0):
            super().__init__(model, decay, half_life_s)
            self.extra = {d: ParamEMA(model, d) for d in decays}
            state["ema"] = self

        def update(self, model, dt_s=None):
            super().update(model, dt_s=dt_s)
            for e in self.extra.values():
                e.update(model, dt_s=dt_s)

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
    fit_and_summarize(scene, out, a, summarize_probe, gt_albedo=True)
    log.close()
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
