"""The materials suite: one preset on every kind of scene, judged by how well its asset relights.

``python -m bench materials [--budget 600] [--threads 2] [--seeds 0] [--override k=v ...] --out DIR``
runs ``fast`` (one subprocess per scene, one at a time: :mod:`bench.run`) on the six scenes of
``SUITE`` and prints one row per scene:

* the oracle (the ground truth shaded with our BSDF and GT-mesh shadows, :mod:`bench.oracle`), the
  relight PSNR and the gap ``oracle - relight`` (dB); beside them the oracle restricted to what the
  training light shows (:mod:`bench.observable_oracle`: the mean material where no training light
  reaches), above which the gap is the data's, not the method's;
* albedo PSNR (all / lit pixels), roughness and metallic MAE, normal error (degrees);
* the learned light's median direction error on the lit foreground (:mod:`bench.shading_report`);
* held-out PBR (masked) and the steps trained;

then the suite's mean gap and its worst scene, and a second table of where each scene's gap lies:
the dB the oracle loses when one of the run's channels (albedo, roughness, metallic, normal) or a
set of them replaces the ground truth's (:mod:`bench.relight_attribution`), and the rest of the gap
(the run's own mesh: positions, silhouette, shadows). ``python -m bench materials --table DIR [--against
BASE]`` prints the table of a finished suite and, against a baseline suite, the rule a preset
change has to pass: **the mean gap improves and no scene's relight gets worse by more than its
noise** (``NOISE_DB``, the spread of a second seed; give ``--seeds 0,1`` to measure it).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from statistics import mean

from bench.relight_attribution import CHANNELS

SUITE = ("sphere_diffuse", "torus_glossy", "spot_textured", "bunny_metal", "spot_svbrdf", "torus_stiff")
"""One scene of each kind: diffuse, glossy dielectric, textured, metal, metal beside dielectric, stiff."""
NOISE_DB = 0.5
"""A relight difference within this many dB is noise (seed to seed) unless two seeds say otherwise."""
COLUMNS = (("relight_oracle_psnr", "oracle", 2), ("relight_observable_psnr", "observable", 2),
           ("relight_psnr", "relight", 2), ("gap", "gap", 2),
           ("albedo_psnr", "albedo", 2), ("albedo_psnr_lit", "albedo lit", 2), ("roughness_mae", "rough MAE", 3),
           ("metallic_mae", "metal MAE", 3), ("normal_mae_deg", "normal deg", 1),
           ("light_dir_error_deg_median", "light deg", 1), ("test_psnr", "PBR masked", 2), ("steps", "steps", 0))


def per_scene_medians(results_dir: Path, row_of, keys) -> dict[str, dict]:
    """``{scene: {key: median over seeds}}`` of a finished suite (``results.json``): ``row_of(run)``
    gives each run's values (None: the run has no row)."""
    from bench.curves import _median
    per_scene: dict[str, list[dict]] = {}
    for r in json.loads((Path(results_dir) / "results.json").read_text())["runs"]:
        row = row_of(r)
        if row is not None:
            per_scene.setdefault(r["scene"], []).append(row)
    return {s: {k: _median([row.get(k) for row in rows]) for k in keys} for s, rows in per_scene.items()}


def suite_rows(results_dir: Path) -> dict[str, dict]:
    """``{scene: row}`` of a finished suite (``results.json``), each value the median over seeds."""
    from bench.curves import final_test

    def row_of(r):
        ev = dict(r.get("relight_eval") or {})
        row = {k: ev.get(k) for k, _, _ in COLUMNS}
        if row["relight_psnr"] is not None and row["relight_oracle_psnr"] is not None:
            row["gap"] = row["relight_oracle_psnr"] - row["relight_psnr"]
        row["test_psnr"], row["steps"] = final_test(r).get("test_psnr"), r.get("steps")
        return row
    return per_scene_medians(results_dir, row_of, [k for k, _, _ in COLUMNS])


def format_table(rows: dict[str, dict]) -> str:
    head = "| scene | " + " | ".join(name for _, name, _ in COLUMNS) + " |"
    lines = [head, "|" + "---|" * (len(COLUMNS) + 1)]
    for scene, row in rows.items():
        cells = ["n/a" if row.get(k) is None else f"{row[k]:.{nd}f}" for k, _, nd in COLUMNS]
        lines.append(f"| {scene} | " + " | ".join(cells) + " |")
    gaps = {s: r["gap"] for s, r in rows.items() if r.get("gap") is not None}
    if gaps:
        worst = max(gaps, key=gaps.get)
        lines.append(f"\nmean relight gap {mean(gaps.values()):.2f} dB over {len(gaps)} scenes; "
                     f"worst {worst} ({gaps[worst]:.2f} dB)")
    return "\n".join(lines)


COST_COLUMNS = (*CHANNELS, "geometry")
"""The attribution's rows (:data:`bench.relight_attribution.CHANNELS`) and the rest of the gap."""


def cost_rows(results_dir: Path) -> dict[str, dict]:
    """``{scene: {channel: dB, "geometry": dB}}`` (medians over seeds) of a finished suite:
    ``relight_cost_db`` of each run and ``geometry`` = the gap minus the cost of all four channels."""
    def row_of(r):
        ev = r.get("relight_eval") or {}
        cost = ev.get("relight_cost_db")
        if not cost:
            return None
        row = {k: cost.get(k) for k in CHANNELS}
        if None not in (ev.get("relight_oracle_psnr"), ev.get("relight_psnr"), cost.get("all four")):
            row["geometry"] = ev["relight_oracle_psnr"] - ev["relight_psnr"] - cost["all four"]
        return row
    return per_scene_medians(results_dir, row_of, COST_COLUMNS)


def format_cost_table(costs: dict[str, dict]) -> str:
    """Markdown: dB below the oracle with only that channel (or set) from the run."""
    lines = ["| scene | " + " | ".join(COST_COLUMNS) + " |", "|" + "---|" * (len(COST_COLUMNS) + 1)]
    for scene, row in costs.items():
        lines.append(f"| {scene} | " + " | ".join("n/a" if row.get(k) is None else f"{row[k]:.2f}"
                                                   for k in COST_COLUMNS) + " |")
    return "\n".join(lines)


def verdict(candidate: dict[str, dict], baseline: dict[str, dict], noise_db: float = NOISE_DB) -> tuple[bool, str]:
    """``(adopt, why)``: adopt when the mean gap over the scenes both suites scored is lower and no
    scene's relight PSNR dropped by more than ``noise_db``."""
    common = [s for s in baseline if candidate.get(s, {}).get("gap") is not None and baseline[s].get("gap") is not None]
    if not common:
        return False, "no scene scored in both suites"
    d_gap = mean(candidate[s]["gap"] for s in common) - mean(baseline[s]["gap"] for s in common)
    worse = {s: baseline[s]["relight_psnr"] - candidate[s]["relight_psnr"] for s in common
             if baseline[s]["relight_psnr"] - candidate[s]["relight_psnr"] > noise_db}
    missing = sorted(set(baseline) - set(common))
    why = (f"mean gap {'+' if d_gap >= 0 else ''}{d_gap:.2f} dB over {len(common)} scenes; "
           + (", ".join(f"{s} {-v:.2f} dB" for s, v in worse.items()) + " worse beyond noise" if worse else
              "no scene worse beyond noise")
           + (f"; not scored: {', '.join(missing)}" if missing else ""))
    return d_gap < 0 and not worse and not missing, why


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench materials", description=__doc__.splitlines()[0])
    ap.add_argument("--table", type=Path, help="print the table of a finished suite instead of running one")
    ap.add_argument("--against", type=Path, help="with --table: a baseline suite to judge against")
    ap.add_argument("--scenes", default=",".join(SUITE))
    ap.add_argument("--scenes-root", default=str(Path(__file__).resolve().parents[2] / "shared" / "scenes"))
    ap.add_argument("--budget", type=float, default=600.0, help="training seconds per scene (default 600)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--seeds", default="0", help="comma-separated training seeds (two: the noise)")
    ap.add_argument("--override", action="append", default=[], metavar="section.field=VALUE")
    ap.add_argument("--out", type=Path)
    ap.add_argument("--skip-done", action="store_true")
    a = ap.parse_args(argv)
    if a.table is None:
        if a.out is None:
            ap.error("--out DIR is needed to run the suite")
        from bench.run import main as run_main
        args = ["--scenes", a.scenes, "--scenes-root", a.scenes_root, "--configs", "fast", "--budget", str(a.budget),
                "--eval-every", str(a.budget), "--threads", str(a.threads), "--no-fit-chamfer",
                "--seeds", a.seeds, "--out", str(a.out)]
        for o in a.override:
            args += ["--override", o]
        if a.skip_done:
            args.append("--skip-done")
        code = run_main(args)
        if code:
            return code
    rows = suite_rows(a.table or a.out)
    print(format_table(rows))
    costs = cost_rows(a.table or a.out)
    if costs:
        print("\nrelight cost by channel: dB below the oracle with only that channel (or set) from the run; "
              "geometry: the rest of the gap (the run's mesh, silhouette, shadows)\n")
        print(format_cost_table(costs))
    if a.against is not None:
        adopt, why = verdict(rows, suite_rows(a.against))
        print(f"\nagainst {a.against}: {'adopt' if adopt else 'do not adopt'}: {why}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
