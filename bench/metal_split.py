"""Where a run's metallic is wrong: split by the true kind, by the light that reaches each pixel and
by the true albedo.

``python -m bench.metal_split RUN SCENE`` reads a bench run's renders of the scene's test views
(``RUN/relight_eval/renders/arrays.npz``: ``metallic``) and the scene's truth
(``SCENE/gt/arrays_test.npz``: ``alpha``, ``metallic``, ``albedo``, ``rgb_linear_per_light``) and
prints, for GT metals and GT dielectrics over the GT foreground, one row per group of pixels:

* ``key``: the first light's contribution ``y_0`` (channel mean, linear) is over :data:`DARK` and
  at least every other light's;
* ``fill``: another light's contribution is over :data:`DARK` and larger than the key's;
* ``dark``: no light's contribution is over :data:`DARK` (unlit, or a metal seen away from its lobe);
* ``dark albedo``: the GT albedo's channel mean is under :data:`DARK_ALBEDO` (dielectrics only:
  a black dielectric and a bright metal both lack a diffuse floor).

Each row gives the pixel count, the share the run calls metal (``m > 0.5``) and the metallic MAE.
The materials suite's one number (``metallic_mae``) cannot say which of these carries the error;
bench/RESULTS.md v55 used this split on spot_svbrdf.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from nepf_core.relight.metrics import FOREGROUND_ALPHA

DARK = 0.02
"""A light's contribution (linear, channel mean) under this does not count as reaching a pixel."""
DARK_ALBEDO = 0.2
"""A GT albedo (channel mean) under this is a dark dielectric."""


def pixel_groups(gt: dict) -> dict[str, np.ndarray]:
    """``{name: [V, H, W] bool}``: the groups of the module docstring, each within the foreground
    (``gt``: the arrays of ``gt/arrays_test.npz``)."""
    fg = np.asarray(gt["alpha"], np.float32) > FOREGROUND_ALPHA
    per_light = np.asarray(gt["rgb_linear_per_light"], np.float32).mean(-1)   # [V, L, H, W]
    key = per_light[:, 0]
    others = per_light[:, 1:].max(1) if per_light.shape[1] > 1 else np.zeros_like(key)
    albedo = np.asarray(gt["albedo"], np.float32).mean(-1)
    return {"key": fg & (key > DARK) & (key >= others),
            "fill": fg & (others > DARK) & (others > key),
            "dark": fg & (key <= DARK) & (others <= DARK),
            "dark albedo": fg & (albedo < DARK_ALBEDO)}


def metal_split(pred_metallic: np.ndarray, gt: dict) -> dict[str, dict]:
    """``{"metal": {group: row}, "dielectric": {group: row}}``, ``row = {"pixels", "called_metal",
    "mae"}`` (groups without pixels left out; ``dark albedo`` on dielectrics only).
    ``pred_metallic``: ``[V, H, W]`` or ``[V, H, W, 1]``."""
    m = np.asarray(pred_metallic, np.float32).reshape(np.asarray(gt["alpha"]).shape)
    m_gt = np.asarray(gt["metallic"], np.float32)
    groups = pixel_groups(gt)
    out: dict[str, dict] = {}
    for kind, is_kind in (("metal", m_gt > 0.5), ("dielectric", m_gt <= 0.5)):
        rows = {}
        for name, sel in groups.items():
            sel = sel & is_kind
            if not sel.any() or (name == "dark albedo" and kind == "metal"):
                continue
            rows[name] = {"pixels": int(sel.sum()), "called_metal": float((m[sel] > 0.5).mean()),
                          "mae": float(np.abs(m[sel] - m_gt[sel]).mean())}
        out[kind] = rows
    return out


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(prog="python -m bench.metal_split", description=__doc__.split("\n\n")[0])
    p.add_argument("run", type=Path, help="a finished bench run (with relight_eval/renders/arrays.npz)")
    p.add_argument("scene", type=Path, help="the scene folder (with gt/arrays_test.npz)")
    p.add_argument("--json", action="store_true", help="print JSON instead of a table")
    args = p.parse_args(argv)
    renders = args.run / "relight_eval" / "renders" / "arrays.npz"
    truth = args.scene / "gt" / "arrays_test.npz"
    for f in (renders, truth):
        if not f.is_file():
            raise SystemExit(f"bench.metal_split: {f.name} is missing under {f.parent.name}/")
    gt = dict(np.load(truth))
    missing = [k for k in ("alpha", "metallic", "albedo", "rgb_linear_per_light") if k not in gt]
    if missing:
        raise SystemExit(f"bench.metal_split: {truth.name} has no {', '.join(missing)} (a scene rendered per light "
                         "is needed: ../shared/scenes)")
    res = metal_split(np.load(renders)["metallic"], gt)
    if args.json:
        print(json.dumps(res, indent=1))
        return
    print("| GT kind | pixels | count | called metal | metallic MAE |\n|---|---|---|---|---|")
    for kind, rows in res.items():
        for name, r in rows.items():
            print(f"| {kind} | {name} | {r['pixels']} | {r['called_metal']:.2f} | {r['mae']:.3f} |")


if __name__ == "__main__":
    main()
