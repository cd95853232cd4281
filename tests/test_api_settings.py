"""Settings, docker-compose.yml and Dockerfile read against each other (Docker cannot run here)."""

from __future__ import annotations

import os
import re
import shlex
from pathlib import Path

import pytest
import yaml

from api.commands import serve_parser
from api.settings import Settings
from worker.commands import worker_parser

REPO = Path(__file__).resolve().parent.parent
FIELDS = {f"NEPF_{name.upper()}" for name in Settings.model_fields}


def compose() -> dict:
    return yaml.safe_load((REPO / "docker-compose.yml").read_text())


def dockerfile_env() -> dict:
    text = (REPO / "Dockerfile").read_text().replace("\\\n", " ")
    env = {}
    for line in text.splitlines():
        if line.strip().startswith("ENV "):
            for tok in shlex.split(line.strip()[4:]):
                k, _, v = tok.partition("=")
                env[k] = v
    return env


def test_every_nepf_variable_set_is_a_setting():
    seen = set()
    for name, svc in compose()["services"].items():
        for k in (svc.get("environment") or {}):
            if k.startswith("NEPF_"):
                seen.add(k)
                assert k in FIELDS, f"{name}: {k} is not a Settings field"
    for k in dockerfile_env():
        if k.startswith("NEPF_"):
            seen.add(k)
            assert k in FIELDS, f"Dockerfile: {k} is not a Settings field"
    assert {"NEPF_DATA_DIR", "NEPF_BROKER_URL", "NEPF_DATABASE_URL"} <= seen


def test_settings_documented():
    doc = (REPO / "docs" / "SERVICE.md").read_text()
    missing = sorted(f for f in FIELDS if f not in doc)
    assert not missing, f"undocumented settings: {missing}"


def test_compose_values_parse_as_settings(monkeypatch):
    for name in ("api", "worker"):
        env = compose()["services"][name]["environment"]
        for k, v in env.items():
            # ${VAR:-default} / ${VAR-default} -> default; ${VAR:?message} (required) -> a value
            v = re.sub(r"\$\{[A-Z_]+:\?[^}]*\}", "set-by-the-user", str(v))
            monkeypatch.setenv(k, re.sub(r"\$\{[A-Z_]+:?-([^}]*)\}", r"\1", v))
        s = Settings()
        assert str(s.data_dir) == "/data" and s.broker_url == "redis://redis:6379/0"
        # no shared disk: the jobs in PostgreSQL, the files in the bucket, the signing key given
        assert not s.embedded and s.db_url.startswith("postgresql+psycopg://")
        assert s.storage_url == "s3://nepf/jobs" and s.secret_key
        assert os.environ["AWS_ENDPOINT_URL"] == "http://seaweedfs:8333"
        assert s.visibility_timeout_s >= 24 * 3600


def test_compose_services_and_commands():
    c = compose()
    svcs = c["services"]
    assert {"redis", "api", "worker", "postgres", "seaweedfs"} <= set(svcs)
    assert "profiles" not in svcs["postgres"]                         # the shared job store
    assert set(c["volumes"]) >= {"api-data", "worker-data", "seaweedfs-data", "redis-data", "pg-data"}
    assert svcs["api"]["volumes"] == ["api-data:/data"] and svcs["worker"]["volumes"] == ["worker-data:/data"]
    weed = svcs["seaweedfs"]["command"]
    assert weed[0] == "mini" and "-master.telemetry=false" in weed and "-bucket=nepf" in weed
    for name in ("api", "worker"):
        assert svcs[name]["depends_on"]["redis"]["condition"] == "service_healthy"
        assert svcs[name]["depends_on"]["seaweedfs"]["condition"] == "service_healthy"
    api_cmd, worker_cmd = svcs["api"]["command"], svcs["worker"]["command"]
    assert api_cmd[:2] == ["nepf", "serve"] and worker_cmd[:2] == ["nepf", "worker"]
    a = serve_parser().parse_args(api_cmd[2:])
    assert a.host == "0.0.0.0" and f"{a.port}:{a.port}" in svcs["api"]["ports"]
    w = worker_parser().parse_args(worker_cmd[2:])
    assert set(w.queues.split(",")) == {"default", "gpu"} and w.concurrency == 1
    # GPU reservation is present (commented in) for the worker
    text = (REPO / "docker-compose.yml").read_text()
    assert re.search(r"#\s+deploy:\s*\n(\s*#.*\n)*?\s*#\s+- driver: nvidia", text)
    assert svcs["redis"]["image"].startswith("redis:7")


def test_dockerfile_copies_what_exists_and_ignores_local_state():
    text = (REPO / "Dockerfile").read_text()
    for src in re.findall(r"^COPY (?!--from)(\S+)", text, re.M):
        assert (REPO / src).exists(), f"COPY {src}: missing"
    assert "CMD [\"nepf\", \"serve\"" in text and "EXPOSE 8000" in text
    assert dockerfile_env()["NEPF_DATA_DIR"] == "/data"
    ignore = (REPO / ".dockerignore").read_text().split()
    for must in ("web/node_modules", "nepf-data", ".git"):
        assert must in ignore
    # the console script the commands use exists
    assert 'nepf = "nepf_core.cli:main"' in (REPO / "pyproject.toml").read_text()


@pytest.mark.parametrize("url", ["redis://redis:6379/0", None])
def test_broker_selection(url, monkeypatch, tmp_path):
    monkeypatch.setenv("NEPF_DATA_DIR", str(tmp_path))
    if url:
        monkeypatch.setenv("NEPF_BROKER_URL", url)
    else:
        monkeypatch.delenv("NEPF_BROKER_URL", raising=False)
    s = Settings()
    if url:
        assert s.effective_broker_url == url and not s.embedded
    else:
        assert s.embedded and s.effective_broker_url == f"nepfsqla+sqlite:///{tmp_path.resolve()}/broker.sqlite3"


def test_nepf_cli_forwards_compose_commands_unchanged():
    """`nepf serve --host ...` / `nepf worker --queues ...` (the compose commands) must reach
    serve_main / worker_main with their options intact."""
    import nepf_core.cli as cli

    seen = []
    orig = cli._delegate
    try:
        cli._delegate = lambda mod, fn, argv: seen.append((mod, fn, list(argv))) or 0
        for name, target in (("api", ("api.commands", "serve_main")), ("worker", ("worker.commands", "worker_main"))):
            cmd = compose()["services"][name]["command"]
            assert cli.main(cmd[1:]) == 0
            assert seen[-1] == (*target, cmd[2:]), (cmd, seen[-1])
    finally:
        cli._delegate = orig


@pytest.mark.parametrize("version,ok", [("7.0.15", True), ("6.2.0", True), ("6.0.9", False), ("5.0.7", False)])
def test_redis_version_floor(version, ok):
    from jobstore.queue import check_redis_version

    if ok:
        check_redis_version(version)
    else:
        with pytest.raises(RuntimeError, match="needs Redis >= 6.2"):
            check_redis_version(version)
