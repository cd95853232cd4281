"""Issue 37, finding 5: a cap on the request head (``NEPF_MAX_HEADER_BYTES``, 64 KiB): 431
``headers_too_large``. Through the ASGI app (the middleware) and through uvicorn with the
protocol ``nepf serve`` runs (``api.header_limit.uvicorn_options``), over a real socket."""

from __future__ import annotations

import json
import os
import socket
import threading
import time
from contextlib import contextmanager

import pytest
import uvicorn
from fastapi.testclient import TestClient

from api.header_limit import uvicorn_options
from api.main import create_app
from api.settings import Settings
from jobstore.engine import dispose_engines
from service_fixtures import free_port, wait_for

MB = 1024 * 1024


@pytest.fixture
def app_with(tmp_path, monkeypatch):
    for k in list(os.environ):
        if k.startswith("NEPF_"):
            monkeypatch.delenv(k)

    def make(**overrides):
        return create_app(Settings(data_dir=tmp_path / "data", reconcile_interval_s=0, **overrides))
    yield make
    dispose_engines()


def test_headers_over_the_cap_are_a_431_through_the_app(app_with):
    """200 headers of 1 KB (accepted before) and one 100 KB Authorization header: 431 in the error
    shape; a head of 60 KB is under the 64 KiB default and reaches the route (401: no token)."""
    with TestClient(app_with()) as c:
        many = {f"x-h{i:03d}": "v" * 1000 for i in range(200)}
        for headers in (many, {"Authorization": "Bearer " + "a" * 100_000}):
            r = c.get("/jobs", headers=headers)
            assert r.status_code == 431, r.status_code
            assert r.json()["code"] == "headers_too_large" and "65536" in r.json()["detail"]
            assert "NEPF_MAX_HEADER_BYTES" in r.json()["detail"]
        r = c.get("/jobs", headers={f"x-h{i:02d}": "v" * 1000 for i in range(60)})
        assert r.status_code == 401
        assert c.get("/healthz").status_code == 200


@contextmanager
def served(app, **config):
    """uvicorn on a free port in a thread, with ``config`` (what ``nepf serve`` passes)."""
    server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=free_port(), log_level="warning", **config))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    try:
        wait_for(lambda: server.started, 15, 0.02, what="uvicorn")
        yield server.config.port
    finally:
        server.should_exit = True
        thread.join(15)


def read_response(sock: socket.socket) -> bytes:
    sock.settimeout(10)
    data = b""
    while True:
        chunk = sock.recv(65536)
        if not chunk:
            return data
        data += chunk


def test_live_server_answers_a_head_over_the_cap_with_431(app_with):
    """A complete head over an 8 KB cap, sent in one piece: uvicorn's protocol answers 431 itself."""
    limit = 8192
    with served(app_with(max_header_bytes=limit), **uvicorn_options(limit)) as port:
        with socket.create_connection(("127.0.0.1", port)) as s:
            s.sendall(b"GET /jobs HTTP/1.1\r\nHost: t\r\nAuthorization: Bearer " + b"a" * 10_000 + b"\r\n\r\n")
            raw = read_response(s)
        head, _, body = raw.partition(b"\r\n\r\n")
        assert head.startswith(b"HTTP/1.1 431"), raw[:200]
        assert json.loads(body)["code"] == "headers_too_large"
        with socket.create_connection(("127.0.0.1", port)) as s:     # a normal request still works
            s.sendall(b"GET /healthz HTTP/1.1\r\nHost: t\r\nConnection: close\r\n\r\n")
            assert read_response(s).startswith(b"HTTP/1.1 200")


def test_live_server_stops_reading_an_endless_header(app_with):
    """The probe's 16 MB Authorization header was read in full (then a 401). Now the server stops
    reading after the 64 KiB cap: a 32 MiB header cannot be sent whole (loopback socket buffers
    take a few MiB once the server stops reading), and what comes back, if anything, is the 431.
    (The ASGI middleware alone would answer 431 only after reading all 32 MiB: this is the
    protocol's job.)"""
    limit = 65536
    total = 32 * MB
    sent, answer = 0, b""
    t0 = time.monotonic()
    with served(app_with(max_header_bytes=limit), **uvicorn_options(limit)) as port:
        with socket.create_connection(("127.0.0.1", port)) as s:
            s.settimeout(20)
            try:
                s.sendall(b"GET /jobs HTTP/1.1\r\nHost: t\r\nAuthorization: Bearer ")
                chunk = b"a" * (256 * 1024)
                while sent < total:
                    s.sendall(chunk)
                    sent += len(chunk)
            except (BrokenPipeError, ConnectionResetError, socket.timeout):
                pass
            try:
                answer = s.recv(65536)
            except OSError:
                pass
    assert sent < total, "the server read the whole 32 MiB header"
    assert answer == b"" or answer.startswith(b"HTTP/1.1 431"), answer[:100]
    assert time.monotonic() - t0 < 30
