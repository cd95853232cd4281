"""Where a run's relight error lies: the oracle with one recovered channel at a time.

``python -m bench.relight_attribution RUN SCENE`` reads the run's renders of the scene's test views
(``RUN/relight_eval/renders/arrays.npz``, written by :func:`bench.relight_eval.relight_metrics`)
and shades the scene's ground truth under ``gt/relight/lights.json`` as the oracle does
(:func:`bench.oracle.oracle_render`: GT points, GT-mesh shadows, the run's BSDF kind), with
the GT map of one channel replaced by the run's:

    PSNR_S = relight_psnr(oracle(GT maps with the channels S from the run), truth)

for ``S`` = nothing (the oracle), each of albedo, roughness, metallic and normal alone, the three
materials, and all four. ``oracle - PSNR_S`` is what channel ``S`` costs with everything else
right; ``PSNR_all - relight`` (the run's own relight, its mesh and its shadows) is what the
geometry's position, silhouette and shadows cost on top. The channels' costs do not add up
(PSNR is a log of a sum of errors, and the errors interact), so the table shows each alone and
the sets together.

The run's map at a pixel is the asset's value where the run's surface crosses that pixel's ray,
not at the GT point; where the run sees background (its alpha under a half) its maps are
whatever the render left (zeros): those pixels cost their share in every row with that channel,
and the table counts them. The per-channel scale of the relight PSNR
(:func:`nepf_core.relight.metrics.relight_psnr`) absorbs a global albedo scale, as in the real
score.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

CHANNELS = {"albedo": ("albedo",), "roughness": ("roughness",), "metallic": ("metallic",),
            "normal": ("normal_world",), "materials": ("albedo", "roughness", "metallic"),
            "all four": ("albedo", "roughness", "metallic", "normal_world")}
"""Each row's name and the GT map keys it replaces by the run's."""


def recovered_maps(renders: dict) -> dict:
    """The run's maps in the GT's keys and shapes: ``albedo [V, H, W, 3]``, ``roughness`` and
    ``metallic [V, H, W]``, ``normal_world [V, H, W, 3]`` (the renders are in the world frame)."""
    return {"albedo": renders["albedo"].astype(np.float32),
            "roughness": renders["roughness"][..., 0].astype(np.float32),
            "metallic": renders["metallic"][..., 0].astype(np.float32),
            "normal_world": renders["normal"].astype(np.float32)}


def attribution(scene_dir: Path, renders: dict, bsdf_kind: str) -> dict:
    """``{"oracle": dB, <row of CHANNELS>: dB, ..., "missed_pixels": n}`` for the run's renders
    ``renders`` (the arrays of ``relight_eval/renders``) on ``scene_dir``; ``missed_pixels``: GT
    foreground pixels the run renders as background."""
    from bench.oracle import oracle_renders
    from nepf_core.relight.lights import load_lights
    from nepf_core.relight.metrics import FOREGROUND_ALPHA, relight_psnr
    relight = Path(scene_dir) / "gt" / "relight"
    lights = load_lights(relight / "lights.json")
    truth = np.load(relight / "arrays.npz")
    t_rgb, t_alpha = truth["rgb_linear"].astype(np.float32), truth["alpha"].astype(np.float32)
    ours = recovered_maps(renders)
    rows = (("oracle", ()), *CHANNELS.items())
    rgbs, _ = oracle_renders(scene_dir, lights, bsdf_kind, True, [{k: ours[k] for k in keys} for _, keys in rows])
    out = {row: float(relight_psnr(rgb, t_rgb, t_alpha)[0]) for (row, _), rgb in zip(rows, rgbs)}
    gt_fg = np.load(Path(scene_dir) / "gt" / "arrays_test.npz")["alpha"] > FOREGROUND_ALPHA
    out["missed_pixels"] = int((gt_fg & (renders["alpha"][..., 0] < 0.5)).sum())
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("scene", type=Path)
    a = ap.parse_args(argv)
    renders = dict(np.load(a.run / "relight_eval" / "renders" / "arrays.npz"))
    kind = json.loads((a.run / "config.json").read_text())["render"]["bsdf_kind"]
    child = a.run / "bench_child.json"   # a bench child's own scores (bench/child.py)
    ev = (json.loads(child.read_text()).get("relight_eval") or {}) if child.is_file() else {}
    rows = attribution(a.scene, renders, kind)
    print(f"{a.scene.name} ({kind} BSDF; {rows.pop('missed_pixels')} GT foreground pixels rendered as background)")
    print("| channels from the run | relight PSNR | below the oracle |")
    print("|---|---|---|")
    for row, value in rows.items():
        print(f"| {row} | {value:.2f} | {rows['oracle'] - value:.2f} |")
    if "relight_psnr" in ev:
        print(f"| the run's own relight (its mesh, shadows) | {ev['relight_psnr']:.2f} | "
              f"{rows['oracle'] - ev['relight_psnr']:.2f} |")


if __name__ == "__main__":
    main()
