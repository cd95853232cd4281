"""``metrics.jsonl``, ``progress.json`` and the error-against-time plot of a run folder."""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

from nepf_core.callbacks import FitCallbacks


class MetricsLog:
    """Append-only ``metrics.jsonl`` (one JSON object per line, flushed per record).

    A run killed mid-write can leave a partial last line; on resume it is closed with a newline,
    so the first new record starts a line of its own instead of being glued to the broken one.
    Non-finite floats are written as ``null``. Each record also goes to ``callbacks.metrics``.
    """

    def __init__(self, path: Path, callbacks: FitCallbacks) -> None:
        self.path = path
        self.cb = callbacks
        self.f = open(path, "a", encoding="utf-8")
        if path.stat().st_size and not _ends_with_newline(path):
            self.f.write("\n")

    def write(self, rec: dict) -> None:
        clean = {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in rec.items()}
        self.f.write(json.dumps(clean) + "\n")
        self.f.flush()
        self.cb.metrics(clean)

    def size(self) -> int:
        """Bytes of the file so far (every record is flushed): where a resume cuts it back to."""
        return self.f.tell()

    def close(self) -> None:
        self.f.close()


def _ends_with_newline(path: Path) -> bool:
    with open(path, "rb") as f:
        f.seek(-1, os.SEEK_END)
        return f.read(1) == b"\n"


def write_json_atomic(path: Path, obj) -> None:
    """Write ``obj`` as JSON through a temporary file and a rename (readers never see half a file)."""
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json.dumps(obj, indent=2))
    os.replace(tmp, path)


def plot_error_vs_time(run: Path) -> None:
    """``RUN/error_vs_time.png``: every held-out metric and the training losses against seconds
    (a failure is written to ``error_vs_time.txt``: a plot must never fail a run)."""
    from nepf_core.plots import plot_error_vs_time as plot
    try:
        plot(run / "metrics.jsonl", run / "error_vs_time.png")
    except Exception as e:
        (run / "error_vs_time.txt").write_text(f"plot failed: {e}\n")
