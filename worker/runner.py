"""Run one job: claim it, call the pipeline (``NEPF_PIPELINE``), record the outcome. No Celery in here.

Delivery semantics (see docs/SERVICE.md; each state change is one conditional UPDATE of
:mod:`jobstore.state`):

* **claim**: one conditional UPDATE moves the job to ``running`` with this worker's lease,
  only if it is queued/running, not cancelled, and nobody holds a live lease. A duplicate or
  late message for a job that is finished or held elsewhere is dropped.
* **redelivery cap**: ``attempts`` is incremented by every claim; past ``NEPF_MAX_DELIVERIES``
  the job fails instead of running again (a job that kills its worker cannot loop forever).
* **heartbeat** (every ``NEPF_HEARTBEAT_S``): renews the lease, writes the latest progress
  (so progress writes are throttled to one per heartbeat), reads the cancel flag. If the lease
  was lost (another worker took over after we stalled), training is stopped.
* **completion**: one conditional UPDATE, only while we hold the lease and the job is running;
  ``completions`` counts it, so a job can never be completed twice.
* **resume**: the pipeline gets ``JobRequest(resume=True)`` and continues from
  ``RUN/checkpoints/latest.pt``.
* **files**: the job's workspace (:mod:`jobstore.storage`) gives the dataset and run folders to
  train in, and keeps each checkpoint and the results where the API and the next worker find
  them; the runner never knows where that is.
* **pipeline**: one fixed signature, ``pipeline(JobRequest) -> summary dict``
  (``nepf_core/pipeline.py``); the setting ``NEPF_PIPELINE`` names it.
"""

from __future__ import annotations

import json
import logging
import os
import socket
import threading
import traceback
from pathlib import Path
from typing import Any, Callable, Optional

from sqlalchemy.orm import sessionmaker

from jobstore import state
from jobstore.models import Job
from jobstore.settings import Settings
from jobstore.storage import Storage, open_storage
from nepf_core.resume import checkpoint_step

from .messages import human_error, scrub_server_paths  # noqa: F401 - importable from here too

log = logging.getLogger("nepf.worker")


#: how long a stopping worker waits for its last checkpoint to reach the object store
SHUTDOWN_FLUSH_S = 20.0


class LeaseLost(RuntimeError):
    """Raised from ``should_stop`` when this worker no longer holds the job's lease."""


class ShutdownRequested(RuntimeError):
    """Raised from ``on_progress`` when training stopped for a worker shutdown and the pipeline
    moves on to its export: the job goes back to the queue instead (the next worker resumes from
    the checkpoint and exports then), so a shutdown waits for one step, not for a whole export."""


def worker_identity() -> str:
    return f"{socket.gethostname()}:{os.getpid()}"


class JobRunner:
    def __init__(self, settings: Settings, Session: sessionmaker, job_id: str,
                 worker_id: Optional[str] = None, pipeline: Optional[Callable[..., dict]] = None,
                 shutdown: Optional[threading.Event] = None, storage: Optional[Storage] = None) -> None:
        self.settings = settings
        # where the job's files are: the data dir, or a scratch copy of the object store's (jobstore.storage)
        self.ws = (storage or open_storage(settings)).workspace(job_id)
        self._notice: Optional[str] = None   # why the job waits (the store is unreachable), shown as its error
        self._notice_dirty = False
        self.Session = Session
        self.job_id = job_id
        self.worker_id = worker_id or worker_identity()
        self._pipeline = pipeline  # None: the one NEPF_PIPELINE names
        self._progress: Optional[dict] = None
        self._progress_dirty = False
        self._first_step: Optional[int] = None
        # the step of the checkpoint this attempt resumes from (0: a fresh start), and the total
        # last reported: progress below it is shown as "resuming" at that step (never 0)
        self._resume_step = 0
        self._total: Optional[int] = None
        self._first_step_written = False
        self._report_mtime: Optional[float] = None
        self._cancel = False
        self._lease_lost = False
        self._lock = threading.Lock()
        self._stop_hb = threading.Event()
        # set when the worker process is stopping (SIGTERM/SIGINT/SIGQUIT, or its nepf serve died)
        self._shutdown = shutdown or threading.Event()
        self._last_poll = 0.0

    # ------------------------------------------------------------------ job state (jobstore.state)
    def claim(self) -> str:
        """'claimed' | 'finished' | 'held' | 'cancelled' | 'missing' | 'gave_up'.

        A job with a checkpoint in its run folder is claimed as ``stage: "resuming"`` at the
        checkpoint's step: the steps trained after it died with the last worker and are trained
        again, so that is where the progress stands (and ``metrics.jsonl`` is cut back to it)."""
        self._resume_step = self.ws.checkpoint_step() or 0
        got = state.claim(self.Session, self.job_id, self.worker_id, lease_s=self.settings.lease_s,
                          max_deliveries=self.settings.max_deliveries, resume_step=self._resume_step)
        self._total = got.total
        return got.outcome

    def _heartbeat_once(self) -> None:
        with self._lock:
            prog = self._progress if self._progress_dirty else None
            self._progress_dirty = False
            first = self._first_step if not self._first_step_written else None
            notice, dirty = self._notice, self._notice_dirty
            self._notice_dirty = False
        values: dict[str, Any] = {"error": notice} if dirty else {}
        if prog is not None:
            values.update({k: prog[k] for k in ("step", "total", "fraction", "stage", "eta_s", "wall_s") if k in prog})
        decisions = self._read_decisions()
        if decisions is not None:
            values["decisions"] = decisions
        beat = state.heartbeat(self.Session, self.job_id, self.worker_id, lease_s=self.settings.lease_s,
                               values=values, first_step=first)
        if not beat.held:
            self._lease_lost = True
            return
        if first is not None:
            self._first_step_written = True
        self._cancel = beat.cancel_requested

    def _read_decisions(self) -> Optional[list]:
        path = self.run_dir / "report.json"
        try:
            m = path.stat().st_mtime
        except FileNotFoundError:
            return None
        if m == self._report_mtime:
            return None
        try:
            rep = json.loads(path.read_text())
        except (json.JSONDecodeError, OSError, UnicodeDecodeError):
            return None
        self._report_mtime = m
        dec = rep.get("decisions") if isinstance(rep, dict) else rep
        return dec if isinstance(dec, list) else None

    def _heartbeat_loop(self) -> None:
        while not self._stop_hb.wait(self.settings.heartbeat_s):
            try:
                self._heartbeat_once()
            except Exception as exc:  # noqa: BLE001 - DB hiccup: try again next beat
                log.warning("heartbeat failed: %s", exc)

    # ------------------------------------------------------------------ callbacks
    def on_progress(self, info: dict) -> None:
        if info.get("stage") == "exporting" and self._shutdown.is_set() and not self._cancel:
            raise ShutdownRequested(f"job {self.job_id}: worker shutting down before the export")
        info = self._not_below_checkpoint(info)
        with self._lock:
            self._progress = info
            self._progress_dirty = True
            # the first step this attempt trained: 1 on a fresh start, checkpoint step + 1 after a
            # resume (steps are trained in order, so any report past the checkpoint means it did)
            if self._first_step is None and int(info.get("step") or 0) > self._resume_step:
                self._first_step = self._resume_step + 1

    def _not_below_checkpoint(self, info: dict) -> dict:
        """``info`` as the job store keeps it: a report below the resumed checkpoint's step (the
        pipeline's ``loading`` at step 0 while it reloads the data) becomes ``resuming`` at that
        step, so the progress never drops under the point the run resumes from."""
        info = dict(info)
        if isinstance(info.get("total"), int) and info["total"] > 0:
            self._total = info["total"]
        if self._resume_step and int(info.get("step") or 0) < self._resume_step:
            info.update(step=self._resume_step, stage="resuming", eta_s=None, total=self._total or info.get("total"),
                        fraction=min(1.0, self._resume_step / self._total) if self._total else info.get("fraction"))
        return info

    def should_stop(self) -> bool:
        if self._lease_lost:
            # another worker owns the job now: leave at once, without exporting into its run folder
            raise LeaseLost(f"job {self.job_id}: lease lost to another worker")
        return self._cancel or self._shutdown.is_set()

    def _waiting_for_storage(self, reason: Optional[str]) -> None:
        """The store is unreachable (``reason``), or answers again (None): say so in the job."""
        with self._lock:
            if reason is not None:
                self._progress = {**(self._progress or {}), "stage": "waiting_for_storage",
                                  "step": self._resume_step, "eta_s": None}
                self._progress_dirty = True
            self._notice = None if reason is None else scrub_server_paths(
                f"waiting for the object store (retrying): {reason}", self.settings)
            self._notice_dirty = True

    # ------------------------------------------------------------------ main
    @property
    def run_dir(self) -> Path:
        return self.ws.run_dir

    def job_request(self, cfg: dict):
        """The pipeline's :class:`~nepf_core.pipeline.JobRequest`: the job's config (preset,
        iters, time budget, working side, held-out split, export sizes, up axis) and the worker's settings
        (device, checkpoint period, the export sizes a job does not set)."""
        from nepf_core.callbacks import FitCallbacks  # torch-free modules
        from nepf_core.pipeline import JobRequest

        s = self.settings
        return JobRequest(data_dir=self.ws.data_dir, run_dir=self.run_dir,
                          preset=cfg.get("preset") or s.default_preset, iters=cfg.get("iters"),
                          time_budget_s=cfg.get("time_budget_s"), device=s.device, resume=True,
                          callbacks=FitCallbacks(on_progress=self.on_progress, should_stop=self.should_stop,
                                                 on_checkpoint=self.ws.on_checkpoint),
                          checkpoint_every=s.checkpoint_every,
                          texture_size=cfg.get("texture_size") or s.export_texture_size,
                          mesh_resolution=s.export_mesh_resolution,
                          max_faces=cfg.get("max_faces") or s.export_max_faces,
                          max_side=s.job_max_side(cfg.get("max_image_side")),
                          holdout_every=cfg.get("holdout_every"), up_axis=cfg.get("up_axis"))

    def run(self) -> str:
        outcome = self.claim()
        if outcome != "claimed":
            log.info("job %s: %s, not running it", self.job_id, outcome)
            return outcome
        with self.Session() as s:
            job = s.get(Job, self.job_id)
            cfg = dict(job.config or {})
        self.ws.may_write = lambda: not self._lease_lost   # a worker that lost the job writes nothing more
        hb = threading.Thread(target=self._heartbeat_loop, name=f"hb-{self.job_id[:8]}", daemon=True)
        hb.start()
        try:
            status, error, result, interrupted = self._run_pipeline(cfg)
        except LeaseLost as exc:
            log.warning("%s; stopping without recording a result", exc)
            self.ws.close()
            return "lease_lost"
        finally:
            self._stop_hb.set()
            hb.join(timeout=10)
            _release_device_memory()
        try:
            self._heartbeat_once()   # last progress/decisions
        except Exception:  # noqa: BLE001
            pass
        self.ws.close()   # the background uploads stop; a scratch copy is dropped
        if interrupted or (status == "cancelled" and self._shutdown.is_set() and not self._cancel):
            return self.requeue()
        return self.finish(status, error, result)

    def _run_pipeline(self, cfg: dict) -> tuple[str, Optional[str], Optional[dict], bool]:
        """Prepare the workspace, run the pipeline, store its results: ``(status, error, result,
        interrupted)``; ``interrupted``: stopped by a worker shutdown (back to the queue)."""
        status, error, result, interrupted = "failed", None, None, False
        try:
            from nepf_core.pipeline import load_pipeline  # torch-free module

            pipeline = self._pipeline or load_pipeline(self.settings.pipeline)
            if not self.ws.prepare(self.should_stop, self._waiting_for_storage):
                return "cancelled", None, None, False        # cancelled or stopped while the store was away
            if self._notice is not None:
                self._waiting_for_storage(None)
            self._resume_step = checkpoint_step(self.run_dir) or 0
            self.run_dir.mkdir(parents=True, exist_ok=True)
            result = pipeline(self.job_request(cfg))
            status = (result or {}).get("status", "succeeded")
            if status not in ("succeeded", "cancelled", "failed"):
                status = "succeeded"
            if status == "cancelled" and self._shutdown.is_set() and not self._cancel:
                self.ws.flush(SHUTDOWN_FLUSH_S)               # its checkpoint goes back with the job
            else:
                self.ws.publish(self.settings.storage_wait_s)   # waits for an unreachable store
        except LeaseLost:
            raise
        except ShutdownRequested as exc:
            log.warning("%s", exc)
            interrupted = True
        except Exception as exc:  # noqa: BLE001 - every failure becomes a failed job with a message
            if self._shutdown.is_set():
                # a cold shutdown (SIGQUIT) raises Celery's cancellation into the pipeline: the job
                # did not fail, its worker stopped; the checkpoint is still there
                log.warning("job %s interrupted by the worker shutdown: %s", self.job_id, exc)
                interrupted = True
            else:
                log.error("job %s failed: %s", self.job_id, "".join(traceback.format_exception(exc))[-4000:])
                status, error = "failed", scrub_server_paths(human_error(exc), self.settings)
        if interrupted:
            self.ws.flush(SHUTDOWN_FLUSH_S)
        return status, error, result, interrupted

    def requeue(self) -> str:
        """Give the job back after a worker shutdown (:func:`jobstore.state.requeue`): the next
        worker resumes it from its checkpoint."""
        if not state.requeue(self.Session, self.job_id, self.worker_id):
            log.warning("job %s: lease lost before the re-queue", self.job_id)
            return "lease_lost"
        log.warning("job %s re-queued: the worker is shutting down; it resumes from its checkpoint", self.job_id)
        return "requeued"

    def finish(self, status: str, error: Optional[str], result: Optional[dict]) -> str:
        if not state.finish(self.Session, self.job_id, self.worker_id, status, outcome_values(error, result, status)):
            log.warning("job %s: lease lost before completion; result not recorded", self.job_id)
            return "lease_lost"
        log.info("job %s %s", self.job_id, status)
        return status


def outcome_values(error: Optional[str], result: Optional[dict], status: str) -> dict[str, Any]:
    """The columns a finished job gets from its pipeline's summary: the result (less the report),
    the decisions, the last step, total and wall time."""
    values: dict[str, Any] = {"error": error}
    if not result:
        return values
    values["result"] = _jsonable({k: v for k, v in result.items() if k != "report"})
    rep = result.get("report")
    if isinstance(rep, dict) and isinstance(rep.get("decisions"), list) and rep["decisions"]:
        values["decisions"] = _jsonable(rep["decisions"])
    for k in ("step", "total"):
        if isinstance(result.get(k), int):
            values[k] = result[k]
    if status == "succeeded":
        values["fraction"] = 1.0
        values["eta_s"] = 0.0
    if isinstance(result.get("wall_s"), (int, float)):
        values["wall_s"] = float(result["wall_s"])
    return values


def _release_device_memory() -> None:
    """The worker process outlives the job: hand cached GPU memory back between jobs."""
    import gc
    import sys

    gc.collect()
    torch = sys.modules.get("torch")
    try:
        if torch is not None and torch.cuda.is_available():
            torch.cuda.empty_cache()
    except Exception:  # noqa: BLE001
        pass


def _jsonable(x):
    return json.loads(json.dumps(x, default=str))
