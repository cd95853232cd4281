"""Relight and material scores of a finished bench run, with its scene's oracle beside them.

A synthetic child run whose scene has ``gt/relight`` calls :func:`relight_metrics` after training
(its time is not training time): ``nepf render``'s channels of ``gt/dtu_test`` scored against
``gt/arrays_test.npz`` (albedo PSNR all / lit, roughness / metallic MAE, normal MAE), ``nepf
relight`` under ``gt/relight/lights.json`` scored with the relight PSNR, the learned light's
median direction error on the lit foreground (:func:`bench.shading_report.shading_rows`, all
albedos), and the oracle (:func:`bench.oracle.oracle_render`) with the same BSDF kind, so that the gap reads as "ours
against the best our BSDF can do", with what each of the run's channels costs alone
(``relight_cost_db``: the oracle's PSNR minus the oracle's with that channel from the run,
:mod:`bench.relight_attribution`), and the oracle restricted to what the training light shows
(``relight_observable_psnr``, :mod:`bench.observable_oracle`): the part of the gap above it no
method that reads the material from lit pixels can close.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

KEYS = ("relight_psnr", "relight_oracle_psnr", "relight_observable_psnr", "relight_scale", "relight_bsdf", "albedo_psnr", "albedo_psnr_lit",
        "roughness_mae", "metallic_mae", "normal_mae_deg", "light_dir_error_deg_median", "relight_cost_db")
"""What :func:`relight_metrics` reports (plus ``seconds``)."""


def has_relight_truth(scene_dir) -> bool:
    gt = Path(scene_dir) / "gt"
    return (gt / "relight" / "lights.json").is_file() and (gt / "arrays_test.npz").is_file()


def relight_metrics(run_dir, scene_dir, device: str = "cpu") -> dict:
    """Scores of the run in ``run_dir`` on the scene ``scene_dir`` (module docstring); renders go to
    ``run_dir/relight_eval``."""
    from bench.relight_attribution import CHANNELS, attribution
    from nepf_core.cli import render_run
    from nepf_core.relight.evaluation import eval_section
    t0 = time.perf_counter()
    gt = Path(scene_dir) / "gt"
    out = Path(run_dir) / "relight_eval"
    info = render_run(run_dir, gt / "dtu_test", out / "renders", device)
    renders = dict(np.load(out / "renders" / "arrays.npz"))
    scene = info["scene"]
    res = eval_section(run_dir, gt / "dtu_test", renders, scene.images, scene.masks, out,
                       relight_dir=gt / "relight", gt_maps=gt / "arrays_test.npz", device=device)
    rows = attribution(Path(scene_dir), renders, res["relight_bsdf"])   # its "oracle" row is the oracle
    res["relight_oracle_psnr"] = rows["oracle"]
    res["relight_cost_db"] = {k: rows["oracle"] - v for k, v in rows.items() if k in CHANNELS}
    res["relight_cost_db"]["missed_pixels"] = rows["missed_pixels"]
    from bench.observable_oracle import observable_oracle
    res["relight_observable_psnr"] = observable_oracle(scene_dir, res["relight_bsdf"])["observable"]
    from bench.shading_report import shading_rows
    res["light_dir_error_deg_median"] = shading_rows(Path(run_dir), Path(scene_dir), 0.0)["light_dir_error_deg_median"]
    res["seconds"] = time.perf_counter() - t0
    return {k: res.get(k) for k in (*KEYS, "seconds")}
