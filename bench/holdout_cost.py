"""What the held-out split costs in quality: the same fit on all views and without views 0, K, 2K, ...

``python -m bench.holdout_cost SCENE_DIR --train-views all|split [--every 8] --budget 600 --out RUN``
trains the ``fast`` preset on ``SCENE_DIR/input/dtu`` (all 32 views, or the views that
``nepf fit --holdout-every K`` trains on) and evaluates both on the scene's own separate
test views (``SCENE_DIR/gt/dtu_test``, never trained on), so that the difference between the
two runs is the cost of the views the split takes out of training. Prints the final test
record as one JSON line (``test_psnr``, ``test_psnr_full``, ``test_ssim``, steps, views).
Run the two variants side by side, at one thread each, in one session.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene", help="a scene folder with input/dtu and gt/dtu_test (../shared/scenes/<name>)")
    ap.add_argument("--train-views", choices=["all", "split"], required=True)
    ap.add_argument("--every", type=int, default=8, help="the split's K (views 0, K, 2K, ... left out)")
    ap.add_argument("--budget", type=float, default=600.0, help="training seconds")
    ap.add_argument("--eval-every", type=float, default=60.0, help="training seconds between evaluations")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", required=True)
    a = ap.parse_args(argv)

    import torch

    from nepf_core.config import fast
    from nepf_core.data.detect import load_scene
    from nepf_core.data.split import split_scene
    from nepf_core.reframe import load_held_out
    from nepf_core.train import EvalTargets, fit

    torch.set_num_threads(a.threads)
    root = Path(a.scene)
    scene = load_scene(root / "input" / "dtu", split="train")
    if a.train_views == "split":
        scene, _ = split_scene(scene, a.every)
    cfg = fast()
    cfg.train.seed = a.seed
    cfg.train.eval_every_s = a.eval_every
    cfg.train.eval_stride = 1
    test = load_held_out(root / "gt" / "dtu_test", scene.world_from_norm)
    res = fit(scene, a.out, cfg, device="cpu", time_budget_s=a.budget, targets=EvalTargets(test_scene=test),
              iters_fixed=False)
    rec = {k: res.last_test.get(k) for k in ("test_psnr", "test_psnr_full", "test_ssim", "test_psnr_radiance")}
    rec.update({"scene": root.name, "train_views": a.train_views, "n_train": scene.n_views, "steps": res.step,
                "wall_s": round(res.wall_s, 1)})
    (Path(a.out) / "holdout_cost.json").write_text(json.dumps(rec, indent=2))
    print(json.dumps(rec), flush=True)


if __name__ == "__main__":
    main()
