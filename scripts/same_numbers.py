"""Per-step losses of short fits, for checking that a refactor keeps the numbers bit-identical.

    cd <checkout> && python scripts/same_numbers.py OUT.json [--fast-steps 200] [--paper-steps 20]

Runs ``fit()`` on a generated scene (``nepf_core.data.synth``: a textured glossy sphere, masks)
with the ``fast`` preset for ``--fast-steps`` steps and the ``paper`` preset for
``--paper-steps`` steps of ``--paper-batch`` rays (its code path: midpoint alpha, autograd normals,
the Hessian term, SIREN heads), seed 0, one thread, ``train.log_every = 1``, no held-out evaluation,
and writes every train record's loss values (``float.hex``, exact) to ``OUT.json``. Run it on
two commits and compare the files with ``cmp``. The checkout in the current directory is the
one imported.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, os.getcwd())   # the checkout in the current directory, not the installed one

import torch  # noqa: E402


def _losses(run_dir: Path) -> list[dict]:
    rows = []
    for line in (run_dir / "metrics.jsonl").read_text().splitlines():
        rec = json.loads(line)
        if rec.get("kind") != "train":
            continue
        rows.append({"step": rec["step"], **{k: float(v).hex() for k, v in sorted(rec.items())
                                             if k.startswith("loss") or k == "inv_s"}})
    return rows


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("out")
    ap.add_argument("--fast-steps", type=int, default=200)
    ap.add_argument("--paper-steps", type=int, default=20)
    ap.add_argument("--paper-batch", type=int, default=64,
                    help="rays per paper step (the preset's 512 cost ~170 s a step on one CPU thread)")
    ap.add_argument("--only", choices=("fast", "paper"), default=None)
    args = ap.parse_args()
    torch.set_num_threads(1)
    from nepf_core import config
    from nepf_core.data.dtu import load_dtu
    from nepf_core.data.synth import make_scene
    from nepf_core.train import fit

    result = {}
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        make_scene(tmp / "scene", shape="sphere", material="textured", n_views=8, n_test=1, resolution=32,
                   write_mesh=False, seed=0)
        scene = load_dtu(tmp / "scene" / "dtu")
        for name, steps in (("fast", args.fast_steps), ("paper", args.paper_steps)):
            if args.only not in (None, name):
                continue
            cfg = config.preset(name)
            batch = args.paper_batch if name == "paper" else cfg.train.batch_rays
            cfg = dataclasses.replace(cfg, train=dataclasses.replace(
                cfg.train, iters=steps, log_every=1, sync_every=0, checkpoint_every=10 ** 9, eval_every_s=0.0,
                seed=0, batch_rays=batch))
            fit(scene, tmp / name, cfg, device="cpu")
            result[name] = _losses(tmp / name)
    Path(args.out).write_text(json.dumps(result, indent=1, sort_keys=True))
    print({k: (len(v), v[-1] if v else None) for k, v in result.items()})


if __name__ == "__main__":
    main()
