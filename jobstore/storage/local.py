"""The embedded default: a job's files in ``DATA_DIR/jobs/<id>/dataset`` and ``.../run``, shared by
the API and the worker (one machine, or a shared filesystem). Behaves exactly as NePF did before
the storage layer existed."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path
from typing import Optional

from . import PRIVATE_DIRS, ArtifactRef, Storage, Workspace, artifact_rel
from .metrics_index import METRICS


def safe_artifact_path(base: Path, rel: str) -> Optional[Path]:
    """``base/rel`` if it is a regular file inside ``base`` and outside ``checkpoints/``; else None.

    Both tests are made on the path with every link resolved, not on the path as written: a
    link inside the run folder (``x.pt -> checkpoints/latest.pt``) must not serve what its target
    would not (issue 37). The written form is checked too, so a 404 does not depend on whether
    the file exists."""
    if artifact_rel(rel) is None:
        return None
    try:
        root = base.resolve(strict=True)
        target = (base / rel).resolve(strict=True)
    except (OSError, RuntimeError, ValueError):
        return None
    if root not in target.parents or not target.is_file():
        return None
    if target.relative_to(root).parts[0] in PRIVATE_DIRS:
        return None
    return target


class LocalWorkspace(Workspace):
    def __init__(self, job_dir: Path) -> None:
        self.data_dir = job_dir / "dataset"
        self.run_dir = job_dir / "run"

    def checkpoint_step(self) -> Optional[int]:
        from nepf_core.resume import checkpoint_step   # stdlib only; the API never calls this

        return checkpoint_step(self.run_dir)


class LocalStorage(Storage):
    multi_machine = False

    def __init__(self, jobs_path: Path) -> None:
        self.jobs_path = Path(jobs_path)

    def setup(self) -> None:
        self.jobs_path.mkdir(parents=True, exist_ok=True)

    def put_dataset(self, job_id: str, root: Path) -> None:
        job_dir = self.jobs_path / job_id
        job_dir.mkdir(parents=True)
        os.rename(root, job_dir / "dataset")
        (job_dir / "run").mkdir()

    def read_metrics(self, job_id: str, since: int, limit: int) -> tuple[list[dict], int]:
        return METRICS.read(self.jobs_path / job_id / "run" / "metrics.jsonl", since, limit)

    def read_manifest(self, job_id: str) -> Optional[dict]:
        try:
            data = json.loads((self.jobs_path / job_id / "run" / "manifest.json").read_text())
            return data if isinstance(data, dict) else None
        except (FileNotFoundError, json.JSONDecodeError, UnicodeDecodeError):
            return None

    def artifact(self, job_id: str, rel: str) -> Optional[ArtifactRef]:
        target = safe_artifact_path(self.jobs_path / job_id / "run", rel)
        return None if target is None else ArtifactRef(path=target)

    def delete_job(self, job_id: str) -> None:
        shutil.rmtree(self.jobs_path / job_id, ignore_errors=True)

    def workspace(self, job_id: str) -> Workspace:
        return LocalWorkspace(self.jobs_path / job_id)
