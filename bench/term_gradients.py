"""Which loss term moves a head: ``python -m bench.term_gradients DATA [--steps 50,200,600] ...``.

At the chosen steps of a ``fast`` fit, for every loss term with a non-zero weight ``w_k``, the
gradient of the weighted term on one head's parameters ``theta`` (``--head``, default ``material``):

    norm_k = | d (w_k L_k) / d theta |_2          (how hard the term pulls the head)
    bias_k = d (w_k L_k) / d b                     (b: the head's last-layer bias, one per output)

``bias_k`` is the term's net pull on each output logit summed over the batch (positive: gradient
descent lowers the logit); for the material head the outputs are albedo r, g, b, roughness and
metallic. ``norm_k`` says whether the images (``loss_surf``, ``loss_vol``) or the priors set the
head; v31 (bench/RESULTS.md) measured ``bias_k`` of the metallic alone with a script, v45 both here.
The gradients are taken with ``torch.autograd.grad`` before the step's ``backward``
(:meth:`nepf_core.train.hooks.TrainHooks.before_backward`), so the run is the one the config
describes: the same steps, the same numbers. Their sum over the terms is the head's gradient of
the step (tests/test_term_gradients.py).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch

from nepf_core.losses import LOSS_TERMS
from nepf_core.train.hooks import TrainHooks

OUTPUT_NAMES = {"material": ("albedo_r", "albedo_g", "albedo_b", "roughness", "metallic"),
                "photon": ("polar", "azimuth", "intensity"),
                "radiance": ("red", "green", "blue")}
"""The last-layer outputs of each head (:mod:`nepf_core.fields.heads`), in order."""


def head_parameters(model, head: str) -> tuple[list[torch.Tensor], torch.Tensor]:
    """``(parameters, last-layer bias)`` of ``model.<head>`` (its MLP built by :func:`build_mlp`)."""
    module = getattr(model, head, None)
    if module is None or not hasattr(module, "mlp"):
        raise ValueError(f"the model has no head {head!r} with an MLP (choose one of {', '.join(OUTPUT_NAMES)})")
    return [p for p in module.parameters() if p.requires_grad], module.mlp.layers[-1].bias


def term_gradients(losses: dict, loss_cfg, params: list[torch.Tensor], bias: torch.Tensor) -> dict[str, dict]:
    """``{term: {"norm": |d(w L)/d theta|, "bias": [d(w L)/d b_j]}}`` for the terms of
    :data:`nepf_core.losses.LOSS_TERMS` in ``losses`` with a non-zero weight in ``loss_cfg`` that
    reach ``params`` (a term with no path to them is left out). The graph is kept for the step's
    own ``backward``; no ``.grad`` changes."""
    rows = {}
    for t in LOSS_TERMS:
        value, weight = losses.get(t.name), getattr(loss_cfg, t.weight)
        if value is None or weight == 0 or not value.requires_grad:
            continue
        grads = torch.autograd.grad(weight * value, params + [bias], retain_graph=True, allow_unused=True)
        if all(g is None for g in grads):
            continue
        norm = torch.sqrt(sum((g.double().pow(2).sum() for g in grads[:-1] if g is not None),
                               torch.zeros((), dtype=torch.float64)))
        g_bias = grads[-1] if grads[-1] is not None else torch.zeros_like(bias)
        rows[t.name] = {"norm": float(norm), "bias": [float(x) for x in g_bias.detach()]}
    return rows


class TermGradients(TrainHooks):
    """Records :func:`term_gradients` of ``head`` at ``steps`` into :attr:`rows`
    (``[{"step": N, "terms": {...}}]``)."""

    def __init__(self, head: str, steps) -> None:
        self.head, self.steps, self.rows = head, set(int(s) for s in steps), []

    def before_backward(self, run, step: int, losses: dict, loss_cfg) -> None:
        if step in self.steps:
            params, bias = head_parameters(run.model, self.head)
            self.rows.append({"step": step, "terms": term_gradients(losses, loss_cfg, params, bias)})


def format_rows(rows: list[dict], head: str) -> str:
    """One Markdown table: a line per step and term, the norm and the bias pull per output."""
    names = OUTPUT_NAMES.get(head) or ()
    width = max((len(t["bias"]) for r in rows for t in r["terms"].values()), default=0)
    names = names if len(names) == width else tuple(f"out{j}" for j in range(width))
    lines = ["| step | term | norm | " + " | ".join(names) + " |", "|---" * (3 + len(names)) + "|"]
    for r in rows:
        for name, t in sorted(r["terms"].items(), key=lambda kv: -kv[1]["norm"]):
            lines.append(f"| {r['step']} | {name} | {t['norm']:.2e} | " + " | ".join(f"{b:.1e}" for b in t["bias"]) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    from bench.run import _parse_overrides
    p = argparse.ArgumentParser(prog="python -m bench.term_gradients", description=__doc__.split("\n\n")[0])
    p.add_argument("data", help="a dataset folder (a scene's input/dtu)")
    p.add_argument("--steps", default="50,100,200,400,600", help="comma-separated steps to probe")
    p.add_argument("--head", default="material", choices=sorted(OUTPUT_NAMES))
    p.add_argument("--iters", type=int, default=1000,
                   help="the run's nominal length, which sets its schedule (warm-ups, coarse-to-fine, the rules' "
                        "warm-up); it stops after the last probed step (default: the suite's 1,000-step screens)")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--device", default="auto", choices=("auto", "cpu", "cuda"))
    p.add_argument("--override", action="append", default=[], metavar="section.field=VALUE")
    p.add_argument("--out", required=True, help="the run folder; term_gradients.json is written there")
    args = p.parse_args(argv)
    from nepf_core.callbacks import FitCallbacks
    from nepf_core.data.detect import load_scene
    from nepf_core.jobs import build_config
    from nepf_core.train import fit
    steps = sorted({int(s) for s in args.steps.split(",") if s.strip()})
    if not steps or steps[0] < 1 or steps[-1] > args.iters:
        raise SystemExit(f"--steps: give step numbers from 1 to --iters ({args.iters}), e.g. 50,200,600")
    torch.set_num_threads(args.threads)
    cfg = build_config("fast", args.iters, {"train.eval_every_s": 0.0, **_parse_overrides(args.override)})
    probe = TermGradients(args.head, steps)
    done = FitCallbacks(should_stop=lambda: bool(probe.rows) and probe.rows[-1]["step"] >= steps[-1])
    fit(load_scene(args.data), args.out, cfg, device=args.device, hooks=[probe], callbacks=done)
    Path(args.out, "term_gradients.json").write_text(json.dumps(probe.rows, indent=1))
    print(format_rows(probe.rows, args.head))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
