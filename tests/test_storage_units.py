"""The storage layer's pure parts: which artifact paths may name an object, the one-range parser of
streamed downloads, the storage URL, backend selection and the shared-secret rule. The S3 backend
itself is tested against a real SeaweedFS server in tests/test_service_object_store.py."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest
from pydantic import ValidationError

from api.service import StartupError, check_secret
from jobstore.settings import Settings
from jobstore.storage import artifact_rel, open_storage
from jobstore.storage.bucket import parse_storage_url
from jobstore.storage.local import LocalStorage
from jobstore.storage.s3 import _range


@pytest.mark.parametrize("rel,ok", [
    ("asset.glb", True), ("textures/orm.png", True), ("previews/view_000.png", True),
    ("checkpoints/latest.pt", False), ("checkpoints", False), ("../dataset/cameras.npz", False),
    ("a/../b", False), ("/etc/passwd", False), ("a//b", False), ("./a", False), ("a\\b", False),
    ("a\x00b", False), ("", False)])
def test_artifact_paths(rel, ok):
    assert (artifact_rel(rel) is not None) == ok


@pytest.mark.parametrize("header,size,want", [
    ("bytes=0-3", 10, (0, 3)), ("bytes=5-", 10, (5, 9)), ("bytes=-4", 10, (6, 9)), ("bytes=8-100", 10, (8, 9)),
    ("bytes=10-12", 10, (10, 9)),          # past the end: the caller answers 416
    ("bytes=0-1,4-5", 10, None),           # several ranges: the whole file (RFC 9110 allows it)
    ("bytes=x-3", 10, None), (None, 10, None), ("items=0-1", 10, None), ("bytes=5-3", 10, None)])
def test_single_range(header, size, want):
    assert _range(header, size) == want


def test_storage_url():
    assert parse_storage_url("s3://bucket") == ("bucket", "")
    assert parse_storage_url("s3://bucket/a/b/") == ("bucket", "a/b/")
    with pytest.raises(ValueError):
        parse_storage_url("http://bucket/x")
    with pytest.raises(ValidationError):
        Settings(storage_url="gs://bucket/x")


def test_default_backend_is_the_data_dir_and_needs_no_secret(tmp_path):
    s = Settings(data_dir=tmp_path)
    storage = open_storage(s)
    assert isinstance(storage, LocalStorage) and not storage.multi_machine
    check_secret(s, storage)                                  # embedded default: nothing required
    ws = storage.workspace("0" * 32)
    assert ws.run_dir == s.jobs_path / ("0" * 32) / "run" and ws.data_dir == s.jobs_path / ("0" * 32) / "dataset"


def test_object_store_needs_a_shared_secret(tmp_path, monkeypatch):
    monkeypatch.setenv("AWS_ENDPOINT_URL", "http://127.0.0.1:9")
    s = Settings(data_dir=tmp_path, storage_url="s3://bucket/prefix")
    storage = open_storage(s)
    assert storage.multi_machine
    with pytest.raises(StartupError, match="NEPF_SECRET_KEY"):
        check_secret(s, storage)
    check_secret(Settings(data_dir=tmp_path, storage_url="s3://bucket/prefix", secret_key="k"), storage)


REPO = Path(__file__).resolve().parent.parent
#: what names a backend: its modules and its client library
BACKEND_MODULES = ("jobstore.storage.local", "jobstore.storage.s3", "jobstore.storage.bucket",
                   "jobstore.storage.remote", "boto3", "botocore")


def test_only_the_storage_package_names_a_backend():
    """The API, the worker and the rest of the job store import ``jobstore.storage`` alone (the
    interface): none imports a backend module or the S3 client."""
    offenders = []
    for path in [*(REPO / "api").rglob("*.py"), *(REPO / "worker").rglob("*.py"), *(REPO / "jobstore").glob("*.py")]:
        for node in ast.walk(ast.parse(path.read_text())):
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else \
                [node.module or ""] if isinstance(node, ast.ImportFrom) else []
            offenders += [f"{path.relative_to(REPO)}: {n}" for n in names if n.startswith(BACKEND_MODULES)]
    assert offenders == []


def test_the_embedded_default_needs_no_s3_client(tmp_path):
    """Without NEPF_STORAGE_URL the API app and a worker's workspace come up without boto3 imported."""
    code = ("import sys; from jobstore.settings import Settings; from api.main import create_app; "
            f"s = Settings(data_dir={str(tmp_path)!r}); create_app(s, reconciler=False); "
            "from jobstore.storage import open_storage; open_storage(s).workspace('0' * 32).checkpoint_step(); "
            "print(sorted(m for m in sys.modules if m.split('.')[0] in ('boto3', 'botocore')))")
    env = {"PATH": "/usr/bin:/bin", "HOME": str(tmp_path)}
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, env=env, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"
