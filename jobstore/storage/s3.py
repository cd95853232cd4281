"""The S3 backend (``NEPF_STORAGE_URL=s3://bucket/prefix``): a job's files are objects under
``prefix/jobs/<id>/dataset/`` and ``prefix/jobs/<id>/run/``; the API keeps none on its disk.

* **Upload**: the API validates the upload in its staging folder as before, then stores every file
  of the dataset (8 at a time) *before* it inserts the job row, so a job row always has a whole
  dataset; the staging folder is deleted at the end of the request.
* **Metrics**: the worker re-uploads ``run/metrics.jsonl`` whenever it grew, at most every
  ``NEPF_STORAGE_SYNC_S`` (2 s, the viewer's chart refresh is slower); the API reads it with a
  conditional GET (``If-None-Match`` on the ETag it has) and keeps the parsed line offsets of the
  last 128 files, so an unchanged file costs one 304.
* **Downloads are streamed** through the API (``Range``, ``If-Range``, ``If-None-Match``
  forwarded), not redirected: the store then need not be reachable from users' browsers (in
  docker-compose it is on the private network) nor allow their origin by CORS, the download keeps
  its ``Content-Disposition`` name, and a token that is revoked stops downloads at once. With
  ``NEPF_STORAGE_PRESIGN_DOWNLOADS=true`` the API answers 307 to a presigned GET instead (one
  object, ``NEPF_STORAGE_PRESIGN_TTL_S``, 300 s), for a public store and large files.
"""

from __future__ import annotations

import json
import threading
from collections import OrderedDict
from concurrent.futures import ThreadPoolExecutor
from datetime import timezone
from email.utils import format_datetime
from pathlib import Path
from typing import TYPE_CHECKING, Optional


from . import ArtifactRef, ObjectStream, Storage, Workspace, artifact_rel
from .bucket import CHUNK, Bucket

if TYPE_CHECKING:
    from jobstore.settings import Settings


def job_prefix(job_id: str) -> str:
    return f"jobs/{job_id}/"


class MetricsCache:
    """Parsed line offsets of recently read ``metrics.jsonl`` objects, keyed by key and ETag."""

    def __init__(self, max_files: int = 128) -> None:
        self._d: "OrderedDict[str, tuple[str, bytes, list[int]]]" = OrderedDict()
        self._lock = threading.Lock()
        self.max_files = max_files

    def read(self, bucket: Bucket, rel: str, since: int, limit: int) -> tuple[list[dict], int]:
        with self._lock:
            hit = self._d.get(rel)
        data, etag = bucket.get_bytes(rel, hit[0] if hit else None)
        if data is None and etag is None:
            return [], since
        if data is None:
            _, data, offsets = hit
        else:
            end = data.rfind(b"\n") + 1
            data = data[:end]                      # complete lines only
            offsets, pos = [0], data.find(b"\n")
            while pos >= 0:
                offsets.append(pos + 1)
                pos = data.find(b"\n", pos + 1)
            with self._lock:
                self._d[rel] = (etag, data, offsets)
                self._d.move_to_end(rel)
                while len(self._d) > self.max_files:
                    self._d.popitem(last=False)
        n = len(offsets) - 1
        if since >= n:
            return [], since
        stop = min(n, since + limit)
        out = []
        for raw in data[offsets[since]:offsets[stop]].split(b"\n")[:-1]:
            try:
                out.append(json.loads(raw.decode("utf-8")))
            except ValueError:
                out.append({"invalid": raw.decode("utf-8", "replace")})
        return out, stop


def _range(value: Optional[str], size: int) -> Optional[tuple[int, int]]:
    """One ``bytes=a-b`` / ``a-`` / ``-n`` range as ``(first, last)``; None for none or several."""
    if not value or not value.startswith("bytes=") or "," in value:
        return None
    a, _, b = value[6:].strip().partition("-")
    try:
        if a == "":
            n = int(b)
            return (max(0, size - n), size - 1) if n > 0 else (size, size)
        first = int(a)
        last = min(int(b), size - 1) if b else size - 1
    except ValueError:
        return None
    return (first, last) if first <= last or first >= size else None


class S3Storage(Storage):
    multi_machine = True

    def __init__(self, bucket: Bucket, settings: "Settings") -> None:
        self.bucket = bucket
        self.settings = settings
        self.metrics = MetricsCache()

    @classmethod
    def from_settings(cls, settings: "Settings") -> "S3Storage":
        return cls(Bucket(settings.storage_url), settings)

    def ping(self) -> None:
        self.bucket.ping()

    def put_dataset(self, job_id: str, root: Path) -> None:
        files = [p for p in sorted(root.rglob("*")) if p.is_file() and not p.is_symlink()]
        base = job_prefix(job_id) + "dataset/"
        try:
            with ThreadPoolExecutor(8) as pool:
                for f in [pool.submit(self.bucket.put_file, base + p.relative_to(root).as_posix(), p) for p in files]:
                    f.result()
        except BaseException:
            try:
                self.bucket.delete_prefix(job_prefix(job_id))
            except Exception:  # noqa: BLE001 - the store is down: nothing more to clean here
                pass
            raise

    def read_metrics(self, job_id: str, since: int, limit: int) -> tuple[list[dict], int]:
        return self.metrics.read(self.bucket, job_prefix(job_id) + "run/metrics.jsonl", since, limit)

    def read_manifest(self, job_id: str) -> Optional[dict]:
        data, _ = self.bucket.get_bytes(job_prefix(job_id) + "run/manifest.json")
        if data is None:
            return None
        try:
            man = json.loads(data.decode("utf-8"))
        except ValueError:
            return None
        return man if isinstance(man, dict) else None

    def artifact(self, job_id: str, rel: str) -> Optional[ArtifactRef]:
        if artifact_rel(rel) is None:
            return None
        key = job_prefix(job_id) + "run/" + rel
        head = self.bucket.head(key)
        if head is None:
            return None
        return ArtifactRef(open=lambda headers: self._open(key, head, headers),
                           presign=lambda ttl, disp, ctype: self.bucket.presign(key, ttl, disp, ctype))

    def _open(self, key: str, head: dict, req: dict) -> ObjectStream:
        etag, size = head.get("ETag", ""), int(head.get("ContentLength", 0))
        headers = {"ETag": etag, "Accept-Ranges": "bytes"}
        if head.get("LastModified") is not None:
            headers["Last-Modified"] = format_datetime(head["LastModified"].astimezone(timezone.utc), usegmt=True)
        if etag and req.get("if-none-match") in (etag, "*"):
            return ObjectStream(304, headers, iter(()), lambda: None)
        rng = _range(req.get("range"), size)
        if_range = req.get("if-range")
        if rng is not None and if_range and if_range not in (etag, headers.get("Last-Modified")):
            rng = None                                     # changed since: the whole object
        if rng is not None and rng[0] >= size:
            return ObjectStream(416, {**headers, "Content-Range": f"bytes */{size}"}, iter(()), lambda: None)
        kw = {"Range": f"bytes={rng[0]}-{rng[1]}"} if rng else {}
        r = self.bucket.get_stream(key, IfMatch=etag, **kw) if etag else self.bucket.get_stream(key, **kw)
        body = r["Body"]
        headers["Content-Length"] = str(r.get("ContentLength", size))
        if rng:
            headers["Content-Range"] = r.get("ContentRange") or f"bytes {rng[0]}-{rng[1]}/{size}"
        return ObjectStream(206 if rng else 200, headers, body.iter_chunks(CHUNK), body.close)

    def delete_job(self, job_id: str) -> None:
        self.bucket.delete_prefix(job_prefix(job_id))

    def workspace(self, job_id: str) -> Workspace:
        from .remote import RemoteWorkspace

        s = self.settings
        return RemoteWorkspace(self.bucket, job_prefix(job_id), s.data_path / "work" / job_id,
                               sync_s=s.storage_sync_s, wait_s=s.storage_wait_s)
