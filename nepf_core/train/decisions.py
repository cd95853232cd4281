"""What adaptivity decided, when and why: the ``decisions`` list of ``report.json``."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class Decision:
    """One decision: ``name`` (e.g. ``specular_lobe``), its ``value``, a human ``reason`` and the
    training ``step`` it was taken at (0: before training)."""

    name: str
    value: Any
    reason: str
    step: int = 0

    def as_record(self) -> dict:
        return {"decision": self.name, "value": self.value, "reason": self.reason, "step": self.step}


class DecisionLog:
    """The run's decisions in the order they were taken (JSON-able records)."""

    def __init__(self, records: list[dict] | None = None) -> None:
        self.records: list[dict] = list(records or [])

    def add(self, decision: Decision | None) -> None:
        if decision is not None:
            self.records.append(decision.as_record())

    def has(self, name: str) -> bool:
        return any(r["decision"] == name for r in self.records)
