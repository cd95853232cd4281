"""schemathesis against /openapi.json with a valid token: no 5xx on any operation."""

from __future__ import annotations

import os
import random

import pytest
import schemathesis
from fastapi.testclient import TestClient
from hypothesis import HealthCheck, given, settings
from schemathesis.checks import not_a_server_error
from sqlalchemy import update

from api.auth import create_token
from api.main import create_app
from api.settings import Settings
from jobstore.engine import dispose_engines
from jobstore.models import Job
from service_fixtures import dataset_zip_bytes

STATE: dict = {}


@pytest.fixture(scope="module")
def api_schema(tmp_path_factory):
    saved = {k: os.environ.pop(k) for k in list(os.environ) if k.startswith("NEPF_")}
    tmp = tmp_path_factory.mktemp("schemathesis")
    app = create_app(Settings(data_dir=tmp / "data", reconcile_interval_s=0))
    svc = app.state.service
    token = create_token(svc.Session, "fuzzer")
    with TestClient(app) as c:
        r = c.post("/jobs", headers={"Authorization": f"Bearer {token}"},
                   files={"dataset": ("d.zip", dataset_zip_bytes(tmp), "application/zip")})
        assert r.status_code == 202, r.text
    job_id = r.json()["id"]
    with svc.Session() as s:   # finished, so that its event stream ends
        s.execute(update(Job).where(Job.id == job_id).values(status="succeeded"))
        s.commit()
    STATE.update(token=token, job_id=job_id)
    yield schemathesis.openapi.from_asgi("/openapi.json", app)
    dispose_engines()
    os.environ.update(saved)


def _check_operation(operation) -> int:
    """Run up to 20 generated cases of one operation; return how many ran."""
    ran = []

    @given(case=operation.as_strategy())
    @settings(max_examples=20, deadline=None, suppress_health_check=list(HealthCheck), database=None)
    def run(case):
        if "job_id" in (case.path_parameters or {}) and random.random() < 0.5:
            case.path_parameters["job_id"] = STATE["job_id"]   # also hit an existing job, not only 404s
        response = case.call(headers={"Authorization": f"Bearer {STATE['token']}"})
        case.validate_response(response, checks=(not_a_server_error,))
        ran.append(1)

    run()
    return len(ran)


def test_no_server_errors(api_schema):
    """Every operation of /openapi.json, fuzzed with a valid token: no 5xx.

    Driven through schemathesis's Python API (``get_all_operations`` + ``as_strategy``)
    rather than its pytest plugin, which breaks on pytest 9 (``Function._nodeid``)."""
    operations = [result.ok() for result in api_schema.get_all_operations()]
    labels = {op.label for op in operations}
    assert "POST /jobs" in labels and "GET /jobs/{job_id}" in labels, labels
    counts = {op.label: _check_operation(op) for op in operations}
    assert all(n > 0 for n in counts.values()), counts
