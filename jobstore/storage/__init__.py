"""Where a job's files live: the local data dir (the embedded default) or an S3-compatible bucket.

``open_storage(settings)`` picks the backend from ``NEPF_STORAGE_URL``: unset, the files stay in
``DATA_DIR/jobs/<id>/{dataset,run}`` exactly as before (:mod:`.local`); ``s3://bucket/prefix``,
they live in the bucket under ``prefix/jobs/<id>/{dataset,run}/`` (:mod:`.s3`), endpoint and
credentials from the standard ``AWS_ENDPOINT_URL``, ``AWS_ACCESS_KEY_ID``,
``AWS_SECRET_ACCESS_KEY`` and ``AWS_DEFAULT_REGION``. Nothing outside this package knows which
backend is in use: the API and the worker call the methods of :class:`Storage` and of the
:class:`Workspace` it hands a worker.

Object keys are derived from the job id (32 hex digits, made by the server) and, for an artifact,
from a path that :func:`artifact_rel` checked; never from anything else a user sends.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Callable, Iterator, Optional

if TYPE_CHECKING:   # the settings object is passed in
    from jobstore.settings import Settings

__all__ = ["Storage", "Workspace", "ArtifactRef", "ObjectStream", "StorageUnavailable", "open_storage",
           "artifact_rel", "JOB_ID", "PRIVATE_DIRS"]

JOB_ID = re.compile(r"^[0-9a-f]{32}$")
#: the run folder's sub-folder that is never served (resume state, not an asset)
PRIVATE_DIRS = ("checkpoints",)


class StorageUnavailable(RuntimeError):
    """The object store did not answer (or refused us): retryable, never the user's data's fault."""


def artifact_rel(rel: str) -> Optional[str]:
    """``rel`` when it may name an artifact of a run folder (a relative POSIX path without ``..``,
    ``.``, empty parts, backslashes or NUL, outside ``checkpoints/``); else None."""
    if not rel or "\x00" in rel or rel.startswith(("/", "\\")) or "\\" in rel:
        return None
    parts = rel.split("/")
    if any(p in ("", ".", "..") for p in parts) or parts[0] in PRIVATE_DIRS:
        return None
    return rel


@dataclass
class ObjectStream:
    """An open object: the HTTP status to answer (200, 206, 304), its headers, and the body."""

    status: int
    headers: dict
    chunks: Iterator[bytes]
    close: Callable[[], None]


@dataclass
class ArtifactRef:
    """One artifact the API may serve: a local file (``path``) or an object (``open``/``presign``)."""

    path: Optional[Path] = None
    open: Optional[Callable[[dict], ObjectStream]] = None          # request headers -> stream
    presign: Optional[Callable[[int, str, str], str]] = None       # (ttl_s, disposition, type) -> URL


class Workspace:
    """A worker's view of one job: local ``data_dir`` and ``run_dir`` to train in, and the hooks
    that move files to and from the store. Every hook is a no-op for the local backend."""

    data_dir: Path
    run_dir: Path
    #: the runner sets it: False once this worker lost the job's lease (it must store nothing more)
    may_write: Callable[[], bool] = staticmethod(lambda: True)

    def checkpoint_step(self) -> Optional[int]:
        """The step of the job's last stored checkpoint (None: none, or unknown yet)."""
        raise NotImplementedError

    def prepare(self, should_stop: Callable[[], bool], on_wait: Callable[[str], None]) -> bool:
        """Bring the dataset and the last checkpoint into ``data_dir``/``run_dir``. While the store
        is unreachable, call ``on_wait(reason)`` and retry, up to ``NEPF_STORAGE_WAIT_S``, then raise
        :class:`StorageUnavailable`. False when ``should_stop()`` became true meanwhile."""
        return True

    def on_checkpoint(self, step: int, path: str) -> None:
        """The pipeline wrote a checkpoint: keep it for another worker (uploaded in the background)."""

    def publish(self, timeout_s: float) -> None:
        """Upload the run folder's results (artifacts, manifest last); retries while the store is
        unreachable for up to ``timeout_s``, then raises :class:`StorageUnavailable`."""

    def flush(self, timeout_s: float) -> bool:
        """Wait until the last checkpoint is stored (True) or ``timeout_s`` passed (False)."""
        return True

    def close(self, keep_files: bool = True) -> None:
        """Stop the background uploads and drop local scratch files (not the local backend's)."""


class Storage:
    """Job files for the API (dataset in, artifacts and metrics out) and workspaces for workers."""

    #: True when every machine reaches the job files (API processes on several machines, workers
    #: elsewhere): then nothing per-machine may hold shared state, such as the ticket signing key
    multi_machine: bool = False

    def setup(self) -> None:
        """Create what the backend needs on this machine; the API calls it once at start."""

    def ping(self) -> None:
        """Raise when the store cannot be used (``/readyz``)."""

    def put_dataset(self, job_id: str, root: Path) -> None:
        """Store the validated dataset folder ``root`` as job ``job_id``'s dataset (``root`` may be
        moved or left for the caller to delete)."""
        raise NotImplementedError

    def read_metrics(self, job_id: str, since: int, limit: int) -> tuple[list[dict], int]:
        """Records ``since .. since+limit`` of the run's ``metrics.jsonl`` and the next cursor."""
        raise NotImplementedError

    def read_manifest(self, job_id: str) -> Optional[dict]:
        raise NotImplementedError

    def artifact(self, job_id: str, rel: str) -> Optional[ArtifactRef]:
        """The artifact ``rel`` of the run folder (None: no such file, or a path never served)."""
        raise NotImplementedError

    def delete_job(self, job_id: str) -> None:
        raise NotImplementedError

    def workspace(self, job_id: str) -> Workspace:
        raise NotImplementedError


def open_storage(settings: "Settings") -> Storage:
    """The backend ``NEPF_STORAGE_URL`` names (unset: the local data dir)."""
    if settings.storage_url:
        from .s3 import S3Storage

        return S3Storage.from_settings(settings)
    from .local import LocalStorage

    return LocalStorage(settings.jobs_path)
