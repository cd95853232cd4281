"""The relight oracle restricted to what the training light shows.

A surface point that no training light reaches (in a cast shadow of every light of
``gt/lights.json``, or facing away from all of them) is black in every training view whatever its
material: no method can read its albedo, roughness or metallic from the images, yet a novel light
in ``gt/relight`` shows it. The oracle (:mod:`bench.oracle`) shades the GT maps everywhere, so its
PSNR is out of reach on a scene with shadows. This module scores the oracle with the GT material
kept only where the training light reaches and the reached pixels' mean material elsewhere (the
best single guess for a material no image shows):

    E(x)       = sum_k V_k(x) I_k (n . l_k)^+ / d_k^2            training lights, GT-mesh shadows
    reached    = E(x) > tau q90_fg(E)                             per GT test-view pixel
    m'(x)      = m(x) where reached, else mean_{reached} m        albedo, roughness, metallic
    observable = relight_psnr(oracle(m'), truth)

``E`` is read as the luminance of the GT points shaded white (albedo 1, roughness 1, metallic 0)
under the training lights by :func:`bench.oracle.oracle_renders`, which is positive exactly where
``E`` is (the glTF BSDF's diffuse term, ``(1 - F) / pi``, never vanishes on a lit point); its
scale does not matter to the relative threshold. ``tau`` (:data:`REACHED_REL`) sits where the
pixel of a 5 %-albedo point is still a few 8-bit levels above black.

It is not a strict ceiling (a method could guess an unseen texture by luck, and the scenes are
path traced, so shadows hold a little indirect light), but no method that reads the material from
the directly lit pixels can beat it by more than such luck. ``observable - oracle`` is the part of
the relight gap that the data cannot close; ``reached_fraction`` is the share of test-view
foreground pixels the training light reaches.

``python -m bench.observable_oracle SCENE_DIR... [--bsdf gltf] [--tau 0.01]`` prints a table.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

REACHED_REL = 0.01
"""``tau``: a pixel is reached when its training irradiance is above this times the foreground's
90th percentile."""
MATERIAL_KEYS = ("albedo", "roughness", "metallic")


def white_maps(gt_maps: dict) -> dict:
    """GT-shaped maps of a white rough dielectric: albedo 1, roughness 1, metallic 0."""
    return {"albedo": np.ones_like(gt_maps["albedo"], np.float32),
            "roughness": np.ones_like(gt_maps["roughness"], np.float32),
            "metallic": np.zeros_like(gt_maps["metallic"], np.float32)}


def reached_mask(white_rgb: np.ndarray, foreground: np.ndarray, tau: float = REACHED_REL) -> np.ndarray:
    """``[V, H, W]`` bool: foreground pixels whose white shading summed over the training lights
    (``white_rgb [K, V, H, W, 3]`` linear) is above ``tau`` times its foreground q90."""
    e = white_rgb.sum(0).mean(-1)
    if not foreground.any():
        return np.zeros_like(foreground)
    q90 = float(np.quantile(e[foreground], 0.9))
    return foreground & (e > tau * q90)


def observable_maps(gt_maps: dict, reached: np.ndarray, foreground: np.ndarray) -> dict:
    """The GT's material maps with every foreground pixel not ``reached`` set to the mean over
    the reached pixels (all views): ``{albedo [V, H, W, 3], roughness, metallic [V, H, W]}``.
    No reached pixel: the maps as they are."""
    out = {}
    unseen = foreground & ~reached
    for key in MATERIAL_KEYS:
        m = gt_maps[key].astype(np.float32).copy()
        if reached.any():
            m[unseen] = m[reached].mean(0)
        out[key] = m
    return out


def observable_oracle(scene_dir, bsdf_kind: str = "gltf", tau: float = REACHED_REL) -> dict:
    """``{"oracle", "observable", "reached_fraction"}`` for ``scene_dir`` (the layout of
    :mod:`bench.oracle`, plus ``gt/lights.json``, the training lights)."""
    from bench.oracle import oracle_renders
    from nepf_core.relight.lights import load_lights
    from nepf_core.relight.metrics import FOREGROUND_ALPHA, relight_psnr
    gt = Path(scene_dir) / "gt"
    gt_maps = dict(np.load(gt / "arrays_test.npz"))
    foreground = gt_maps["alpha"] > FOREGROUND_ALPHA
    (white,), _ = oracle_renders(scene_dir, load_lights(gt / "lights.json"), "gltf", True, [white_maps(gt_maps)])
    reached = reached_mask(white, foreground, tau)
    truth = np.load(gt / "relight" / "arrays.npz")
    t_rgb, t_alpha = truth["rgb_linear"].astype(np.float32), truth["alpha"].astype(np.float32)
    rgbs, _ = oracle_renders(scene_dir, load_lights(gt / "relight" / "lights.json"), bsdf_kind, True,
                             [{}, observable_maps(gt_maps, reached, foreground)])
    oracle, observable = (float(relight_psnr(rgb, t_rgb, t_alpha)[0]) for rgb in rgbs)
    return {"oracle": oracle, "observable": observable,
            "reached_fraction": float(reached.sum() / max(int(foreground.sum()), 1))}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.observable_oracle", description=__doc__.splitlines()[0])
    ap.add_argument("scenes", nargs="+", type=Path, help="scene folders (each with gt/lights.json and gt/relight)")
    ap.add_argument("--bsdf", default="gltf", choices=["paper", "gltf"])
    ap.add_argument("--tau", type=float, default=REACHED_REL, help="reached: irradiance > tau x foreground q90")
    a = ap.parse_args(argv)
    print(f"| scene | oracle ({a.bsdf}) | observable oracle | what the data cannot close | reached |")
    print("|---|---|---|---|---|")
    for sd in a.scenes:
        if not ((sd / "gt" / "lights.json").is_file() and (sd / "gt" / "relight" / "lights.json").is_file()):
            print(f"{sd.name}: no gt/lights.json or gt/relight, skipped", file=sys.stderr)
            continue
        r = observable_oracle(sd, a.bsdf, a.tau)
        print(f"| {sd.name} | {r['oracle']:.2f} | {r['observable']:.2f} | {r['oracle'] - r['observable']:.2f} | "
              f"{100 * r['reached_fraction']:.1f} % |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
