"""What a rule is: callbacks at fixed points of a run, each returning the decisions it took.

The loop calls every rule at every point (through
:class:`~nepf_core.train.adaptivity.Adaptivity`, which keeps them in order and logs what they
return) and never names one. Each rule decides for itself whether a step is one of its steps:
every ``rules.check_every`` steps, every ``train.occupancy_every`` steps, at a held-out
evaluation. This is nerfstudio's ``TrainingCallback`` with the cadence inside the callback.

The points, in the order of a run (a rule overrides those it needs):

============================  ===========================================================
:meth:`RuleCallback.on_data`   before the model is built: the data decide the mask loss, the
                               background model and the object's frame (:class:`DataContext`)
:meth:`~RuleCallback.on_model`  the model exists: the occupancy grid's visual hull
:meth:`~RuleCallback.before_step`  the learning-rate factor of the step is known: a rule may
                               lower it or end the run; the occupancy grid refreshes (:class:`StepStart`)
:meth:`~RuleCallback.on_batch`  the rays are drawn: a rule may leave rays out, or ask the render
                               for evidence (:class:`StepBatch`)
:meth:`~RuleCallback.after_step`  the optimiser step is done: a rule reads its evidence and
                               decides (:class:`StepEnd`)
:meth:`~RuleCallback.on_evaluation`  a held-out record (:class:`EvaluationContext`)
:meth:`~RuleCallback.on_report`  ``report.json`` is written (:class:`ReportContext`)
============================  ===========================================================

plus :meth:`~RuleCallback.step_stats` (keys of each train record in ``metrics.jsonl``) and
:meth:`~RuleCallback.state_dict` / :meth:`~RuleCallback.load_state_dict` (the rule's counters in
every checkpoint, under :attr:`~RuleCallback.state_key`).

A rule that decides changes the :class:`~nepf_core.train.run_state.RunState` itself (it is given
the run's) and returns the :class:`~nepf_core.train.decisions.Decision` that records why; a rule
that only observes returns nothing.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable, Iterable

import numpy as np

from nepf_core.render.surface import SurfaceRequest
from nepf_core.train.decisions import Decision

Decisions = Iterable["Decision | None"]
"""What a callback returns: the decisions it took (``None`` entries are skipped)."""


@dataclass
class DataContext:
    """Before the model is built."""

    scene: Any
    """The training views; a rule may replace them (the same views in the object's frame)."""
    surface_points: np.ndarray | None = None
    """``[P, 3]`` points where the images saw a surface (captures without masks), for the
    surface-points prior (:mod:`nepf_core.train.surface_points`); None: none."""


@dataclass
class ModelContext:
    """The model has been built on the data's decisions; nothing has been trained."""

    model: Any
    scene: Any


@dataclass
class StepStart:
    """Before a step's rays are drawn; the schedule (annealing, grid levels) is set."""

    step: int
    """Steps done so far (this step will make it ``step + 1``)."""
    wall: float
    """Training seconds so far."""
    progress: float
    """Share of the run done, by steps or by the time budget (:func:`nepf_core.train.schedule.progress_fraction`)."""
    model: Any
    lr_factor: float
    """The learning-rate factor of the regular schedule; a rule may lower it."""
    stop: bool = False
    """Set by a rule to end the run before this step (the rules after it are not called)."""


@dataclass
class StepBatch:
    """The rays of a step, drawn and not yet rendered."""

    step: int
    """Steps done before this one (as :attr:`StepStart.step`)."""
    model: Any
    rays: Any
    """The :class:`~nepf_core.rays.RayBatch` to render; a rule may replace it by a subset."""
    generator: Any
    """The run's :class:`torch.Generator` (draws must use it: a resumed run draws the same)."""
    request: SurfaceRequest = field(default_factory=SurfaceRequest)
    """What the render computes beyond the losses' needs; a rule adds what it will read."""
    left_out: Any = None
    """Rays left out of :attr:`rays` that the background alone renders (a RayBatch), or None."""


@dataclass
class StepEnd:
    """A step once the optimiser has taken it."""

    step: int
    """Steps done, this one included (the step number of records and decisions)."""
    model: Any
    rays: Any
    """The rays rendered (after any rule thinned them)."""
    out: Any
    """The :class:`~nepf_core.render.renderer.RenderOutput` of those rays."""
    losses: dict
    """The loss terms by record name (:func:`nepf_core.losses.compute_losses`)."""


@dataclass
class EvaluationContext:
    """A held-out evaluation (``record``: its ``kind == "test"`` metrics, ``test_psnr``, ``wall_s``)."""

    step: int
    record: dict
    progress: float | None = None


@dataclass
class ReportContext:
    """``report.json`` being written at the end of a run."""

    step: int
    report: dict
    """The report so far; a rule adds its own keys."""
    decided: Callable[[str], bool]
    """Whether a decision of this name was taken during the run."""


class RuleCallback:
    """A training rule. Every method is optional; each point's method returns the decisions taken."""

    state_key: str = ""
    """Key of :meth:`state_dict` in the checkpoint's ``adaptivity`` record ("": nothing to save)."""

    def on_data(self, ctx: DataContext) -> Decisions:
        """Once per run, before the model is built (a resumed run too; its checkpoint's decisions
        and counters then replace what this call logged)."""
        return ()

    def on_model(self, ctx: ModelContext) -> Decisions:
        """Once per run, when the model is built (a resumed run's checkpoint then restores its weights)."""
        return ()

    def before_step(self, ctx: StepStart) -> Decisions:
        """Every step, before its rays are drawn."""
        return ()

    def on_batch(self, ctx: StepBatch) -> Decisions:
        """Every step, between drawing the rays and rendering them."""
        return ()

    def after_step(self, ctx: StepEnd) -> Decisions:
        """Every step, once the optimiser has taken it (and before its records are written)."""
        return ()

    def on_evaluation(self, ctx: EvaluationContext) -> Decisions:
        """After each held-out evaluation."""
        return ()

    def on_report(self, ctx: ReportContext) -> Decisions:
        """At the end of the run (or its failure), when ``report.json`` is written."""
        return ()

    def step_stats(self) -> dict:
        """Keys for the step's ``metrics.jsonl`` record."""
        return {}

    def state_dict(self) -> dict:
        return {}

    def load_state_dict(self, state: dict) -> None:
        """Counters from :meth:`state_dict` (an empty dict: a checkpoint without them)."""
