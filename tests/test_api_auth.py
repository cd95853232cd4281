"""Auth: a missing token is 401; another owner's job is 404 on every route, artifacts included;
SSE tickets are job-scoped, signed and expire."""

from __future__ import annotations

import json
import os
import time
import types

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import select, update

from api.auth import create_token, make_ticket
from api.main import create_app
from api.settings import Settings
from jobstore.engine import dispose_engines
from jobstore.models import Job, Token
from service_fixtures import dataset_zip_bytes


@pytest.fixture
def env(tmp_path, monkeypatch):
    for k in list(os.environ):
        if k.startswith("NEPF_"):
            monkeypatch.delenv(k)
    settings = Settings(data_dir=tmp_path / "data", reconcile_interval_s=0)
    app = create_app(settings)
    svc = app.state.service
    alice, bob = create_token(svc.Session, "alice"), create_token(svc.Session, "bob")
    client = TestClient(app)
    r = client.post("/jobs", headers={"Authorization": f"Bearer {alice}"},
                    files={"dataset": ("d.zip", dataset_zip_bytes(tmp_path), "application/zip")})
    assert r.status_code == 202, r.text
    job_id = r.json()["id"]
    run = settings.jobs_path / job_id / "run"
    (run / "asset.glb").write_bytes(b"glTF" + b"\0" * 16)
    (run / "metrics.jsonl").write_text(json.dumps({"step": 1, "wall_s": 0.1, "loss": 1.0}) + "\n")
    (run / "manifest.json").write_text(json.dumps({"artifacts": [{"kind": "glb", "path": "asset.glb",
                                                                  "bytes": 20, "sha256": "0" * 64}]}))
    yield client, svc, job_id, alice, bob
    client.close()
    dispose_engines()


def token_id(svc, owner: str) -> int:
    with svc.Session() as s:
        return s.execute(select(Token.id).where(Token.owner == owner)).scalar_one()


def routes(job_id):
    return [("GET", f"/jobs/{job_id}"), ("GET", f"/jobs/{job_id}/metrics"), ("GET", f"/jobs/{job_id}/events"),
            ("POST", f"/jobs/{job_id}/events/ticket"), ("GET", f"/jobs/{job_id}/artifacts"),
            ("GET", f"/jobs/{job_id}/artifacts/asset.glb"), ("POST", f"/jobs/{job_id}/cancel"),
            ("DELETE", f"/jobs/{job_id}")]


def test_missing_or_bad_token_is_401(env):
    client, svc, job_id, alice, bob = env
    for method, path in routes(job_id) + [("GET", "/jobs"), ("POST", "/jobs")]:
        for headers in ({}, {"Authorization": "Bearer nepf_not-a-real-token"}, {"Authorization": "Basic YTpi"}):
            r = client.request(method, path, headers=headers)
            assert r.status_code == 401, (method, path, headers, r.status_code)
            assert r.headers.get("www-authenticate") == "Bearer"


def test_other_owner_gets_404_on_every_route(env):
    client, svc, job_id, alice, bob = env
    for method, path in routes(job_id):
        r = client.request(method, path, headers={"Authorization": f"Bearer {bob}"})
        assert r.status_code == 404, (method, path, r.status_code, r.text)
        assert r.json()["code"] == "not_found"
    assert client.get("/jobs", headers={"Authorization": f"Bearer {bob}"}).json()["items"] == []
    # a job id that does not exist looks exactly the same
    r = client.get(f"/jobs/{'0' * 32}", headers={"Authorization": f"Bearer {bob}"})
    assert r.status_code == 404 and r.json()["code"] == "not_found"
    # the owner still sees everything (and bob's attempts changed nothing)
    a = {"Authorization": f"Bearer {alice}"}
    assert client.get(f"/jobs/{job_id}", headers=a).json()["cancel_requested"] is False
    assert client.get(f"/jobs/{job_id}/artifacts/asset.glb", headers=a).status_code == 200


def test_sse_ticket_is_job_scoped_and_expires(env, monkeypatch):
    client, svc, job_id, alice, bob = env
    a = {"Authorization": f"Bearer {alice}"}
    with svc.Session() as s:   # make the stream end immediately
        s.execute(update(Job).where(Job.id == job_id).values(status="succeeded"))
        s.commit()
    t = client.post(f"/jobs/{job_id}/events/ticket", headers=a).json()
    assert t["url"].startswith(f"/jobs/{job_id}/events?ticket=")
    r = client.get(t["url"])                       # no header: the ticket is the credential
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/event-stream")
    assert "event: end" in r.text and "event: metrics" in r.text
    # a ticket for another job, a forged one, an expired one: 401
    other = make_ticket(svc.secret, "alice", "f" * 32, token_id(svc, "alice"))
    assert client.get(f"/jobs/{job_id}/events?ticket={other}").status_code == 401
    forged = t["ticket"][:-2] + ("AA" if not t["ticket"].endswith("AA") else "BB")
    assert client.get(f"/jobs/{job_id}/events?ticket={forged}").status_code == 401
    # a ticket signed NEPF_TICKET_TTL_S + 1 seconds ago (its timestamp is part of the signed text)
    import itsdangerous.timed
    past = time.time() - svc.settings.ticket_ttl_s - 1
    monkeypatch.setattr(itsdangerous.timed, "time", types.SimpleNamespace(time=lambda: past))
    expired = make_ticket(svc.secret, "alice", job_id, token_id(svc, "alice"))
    monkeypatch.undo()
    assert client.get(f"/jobs/{job_id}/events?ticket={expired}").status_code == 401
    # bob's valid ticket for alice's job id: 404, like every other route
    bobs = make_ticket(svc.secret, "bob", job_id, token_id(svc, "bob"))
    assert client.get(f"/jobs/{job_id}/events?ticket={bobs}").status_code == 404
    # a ticket naming bob's token for alice: the token must be the owner's own
    mixed = make_ticket(svc.secret, "alice", job_id, token_id(svc, "bob"))
    assert client.get(f"/jobs/{job_id}/events?ticket={mixed}").status_code == 401


def test_a_ticket_stops_working_once_its_token_is_revoked(env):
    """Issue 37: a ticket minted with a token kept working for its 300 s after the token was
    revoked. The stream checks, at connect time, that the token is still live."""
    client, svc, job_id, alice, bob = env
    with svc.Session() as s:
        s.execute(update(Job).where(Job.id == job_id).values(status="succeeded"))
        s.commit()
    url = client.post(f"/jobs/{job_id}/events/ticket", headers={"Authorization": f"Bearer {alice}"}).json()["url"]
    assert client.get(url).status_code == 200
    with svc.Session() as s:
        s.execute(update(Token).where(Token.owner == "alice").values(revoked=True))
        s.commit()
    r = client.get(url)
    assert r.status_code == 401 and r.json()["code"] == "unauthorized", r.text


def test_artifact_paths_cannot_escape_the_job_folder(env):
    client, svc, job_id, alice, bob = env
    a = {"Authorization": f"Bearer {alice}"}
    run = svc.settings.jobs_path / job_id / "run"
    (run / "escape.txt").symlink_to(svc.settings.data_path / "secret.key")
    (run / "checkpoints").mkdir()
    (run / "checkpoints" / "latest.pt").write_bytes(b"x")
    for p in ["../dataset/cameras.npz", "..%2Fdataset%2Fcameras.npz", "%2E%2E/%2E%2E/secret.key",
              "/etc/passwd", "escape.txt", "checkpoints/latest.pt", "nope.glb", "", "previews/../../run/asset.glb"]:
        r = client.get(f"/jobs/{job_id}/artifacts/{p}", headers=a)
        assert r.status_code == 404, (p, r.status_code)
    r = client.get(f"/jobs/{job_id}/artifacts/asset.glb", headers=a)
    assert r.status_code == 200 and r.headers["content-type"] == "model/gltf-binary"
    r = client.get(f"/jobs/{job_id}/artifacts/metrics.jsonl", headers=a)
    assert r.headers["content-type"] == "application/x-ndjson"


def test_links_into_checkpoints_are_not_served(env):
    """Issue 37: the ``checkpoints/`` exclusion looked at the path as written, so a link inside
    the run folder (``x.pt -> checkpoints/latest.pt``) served the checkpoint. The resolved path
    is checked now: a link to a file or to the folder, relative or absolute, is a 404."""
    client, svc, job_id, alice, bob = env
    a = {"Authorization": f"Bearer {alice}"}
    run = svc.settings.jobs_path / job_id / "run"
    (run / "checkpoints").mkdir()
    (run / "checkpoints" / "latest.pt").write_bytes(b"weights")
    (run / "x.pt").symlink_to("checkpoints/latest.pt")
    (run / "ck").symlink_to(run / "checkpoints")
    (run / "previews").mkdir()
    (run / "previews" / "y.pt").symlink_to("../checkpoints/latest.pt")
    for p in ("x.pt", "ck/latest.pt", "previews/y.pt", "checkpoints/latest.pt"):
        r = client.get(f"/jobs/{job_id}/artifacts/{p}", headers=a)
        assert r.status_code == 404 and r.json()["code"] == "not_found", (p, r.status_code)
    (run / "asset_link.glb").symlink_to("asset.glb")            # a link within the run folder still works
    assert client.get(f"/jobs/{job_id}/artifacts/asset_link.glb", headers=a).status_code == 200


def test_list_is_paginated_newest_first(env, tmp_path):
    client, svc, job_id, alice, bob = env
    a = {"Authorization": f"Bearer {alice}"}
    z = dataset_zip_bytes(tmp_path / "more") if (tmp_path / "more").mkdir() is None else None
    ids = [job_id]
    for _ in range(2):
        time.sleep(0.01)
        ids.append(client.post("/jobs", headers=a, files={"dataset": ("d.zip", z, "application/zip")}).json()["id"])
    page1 = client.get("/jobs?limit=2", headers=a).json()
    assert [j["id"] for j in page1["items"]] == ids[::-1][:2] and page1["total"] == 3
    page2 = client.get(page1["next"], headers=a).json()
    assert [j["id"] for j in page2["items"]] == [ids[0]] and page2["next"] is None


def test_cancel_queued_then_delete(env):
    client, svc, job_id, alice, bob = env
    a = {"Authorization": f"Bearer {alice}"}
    assert client.delete(f"/jobs/{job_id}", headers=a).status_code == 409      # still queued
    r = client.post(f"/jobs/{job_id}/cancel", headers=a)
    assert r.status_code == 202 and r.json()["status"] == "cancelled"
    assert client.post(f"/jobs/{job_id}/cancel", headers=a).status_code == 409
    assert client.get(f"/jobs/{job_id}/artifacts/asset.glb", headers=a).status_code == 200  # partial results stay
    assert client.delete(f"/jobs/{job_id}", headers=a).status_code == 204
    assert client.get(f"/jobs/{job_id}", headers=a).status_code == 404
    assert not (svc.settings.jobs_path / job_id).exists()


def test_health_and_ready(env):
    client, svc, job_id, alice, bob = env
    assert client.get("/healthz").json()["ok"] is True
    r = client.get("/readyz")
    assert r.status_code == 200 and r.json()["checks"]["database"] == "ok" and r.json()["checks"]["broker"] == "ok"


def test_local_token_is_created_once_and_tokens_can_be_revoked(tmp_path, monkeypatch, capsys):
    from api.auth import TokenVerifier
    from api.commands import ensure_local_token, token_main
    from jobstore.engine import session_factory

    for k in list(os.environ):
        if k.startswith("NEPF_"):
            monkeypatch.delenv(k)
    settings = Settings(data_dir=tmp_path / "d")
    tok1, created1 = ensure_local_token(settings)
    tok2, created2 = ensure_local_token(settings)
    assert created1 and not created2 and tok1 == tok2
    assert (tmp_path / "d" / "local-token").stat().st_mode & 0o077 == 0
    verifier = TokenVerifier(session_factory(settings.db_url), 0)
    assert verifier.owner_of(tok1) == "local"
    assert token_main(["--data-dir", str(tmp_path / "d"), "create", "dave"]) == 0
    tok3 = capsys.readouterr().out.strip()
    assert verifier.owner_of(tok3) == "dave"
    assert token_main(["--data-dir", str(tmp_path / "d"), "revoke", tok3[:12]]) == 0
    assert verifier.owner_of(tok3) is None
    # a revoked local token is replaced on the next start
    assert token_main(["--data-dir", str(tmp_path / "d"), "revoke", tok1[:12]]) == 0
    tok4, created4 = ensure_local_token(settings)
    assert created4 and tok4 != tok1
    dispose_engines()
