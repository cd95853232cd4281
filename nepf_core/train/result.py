"""What ``fit()`` returns, and the error it raises when training cannot go on."""

from __future__ import annotations

from dataclasses import dataclass, field


class FitError(RuntimeError):
    """Training cannot continue (for example, too many non-finite steps)."""


@dataclass
class FitResult:
    status: str
    """``succeeded``, ``cancelled`` or ``stopped_early``."""
    step: int
    total: int
    wall_s: float
    run_dir: str
    nonfinite_steps: int = 0
    last_test: dict = field(default_factory=dict)
    report: dict = field(default_factory=dict)
