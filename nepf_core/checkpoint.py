"""Checkpoints for exact resume: model, optimiser, schedule step, RNG states, loop state."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch


def save_checkpoint(path: Path, *, model, optimizer, step: int, wall_s: float, generator: torch.Generator,
                    extra: dict) -> None:
    """Write atomically (temp file + rename) so a kill mid-write never corrupts ``latest.pt``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    state = {
        "model": model.state_dict(), "optimizer": optimizer.state_dict(), "step": step, "wall_s": wall_s,
        "rng_torch": torch.get_rng_state(), "rng_numpy": np.random.get_state(),
        "rng_generator": generator.get_state(),
        "rng_cuda": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else None,
        "extra": extra,
    }
    tmp = path.with_suffix(".tmp")
    torch.save(state, tmp)
    os.replace(tmp, path)


def load_checkpoint(path: Path, *, model, optimizer, generator: torch.Generator, map_location) -> dict:
    """Restore everything :func:`save_checkpoint` wrote; returns the state dict."""
    state = torch.load(path, map_location=map_location, weights_only=False)
    model.load_state_dict(state["model"])
    if optimizer is not None:
        optimizer.load_state_dict(state["optimizer"])
    torch.set_rng_state(state["rng_torch"])
    np.random.set_state(state["rng_numpy"])
    generator.set_state(state["rng_generator"])
    if state.get("rng_cuda") is not None and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["rng_cuda"])
    return state


def prune_checkpoints(folder: Path, keep: int) -> None:
    """Keep the newest ``keep`` numbered checkpoints (``latest.pt`` is never removed)."""
    files = sorted(Path(folder).glob("ckpt_*.pt"))
    for f in files[:-keep] if keep > 0 else []:
        f.unlink(missing_ok=True)
