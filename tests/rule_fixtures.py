"""Helpers for the adaptivity tests: a coordinator on ``tiny`` and fake render outputs."""

from __future__ import annotations

import dataclasses
import json
from types import SimpleNamespace

import torch

from nepf_core.config import fast, tiny
from nepf_core.train.adaptivity import Adaptivity
from nepf_core.train.run_state import RunState


def make_adapt(*, enabled=True, iters_fixed=True, iters=1000, w_hessian=5e-4, plateau_window=1, preset=tiny,
               w_albedo_flat=None, **rules):
    """``(Adaptivity, RunState)`` on ``preset`` (``tiny``); the plateau tests hand-work single
    evaluations (``plateau_window=1``) unless they test the running mean. ``rules``: RuleConfig
    overrides (the config's ``rules`` section)."""
    cfg = preset()
    cfg.train.iters = iters
    cfg.train.adaptive = enabled
    cfg.loss.w_hessian = w_hessian
    if w_albedo_flat is not None:
        cfg.loss.w_albedo_flat = w_albedo_flat
    cfg.rules = dataclasses.replace(cfg.rules, plateau_window=plateau_window, **rules)
    rs = RunState.from_config(cfg)
    return Adaptivity(cfg, rs, iters_fixed=iters_fixed), rs


def resumed(a: Adaptivity, rs: RunState, **kw):
    """A fresh coordinator restored from ``a``'s checkpoint state (through JSON, as saved)."""
    b, rs_b = make_adapt(**kw)
    b.load_state(json.loads(json.dumps(a.state())))
    for k, v in RunState.from_dict(json.loads(json.dumps(rs.to_dict())), rs_b).to_dict().items():
        setattr(rs_b, k, v)
    return b, rs_b


def fake_out(share=None, metallic=0.0, n=32, opaque=True):
    """A RenderOutput-like object: ``n`` rays, all on the surface when ``opaque``; with ``share`` the
    lobe split of a specular check (pass ``check=True`` to ``after_step``)."""
    lobe = None if share is None else SimpleNamespace(share=torch.full((n,), float(share)))
    return SimpleNamespace(weight_sum=torch.full((n,), 0.9 if opaque else 0.1), lobe=lobe,
                           surface=SimpleNamespace(metallic=torch.full((n,), float(metallic))))


def losses(eik=0.0):
    return {"loss_eik": torch.tensor(float(eik))}


def named(a: Adaptivity, decision: str) -> list[dict]:
    return [d for d in a.decisions if d["decision"] == decision]


def records(run) -> list[dict]:
    return [json.loads(l) for l in (run / "metrics.jsonl").read_text().splitlines()]


__all__ = ["fake_out", "fast", "losses", "make_adapt", "named", "records", "resumed", "tiny"]
