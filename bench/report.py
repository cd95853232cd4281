"""Tables, ratios and plots of a benchmark (``results.json`` -> ``table.md``, ``error_vs_time_<scene>.png``;
the table's markdown is :mod:`bench.report_table`).

``python -m bench report DIR [--target-psnr X]`` rebuilds them from ``DIR/results.json``.

Definitions (also written into ``table.md``):

* **final** test numbers come from the last ``kind: "test"`` record (``final: true``) of the
  run's ``metrics.jsonl``; PSNR is of sRGB values, *masked* = GT foreground pixels only.
* **Chamfer** is the final model's, re-evaluated at ``chamfer_resolution``³ with
  ``chamfer_samples`` samples per mesh, in unit-sphere units (world / scene scale); when that
  failed or was skipped the last in-training value (128³) is shown, marked ``*``.
* **wall_s** is training time only (evaluation, checkpoints and Chamfer meshes excluded).
* **time to reach P**: the first test record whose masked test PSNR >= P; "not reached" otherwise.
  The resolution is the evaluation period (``--eval-every``).
* **X** (table): ``--target-psnr`` or, per scene, the lowest final masked test PSNR among the
  scene's rows, so that every row has a time.
* **fast vs paper**: P = the best test PSNR ``paper`` reached; times of both and
  ratio = t_paper / t_fast (> 1: fast gets there sooner).
* **adaptive vs a baseline** (``all_on``: everything on, no empty ray left out;
  ``naive``: the brief's dense-grid reference rebuilt on the NePF model, ``bench/run.py``):
  P = min(final_adaptive, final_baseline); times of both, the final PSNR difference
  (adaptive - baseline) and time saved = (t_baseline - t_adaptive) / t_baseline.
* **smoothed** (per pair): the same comparisons on each run's running mean of
  ``SMOOTH_WINDOW`` (3) consecutive evaluations, the window of the plateau rule; a point exists
  from the third evaluation on. final = the mean of the last three evaluations; time = first
  evaluation at which the running mean reaches the target. One evaluation of spot_textured moves
  by 0.5-1 dB (docs/FAST.md), so a single evaluation decides a raw first crossing.
* **saved over levels** (per pair, smoothed): the time saved at every whole-dB level both smoothed
  curves climb to (from the first whole dB above both curves' first points up to the lower
  smoothed final, which is the last level): the median over levels, and how many levels saved
  >= 30 % (levels one run never reaches are left out). The single "time to the lower final"
  rewards a baseline that plateaus early and low; this shows whether the saving holds all the way up.
* With ``--repeats N`` > 1 every number is the median over repeats (pairs are matched by
  repeat index).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from bench.curves import (_curve, _finite, _groups, _median, _median_time, _saved_pct, best_psnr, chamfer_of,
                          final_test, level_savings, run_seed, smoothed_curve, tail_mean, time_to_reach,
                          time_to_reach_smoothed)
from bench.relight_report import relight_row
from bench.report_table import write_table

TOLERANCE_DB = 0.3
"""The issue's "at <= 0.3 dB lower PSNR" (per-pair table, "within 0.3 dB" column)."""

BASELINES = ("all_on", "naive")
"""Variants the adaptive run is compared against (``bench/run.py`` ``VARIANTS``)."""


def summarize(results: dict, target_psnr: float | None = None) -> dict:
    """Rows (one per scene/config/variant, medians over repeats) and the comparisons."""
    groups = _groups(results.get("runs", []))
    return {"rows": _scene_rows(groups, target_psnr), "fast_vs_paper": _fast_vs_paper(groups),
            "adaptive_vs_all_on": _adaptive_vs_baselines(groups)}


def _scene_rows(groups: dict, target_psnr: float | None) -> list[dict]:
    """One row per ``(scene, config, variant)``: medians over its repeats, and the time to X."""
    rows = []
    for (scene, config, variant), recs in groups.items():
        fins = [final_test(r) for r in recs]
        chs = [chamfer_of(r) for r in recs]
        rows.append({
            "scene": scene, "config": config, "variant": variant, "n": len(recs),
            "status": ",".join(sorted({str(r.get("status")) for r in recs})),
            "errors": [r["error"] for r in recs if r.get("error")],
            "budget_s": recs[0].get("budget_s"),
            "steps": _median([r.get("steps") for r in recs]), "train_wall_s": _median([r.get("train_wall_s") for r in recs]),
            **{k: _median([f.get(k) for f in fins]) for k in ("test_psnr", "test_psnr_full", "test_psnr_radiance",
                                                               "albedo_psnr", "albedo_psnr_lit")},
            "best_test_psnr": _median([best_psnr(r) for r in recs]),
            "chamfer": _median([c for c, _ in chs]), "chamfer_fine": all(fine for _, fine in chs),
            "chamfer_resolution": recs[0].get("chamfer_resolution"),
            "peak_rss_mb": _median([r.get("peak_rss_mb_process") for r in recs]),
            "peak_rss_mb_fit": _median([r.get("peak_rss_mb_fit") for r in recs]),
            "s_per_step": _median([_sps(r) for r in recs if _sps(r) is not None]),
            "nonfinite_steps": _median([r.get("nonfinite_steps") for r in recs]),
            "cpu_util": _median([(r.get("cpu_user_s", 0) + r.get("cpu_sys_s", 0)) / r["process_wall_s"]
                                 for r in recs if r.get("process_wall_s")]),
            "loadavg_start": recs[0].get("loadavg_start"),
            **relight_row(recs),
        })
    for row in rows:   # the common target X of a scene
        if target_psnr is not None:
            row["target_X"] = target_psnr
        else:
            finals = [r["test_psnr"] for r in rows if r["scene"] == row["scene"] and _finite(r["test_psnr"])]
            row["target_X"] = min(finals) if finals else None
        tt = _median_time(groups[(row["scene"], row["config"], row["variant"])], lambda r, x=row["target_X"]: x)
        row["t_to_X"], row["t_to_X_reached"] = tt["t"], f"{tt['reached']}/{tt['n']}"
    return rows


def _fast_vs_paper(groups: dict) -> list[dict]:
    """Per scene and variant: the time ``fast`` and ``paper`` take to reach ``paper``'s best."""
    out = []
    for scene in sorted({k[0] for k in groups}):
        for variant in sorted({k[2] for k in groups}):
            fp, pp = groups.get((scene, "fast", variant)), groups.get((scene, "paper", variant))
            if not fp or not pp:
                continue
            per = []
            for p, f in zip(pp, fp):
                target = best_psnr(p)
                tp, tf = time_to_reach(p, target), time_to_reach(f, target)
                per.append({"paper_best": target, "t_paper": tp, "t_fast": tf,
                            "ratio": (tp / tf) if tp is not None and tf else None,
                            "fast_final": final_test(f).get("test_psnr"), "fast_best": best_psnr(f)})
            out.append({
                "scene": scene, "variant": variant, "n": len(per), "per_repeat": per,
                "paper_best": _median([x["paper_best"] for x in per]),
                "t_paper": _median([x["t_paper"] for x in per]),
                "t_fast": _median([x["t_fast"] for x in per]) if all(x["t_fast"] is not None for x in per) else None,
                "fast_reached": sum(x["t_fast"] is not None for x in per),
                "ratio": _median([x["ratio"] for x in per]) if all(x["ratio"] is not None for x in per) else None,
                "fast_best": _median([x["fast_best"] for x in per]),
                "budget_paper": pp[0].get("budget_s"), "budget_fast": fp[0].get("budget_s")})
    return out


_PAIR_MEDIANS = ("target", "final_adaptive", "final_all_on", "diff", "t_adaptive", "t_all_on", "saved_pct",
                 "s_per_step_adaptive", "s_per_step_all_on", "chamfer_adaptive", "chamfer_all_on",
                 "albedo_adaptive", "albedo_all_on")


def _adaptive_vs_baselines(groups: dict) -> list[dict]:
    """Per scene, config and baseline of :data:`BASELINES`: the adaptive runs against the
    baseline's, paired by repeat (:func:`_pair`), and the medians over pairs."""
    out = []
    scenes, configs = sorted({k[0] for k in groups}), sorted({k[1] for k in groups})
    for scene, config, baseline in [(sc, co, b) for sc in scenes for co in configs for b in BASELINES]:
        ap, bp = groups.get((scene, config, "adaptive")), groups.get((scene, config, baseline))
        if not ap or not bp:
            continue
        per = [_pair(a, b) for a, b in zip(ap, bp)]
        row = {"scene": scene, "config": config, "baseline": baseline, "n": len(per), "per_repeat": per}
        for k in _PAIR_MEDIANS:
            vals = [x[k] for x in per]
            row[k] = _median(vals) if all(v is not None for v in vals) else None
        row["left_out"] = per[0]["left_out"] if per else []
        out.append(row)
    return out


def _pair(a: dict, b: dict) -> dict:
    """One adaptive run ``a`` against its baseline ``b``: finals, times to the lower final (raw,
    tail mean, within :data:`TOLERANCE_DB`, smoothed) and the time saved at each level."""
    fa, fb = final_test(a).get("test_psnr"), final_test(b).get("test_psnr")
    target = min(fa, fb) if _finite(fa) and _finite(fb) else None
    ta, tb = time_to_reach(a, target), time_to_reach(b, target)
    p = {"target": target, "final_adaptive": fa, "final_all_on": fb,
         "diff": (fa - fb) if target is not None else None, "t_adaptive": ta, "t_all_on": tb,
         "saved_pct": _saved_pct(ta, tb),
         "s_per_step_adaptive": _sps(a), "s_per_step_all_on": _sps(b),
         "chamfer_adaptive": chamfer_of(a)[0], "chamfer_all_on": chamfer_of(b)[0],
         "seed": run_seed(a), "steps_adaptive": a.get("steps"), "steps_all_on": b.get("steps"),
         "wall_adaptive": a.get("train_wall_s"), "wall_all_on": b.get("train_wall_s"),
         "tail_adaptive": tail_mean(a), "tail_all_on": tail_mean(b),
         "albedo_adaptive": final_test(a).get("albedo_psnr"),
         "albedo_all_on": final_test(b).get("albedo_psnr"),
         "left_out": _left_out(a)}
    tt = min(p["tail_adaptive"], p["tail_all_on"]) \
        if _finite(p["tail_adaptive"]) and _finite(p["tail_all_on"]) else None
    p["tail_saved_pct"] = _saved_pct(time_to_reach(a, tt), time_to_reach(b, tt))
    # the tolerance read literally: the adaptive run's time to come within
    # TOLERANCE_DB of the baseline's final, against the baseline's time to its final
    tol_a = time_to_reach(a, fb - TOLERANCE_DB) if _finite(fb) else None
    tol_b = time_to_reach(b, fb) if _finite(fb) else None
    p.update({"t_adaptive_tol": tol_a, "t_all_on_tol": tol_b, "tol_saved_pct": _saved_pct(tol_a, tol_b)})
    sa, sb = smoothed_curve(a), smoothed_curve(b)
    fsa, fsb = (sa[-1][1] if sa else None), (sb[-1][1] if sb else None)
    st = min(fsa, fsb) if fsa is not None and fsb is not None else None
    sta, stb = time_to_reach_smoothed(a, st), time_to_reach_smoothed(b, st)
    sto_a = time_to_reach_smoothed(a, fsb - TOLERANCE_DB) if fsb is not None else None
    sto_b = time_to_reach_smoothed(b, fsb) if fsb is not None else None
    p.update({"smooth_final_adaptive": fsa, "smooth_final_all_on": fsb,
              "smooth_diff": (fsa - fsb) if st is not None else None,
              "smooth_t_adaptive": sta, "smooth_t_all_on": stb, "smooth_saved_pct": _saved_pct(sta, stb),
              "smooth_t_adaptive_tol": sto_a, "smooth_t_all_on_tol": sto_b,
              "smooth_tol_saved_pct": _saved_pct(sto_a, sto_b)})
    lv = [x["saved_pct"] for x in level_savings(a, b) if x["saved_pct"] is not None]
    p.update({"levels_n": len(lv), "levels_saved_median_pct": _median(lv) if lv else None,
              "levels_saved_30_n": sum(v >= 30.0 for v in lv)})
    return p


def _sps(r: dict):
    return r["train_wall_s"] / r["steps"] if _finite(r.get("train_wall_s")) and r.get("steps") else None


def _left_out(r: dict) -> list[str]:
    """Short list of what adaptivity decided (``report.json`` decisions), for the comparison table."""
    rep = r.get("report") or {}
    dec = rep.get("decisions") if isinstance(rep, dict) else None
    out = []
    for d in dec or []:
        if isinstance(d, dict) and d.get("decision"):
            out.append(f"{d['decision']}={d.get('value')}")
    return out


def plot_scene(results: dict, scene: str, out_png: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    runs = [r for r in results.get("runs", []) if r["scene"] == scene]
    groups = _groups(runs)
    panels = [("test_psnr", "test PBR PSNR, masked (dB)"), ("test_psnr_radiance", "test radiance PSNR, masked (dB)"),
              ("chamfer", "Chamfer (unit sphere)"),
              ("albedo_psnr", "albedo PSNR, aligned (dB)"), ("albedo_psnr_lit", "albedo PSNR, lit pixels (dB)")]
    fig, axes = plt.subplots(1, len(panels), figsize=(5 * len(panels), 4.2))
    chamfer_ax = axes[[k for k, _ in panels].index("chamfer")]
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for i, ((_, config, variant), recs) in enumerate(sorted(groups.items())):
        col = colors[i % len(colors)]
        label = config if variant == "adaptive" and len({k[2] for k in groups}) == 1 else f"{config} / {variant}"
        for j, r in enumerate(recs):
            c = _curve(r)
            for ax, (key, _) in zip(axes, panels):
                pts = [(t["wall_s"], t[key]) for t in c if _finite(t.get(key))]
                if pts:
                    ax.plot(*zip(*pts), marker="o", ms=3, color=col, alpha=1.0 if j == 0 else 0.35,
                            lw=1.5 if j == 0 else 0.8, label=label if j == 0 else None)
            if _finite(r.get("chamfer_final")):
                chamfer_ax.plot([r.get("train_wall_s") or (c[-1]["wall_s"] if c else 0)], [r["chamfer_final"]],
                             marker="*", ms=11, color=col, ls="none",
                             label=f"{label} final {r.get('chamfer_resolution')}³" if j == 0 else None)
    for ax, (key, ylabel) in zip(axes, panels):
        ax.set_xlim(left=0)   # a panel with only the final Chamfer star would zoom onto one instant
        ax.set_xlabel("training wall time (s)")
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3)
        if key == "chamfer" and ax.lines:
            ax.set_yscale("log")
        if ax.lines:
            ax.legend(fontsize=8)
    fig.suptitle(f"{scene}: held-out error against training time")
    fig.tight_layout()
    fig.savefig(out_png, dpi=90)
    plt.close(fig)


def write_all(results: dict, out_dir: Path, target_psnr: float | None = None) -> dict:
    """``results.json`` (runs + summary), ``table.md``, ``error_vs_time_<scene>.png``."""
    out_dir = Path(out_dir)
    if target_psnr is None:
        target_psnr = (results.get("settings") or {}).get("target_psnr")
    summary = summarize(results, target_psnr)
    results["summary"] = summary
    tmp = out_dir / "results.json.tmp"
    tmp.write_text(json.dumps(results, indent=1, default=str))
    tmp.replace(out_dir / "results.json")
    write_table(results, summary, out_dir / "table.md")
    (out_dir / "command.txt").write_text(results.get("command", "") + "\n")
    (out_dir / "machine.json").write_text(json.dumps(results.get("machine", {}), indent=1))
    for scene in sorted({r["scene"] for r in results.get("runs", [])}):
        try:
            plot_scene(results, scene, out_dir / f"error_vs_time_{scene}.png")
        except Exception as e:  # a plot never loses the numbers
            (out_dir / f"error_vs_time_{scene}.txt").write_text(f"plot failed: {type(e).__name__}: {e}\n")
    return summary


def merge_results(dirs: list[Path]) -> dict:
    """One ``results.json`` dict from several: every run, with the first folder's machine and
    settings, and the command of each folder joined by `` & `` (they ran side by side)."""
    parts = []
    for d in dirs:
        f = d / "results.json"
        if not f.exists():
            raise SystemExit(f"--merge: {f} not found")
        parts.append(json.loads(f.read_text()))
    merged = dict(parts[0])
    merged["runs"] = [r for part in parts for r in part.get("runs", [])]
    merged["command"] = " & ".join(str(part.get("command", "?")) for part in parts)
    merged["merged_from"] = [str(d) for d in dirs]
    return merged


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m bench report", description="rebuild table.md and plots")
    p.add_argument("results_dir")
    p.add_argument("--target-psnr", type=float, default=None)
    p.add_argument("--merge", nargs="+", default=None, metavar="DIR",
                   help="first write RESULTS_DIR/results.json from the runs of these results folders "
                        "(e.g. two benchmarks run side by side at the same time, one variant each)")
    a = p.parse_args(argv)
    d = Path(a.results_dir)
    if a.merge:
        d.mkdir(parents=True, exist_ok=True)
        (d / "results.json").write_text(json.dumps(merge_results([Path(x) for x in a.merge]), indent=2))
    results = json.loads((d / "results.json").read_text())
    write_all(results, d, a.target_psnr)
    print((d / "table.md").read_text())
    return 0


if __name__ == "__main__":
    sys.exit(main())
