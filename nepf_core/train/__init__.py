"""Training: ``fit()`` and what it is made of.

* :mod:`.loop`: :func:`fit` and :class:`TrainingRun` (the step, records, evaluations, checkpoints);
* :mod:`.run_state`: the switches in effect (lobe, fade, Hessian weight, background, mask loss);
* :mod:`.adaptivity` and :mod:`.rules`: the decisions that change the run state;
* :mod:`.schedule`, :mod:`.clock`, :mod:`.setup`: learning rate, training time, optimiser;
* :mod:`.evaluation`, :mod:`.metrics_log`: sync / held-out metrics and the run folder's records;
* :mod:`.hooks`: observers for probes and tests; :mod:`.load`: :func:`load_model`.
"""

import importlib

_EXPORTS = {"EvalTargets": "evaluation", "evaluate_test": "evaluation", "sync_psnr": "evaluation",
            "TrainHooks": "hooks", "load_model": "load", "TrainingRun": "loop", "fit": "loop",
            "MetricsLog": "metrics_log", "FitError": "result", "FitResult": "result", "RunState": "run_state",
            "lr_factor": "schedule", "resolve_device": "setup"}
__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    """The exports, imported on first use (``nepf_core.config`` imports ``train.rules.config``, the
    ``rules`` section, while ``train.loop`` imports ``nepf_core.config``)."""
    if name not in _EXPORTS:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(importlib.import_module(f"{__name__}.{_EXPORTS[name]}"), name)
