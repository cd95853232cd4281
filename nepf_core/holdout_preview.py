"""A side-by-side picture of one held-out view, written at every held-out evaluation.

    [ render | ground truth | error ],   error = clip(4 mean_c |render - gt|, 0, 1) in the
                                          'inferno' colour map (sRGB values)

Inputs are sRGB ``[H, W, 3]`` in [0, 1]. Why: a job's page shows the latest one beside the error
chart, so a user sees the object appear long before the export (docs/WEB.md). The error is
amplified 4x so that the last few dB of a converging run still show. numpy and Pillow only (no
torch), so the service's stand-ins can write one too. The file is written atomically (a
temporary name, then a rename): the API may serve it while training writes the next one.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

#: where a run keeps it, relative to the run folder (served as an artifact)
PREVIEW_PATH = "holdout/latest.png"
ERROR_GAIN = 4.0
GAP = 2
"""Pixels of black between the three panels."""


def side_by_side(render_srgb: np.ndarray, gt_srgb: np.ndarray) -> np.ndarray:
    """``[H, W, 3]`` x 2 (sRGB, [0, 1]) -> ``[H, 3 W + 2 GAP, 3]`` uint8: render, ground truth, error."""
    if render_srgb.shape != gt_srgb.shape or render_srgb.ndim != 3 or render_srgb.shape[-1] != 3:
        raise ValueError(f"render {render_srgb.shape} and ground truth {gt_srgb.shape} must both be [H, W, 3]")
    from matplotlib import colormaps

    err = np.clip(ERROR_GAIN * np.abs(render_srgb - gt_srgb).mean(-1), 0.0, 1.0)
    err_rgb = colormaps["inferno"](err)[..., :3]
    h = render_srgb.shape[0]
    gap = np.zeros((h, GAP, 3))
    panel = np.concatenate([np.clip(render_srgb, 0, 1), gap, np.clip(gt_srgb, 0, 1), gap, err_rgb], axis=1)
    return (panel * 255.0 + 0.5).astype(np.uint8)


def write_holdout_preview(run_dir, render_srgb: np.ndarray, gt_srgb: np.ndarray) -> str:
    """Write :func:`side_by_side` to ``run_dir/`` :data:`PREVIEW_PATH` atomically; returns that
    relative path (what a ``kind: "test"`` record names as ``preview``)."""
    from PIL import Image

    path = Path(run_dir) / PREVIEW_PATH
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    Image.fromarray(side_by_side(render_srgb, gt_srgb)).save(tmp, format="PNG")
    os.replace(tmp, path)
    return PREVIEW_PATH
