"""The viewer's static mount at / never shadows the API routes."""

from __future__ import annotations

import os

from fastapi.testclient import TestClient

from api.main import create_app
from api.settings import Settings
from jobstore.engine import dispose_engines


def test_static_mount_serves_viewer_and_keeps_api(tmp_path, monkeypatch):
    for k in list(os.environ):
        if k.startswith("NEPF_"):
            monkeypatch.delenv(k)
    web = tmp_path / "dist"
    (web / "assets").mkdir(parents=True)
    (web / "index.html").write_text("<!doctype html><title>viewer</title>")
    (web / "assets" / "app.js").write_text("console.log(1)")
    (web / "jobs").write_text("a file named like a route")     # must not win over the API
    app = create_app(Settings(data_dir=tmp_path / "data", web_dir=web, reconcile_interval_s=0))
    with TestClient(app) as c:
        r = c.get("/")
        assert r.status_code == 200 and "<title>viewer</title>" in r.text
        assert c.get("/assets/app.js").headers["content-type"].startswith(("text/javascript", "application/javascript"))
        assert c.get("/jobs").status_code == 401                     # the API route, not the file
        assert c.get("/healthz").json()["ok"] is True
        assert "/jobs/{job_id}" in c.get("/openapi.json").json()["paths"]
        assert c.get("/docs").status_code == 200
        # issue 37: the viewer's 404s have the API's error shape, not {"detail": "Not Found"}
        for path in ("/nope.js", "/assets/missing.css"):
            r = c.get(path)
            assert r.status_code == 404 and r.json() == {"detail": "Not Found", "code": "not_found", "errors": []}
    dispose_engines()


def test_placeholder_without_a_built_viewer(tmp_path, monkeypatch):
    for k in list(os.environ):
        if k.startswith("NEPF_"):
            monkeypatch.delenv(k)
    app = create_app(Settings(data_dir=tmp_path / "data", web_dir=tmp_path / "missing", reconcile_interval_s=0))
    with TestClient(app) as c:
        r = c.get("/")
        assert r.status_code == 200 and "/docs" in r.text
    dispose_engines()
