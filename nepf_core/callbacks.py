"""Callbacks that connect ``fit()`` to its caller (CLI progress bar, worker, tests).

``fit()`` never sees Celery or a database; it calls these and nothing else.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Optional


@dataclass
class FitCallbacks:
    """Optional hooks; any of them may be None.

    Attributes:
        on_progress: called with ``{"step", "total", "fraction", "stage", "eta_s", "ends_by",
            "wall_s"}`` after every step (cheap: callers should throttle their own I/O);
            ``eta_s`` is the time left to whichever limit ends the run first, ``ends_by`` which
            (``"time"`` budget or ``"steps"``; :func:`nepf_core.train.schedule.run_eta`).
        on_metrics: called with each record also written to ``metrics.jsonl``.
        should_stop: polled every step; returning True stops training cooperatively
            (outputs are still written, the run is marked ``cancelled``).
        on_checkpoint: called with ``(step, path)`` after each checkpoint is written.
    """

    on_progress: Optional[Callable[[dict], None]] = None
    on_metrics: Optional[Callable[[dict], None]] = None
    should_stop: Optional[Callable[[], bool]] = None
    on_checkpoint: Optional[Callable[[int, str], None]] = None

    def progress(self, info: dict) -> None:
        if self.on_progress is not None:
            self.on_progress(info)

    def metrics(self, record: dict) -> None:
        if self.on_metrics is not None:
            self.on_metrics(record)

    def stop_requested(self) -> bool:
        return bool(self.should_stop is not None and self.should_stop())

    def checkpoint(self, step: int, path: str) -> None:
        if self.on_checkpoint is not None:
            self.on_checkpoint(step, path)
