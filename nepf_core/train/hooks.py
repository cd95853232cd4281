"""Hooks: how code outside the library observes a training run (bench probes, tests).

Subclass :class:`TrainHooks`, override what you need and pass instances to
``fit(..., hooks=[...])``. Each method receives the :class:`nepf_core.train.loop.TrainingRun`
(``run.model``, ``run.ema``, ``run.optimizer``, ``run.cfg``, ``run.scene``, ``run.targets``,
``run.run_state``, ``run.device``, ``run.step``, ``run.clock.wall()``). Hooks may read
everything and may add keys to an evaluation record; they must not change the model, the
optimiser or the random generators, or the run is no longer the one the config describes.
(:class:`nepf_core.callbacks.FitCallbacks` is the caller's side: progress, metrics, stop.)
"""

from __future__ import annotations


class TrainHooks:
    """No-op base class; every method is optional."""

    def before_step(self, run, step: int) -> None:
        """Before the rays of step ``step + 1`` are drawn (learning rate already set)."""

    def before_backward(self, run, step: int, losses: dict, loss_cfg) -> None:
        """Step ``step``'s loss terms (``losses``: by name, unweighted, their graph alive, and
        ``"loss"``, the weighted sum) and the :class:`~nepf_core.losses.LossConfig` in effect (the
        run state's weights), before ``backward``. A probe may take ``torch.autograd.grad`` of any
        term with ``retain_graph=True`` (which leaves every ``.grad`` as it was); it must not call
        ``backward`` (bench/term_gradients.py)."""

    def after_step(self, run, step: int, out, losses: dict) -> None:
        """After the optimiser step ``step`` (``out``: the RenderOutput, ``losses``: the terms)."""

    def on_evaluation(self, run, record: dict) -> None:
        """A held-out evaluation (``record``: the metrics, ``kind == "test"``), before it is
        written to ``metrics.jsonl`` and seen by the plateau rule; keys added here are written
        too. ``run.model`` holds the live weights (the record was measured with ``run.ema``
        applied when there is one)."""

    def on_checkpoint(self, run, step: int, path: str) -> None:
        """After ``checkpoints/latest.pt`` was written at ``step``."""
