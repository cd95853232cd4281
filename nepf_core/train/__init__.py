"""Training: ``fit()`` and what it is made of.

* :mod:`.loop`: :func:`fit` and :class:`TrainingRun` (the step, records, evaluations, checkpoints);
* :mod:`.run_state`: the switches in effect (lobe, fade, Hessian weight, background, mask loss);
* :mod:`.adaptivity` and :mod:`.rules`: the decisions that change the run state;
* :mod:`.schedule`, :mod:`.clock`, :mod:`.setup`: learning rate, training time, optimiser;
* :mod:`.evaluation`, :mod:`.metrics_log`: sync / held-out metrics and the run folder's records;
* :mod:`.hooks`: observers for probes and tests; :mod:`.load`: :func:`load_model`.
"""

from nepf_core.train.evaluation import EvalTargets, evaluate_test, sync_psnr
from nepf_core.train.hooks import TrainHooks
from nepf_core.train.load import load_model
from nepf_core.train.loop import TrainingRun, fit
from nepf_core.train.metrics_log import MetricsLog
from nepf_core.train.result import FitError, FitResult
from nepf_core.train.run_state import RunState
from nepf_core.train.schedule import lr_factor
from nepf_core.train.setup import resolve_device

__all__ = ["EvalTargets", "FitError", "FitResult", "MetricsLog", "RunState", "TrainHooks", "TrainingRun",
           "evaluate_test", "fit", "load_model", "lr_factor", "resolve_device", "sync_psnr"]
