"""Training wall time: seconds of training only, across resumes.

``wall = wall_before_resume + (now - start) - excluded``, where ``excluded`` sums the time spent
in sync and held-out evaluations, checkpoint writes and mesh extraction for Chamfer, so every
``wall_s`` in ``metrics.jsonl`` compares runs by their training time alone.
"""

from __future__ import annotations

import time
from contextlib import contextmanager


class TrainClock:
    def __init__(self, wall_before: float = 0.0) -> None:
        self.wall_before = wall_before
        self.start = time.perf_counter()
        self.excluded = 0.0

    def wall(self) -> float:
        return self.wall_before + (time.perf_counter() - self.start) - self.excluded

    @contextmanager
    def paused(self):
        """Time inside the block does not count as training (it is added to ``excluded`` at the end)."""
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.excluded += time.perf_counter() - t0
