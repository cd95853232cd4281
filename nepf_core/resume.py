"""Where a resumed run starts, readable without torch, and a metrics log that counts each step once.

``RUN/checkpoints/latest.json`` sits beside ``latest.pt`` and names its step::

    {"step": 100, "wall_s": 41.2, "metrics_bytes": 18342}

``metrics_bytes`` is the length ``RUN/metrics.jsonl`` had when the checkpoint was taken. It is
written *after* ``latest.pt`` (both atomically), so it never names a step the ``.pt`` does not
hold; a kill between the two leaves it one checkpoint behind, which readers tolerate (below).

Why: a worker killed at step 130 with a checkpoint at 100 trains 101..130 again when it
resumes, and ``metrics.jsonl`` would list those steps twice. On resume the core cuts
the log back to what it held at the checkpoint (:func:`cut_metrics_to_checkpoint`), so each
step is listed once, with the values of the run that goes on. The worker (``worker/runner.py``)
reads :func:`checkpoint_step` to show ``stage: "resuming"`` at the checkpoint's step while the
resumed run loads, instead of step 0.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Optional

CHECKPOINT_INFO = Path("checkpoints") / "latest.json"
METRICS = "metrics.jsonl"


def write_checkpoint_info(run_dir, step: int, wall_s: float, metrics_bytes: Optional[int] = None) -> None:
    """Write ``checkpoints/latest.json`` (temp file + rename: a reader never sees half of it)."""
    path = Path(run_dir) / CHECKPOINT_INFO
    path.parent.mkdir(parents=True, exist_ok=True)
    info = {"step": int(step), "wall_s": float(wall_s)}
    if metrics_bytes is not None:
        info["metrics_bytes"] = int(metrics_bytes)
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(info))
    os.replace(tmp, path)


def read_checkpoint_info(run_dir) -> Optional[dict]:
    """``checkpoints/latest.json`` as a dict, or None when missing or unreadable."""
    try:
        info = json.loads((Path(run_dir) / CHECKPOINT_INFO).read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(info, dict) or not isinstance(info.get("step"), int) or info["step"] < 0:
        return None
    return info


def checkpoint_step(run_dir) -> Optional[int]:
    """The step of the run folder's latest checkpoint, or None (no checkpoint yet)."""
    info = read_checkpoint_info(run_dir)
    return None if info is None else info["step"]


def drop_records_after(path, step: int) -> int:
    """Rewrite the JSON-lines file ``path`` without the records whose ``step`` is above ``step``
    (and without a line cut by a kill); returns how many lines were dropped. Lines without a
    ``step`` are kept. The file is replaced atomically (a reader sees the old or the new one)."""
    path = Path(path)
    try:
        lines = path.read_bytes().split(b"\n")
    except FileNotFoundError:
        return 0
    keep = []
    for raw in lines:
        if not raw.strip():
            continue
        try:
            rec = json.loads(raw)
        except ValueError:
            continue
        s = rec.get("step") if isinstance(rec, dict) else None
        if isinstance(s, (int, float)) and not isinstance(s, bool) and s > step:
            continue
        keep.append(raw)
    dropped = sum(1 for raw in lines if raw.strip()) - len(keep)
    if dropped:
        tmp = path.with_suffix(path.suffix + ".tmp")
        tmp.write_bytes(b"".join(r + b"\n" for r in keep))
        os.replace(tmp, path)
    return dropped


def cut_metrics_to_checkpoint(run_dir, step: int) -> int:
    """Make ``RUN/metrics.jsonl`` hold what it held when the checkpoint of ``step`` was taken.

    When ``checkpoints/latest.json`` names that step, the file is cut to its ``metrics_bytes``
    (exact: an evaluation written after the checkpoint at the same step goes too, since the
    resumed run writes it again). Otherwise (a kill between ``latest.pt`` and its info file, or
    a run folder from an older version) the records above ``step`` are dropped. Returns the
    bytes or lines removed (0: nothing to do)."""
    path = Path(run_dir) / METRICS
    info = read_checkpoint_info(run_dir)
    size = path.stat().st_size if path.exists() else 0
    if info is not None and info["step"] == step and isinstance(info.get("metrics_bytes"), int) \
            and 0 <= info["metrics_bytes"] <= size:
        if info["metrics_bytes"] == size:
            return 0
        tmp = path.with_suffix(".jsonl.tmp")
        with open(path, "rb") as src:
            tmp.write_bytes(src.read(info["metrics_bytes"]))
        os.replace(tmp, path)   # a new file, not a truncation in place: readers re-index it
        return size - info["metrics_bytes"]
    return drop_records_after(path, step)
