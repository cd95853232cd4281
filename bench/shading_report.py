"""Where a decomposition's albedo error comes from: the shading it did not take.

``python -m bench.shading_report RUN SCENE [--min-albedo 0.5]`` reads a bench run's renders of the
scene's test views (``RUN/relight_eval/renders/arrays.npz``: albedo, normal, light_dir,
light_intensity, depth) and the scene's truth (``SCENE/gt/arrays_test.npz``, ``gt/lights.json``,
the test cameras of ``gt/dtu_test``), and prints, over GT-foreground pixels lit by the training
light whose GT albedo luminance is at least ``--min-albedo``:

* the angle between the learned light direction ``l(x)`` and the true direction from the
  recovered surface point to the light that lights it most (the key light, or where the key light
  does not reach, the fill; :func:`main_light_direction`) (median, 90th percentile);
* per quintile of the GT shading ``s = t / a`` (the pixel over its GT albedo: irradiance and
  cosine), the median GT and recovered ``n.l``, the recovered irradiance ``I (n.l)``, and the
  recovered albedo over the GT one (after one least-squares scale per channel, as the albedo
  PSNR aligns it).

A recovered albedo that follows the GT shading (low in the dim quintiles, high in the bright
ones) means the shading went into the albedo: the light field's irradiance is flatter than the
truth. For a diffuse surface only ``n.l`` is identifiable (``l`` may turn about ``n``), so the
angle alone is not an error unless ``n.l`` is off too. Needs a DTU-format scene
(``../shared/scenes``); the quintiles' shading is the image over the GT albedo (all lights).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np


def training_image(gt) -> np.ndarray:
    """``[V, H, W, 3]`` linear test images under every training light: ``rgba_linear`` (the shared
    scenes), ``rgb_linear`` (``nepf make-scene``), or the sum of ``rgb_linear_per_light``."""
    if "rgba_linear" in gt.files:
        return gt["rgba_linear"][..., :3].astype(np.float32)
    if "rgb_linear" in gt.files:
        return gt["rgb_linear"].astype(np.float32)
    return gt["rgb_linear_per_light"].sum(1).astype(np.float32)


def main_light_direction(x: np.ndarray, n: np.ndarray, positions: np.ndarray, power: np.ndarray) -> np.ndarray:
    """``[..., 3]`` unit direction from each point ``x [..., 3]`` to the light that gives it the most
    irradiance ``I_k (n . l_k)^+ / d_k^2`` (GT normals ``n``), among ``positions [L, 3]`` with
    powers ``power [L]``: with a key and a fill light, the one the learned light should follow."""
    to = positions.reshape((1,) * (x.ndim - 1) + positions.shape) - x[..., None, :]   # [..., L, 3]
    d2 = (to ** 2).sum(-1)
    dirs = to / np.sqrt(d2)[..., None]
    k = (power * np.clip((dirs * n[..., None, :]).sum(-1), 0, None) / d2).argmax(-1)
    return np.take_along_axis(dirs, k[..., None, None], axis=-2)[..., 0, :]


def shading_rows(run: Path, scene_dir: Path, min_albedo: float = 0.5) -> dict:
    from nepf_core.rays import PixelSampler, unlit_threshold
    from nepf_core.reframe import load_held_out
    from nepf_core.relight.metrics import FOREGROUND_ALPHA, channel_scale
    from nepf_core.train import load_model

    _model, _cfg, state = load_model(run, "cpu")
    wfn = np.asarray(state["extra"]["world_from_norm"], dtype=np.float64)
    test = load_held_out(scene_dir / "gt" / "dtu_test", wfn)
    pred = np.load(run / "relight_eval" / "renders" / "arrays.npz")
    gt = np.load(scene_dir / "gt" / "arrays_test.npz")
    lights = json.loads((scene_dir / "gt" / "lights.json").read_text())["lights"]
    light_pos = np.asarray([lt["position_world"] for lt in lights], dtype=np.float64)            # [L, 3]
    light_power = np.asarray([np.mean(lt.get("intensity_rgb", [1.0])) for lt in lights])        # [L]
    fg = gt["alpha"] > FOREGROUND_ALPHA
    img = training_image(gt)
    lit = img.max(-1) >= unlit_threshold(img, fg, 0.01)   # the albedo-lit metric's pixels
    alb_gt, alb = gt["albedo"].astype(np.float32), pred["albedo"].astype(np.float32)
    keep_all = fg & lit
    scale = channel_scale(alb, alb_gt, keep_all)
    sampler = PixelSampler(test, "cpu")
    cols = []
    for v in range(test.n_views):
        r = sampler.view_rays(v)
        o = r.origins.numpy().reshape(test.height, test.width, 3)
        d = r.directions.numpy().reshape(test.height, test.width, 3)
        x = (o + d * pred["depth"][v].astype(np.float32)) * wfn[0, 0] + wfn[:3, 3]   # world
        to_light = main_light_direction(x, gt["normal_world"][v].astype(np.float64), light_pos, light_power)
        keep = keep_all[v] & (alb_gt[v].mean(-1) >= min_albedo)
        l_pred = pred["light_dir"][v].astype(np.float32)
        n_pred = pred["normal"][v].astype(np.float32)
        ndl = (n_pred * l_pred).sum(-1)
        cols.append(np.stack([
            np.degrees(np.arccos(np.clip((l_pred * to_light).sum(-1), -1, 1)))[keep],
            (gt["normal_world"][v].astype(np.float32) * to_light).sum(-1)[keep],
            ndl[keep],
            (pred["light_intensity"][v][..., 0].astype(np.float32) * ndl.clip(0))[keep],
            ((alb[v] * scale).mean(-1) / alb_gt[v].mean(-1).clip(1e-3))[keep],
            (img[v].mean(-1) / alb_gt[v].mean(-1).clip(1e-3))[keep],
        ], -1))
    R = np.concatenate(cols)
    if len(R) == 0:
        raise ValueError(f"no lit foreground pixel of {scene_dir.name} has a GT albedo luminance "
                         f">= {min_albedo} (the scene's albedo is darker: try a smaller --min-albedo)")
    out = {"pixels": int(len(R)), "light_dir_error_deg_median": float(np.median(R[:, 0])),
           "light_dir_error_deg_p90": float(np.percentile(R[:, 0], 90)), "quintiles": []}
    edges = np.percentile(R[:, 5], [0, 20, 40, 60, 80, 100])
    for i in range(5):
        s = (R[:, 5] >= edges[i]) & (R[:, 5] <= edges[i + 1])
        out["quintiles"].append({"gt_shading": [float(edges[i]), float(edges[i + 1])],
                                 "ndl_gt": float(np.median(R[s, 1])), "ndl": float(np.median(R[s, 2])),
                                 "irradiance": float(np.median(R[s, 3])),
                                 "albedo_ratio": float(np.median(R[s, 4]))})
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("scene", type=Path)
    ap.add_argument("--min-albedo", type=float, default=0.5, help="GT albedo luminance of the pixels kept")
    a = ap.parse_args(argv)
    try:
        rep = shading_rows(a.run, a.scene, a.min_albedo)
    except ValueError as e:   # an error, not an exit, in shading_rows: a suite run (bench/child.py) records it and goes on
        raise SystemExit(f"shading_report: {e}") from None
    print(f"{rep['pixels']} pixels; light direction error: median {rep['light_dir_error_deg_median']:.1f} deg, "
          f"90th percentile {rep['light_dir_error_deg_p90']:.1f} deg")
    print("| GT shading | n.l GT | n.l recovered | irradiance I n.l | albedo recovered / GT |")
    print("|---|---|---|---|---|")
    for q in rep["quintiles"]:
        lo, hi = q["gt_shading"]
        print(f"| {lo:.2f}-{hi:.2f} | {q['ndl_gt']:.2f} | {q['ndl']:.2f} | {q['irradiance']:.2f} | {q['albedo_ratio']:.2f} |")


if __name__ == "__main__":
    main()
