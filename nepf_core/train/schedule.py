"""The learning-rate and annealing schedules, as functions of training progress.

Progress ``p = max(step / iters, wall / budget)`` in ``[0, 1]`` (the wall clock counts only
with a time budget), so a time-budgeted run follows the same curves over its seconds.
"""

from __future__ import annotations

import math


def lr_factor(progress_warm: float, progress: float, alpha: float) -> float:
    """NeuS schedule: ``w`` during warm-up (``w`` in [0,1]); then
    ``((cos(pi p) + 1) / 2) (1 - alpha) + alpha`` for post-warm-up progress ``p``."""
    if progress_warm < 1.0:
        return max(progress_warm, 1e-3)
    return ((math.cos(math.pi * min(progress, 1.0)) + 1.0) * 0.5) * (1.0 - alpha) + alpha


def progress_fraction(step: int, total: int, wall_s: float, time_budget_s: float | None) -> float:
    """``min(max(step / total, wall / budget), 1)`` (the second term only with a budget)."""
    p = step / max(total, 1)
    if time_budget_s:
        p = max(p, wall_s / time_budget_s)
    return min(p, 1.0)


def run_eta(step: int, total: int, wall_s: float, time_budget_s: float | None) -> tuple[float | None, str]:
    """``(seconds left, "time" | "steps")``: the end of whichever limit comes first.

    Steps end in ``(total - step) * wall / step`` seconds (the mean step time so far); a budget
    in ``budget - wall``. This equals ``wall / p - wall`` for the progress ``p`` of
    :func:`progress_fraction` (its ``max`` picks the nearer end). ``None`` before the first step
    without a budget (no rate yet)."""
    by_time = max(time_budget_s - wall_s, 0.0) if time_budget_s else None
    by_steps = (total - step) * wall_s / step if step > 0 else None
    if by_steps is not None:
        by_steps = max(by_steps, 0.0)
    if by_time is not None and (by_steps is None or by_time <= by_steps):
        return by_time, "time"
    return by_steps, "steps"


def scheduled_lr_factor(step: int, p: float, total: int, tc, budgeted: bool) -> float:
    """The regular schedule's factor at ``step`` / progress ``p`` (``tc``: the TrainConfig).

    Without a budget, warm-up is ``step / warmup_steps`` and the cosine runs over the steps after
    it; with a budget the cosine runs over the progress ``p`` itself (the step count is unknown)."""
    warm = step / max(tc.warmup_steps, 1)
    if budgeted:
        return lr_factor(min(warm, 1.0), p, tc.lr_alpha)
    post = (p * total - tc.warmup_steps) / max(total - tc.warmup_steps, 1)
    return lr_factor(warm, post, tc.lr_alpha)


def cos_anneal_ratio(p: float, total: int, anneal_end: int) -> float:
    """NeuS cosine annealing ratio ``min(1, p total / anneal_end)`` (1 when ``anneal_end <= 0``)."""
    return 1.0 if anneal_end <= 0 else min(1.0, (p * total) / anneal_end)


def coarse_to_fine(p: float, frac: float) -> float:
    """Share of the grid levels' schedule done: ``min(1, p / frac)``."""
    return min(1.0, p / max(frac, 1e-6))

