"""Which samples of a ray carry weight: ``python -m bench.ray_samples DATA [--max-side 540]``.

Trains ``fast`` on ``DATA`` (a scene's ``input/dtu`` or a real capture) for ``--steps`` steps and,
at a few steps along the way, renders ``--rays`` training rays (their own generator; the run's
random state is left alone) and counts, per ray:

* the object's samples (the NeuS samples inside the region, ``S`` per ray) and the background
  volume's (``n`` per ray);
* how many of each carry weight: ``w > 1e-3`` of the pixel, the background's weights taken as
  ``(1 - sum_i w_i) w_j`` (its share of the pixel);
* how many are needed for 99 % of the ray's weight of that kind (sorted by weight);
* the object's samples the heads are evaluated at (``w > head_weight_threshold``), and the share
  of the pixel the object covers (``sum_i w_i``).

It answers issue 32's item 3 ("most of the time goes to samples that change nothing") with a
count rather than a guess. Prints one Markdown row per measured step and writes ``--json``.
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

import torch

from nepf_core.train.hooks import TrainHooks

CARRIES = 1e-3
"""A sample 'carries weight' when its share of the pixel exceeds this."""


def needed_for(weights: torch.Tensor, share: float = 0.99) -> torch.Tensor:
    """``[R, S] -> [R]``: the fewest samples whose weights sum to ``share`` of the row's total
    (0 for a row without weight)."""
    w = weights.sort(dim=-1, descending=True).values
    total = w.sum(-1, keepdim=True)
    reached = w.cumsum(-1) >= share * total
    count = (~reached).sum(-1) + 1
    return torch.where(total[:, 0] > 0, count, torch.zeros_like(count))


def measure(model, rays, render_cfg) -> dict:
    """Per-ray sample statistics of one batch (module docstring), means over the rays."""
    from nepf_core.render.renderer import sample_weights
    from nepf_core.render.sampling import object_segment

    near, far, _, cut = object_segment(rays.origins, rays.directions, model.cfg.object_halfspace)
    sw = sample_weights(model, rays, render_cfg, near, far, train=False, cos_anneal=1.0, generator=None)
    fg = sw.weights
    cover = fg.sum(-1)
    row = {"rays": int(fg.shape[0]), "object_samples": fg.shape[1], "object_cover": float(cover.mean()),
           "object_carrying": float((fg > CARRIES).sum(-1).float().mean()),
           "object_for_99pct": float(needed_for(fg).float().mean()),
           "head_evals": float((fg > render_cfg.head_weight_threshold).sum(-1).float().mean())}
    if getattr(model, "background", None) is not None:
        wb, _ = model.background.weights_and_colours(rays.origins, rays.directions, start=cut)
        share = (1.0 - cover)[:, None] * wb
        row.update({"background_samples": wb.shape[1], "background_carrying": float((share > CARRIES).sum(-1).float().mean()),
                    "background_for_99pct": float(needed_for(share).float().mean())})
    return row


class RaySampleProbe(TrainHooks):
    """Measures at the given steps (:func:`measure`), after the optimiser step."""

    def __init__(self, at_steps, n_rays: int) -> None:
        self.at, self.n_rays, self.rows = set(at_steps), n_rays, []

    def after_step(self, run, step: int, out, losses: dict) -> None:
        if step not in self.at:
            return
        with torch.random.fork_rng(devices=[]), torch.no_grad():
            rays = run.sampler.sample(self.n_rays, generator=torch.Generator().manual_seed(step))
            self.rows.append({"step": step, **measure(run.model, rays, run.run_cfg.render)})


def main(argv=None) -> int:
    from nepf_core.data.detect import load_scene
    from nepf_core.jobs import build_config
    from nepf_core.train import fit

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("data")
    ap.add_argument("--max-side", type=int, default=540)
    ap.add_argument("--steps", type=int, default=600)
    ap.add_argument("--at", default="100,300,600", help="steps to measure at")
    ap.add_argument("--rays", type=int, default=2048)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--json", type=Path)
    a = ap.parse_args(argv)
    torch.set_num_threads(a.threads)
    probe = RaySampleProbe([int(s) for s in a.at.split(",")], a.rays)
    cfg = build_config("fast", a.steps, {"train.eval_every_s": 0.0, "train.sync_every": 0,
                                         "train.checkpoint_every": 10 ** 9})
    with tempfile.TemporaryDirectory() as run:
        fit(load_scene(a.data, max_side=a.max_side), run, cfg, device="cpu", hooks=[probe])
    keys = list(probe.rows[0]) if probe.rows else []
    print("| " + " | ".join(keys) + " |\n|" + "---|" * len(keys))
    for r in probe.rows:
        print("| " + " | ".join(f"{r[k]:.3g}" if isinstance(r[k], float) else str(r[k]) for k in keys) + " |")
    if a.json:
        a.json.write_text(json.dumps(probe.rows, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
