"""A thin boto3 wrapper over one bucket and key prefix: the object operations the backends use,
with every store failure turned into :class:`StorageUnavailable` (a message that names the
endpoint and the error, never a stack trace).

Why boto3: it is the reference S3 client, used against AWS, MinIO, SeaweedFS, R2 and Ceph alike;
it reads the standard ``AWS_*`` variables and the rest of the AWS credential chain (instance roles),
signs presigned URLs, and its transfer manager does multipart uploads of large checkpoints. obstore
is younger, and s3fs pins aiobotocore to narrow botocore ranges (a frequent resolver conflict).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Iterator, Optional
from urllib.parse import urlparse

import boto3
from boto3.exceptions import Boto3Error
from botocore.config import Config
from botocore.exceptions import BotoCoreError, ClientError

from . import StorageUnavailable

CHUNK = 1 << 20


def parse_storage_url(url: str) -> tuple[str, str]:
    """``s3://bucket/some/prefix`` -> ``("bucket", "some/prefix/")`` (prefix "" when none)."""
    u = urlparse(url)
    if u.scheme != "s3" or not u.netloc:
        raise ValueError(f"NEPF_STORAGE_URL={url!r}: expected s3://bucket[/prefix]")
    prefix = u.path.strip("/")
    return u.netloc, (prefix + "/" if prefix else "")


def not_found(exc: ClientError) -> bool:
    code = str(exc.response.get("Error", {}).get("Code", ""))
    return code in ("404", "NoSuchKey", "NotFound")


class Bucket:
    """Objects under ``s3://bucket/prefix``; keys passed in are relative to the prefix."""

    def __init__(self, url: str, *, connect_timeout: float = 5.0, read_timeout: float = 60.0) -> None:
        self.url = url
        self.bucket, self.prefix = parse_storage_url(url)
        endpoint = os.environ.get("AWS_ENDPOINT_URL_S3") or os.environ.get("AWS_ENDPOINT_URL")
        self.where = f"{url} ({endpoint or 'AWS S3'})"
        cfg = Config(connect_timeout=connect_timeout, read_timeout=read_timeout, signature_version="s3v4",
                     retries={"max_attempts": 3, "mode": "standard"},
                     s3={"addressing_style": "path" if endpoint else "auto"},
                     # checksums only where S3 requires them: S3-compatible stores differ in which of
                     # the newer flexible checksums (botocore >= 1.36's default) they accept
                     request_checksum_calculation="when_required",
                     response_checksum_validation="when_required",
                     max_pool_connections=32)
        self.client = boto3.session.Session().client("s3", endpoint_url=endpoint or None, config=cfg)

    def key(self, rel: str) -> str:
        return self.prefix + rel

    def error(self, exc: Exception, what: str) -> StorageUnavailable:
        if isinstance(exc, ClientError):
            err = exc.response.get("Error", {})
            detail = f"{err.get('Code', '?')}: {err.get('Message', '')}".strip()
        else:
            detail = f"{type(exc).__name__}: {exc}"
        return StorageUnavailable(f"object store {self.where} failed to {what}: {detail}"[:500])

    # ------------------------------------------------------------------ operations
    def ping(self) -> None:
        try:
            self.client.head_bucket(Bucket=self.bucket)
        except (BotoCoreError, ClientError) as exc:
            raise self.error(exc, "answer") from None

    def put_file(self, rel: str, path: Path) -> None:
        try:
            self.client.upload_file(str(path), self.bucket, self.key(rel))
        except (BotoCoreError, ClientError, Boto3Error) as exc:   # S3UploadFailedError wraps ClientError
            raise self.error(exc, f"store {rel}") from None

    def put_bytes(self, rel: str, data: bytes, content_type: str = "application/octet-stream") -> None:
        try:
            self.client.put_object(Bucket=self.bucket, Key=self.key(rel), Body=data, ContentType=content_type)
        except (BotoCoreError, ClientError) as exc:
            raise self.error(exc, f"store {rel}") from None

    def get_bytes(self, rel: str, etag: Optional[str] = None) -> tuple[Optional[bytes], Optional[str]]:
        """``(data, etag)``; ``(None, None)`` when missing; ``(None, etag)`` when unchanged since ``etag``."""
        kw = {"IfNoneMatch": etag} if etag else {}
        try:
            r = self.client.get_object(Bucket=self.bucket, Key=self.key(rel), **kw)
            with r["Body"] as body:
                return body.read(), r.get("ETag")
        except ClientError as exc:
            code = str(exc.response.get("Error", {}).get("Code", ""))
            if code in ("304", "NotModified"):
                return None, etag
            if not_found(exc):
                return None, None
            raise self.error(exc, f"read {rel}") from None
        except BotoCoreError as exc:
            raise self.error(exc, f"read {rel}") from None

    def head(self, rel: str) -> Optional[dict]:
        try:
            return self.client.head_object(Bucket=self.bucket, Key=self.key(rel))
        except ClientError as exc:
            if not_found(exc):
                return None
            raise self.error(exc, f"read {rel}") from None
        except BotoCoreError as exc:
            raise self.error(exc, f"read {rel}") from None

    def get_stream(self, rel: str, **kw) -> dict:
        """``get_object`` (``Range``, ``IfNoneMatch``...); its ``Body`` is read by the caller."""
        try:
            return self.client.get_object(Bucket=self.bucket, Key=self.key(rel), **kw)
        except (BotoCoreError, ClientError) as exc:
            raise self.error(exc, f"read {rel}") from None

    def list(self, rel_prefix: str) -> Iterator[tuple[str, int]]:
        """``(key relative to rel_prefix, size)`` of every object under ``rel_prefix``."""
        full = self.key(rel_prefix)
        try:
            for page in self.client.get_paginator("list_objects_v2").paginate(Bucket=self.bucket, Prefix=full):
                for obj in page.get("Contents", []) or []:
                    yield obj["Key"][len(full):], int(obj.get("Size", 0))
        except (BotoCoreError, ClientError) as exc:
            raise self.error(exc, f"list {rel_prefix}") from None

    def download(self, rel: str, dest: Path) -> None:
        dest.parent.mkdir(parents=True, exist_ok=True)
        tmp = dest.with_name(dest.name + ".part")
        try:
            self.client.download_file(self.bucket, self.key(rel), str(tmp))
        except (BotoCoreError, ClientError) as exc:
            raise self.error(exc, f"read {rel}") from None
        os.replace(tmp, dest)

    def delete_prefix(self, rel_prefix: str) -> int:
        keys = [self.key(rel_prefix + k) for k, _ in self.list(rel_prefix)]
        for i in range(0, len(keys), 1000):
            try:
                self.client.delete_objects(Bucket=self.bucket, Delete={
                    "Objects": [{"Key": k} for k in keys[i:i + 1000]], "Quiet": True})
            except (BotoCoreError, ClientError) as exc:
                raise self.error(exc, f"delete {rel_prefix}") from None
        return len(keys)

    def presign(self, rel: str, ttl_s: int, disposition: str, content_type: str) -> str:
        return self.client.generate_presigned_url(
            "get_object", ExpiresIn=int(ttl_s),
            Params={"Bucket": self.bucket, "Key": self.key(rel), "ResponseContentDisposition": disposition,
                    "ResponseContentType": content_type})
