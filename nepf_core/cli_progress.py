"""The ``nepf fit`` progress bar: one bar, one ETA.

The bar advances with the run's progress ``fraction`` (``max(step / iters, wall / budget)``,
:func:`nepf_core.train.schedule.progress_fraction`) in thousandths, and its text shows the
run's own ETA (``eta_s``: the time left to whichever limit, steps or time budget, ends the run
first; :func:`nepf_core.train.schedule.run_eta`). tqdm's elapsed/remaining fields are left out
of the bar format: tqdm extrapolates its own rate over its own total, which on a budgeted run
(or one whose step rate changes) gives a second ETA that disagrees with the first.
"""

from __future__ import annotations

from nepf_core.callbacks import FitCallbacks

BAR_UNITS = 1000
BAR_FORMAT = "{percentage:3.0f}%|{bar}| {desc}"   # {desc}: our text (tqdm prefixes {postfix} with ", ")
ENDS_BY = {"time": "time budget", "steps": "steps"}


def format_duration(seconds: float) -> str:
    """``M:SS`` below an hour, ``H:MM:SS`` above (rounded to whole seconds)."""
    s = int(round(max(seconds, 0.0)))
    h, rem = divmod(s, 3600)
    m, sec = divmod(rem, 60)
    return f"{h}:{m:02d}:{sec:02d}" if h else f"{m}:{sec:02d}"


def progress_text(info: dict) -> str:
    """The bar's text for a progress record (``FitCallbacks.on_progress``), e.g.
    ``"training · step 500/20000 · 0:28 · ETA 1:25 (time budget)"``."""
    parts = [str(info.get("stage") or "")]
    if info.get("total"):
        parts.append(f"step {info.get('step', 0)}/{info['total']}")
    if info.get("wall_s") is not None:
        parts.append(format_duration(float(info["wall_s"])))
    if info.get("eta_s") is not None:
        by = ENDS_BY.get(info.get("ends_by") or "", "")
        parts.append(f"ETA {format_duration(float(info['eta_s']))}" + (f" ({by})" if by else ""))
    return " · ".join(p for p in parts if p)


def bar_position(info: dict) -> int:
    """The bar's position in :data:`BAR_UNITS` for ``info["fraction"]`` (clamped to [0, 1])."""
    frac = min(max(float(info.get("fraction") or 0.0), 0.0), 1.0)
    return int(round(frac * BAR_UNITS))


def progress_callbacks() -> tuple[FitCallbacks, object]:
    """``(callbacks, bar)``: a tqdm bar driven by the run's progress and its metrics printed
    above it (held-out and sync evaluations)."""
    from tqdm import tqdm

    bar = tqdm(total=BAR_UNITS, bar_format=BAR_FORMAT, dynamic_ncols=True)

    def on_progress(info: dict) -> None:
        pos = bar_position(info)
        if pos != bar.n:
            bar.n = pos
        bar.set_description_str(progress_text(info))   # refreshes the bar

    def on_metrics(rec: dict) -> None:
        if rec.get("kind") == "test":
            ssim = rec.get("test_ssim")
            bar.write(f"[{rec['wall_s']:.0f}s] step {rec['step']}: test PSNR {_num(rec.get('test_psnr'))} dB"
                      + (f", SSIM {ssim:.3f}" if ssim is not None else "")
                      + (f" on {rec['test_views']} held-out views" if rec.get("test_views") else "")
                      + (f", albedo PSNR {rec['albedo_psnr']:.2f} dB" if rec.get("albedo_psnr") is not None else "")
                      + (f", Chamfer {rec['chamfer']:.4f}" if rec.get("chamfer") is not None else ""))
        elif rec.get("kind") == "sync":
            bar.write(f"step {rec['step']}: sync PSNR L_r {_num(rec.get('psnr_r'))}  "
                      f"L_surf {_num(rec.get('psnr_surf'))}  L_vol {_num(rec.get('psnr_vol'))} dB")

    return FitCallbacks(on_progress=on_progress, on_metrics=on_metrics), bar


def _num(v) -> str:
    """``v`` with two decimals; ``nan`` for a missing (non-finite, written as null) value."""
    return "nan" if v is None else f"{v:.2f}"
