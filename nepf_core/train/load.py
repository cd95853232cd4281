"""Rebuild a trained model from a run folder."""

from __future__ import annotations

import json
from pathlib import Path

import torch

from nepf_core.config import NePFConfig
from nepf_core.model import NePFModel
from nepf_core.train.result import FitError
from nepf_core.train.run_state import RunState
from nepf_core.train.setup import resolve_device


def load_model(run_dir, device: str = "auto") -> tuple[NePFModel, NePFConfig, dict]:
    """``(model, cfg, state)`` of a run: ``cfg`` from ``config.json`` (what the user asked for),
    the weights from ``checkpoints/latest.pt`` (the parameter average when the run kept one),
    and ``state`` the checkpoint dict with ``state["run_state"]``, the
    :class:`~nepf_core.train.run_state.RunState` at the checkpoint: render and export with
    ``state["run_state"].shading()`` (a dropped lobe stays dropped). The model is built with the
    run state's background model."""
    run = Path(run_dir)
    cfg_path, ck = run / "config.json", run / "checkpoints" / "latest.pt"
    if not cfg_path.exists() or not ck.exists():
        raise FitError(f"{run} is not a finished or checkpointed NePF run (missing config.json or checkpoints/latest.pt)")
    cfg = NePFConfig.from_dict(json.loads(cfg_path.read_text()))
    dev = resolve_device(device)
    state = torch.load(ck, map_location=dev, weights_only=False)
    run_state = RunState.from_checkpoint(state.get("extra"), cfg)
    model = NePFModel(run_state.model_config(cfg.model)).to(dev)
    model.load_state_dict(state["model"])
    ema = (state.get("extra") or {}).get("ema")
    if ema:  # the averaged weights are the run's model (nepf_core.weight_average); buffers stay
        model.load_state_dict(ema["params"], strict=False)
    state["run_state"] = run_state
    model.eval()
    return model, cfg, state
