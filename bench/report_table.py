"""``table.md`` of a benchmark: the markdown :func:`write_table` writes from a
:func:`bench.report.summarize` summary, one function per section. The definitions of every number
are :mod:`bench.report`'s docstring, copied to the end of the table."""

from __future__ import annotations

import math
from pathlib import Path

from bench.curves import final_test
from bench.relight_report import relight_table_lines


def _fmt(x, nd=2, none="n/a"):
    if x is None:
        return none
    if isinstance(x, float) and not math.isfinite(x):
        return str(x)
    if isinstance(x, (int, float)):
        return f"{x:.{nd}f}"
    return str(x)


def _la(x):
    return "n/a" if not x else "/".join(f"{v:.1f}" for v in x)


def _fmt_t(x):
    return "not reached" if x is None else f"{x:.0f}"


def write_table(results: dict, summary: dict, path: Path) -> None:
    """``path``: the machine, the runs, the relight table, the comparisons, real data, definitions."""
    import bench.report
    L = _machine_lines(results) + _runs_lines(summary) + relight_table_lines(summary["rows"])
    errs = [(r["scene"], r["config"], r["variant"], e) for r in summary["rows"] for e in r["errors"]]
    if errs:
        L += ["Errors:", ""] + [f"* {s}/{c}/{v}: {e}" for s, c, v, e in errs] + [""]
    if summary["fast_vs_paper"]:
        L += _fast_vs_paper_lines(summary["fast_vs_paper"])
    if summary["adaptive_vs_all_on"]:
        pairs = summary["adaptive_vs_all_on"]
        L += _adaptive_lines(pairs) + _pair_lines(pairs) + _smoothed_pair_lines(pairs)
    L += _real_data_lines(results)
    definitions = (bench.report.__doc__ or "").split("Definitions (also written into ``table.md``):")[-1].strip()
    L += ["## Definitions", "", definitions, ""]
    path.write_text("\n".join(L))


def _machine_lines(results: dict) -> list[str]:
    m = results.get("machine", {})
    L = ["# NePF benchmark", "",
         f"Command: `{results.get('command', '')}`  ", f"Working directory: `{results.get('cwd', '')}`  ",
         f"Started {results.get('started', '?')}, finished {results.get('finished', '?')}.", "",
         "Machine: " + ", ".join(f"{k} {m.get(k)}" for k in ("cpu_model", "cpu_count", "cpus_allowed", "mem_total_mb",
                                                             "torch", "threads", "cgroup_cpu_max") if k in m)
         + f"; load average (1, 5, 15 min) at start {_la(m.get('loadavg'))} and end {_la(m.get('loadavg_end'))}.", ""]
    return L


def _runs_lines(summary: dict) -> list[str]:
    L = ["## Runs", "",
         "| scene | config | variant | n | status | budget s | steps | train wall s | test PSNR masked | "
         "test PSNR full | radiance PSNR masked | albedo PSNR | albedo PSNR lit px | Chamfer (unit sphere) | peak RSS MB | s/step | "
         "NaN steps | X (dB) | time to X (s) | CPU util |",
         "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in sorted(summary["rows"], key=lambda r: (r["scene"], r["config"], r["variant"])):
        ch = _fmt(r["chamfer"], 5) + ("" if r["chamfer_fine"] or r["chamfer"] is None else "*")
        tx = _fmt_t(r["t_to_X"]) + (f" ({r['t_to_X_reached']})" if r["n"] > 1 else "")
        L.append(f"| {r['scene']} | {r['config']} | {r['variant']} | {r['n']} | {r['status']} | {_fmt(r['budget_s'], 0)} | "
                 f"{_fmt(r['steps'], 0)} | {_fmt(r['train_wall_s'], 0)} | {_fmt(r['test_psnr'])} | "
                 f"{_fmt(r['test_psnr_full'])} | {_fmt(r.get('test_psnr_radiance'))} | {_fmt(r['albedo_psnr'])} | {_fmt(r['albedo_psnr_lit'])} | {ch} | {_fmt(r['peak_rss_mb'], 0)} | "
                 f"{_fmt(r['s_per_step'], 3)} | {_fmt(r['nonfinite_steps'], 0)} | {_fmt(r['target_X'])} | {tx} | "
                 f"{_fmt(r['cpu_util'], 2)} |")
    res = {r["chamfer_resolution"] for r in summary["rows"]}
    L += ["", f"Chamfer: final model, marching cubes at {sorted(x for x in res if x)}³, "
              "100k-sample default per mesh, unit-sphere units; `*` = last in-training value (128³) because "
              "the fine one failed or was skipped. Peak RSS: the whole run process (os.wait4), including the "
              "final Chamfer mesh. Albedo PSNR (per-channel least-squares scale, sRGB) over every foreground "
              "pixel, and over the lit ones only (test pixel max channel >= 1% of the foreground 99th "
              "percentile; where the fixed light never reaches, no view constrains the albedo). X: `--target-psnr` or the lowest final masked PSNR of the scene's rows. "
              "CPU util: CPU seconds / process seconds of the run (at most the thread count; lower means "
              "the machine was shared or the run waited on I/O).", ""]
    return L


def _fast_vs_paper_lines(rows: list[dict]) -> list[str]:
    L = ["## fast vs paper: time to reach paper's best test PSNR", "",
         "| scene | variant | paper best (dB) | paper time (s) | fast time (s) | ratio paper/fast | "
         "fast best (dB) | budgets paper/fast (s) |", "|---|---|---|---|---|---|---|---|"]
    for x in rows:
        rt = _fmt(x["ratio"]) + "x" if x["ratio"] is not None else "n/a (fast did not reach it)"
        reached = "" if x["n"] == 1 else f" ({x['fast_reached']}/{x['n']})"
        L.append(f"| {x['scene']} | {x['variant']} | {_fmt(x['paper_best'])} | {_fmt_t(x['t_paper'])} | "
                 f"{_fmt_t(x['t_fast'])}{reached} | "
                 f"{rt} | {_fmt(x['fast_best'])} | {_fmt(x['budget_paper'], 0)}/{_fmt(x['budget_fast'], 0)} |")
    L.append("")
    return L


def _adaptive_lines(rows: list[dict]) -> list[str]:
    L = ["## adaptive vs everything-on baselines: time to reach the same test PSNR", "",
         "Baselines: `all_on` = adaptivity off and no empty ray left out (NeuS coarse-to-fine sampler, "
         "same sample counts); `naive` = the brief's dense-grid reference rebuilt on the NePF model "
         "(one 96^3 grid level, 1024 rays x 48 uniform samples, FD normals, nothing adaptive).", "",
         "| scene | config | baseline | target (dB) | final adaptive | final baseline | diff (dB) | "
         "t adaptive (s) | t baseline (s) | time saved | s/step adaptive / baseline | "
         "Chamfer adaptive / baseline | albedo adaptive / baseline | adaptive decisions |",
         "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for x in rows:
        L.append(f"| {x['scene']} | {x['config']} | {x['baseline']} | {_fmt(x['target'])} | "
                 f"{_fmt(x['final_adaptive'])} | "
                 f"{_fmt(x['final_all_on'])} | {_fmt(x['diff'], 2)} | {_fmt_t(x['t_adaptive'])} | "
                 f"{_fmt_t(x['t_all_on'])} | {_fmt(x['saved_pct'], 0)}% | "
                 f"{_fmt(x['s_per_step_adaptive'], 3)} / {_fmt(x['s_per_step_all_on'], 3)} | "
                 f"{_fmt(x['chamfer_adaptive'], 5)} / {_fmt(x['chamfer_all_on'], 5)} | "
                 f"{_fmt(x['albedo_adaptive'])} / {_fmt(x['albedo_all_on'])} | "
                 f"{'; '.join(x['left_out']) or '-'} |")
    L.append("")
    return L


def _pair_lines(rows: list[dict]) -> list[str]:
    L = ["### Per pair", "",
         "Matched by seed (`train.seed`). final = last evaluation; tail = mean of the evaluations in the "
         "last 10 % of each run's training time; time saved to the pair's lower final, and to the lower "
         "tail mean (first evaluation at or above it); \"within 0.3 dB\": the adaptive run's time to "
         "the baseline's final minus 0.3 dB against the baseline's time to its final.", "",
         "| scene | baseline | seed | steps adaptive / baseline | train s adaptive / baseline | final adaptive / baseline (dB) | "
         "diff | t to lower final adaptive / baseline (s) | saved | tail adaptive / baseline (dB) | saved to lower tail | "
         "t within 0.3 dB adaptive / baseline (s) | saved within 0.3 dB | "
         "albedo adaptive / baseline | Chamfer adaptive / baseline |",
         "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for x in rows:
        for p in x["per_repeat"]:
            ta_, tb_ = p["tail_adaptive"], p["tail_all_on"]
            sv = p.get("tail_saved_pct")
            L.append(f"| {x['scene']} | {x['baseline']} | {p['seed']} | {_fmt(p['steps_adaptive'], 0)} / "
                     f"{_fmt(p['steps_all_on'], 0)} | {_fmt(p['wall_adaptive'], 0)} / {_fmt(p['wall_all_on'], 0)} | "
                     f"{_fmt(p['final_adaptive'])} / {_fmt(p['final_all_on'])} | {_fmt(p['diff'])} | "
                     f"{_fmt_t(p['t_adaptive'])} / {_fmt_t(p['t_all_on'])} | {_fmt(p['saved_pct'], 0)}% | "
                     f"{_fmt(ta_)} / {_fmt(tb_)} | {_fmt(sv, 0)}% | "
                     f"{_fmt_t(p['t_adaptive_tol'])} / {_fmt_t(p['t_all_on_tol'])} | {_fmt(p['tol_saved_pct'], 0)}% | "
                     f"{_fmt(p['albedo_adaptive'])} / {_fmt(p['albedo_all_on'])} | "
                     f"{_fmt(p['chamfer_adaptive'], 5)} / {_fmt(p['chamfer_all_on'], 5)} |")
    L.append("")
    return L


def _smoothed_pair_lines(rows: list[dict]) -> list[str]:
    L = ["### Per pair, smoothed (running mean of 3 evaluations)", "",
         "final = mean of the last 3 evaluations; times = first evaluation at which the running mean of "
         "3 reaches the lower smoothed final, or (within 0.3 dB) the baseline's smoothed final minus 0.3 dB "
         "for the adaptive run against the baseline's smoothed final for the baseline.", "",
         "| scene | baseline | seed | final adaptive / baseline (dB) | diff | t to lower final adaptive / "
         "baseline (s) | saved | t within 0.3 dB adaptive / baseline (s) | saved within 0.3 dB | "
         "saved over levels: median (levels >= 30 % / levels) |",
         "|---|---|---|---|---|---|---|---|---|---|"]
    for x in rows:
        for p in x["per_repeat"]:
            L.append(f"| {x['scene']} | {x['baseline']} | {p['seed']} | {_fmt(p['smooth_final_adaptive'])} / "
                     f"{_fmt(p['smooth_final_all_on'])} | {_fmt(p['smooth_diff'])} | "
                     f"{_fmt_t(p['smooth_t_adaptive'])} / {_fmt_t(p['smooth_t_all_on'])} | "
                     f"{_fmt(p['smooth_saved_pct'], 0)}% | {_fmt_t(p['smooth_t_adaptive_tol'])} / "
                     f"{_fmt_t(p['smooth_t_all_on_tol'])} | {_fmt(p['smooth_tol_saved_pct'], 0)}% | "
                     f"{_fmt(p['levels_saved_median_pct'], 0)}% ({p['levels_saved_30_n']} / {p['levels_n']}) |")
    L.append("")
    return L


def _real_data_lines(results: dict) -> list[str]:
    L = []
    real = [r for r in results.get("runs", []) if r.get("mode") == "real"]
    if real:
        L += ["## Real data", ""]
        for r in real:
            sp = r.get("split") or {}
            me = r.get("mesh") or {}
            L.append(f"* {r['id']}: {sp.get('n_train')} train / {sp.get('n_test')} test views "
                     f"(held out {sp.get('test_views')}), {sp.get('resolution')} px (downscale {sp.get('downscale')}); "
                     f"final masked test PBR PSNR {_fmt(final_test(r).get('test_psnr'))} dB; mesh "
                     f"{me.get('path', me.get('error'))} ({me.get('faces')} faces)")
        L.append("")
    return L
