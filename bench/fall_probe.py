"""Why does held-out PSNR fall late in a run? Three measurements at every held-out evaluation of **one** run.

``python -m bench.fall_probe SCENE_DIR OUT --budget 600 --seed 3``

Trains the ``fast`` preset (adaptive, as ``bench run`` does) and, at every held-out evaluation,
records beside the run's own held-out PSNR (the preset's sampling):

* ``dense``: the same held-out views and weights rendered with dense sampling
  (``--dense`` coarse + importance samples, 4 up-sampling rounds). If the fall is a sampling
  artefact of a sharpening surface (``inv_s`` growing past what 24 + 8 samples resolve), this
  curve does not fall;
* ``train``: ``--train-views`` training views spread over the set, with the preset's sampling.
  If the fall is over-fitting of the training views, this curve keeps rising while the
  held-out one falls;
* ``inv_s``: the NeuS sharpness at that evaluation.

Rows go to ``OUT/probe.jsonl`` as ``{"eval", "weights", "test_psnr", "inv_s"}`` (``weights`` is
``held_out``, ``dense`` or ``train``; the wall clock of evaluation ``n`` is that of the n-th
``test`` record of ``metrics.jsonl``); the summary printed and written to
``OUT/probe_summary.json`` gives, per row kind, the peak (over evaluations), the last value and
the fall between them. The extra renders are excluded from the training clock like the
regular evaluation (they run inside it).
"""
from __future__ import annotations

import dataclasses
import json
import sys
from pathlib import Path

from bench.probe_fit import fit_and_summarize, probe_parser, synthetic_scene


def main(argv: list[str] | None = None) -> int:
    p = probe_parser("python -m bench.fall_probe", __doc__)
    p.add_argument("--train-views", type=int, default=8, help="training views rendered at each evaluation")
    p.add_argument("--dense", default="64,64", help="coarse,importance samples of the dense render")
    p.add_argument("--variant", default="adaptive", choices=("adaptive", "all_on"))
    a = p.parse_args(argv)
    scene_dir = synthetic_scene(a.scene_dir)
    try:
        n_coarse, n_imp = (int(x) for x in a.dense.split(","))
    except ValueError:
        raise SystemExit(f"--dense must be two integers 'coarse,importance', got {a.dense!r}")
    if a.train_views < 1:
        raise SystemExit("--train-views must be >= 1")

    import numpy as np
    import torch
    torch.set_num_threads(a.threads)
    import nepf_core.fit as fitmod
    from nepf_core.reframe import load_held_out

    from bench.run import VARIANTS

    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    log = (out / "probe.jsonl").open("w")
    state: dict = {"n": 0}
    regular_eval = fitmod.evaluate_test

    def probe_eval(model, cfg, targets, device, world_from_norm, stride, with_chamfer):
        rec = regular_eval(model, cfg, targets, device, world_from_norm, stride, with_chamfer)
        if "train" not in state:
            train = load_held_out(str(scene_dir / "input" / "dtu"), world_from_norm)
            idx = np.linspace(0, train.n_views - 1, min(a.train_views, train.n_views)).round().astype(int)
            state["train"] = dataclasses.replace(targets, test_scene=train.subset(sorted(set(idx))), gt_albedo=None)
        dense_cfg = dataclasses.replace(cfg, render=dataclasses.replace(
            cfg.render, n_samples=n_coarse, n_importance=n_imp, up_sample_steps=4))
        dense = regular_eval(model, dense_cfg, targets, device, world_from_norm, stride, False)
        train = regular_eval(model, cfg, state["train"], device, world_from_norm, stride, False)
        state["n"] += 1
        inv_s = float(model.deviation().detach())
        for name, r in (("held_out", rec), ("dense", dense), ("train", train)):
            log.write(json.dumps({"eval": state["n"], "weights": name, "test_psnr": r.get("test_psnr"),
                                  "inv_s": inv_s}) + "\n")
        log.flush()
        return rec

    fitmod.evaluate_test = probe_eval
    fit_and_summarize(scene_dir, out, a, summarize_fall, extra_overrides=VARIANTS[a.variant])
    log.close()
    return 0


def summarize_fall(probe_path: Path, metrics_path: Path) -> dict:
    """Per row kind: ``peak`` (max over evaluations, with its wall_s), ``last`` and ``fall = peak - last``.

    The probe rows carry the evaluation index; the wall clock comes from the n-th ``test``
    record of ``metrics.jsonl`` (both are written once per evaluation, in order).
    """
    tests = [json.loads(line) for line in metrics_path.read_text().splitlines() if '"kind": "test"' in line]
    rows = [json.loads(line) for line in probe_path.read_text().splitlines() if line.strip()]
    out: dict = {}
    for name in sorted({r["weights"] for r in rows}):
        ser = [(tests[r["eval"] - 1]["wall_s"] if r["eval"] - 1 < len(tests) else None, r["test_psnr"], r["inv_s"])
               for r in rows if r["weights"] == name and r["test_psnr"] is not None]
        if not ser:
            continue
        k = max(range(len(ser)), key=lambda i: ser[i][1])
        out[name] = {"peak": ser[k][1], "peak_wall_s": ser[k][0], "last": ser[-1][1], "last_wall_s": ser[-1][0],
                     "fall": ser[k][1] - ser[-1][1], "inv_s_at_peak": ser[k][2], "inv_s_last": ser[-1][2]}
    return out


if __name__ == "__main__":
    sys.exit(main())
