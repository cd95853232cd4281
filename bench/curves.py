"""Per-run quantities of a benchmark run record (``results.json`` -> one run): its held-out curve,
final numbers, times to reach a PSNR (raw and on the running mean the plateau rule uses), the
per-level time savings of a pair, and the medians over repeats. :mod:`bench.report` turns them
into tables and plots; the definitions are in its docstring and ``bench/README.md``."""

from __future__ import annotations

import math
import statistics

SMOOTH_WINDOW = 3
"""Evaluations in the running mean (the plateau rule's window)."""



def _curve(rec: dict) -> list[dict]:
    return [t for t in rec.get("test_curve") or [] if t.get("wall_s") is not None]


def final_test(rec: dict) -> dict:
    """The final held-out record of a run ({} when it has none)."""
    c = _curve(rec)
    finals = [t for t in c if t.get("final")]
    return (finals or c or [{}])[-1]


def best_psnr(rec: dict) -> float | None:
    vals = [t["test_psnr"] for t in _curve(rec) if _finite(t.get("test_psnr"))]
    return max(vals) if vals else None


def time_to_reach(rec: dict, target: float | None) -> float | None:
    """First ``wall_s`` at which masked test PSNR >= ``target`` (None: not reached)."""
    if target is None or not _finite(target):
        return None
    for t in _curve(rec):
        if _finite(t.get("test_psnr")) and t["test_psnr"] >= target - 1e-9:
            return float(t["wall_s"])
    return None


def smoothed_curve(rec: dict, window: int = SMOOTH_WINDOW) -> list[tuple[float, float]]:
    """``[(wall_s, mean of the masked test PSNR of this and the previous window - 1 evaluations)]``,
    from the ``window``-th evaluation on (``[]`` with fewer)."""
    c = [t for t in _curve(rec) if _finite(t.get("test_psnr"))]
    return [(float(c[i]["wall_s"]), sum(t["test_psnr"] for t in c[i - window + 1:i + 1]) / window)
            for i in range(window - 1, len(c))]


def time_to_reach_smoothed(rec: dict, target: float | None, window: int = SMOOTH_WINDOW) -> float | None:
    """First ``wall_s`` at which :func:`smoothed_curve` >= ``target`` (None: not reached)."""
    return _first_reach(smoothed_curve(rec, window), target)


def _first_reach(curve: list[tuple[float, float]], target: float | None) -> float | None:
    """First ``t`` of ``[(t, value)]`` with ``value >= target`` (None: not reached or no target)."""
    if target is None or not _finite(target):
        return None
    return next((t for t, v in curve if v >= target - 1e-9), None)


def level_savings(a: dict, b: dict, step_db: float = 1.0, window: int = SMOOTH_WINDOW) -> list[dict]:
    """Time saved by run ``a`` over run ``b`` at every shared PSNR level of their smoothed curves.

    Levels ``P_k = P_0 + k step_db`` (``P_0`` the first whole dB above both curves' first
    smoothed values, so neither is credited with a level it started above) up to the lower
    smoothed final ``P_f``, and ``P_f`` itself; per level ``{"level", "t_a", "t_b", "saved_pct"}``
    with ``t`` = :func:`time_to_reach_smoothed` and saved = ``100 (t_b - t_a) / t_b``. Why: the
    single "time to the lower final" rewards a baseline that plateaus early and low (a run that
    climbs past it later counts as slower even when it is ahead at every other level)."""
    sa, sb = smoothed_curve(a, window), smoothed_curve(b, window)
    if not sa or not sb:
        return []
    final = min(sa[-1][1], sb[-1][1])
    start = math.floor(max(sa[0][1], sb[0][1])) + step_db
    n_whole = max(math.ceil((final - 1e-9 - start) / step_db), 0)
    levels = [start + k * step_db for k in range(n_whole)] + [final]
    out = []
    for lv in levels:
        ta, tb = _first_reach(sa, lv), _first_reach(sb, lv)
        out.append({"level": lv, "t_a": ta, "t_b": tb, "saved_pct": _saved_pct(ta, tb)})
    return out


def chamfer_of(rec: dict) -> tuple[float | None, bool]:
    """``(chamfer, is_final_fine)``: the fine final Chamfer, else the last in-training one."""
    if _finite(rec.get("chamfer_final")):
        return rec["chamfer_final"], True
    vals = [t["chamfer"] for t in _curve(rec) if _finite(t.get("chamfer"))]
    return (vals[-1], False) if vals else (None, False)


def _finite(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def _median(xs):
    xs = [x for x in xs if _finite(x)]
    return statistics.median(xs) if xs else None


# ----------------------------------------------------------------------------------------------
# aggregation
# ----------------------------------------------------------------------------------------------

def _groups(runs: list[dict]) -> dict[tuple, list[dict]]:
    g: dict[tuple, list[dict]] = {}
    for r in runs:
        g.setdefault((r["scene"], r["config"], r["variant"]), []).append(r)
    for v in g.values():
        v.sort(key=lambda r: (r.get("repeat", 0), run_seed(r)))
    return g


def run_seed(rec: dict) -> int:
    """``train.seed`` of a run: its ``--override`` if any, else its repeat index (bench/run.py)."""
    ov = rec.get("overrides") or {}
    return int(ov.get("train.seed", rec.get("repeat", 0)))


def tail_mean(rec: dict, frac: float = 0.1) -> float | None:
    """Mean masked test PSNR of the evaluations in the last ``frac`` of the run's training time
    (``wall_s >= (1 - frac) * last wall_s``): one evaluation moves by up to ~1 dB on spot_textured."""
    c = [t for t in _curve(rec) if _finite(t.get("test_psnr"))]
    if not c:
        return None
    t_end = float(c[-1]["wall_s"])
    vals = [t["test_psnr"] for t in c if float(t["wall_s"]) >= (1.0 - frac) * t_end]
    return sum(vals) / len(vals)


def _median_time(recs: list[dict], target_of) -> dict:
    """Median time to reach a per-repeat target over repeats, with the reached count."""
    ts = [time_to_reach(r, target_of(r)) for r in recs]
    reached = [t for t in ts if t is not None]
    return {"t": statistics.median(reached) if len(reached) == len(ts) and ts else None,
            "reached": len(reached), "n": len(ts), "per_repeat": ts}


def _saved_pct(t_adaptive, t_baseline):
    """Time saved by the adaptive run, ``100 (t_b - t_a) / t_b`` (None when either is missing)."""
    return 100.0 * (t_baseline - t_adaptive) / t_baseline if t_adaptive is not None and t_baseline else None
