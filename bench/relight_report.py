"""The bench tables' relighting section: per row (scene, config, variant), medians over repeats of
the child runs' ``relight_eval`` (:mod:`bench.relight_eval`)."""

from __future__ import annotations

import math

COLUMNS = (("relight_psnr", "relight PSNR", 2), ("relight_oracle_psnr", "oracle", 2),
           ("albedo_psnr", "albedo PSNR", 2), ("albedo_psnr_lit", "albedo PSNR lit px", 2),
           ("roughness_mae", "roughness MAE", 3), ("metallic_mae", "metallic MAE", 3),
           ("normal_mae_deg", "normal MAE (deg)", 2))


def _median(xs):
    xs = sorted(x for x in xs if isinstance(x, (int, float)) and math.isfinite(x))
    if not xs:
        return None
    n = len(xs)
    return xs[n // 2] if n % 2 else 0.5 * (xs[n // 2 - 1] + xs[n // 2])


def relight_row(recs: list[dict]) -> dict:
    """``{"relight": {key: median}, "relight_bsdf": kind}`` over the runs ``recs`` (empty dict
    values when no run has relight scores)."""
    evs = [r.get("relight_eval") or {} for r in recs]
    row = {k: _median([e.get(k) for e in evs]) for k, _, _ in COLUMNS}
    kinds = sorted({str(e["relight_bsdf"]) for e in evs if e.get("relight_bsdf")})
    return {"relight": row, "relight_bsdf": ",".join(kinds)}


def relight_table_lines(rows: list[dict]) -> list[str]:
    """Markdown lines of the relighting section (nothing when no row has a relight score)."""
    rows = [r for r in rows if any(v is not None for v in (r.get("relight") or {}).values())]
    if not rows:
        return []
    L = ["## Relighting and materials", "",
         "| scene | config | variant | BSDF | " + " | ".join(h for _, h, _ in COLUMNS) + " | gap to oracle |",
         "|---|---|---|---|" + "---|" * (len(COLUMNS) + 1)]
    for r in sorted(rows, key=lambda r: (r["scene"], r["config"], r["variant"])):
        v = r["relight"]
        cells = ["n/a" if v.get(k) is None else f"{v[k]:.{nd}f}" for k, _, nd in COLUMNS]
        gap = (v["relight_oracle_psnr"] - v["relight_psnr"]
               if v.get("relight_psnr") is not None and v.get("relight_oracle_psnr") is not None else None)
        L.append(f"| {r['scene']} | {r['config']} | {r['variant']} | {r.get('relight_bsdf') or 'n/a'} | "
                 + " | ".join(cells) + f" | {'n/a' if gap is None else f'{gap:.2f}'} |")
    L += ["", "Relight PSNR: the final model rendered by `nepf relight` under the scene's gt/relight lights "
              "at the gt/dtu_test cameras, one scale per colour channel over all lights, views and GT-foreground "
              "pixels fitted on the displayed range (`nepf_core.relight.metrics.displayed_range_scale`), then "
              "clipped, sRGB, PSNR over those pixels. Oracle: the GT maps shaded with the same BSDF and the GT "
              "mesh's shadows (bench/oracle.py), the ceiling our BSDF sets. Albedo PSNR (a per-channel "
              "least-squares scale: an albedo has no highlights) over the GT foreground and its lit pixels; "
              "roughness / metallic MAE over the GT foreground; normal MAE in degrees, world frame.", ""]
    return L
