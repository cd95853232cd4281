"""The worker's pipeline seam: one typed request in, one summary dict out.

The service worker runs a job by calling the function named by the setting ``NEPF_PIPELINE``
(``"package.module:function"``, default ``nepf_core.pipeline:run_pipeline``) with a single
:class:`JobRequest`. Every pipeline has this one signature::

    pipeline(request: JobRequest) -> dict

and returns the summary of :func:`nepf_core.jobs.run_job` (``{"status": "succeeded" |
"cancelled" | "stopped_early", "step", "total", "wall_s", "manifest", "report", ...}``). The
contract the worker relies on: progress goes through ``request.callbacks.progress``;
``request.callbacks.stop_requested()`` is polled and, once True, the pipeline stops and
returns ``status="cancelled"``; with ``request.resume`` it continues from what it already
wrote into ``request.run_dir``; bad input raises (``DatasetError`` for a dataset).

Another function with the same signature replaces the training, e.g. a lighter stand-in in
the service tests (``tests/service_fixtures.py:fake_pipeline``) or a wrapper that changes the
export sizes. See docs/SERVICE.md, "Extending/testing: the pipeline setting".

This module imports neither torch nor the service: the worker imports it before a job starts.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Optional

from nepf_core.callbacks import FitCallbacks

__all__ = ["JobRequest", "Pipeline", "run_pipeline", "load_pipeline", "DEFAULT_PIPELINE"]


@dataclass(frozen=True)
class JobRequest:
    """What one job asks for; the worker builds it from the job's config and the settings.

    Attributes:
        data_dir: the validated dataset folder (any layout ``nepf_core.data.detect`` reads).
        run_dir: where checkpoints, metrics, report and the export go (created if missing).
        preset: ``"fast" | "paper" | "tiny"``.
        iters: training steps (None: the preset's count).
        time_budget_s: wall-clock budget of the training (None: none).
        device: ``"auto" | "cpu" | "cuda" | "cuda:N" | "mps"``.
        resume: continue from ``run_dir/checkpoints/latest.pt`` when it exists.
        callbacks: progress and cooperative-stop hooks (:class:`FitCallbacks`).
        checkpoint_every: checkpoint period in steps (None: the preset's).
        texture_size, mesh_resolution, max_faces: export sizes (None: the preset's defaults,
            ``nepf_core.jobs.EXPORT_DEFAULTS``).
        max_side: working resolution: longer image sides are area-resampled down to it at
            load, intrinsics scaled to match (None/0: full size).
        holdout_every: views ``0, K, 2K, ...`` are held out of training and evaluated during
            it (0: none; None: the default rule of ``nepf_core.data.split``).
        up_axis: the input world's up axis, ``"+x"`` ... ``"-z"``, rotated to glTF's +Y at export
            (None / ``"auto"``: detected from the cameras; ``nepf_core.up_axis``).
    """

    data_dir: Path
    run_dir: Path
    preset: str = "fast"
    iters: Optional[int] = None
    time_budget_s: Optional[float] = None
    device: str = "auto"
    resume: bool = True
    callbacks: FitCallbacks = field(default_factory=FitCallbacks)
    checkpoint_every: Optional[int] = None
    texture_size: Optional[int] = None
    mesh_resolution: Optional[int] = None
    max_faces: Optional[int] = None
    max_side: Optional[int] = None
    holdout_every: Optional[int] = None
    up_axis: Optional[str] = None


Pipeline = Callable[[JobRequest], dict]
"""The one signature of a pipeline (see the module docstring)."""

DEFAULT_PIPELINE = "nepf_core.pipeline:run_pipeline"


def run_pipeline(request: JobRequest) -> dict:
    """The real pipeline: :func:`nepf_core.jobs.run_job` (load, fit, export) on ``request``."""
    from nepf_core.jobs import run_job  # torch is imported here, when a job runs

    overrides = None
    if request.checkpoint_every is not None:
        overrides = {"train.checkpoint_every": int(request.checkpoint_every)}
    return run_job(request.data_dir, request.run_dir, preset=request.preset, iters=request.iters,
                   time_budget_s=request.time_budget_s, device=request.device,
                   callbacks=request.callbacks, resume=request.resume,
                   texture_size=request.texture_size, mesh_resolution=request.mesh_resolution,
                   max_faces=request.max_faces, overrides=overrides, max_side=request.max_side,
                   holdout_every=request.holdout_every, up_axis=request.up_axis)


def load_pipeline(spec: str, setting: str = "NEPF_PIPELINE") -> Pipeline:
    """The function named by ``spec`` (``"package.module:function"``).

    Raises ``ValueError`` naming ``setting`` and ``spec`` when the module cannot be imported or
    has no such callable.
    """
    module_name, sep, attr = spec.partition(":")
    if not sep or not module_name or not attr:
        raise ValueError(f"{setting}={spec!r}: expected 'package.module:function'")
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise ValueError(f"{setting}={spec!r}: cannot import module {module_name!r} ({exc})") from None
    fn = getattr(module, attr, None)
    if not callable(fn):
        raise ValueError(f"{setting}={spec!r}: module {module_name!r} has no function {attr!r}")
    return fn
