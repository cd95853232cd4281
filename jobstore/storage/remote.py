"""A worker's scratch copy of a job whose files live in the object store.

* :meth:`RemoteWorkspace.prepare` downloads the dataset and the last checkpoint
  (``run/checkpoints/latest.{pt,json}``, ``run/metrics.jsonl``) into ``DATA_DIR/work/<id>/``.
* Each checkpoint the pipeline reports (``FitCallbacks.on_checkpoint``) is *snapshotted* at once
  (a hard link of ``latest.pt``, which the core replaces by rename, and copies of ``latest.json``
  and ``metrics.jsonl``: a consistent set) and uploaded by a background thread in the order
  metrics, ``latest.pt``, ``latest.json``; ``latest.json`` is the commit mark another worker
  resumes from. Training never waits for the store: a newer snapshot replaces one not yet sent.
* The same thread re-uploads the files the viewer reads while a job trains (:data:`LIVE_FILES`:
  ``metrics.jsonl``, the held-out picture ``holdout/latest.png``) when they changed, every
  ``NEPF_STORAGE_SYNC_S``.
* :meth:`publish` uploads the results once training ends (``manifest.json`` last, so the API
  never lists an artifact that is not there yet).

Faults: at the start the workspace *waits* for an unreachable store (``on_wait`` tells the
runner, which shows ``stage: "waiting_for_storage"``), up to ``NEPF_STORAGE_WAIT_S``; mid-job,
training goes on and the uploads are retried with back-off until the store returns; the job
ends only once its results are stored (waiting up to ``NEPF_STORAGE_WAIT_S`` again).
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Callable, Optional

from . import StorageUnavailable, Workspace
from .bucket import Bucket

log = logging.getLogger("nepf.storage")
CHECKPOINT_FILES = ("latest.pt", "latest.json")
#: run files the viewer shows while the job trains: uploaded whenever they change (both are
#: written by replacing the file, or appended by whole lines)
LIVE_FILES = {"metrics.jsonl": "application/x-ndjson", "holdout/latest.png": "image/png"}


def _safe_rel(rel: str) -> bool:
    parts = rel.split("/")
    return bool(rel) and "\\" not in rel and "\x00" not in rel and not any(p in ("", ".", "..") for p in parts)


def _link_or_copy(src: Path, dst: Path) -> None:
    try:
        os.link(src, dst)
    except OSError:
        shutil.copy2(src, dst)


class RemoteWorkspace(Workspace):
    def __init__(self, bucket: Bucket, prefix: str, scratch: Path, *, sync_s: float, wait_s: float) -> None:
        self.bucket, self.prefix, self.scratch = bucket, prefix, Path(scratch)
        self.data_dir, self.run_dir = self.scratch / "dataset", self.scratch / "run"
        self.sync_s, self.wait_s = float(sync_s), float(wait_s)
        self.may_write: Callable[[], bool] = lambda: True   # the runner: False once the lease is lost
        self.last_error: Optional[str] = None
        self._cv = threading.Condition()
        self._pending: Optional[Path] = None     # a snapshot waiting for upload
        self._busy = False
        self._closed = False
        self._seq = 0
        self._live_sig: dict[str, Optional[tuple]] = {}
        self._thread: Optional[threading.Thread] = None

    # ------------------------------------------------------------------ start
    def checkpoint_step(self) -> Optional[int]:
        try:
            data, _ = self.bucket.get_bytes(self.prefix + "run/checkpoints/latest.json")
            step = json.loads(data)["step"] if data else None
        except (StorageUnavailable, ValueError, KeyError, TypeError):
            return None
        return step if isinstance(step, int) and step >= 0 else None

    def prepare(self, should_stop: Callable[[], bool], on_wait: Callable[[str], None]) -> bool:
        deadline, delay = time.monotonic() + self.wait_s, 1.0
        while True:
            if should_stop():
                return False
            try:
                self._download()
                break
            except StorageUnavailable as exc:
                if time.monotonic() > deadline:
                    raise StorageUnavailable(f"{exc}; gave up after {self.wait_s:g} s (NEPF_STORAGE_WAIT_S)") from None
                log.warning("waiting for the object store: %s", exc)
                on_wait(str(exc))
                end = time.monotonic() + delay
                while time.monotonic() < end and not should_stop():
                    time.sleep(0.2)
                delay = min(delay * 2, 15.0)
        self._thread = threading.Thread(target=self._loop, name="nepf-uploads", daemon=True)
        self._thread.start()
        return True

    def _download(self) -> None:
        shutil.rmtree(self.scratch, ignore_errors=True)
        self.data_dir.mkdir(parents=True)
        self.run_dir.mkdir(parents=True)
        wanted = [("dataset/" + rel, self.data_dir / rel) for rel, _ in self.bucket.list(self.prefix + "dataset/")
                  if _safe_rel(rel)]
        if not wanted:
            raise FileNotFoundError(f"the job's dataset is not in the object store ({self.bucket.url}, "
                                    f"{self.prefix}dataset/); it was deleted or never stored")
        for rel, _ in self.bucket.list(self.prefix + "run/"):
            if _safe_rel(rel) and (not rel.startswith("checkpoints/") or rel[12:] in CHECKPOINT_FILES):
                wanted.append(("run/" + rel, self.run_dir / rel))
        with ThreadPoolExecutor(8) as pool:
            for f in [pool.submit(self.bucket.download, self.prefix + rel, dest) for rel, dest in wanted]:
                f.result()
        self._live_sig = {rel: self._sig(self.run_dir / rel) for rel in LIVE_FILES}   # stored already

    # ------------------------------------------------------------------ during the run
    def on_checkpoint(self, step: int, path: str) -> None:
        try:
            self._snapshot()
        except OSError as exc:   # a full scratch disk must not fail the training: the next one may pass
            log.warning("checkpoint %s not kept for upload: %s", step, exc)

    def _snapshot(self) -> None:
        ck = self.run_dir / "checkpoints"
        self._seq += 1
        snap = self.scratch / f"snapshot-{self._seq}"
        snap.mkdir(parents=True)
        for name in CHECKPOINT_FILES:
            if (ck / name).exists():
                _link_or_copy(ck / name, snap / name)
        if (self.run_dir / "metrics.jsonl").exists():
            shutil.copyfile(self.run_dir / "metrics.jsonl", snap / "metrics.jsonl")
        with self._cv:
            old, self._pending = self._pending, snap
            self._cv.notify_all()
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)

    @staticmethod
    def _sig(path: Path) -> Optional[tuple]:
        try:
            st = path.stat()
        except FileNotFoundError:
            return None
        return st.st_size, st.st_mtime_ns, st.st_ino

    def _upload_snapshot(self, snap: Path) -> None:
        for name, rel in (("metrics.jsonl", "run/metrics.jsonl"), ("latest.pt", "run/checkpoints/latest.pt"),
                          ("latest.json", "run/checkpoints/latest.json")):
            if (snap / name).exists() and self.may_write():
                self.bucket.put_file(self.prefix + rel, snap / name)
        self._live_sig.pop("metrics.jsonl", None)   # the snapshot's is older than the live file: send it again

    def _sync_live(self) -> None:
        for rel, ctype in LIVE_FILES.items():
            path = self.run_dir / rel
            sig = self._sig(path)
            if sig is None or sig == self._live_sig.get(rel) or not self.may_write():
                continue
            data = path.read_bytes()
            if rel.endswith(".jsonl"):
                data = data[:data.rfind(b"\n") + 1]     # complete records only
            self.bucket.put_bytes(self.prefix + "run/" + rel, data, ctype)
            self._live_sig[rel] = sig

    def _loop(self) -> None:
        backoff = 1.0
        while True:
            with self._cv:
                if self._pending is None and not self._closed:
                    self._cv.wait(self.sync_s)
                if self._closed:
                    return
                snap, self._pending = self._pending, None
                self._busy = True
            try:
                if snap is not None:
                    self._upload_snapshot(snap)
                    shutil.rmtree(snap, ignore_errors=True)
                    snap = None
                self._sync_live()
                self.last_error, backoff = None, 1.0
            except StorageUnavailable as exc:
                if self.last_error is None:
                    log.warning("object store unreachable; training goes on, uploads are retried: %s", exc)
                self.last_error = str(exc)
            except OSError as exc:      # a local file vanished under us (a new snapshot): next round
                log.warning("upload skipped: %s", exc)
            finally:
                with self._cv:
                    if snap is not None:            # not sent: keep it unless a newer one came
                        if self._pending is None:
                            self._pending = snap
                        else:
                            shutil.rmtree(snap, ignore_errors=True)
                    self._busy = False
                    self._cv.notify_all()
            if self.last_error is not None:
                with self._cv:
                    self._cv.wait_for(lambda: self._closed, backoff)
                backoff = min(backoff * 2, 15.0)

    def flush(self, timeout_s: float) -> bool:
        if self._thread is None:
            return True
        with self._cv:
            self._cv.notify_all()
            return self._cv.wait_for(lambda: self._pending is None and not self._busy, timeout_s)

    # ------------------------------------------------------------------ the end
    def publish(self, timeout_s: float) -> None:
        deadline = time.monotonic() + timeout_s
        if not self.flush(timeout_s):
            raise StorageUnavailable(f"{self.last_error or 'the object store did not answer'}; the last "
                                     f"checkpoint could not be stored in {timeout_s:g} s (NEPF_STORAGE_WAIT_S)")
        self._stop_thread()
        files = sorted((p.relative_to(self.run_dir).as_posix() for p in self.run_dir.rglob("*")
                        if p.is_file() and not p.is_symlink()), key=lambda r: r == "manifest.json")
        todo = [r for r in files if not r.startswith("checkpoints/") and not r.endswith((".tmp", ".part"))]
        delay = 1.0
        while todo:
            try:
                while todo and self.may_write():
                    self.bucket.put_file(self.prefix + "run/" + todo[0], self.run_dir / todo[0])
                    todo.pop(0)
                return
            except StorageUnavailable as exc:
                if time.monotonic() + delay > deadline:
                    raise StorageUnavailable(f"{exc}; the results could not be stored in {timeout_s:g} s "
                                             "(NEPF_STORAGE_WAIT_S)") from None
                log.warning("waiting for the object store to store the results: %s", exc)
                time.sleep(delay)
                delay = min(delay * 2, 15.0)

    def _stop_thread(self) -> None:
        with self._cv:
            self._closed = True
            self._cv.notify_all()
        if self._thread is not None:
            self._thread.join(timeout=60)
            self._thread = None

    def close(self, keep_files: bool = False) -> None:
        self._stop_thread()
        if not keep_files:
            shutil.rmtree(self.scratch, ignore_errors=True)
