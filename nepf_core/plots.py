"""Error-against-time plots from ``metrics.jsonl`` (matplotlib, Agg backend)."""

from __future__ import annotations

import json
from pathlib import Path


def read_metrics(path) -> list[dict]:
    """All records of a ``metrics.jsonl`` (skips a torn last line)."""
    recs = []
    for line in Path(path).read_text().splitlines():
        try:
            recs.append(json.loads(line))
        except json.JSONDecodeError:
            continue
    return recs


def plot_error_vs_time(metrics_path, out_png) -> None:
    """One panel per metric (test PSNR, albedo PSNR, Chamfer, sync PSNRs, loss) against ``wall_s``."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    recs = read_metrics(metrics_path)
    panels = [("test_psnr", "test PBR PSNR (dB)", "test"), ("test_psnr_radiance", "test radiance PSNR (dB)", "test"),
              ("albedo_psnr", "albedo PSNR (dB)", "test"),
              ("albedo_psnr_lit", "albedo PSNR, lit pixels (dB)", "test"),
              ("chamfer", "Chamfer (unit sphere)", "test"), ("psnr_r", "sync PSNR (dB)", "sync"),
              ("loss", "training loss", "train")]
    panels = [p for p in panels if any(p[0] in r and r[p[0]] is not None for r in recs)]
    if not panels:
        panels = [("loss", "training loss", "train")]
    fig, axes = plt.subplots(1, len(panels), figsize=(4 * len(panels), 3.2), squeeze=False)
    for ax, (key, label, kind) in zip(axes[0], panels):
        rs = [r for r in recs if r.get("kind", "train") == kind and r.get(key) is not None]
        if key == "psnr_r":
            for k2, name in (("psnr_r", "L_r"), ("psnr_surf", "L_surf"), ("psnr_vol", "L_vol")):
                ax.plot([r["wall_s"] for r in rs if k2 in r], [r[k2] for r in rs if k2 in r], label=name)
            ax.legend()
        else:
            ax.plot([r["wall_s"] for r in rs], [r[key] for r in rs], marker="o" if kind == "test" else None)
        if key in ("loss", "chamfer"):
            ax.set_yscale("log")
        ax.set_xlabel("training wall time (s)")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(out_png, dpi=90)
    plt.close(fig)
