"""Upload hardening (issue 23): overlapping-entry zip bombs, the zip-size ratio cap, entry names
the file system refuses, a cap on the whole request body that stops reading, and the HTTP
details (artifact media types in the OpenAPI, ``Allow`` on 405)."""

from __future__ import annotations

import asyncio
import io
import json
import struct
import threading
import zipfile
from contextlib import contextmanager
from pathlib import Path, PurePosixPath

import httpx
import pytest
import uvicorn
from sqlalchemy import func, select

from api.errors import ApiError
from api.artifacts import CONTENT_TYPES, content_type_for
from api.settings import Settings
from api.zip_safety import RATIO_FLOOR_BYTES, extract_members, extraction_budget
from jobstore.models import Job
from service_fixtures import free_port, leftover_files, wait_for
from test_api_uploads import make_client, post, raw_zip, zbytes_from  # noqa: F401 - make_client is a fixture

MB = 1024 * 1024
EOCD = b"PK\x05\x06"
CENTRAL = b"PK\x01\x02"


# ---------------------------------------------------------------- zip builders
def central_records(data: bytes) -> tuple[int, int, list[int]]:
    """(central directory offset, its size, offset of each central record) of a plain zip."""
    eocd = data.rfind(EOCD)
    cd_size, cd_offset = struct.unpack_from("<II", data, eocd + 12)
    records, pos = [], cd_offset
    while pos < cd_offset + cd_size:
        assert data[pos:pos + 4] == CENTRAL
        name_len, extra_len, comment_len = struct.unpack_from("<HHH", data, pos + 28)
        records.append(pos)
        pos += 46 + name_len + extra_len + comment_len
    return cd_offset, cd_size, records


def overlap_bomb(n: int = 12, payload: bytes = b"\0" * (256 * 1024)) -> bytes:
    """One local header and deflate stream, and ``n`` central-directory entries that all point at
    it: built with zipfile, then the other local entries are cut out and the offsets patched."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as z:
        for i in range(n):
            z.writestr(f"scan/part{i:03d}.bin", payload)
    data = buf.getvalue()
    cd_offset, cd_size, records = central_records(data)
    first_end = struct.unpack_from("<I", data, records[1] + 42)[0]   # where entry 1's local header was
    central = bytearray(data[cd_offset:cd_offset + cd_size])
    for rec in records:
        struct.pack_into("<I", central, rec - cd_offset + 42, 0)       # every entry -> local header at 0
    eocd = bytearray(data[data.rfind(EOCD):])
    struct.pack_into("<I", eocd, 16, first_end)                        # the central directory moved up
    bomb = data[:first_end] + bytes(central) + bytes(eocd)
    with zipfile.ZipFile(io.BytesIO(bomb)) as z:                       # a zip that zipfile opens
        assert len(z.infolist()) == n and {i.header_offset for i in z.infolist()} == {0}
    return bomb


def patched_compress_size(data: bytes, entry: int, size: int) -> bytes:
    """``data`` with central record ``entry`` declaring ``size`` compressed bytes."""
    _, _, records = central_records(data)
    out = bytearray(data)
    struct.pack_into("<I", out, records[entry] + 20, size)
    return bytes(out)


def stored_zip(entries: list[tuple[str, bytes]]) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_STORED) as z:
        for name, data in entries:
            z.writestr(name, data)
    return buf.getvalue()


def zeros_zip(n: int, size: int) -> bytes:
    return raw_zip([(f"scan/zeros{i}.bin", b"\0" * size) for i in range(n)])


def assert_rejected(r, status: int, code: str, *words: str, data: Path, svc) -> dict:
    """The answer is ``status``/``code``, names ``words``, shows no server path, leaves nothing."""
    assert r.status_code == status, r.text
    body = r.json()
    assert body["code"] == code, body
    for w in words:
        assert w in body["detail"], body
    assert str(data) not in body["detail"] and str(data.resolve()) not in body["detail"], body
    assert leftover_files(data) == []
    with svc.Session() as s:
        assert s.execute(select(func.count()).select_from(Job)).scalar_one() == 0
    return body


# ---------------------------------------------------------------- overlap and ratio bombs
def test_overlap_bomb_rejected_before_extraction(make_client):
    client, svc, data = make_client()
    bomb = overlap_bomb()
    assert len(bomb) < 4096            # 12 x 256 KiB declared from a few KB on disk
    assert_rejected(post(client, bomb), 422, "zip_overlap", "scan/part000.bin", "overlap", data=data, svc=svc)


def test_entry_whose_data_runs_into_the_next_is_an_overlap(make_client):
    client, svc, data = make_client()
    z = stored_zip([("scan/a.bin", b"a" * 100), ("scan/b.bin", b"b" * 100)])
    body = assert_rejected(post(client, patched_compress_size(z, 0, 150)), 422, "zip_overlap",
                           data=data, svc=svc)
    assert "scan/a.bin" in body["detail"] and "scan/b.bin" in body["detail"]


def test_entry_past_the_archive_data_rejected(make_client):
    client, svc, data = make_client()
    z = stored_zip([("scan/a.bin", b"a" * 100), ("scan/b.bin", b"b" * 100)])
    assert_rejected(post(client, patched_compress_size(z, 1, 10_000)), 422, "corrupt_zip", "scan/b.bin",
                    "runs past", data=data, svc=svc)


def test_total_declared_size_bounded_by_ratio_to_zip_size(make_client):
    """12 entries of 1 MiB zeros (each under the per-entry 1 MB threshold): ~12 KB on disk."""
    client, svc, data = make_client()
    z = zeros_zip(12, MB)
    assert 12 * MB > RATIO_FLOOR_BYTES and 12 * MB > 200 * len(z)
    assert_rejected(post(client, z), 422, "zip_bomb", "on disk", "NEPF_MAX_ZIP_RATIO", data=data, svc=svc)


def test_extraction_budget_hand_values():
    s = Settings(max_unzipped_mb=8192, max_zip_ratio=200)
    assert extraction_budget(s, MB) == 200 * MB                     # ratio x zip size
    assert extraction_budget(s, 1024) == 8 * MB                     # the floor for tiny zips
    assert extraction_budget(s, 100 * MB) == 8192 * MB              # the absolute cap
    assert extraction_budget(Settings(max_unzipped_mb=1, max_zip_ratio=200), MB) == MB


def _members(zf: zipfile.ZipFile) -> list:
    return [(info, PurePosixPath(info.filename)) for info in zf.infolist()]


def test_extraction_counts_written_bytes_against_the_budget(tmp_path):
    """Headers can lie: the bytes really written are counted, whatever was declared."""
    zf = zipfile.ZipFile(io.BytesIO(stored_zip([("a.bin", b"a" * 3000), ("b.bin", b"b" * 3000)])))
    with pytest.raises(ApiError) as exc:
        extract_members(zf, _members(zf), tmp_path / "out", budget=5000)
    assert exc.value.code == "zip_bomb" and "size cap" in exc.value.message
    extract_members(zf, _members(zf), tmp_path / "ok", budget=6000)
    assert (tmp_path / "ok" / "b.bin").read_bytes() == b"b" * 3000


def test_extraction_os_error_is_a_422_without_the_server_path(tmp_path):
    """The fallback under the name checks: a file where a folder must go (``a`` and ``a/b``)."""
    zf = zipfile.ZipFile(io.BytesIO(stored_zip([("a", b"x"), ("a/b", b"y")])))
    with pytest.raises(ApiError) as exc:
        extract_members(zf, _members(zf), tmp_path / "out", budget=MB)
    assert exc.value.status == 422 and exc.value.code == "zip_unextractable"
    assert "'a/b'" in exc.value.message and str(tmp_path) not in exc.value.message


# ---------------------------------------------------------------- entry names
def test_entry_name_of_300_characters(make_client):
    client, svc, data = make_client()
    z = raw_zip([("scan/" + "n" * 296 + ".png", b"x")])
    assert_rejected(post(client, z), 422, "zip_name_too_long", "300 bytes", "255", data=data, svc=svc)


def test_path_of_25_folders_of_200_characters(make_client):
    client, svc, data = make_client()
    name = "/".join(f"{i:02d}" + "d" * 198 for i in range(25)) + "/000.png"
    z = raw_zip([(name, b"x")])
    assert_rejected(post(client, z), 422, "zip_path_too_long", f"{len(name)} bytes", "1024", data=data, svc=svc)


@pytest.mark.parametrize("order", ["file_first", "folder_first"])
def test_file_and_folder_of_the_same_name(make_client, order):
    client, svc, data = make_client()
    entries = [("ds/image", b"I am a file"), ("ds/image/000.png", b"x")]
    z = raw_zip(entries if order == "file_first" else entries[::-1])
    assert_rejected(post(client, z), 422, "zip_path_conflict", "'ds/image'", "folder", data=data, svc=svc)


# ---------------------------------------------------------------- whole-body cap
def multipart_stream(parts: list[tuple[str, object]], boundary: str = "B0undary", chunk: int = 256 * 1024):
    """A lazily generated multipart body; a part is bytes or ``(filler byte, n bytes)``."""
    for name, content in parts:
        filename = '; filename="ds.zip"' if name == "dataset" else ""
        yield (f"--{boundary}\r\nContent-Disposition: form-data; name=\"{name}\"{filename}\r\n"
               f"Content-Type: application/octet-stream\r\n\r\n").encode()
        if isinstance(content, bytes):
            yield content
        else:
            filler, n = content
            while n > 0:
                yield filler * min(chunk, n)
                n -= chunk
        yield b"\r\n"
    yield f"--{boundary}--\r\n".encode()


def asgi_post(app, token: str, body, content_length: int | None = None) -> tuple[int, dict, dict, int]:
    """POST /jobs straight into the ASGI app, the body pulled chunk by chunk (chunked encoding: no
    Content-Length unless given); returns status, headers, JSON body and the bytes pulled."""
    headers = [(b"authorization", f"Bearer {token}".encode()),
               (b"content-type", b"multipart/form-data; boundary=B0undary")]
    headers.append((b"content-length", str(content_length).encode()) if content_length is not None
                   else (b"transfer-encoding", b"chunked"))
    scope = {"type": "http", "asgi": {"version": "3.0"}, "http_version": "1.1", "method": "POST",
             "scheme": "http", "path": "/jobs", "raw_path": b"/jobs", "root_path": "", "query_string": b"",
             "headers": headers, "client": ("127.0.0.1", 1), "server": ("test", 80)}
    chunks = iter(body)
    pulled = 0
    ended = False
    sent: list[dict] = []

    async def receive():
        nonlocal pulled, ended
        chunk = next(chunks, None)
        if chunk is None:
            if ended:
                return {"type": "http.disconnect"}
            ended = True
            return {"type": "http.request", "body": b"", "more_body": False}
        pulled += len(chunk)
        return {"type": "http.request", "body": chunk, "more_body": True}

    async def send(message):
        sent.append(message)

    asyncio.run(app(scope, receive, send))
    start = next(m for m in sent if m["type"] == "http.response.start")
    payload = b"".join(m.get("body", b"") for m in sent if m["type"] == "http.response.body")
    return start["status"], {k.decode(): v.decode() for k, v in start["headers"]}, json.loads(payload), pulled


def _token(client) -> str:
    return client.headers["Authorization"].split()[1]


def test_extra_part_counts_against_the_cap(make_client, tmp_path):
    """1 MiB cap: a valid dataset followed by a 50 MiB extra part is refused (413) early."""
    client, svc, data = make_client(max_upload_mb=1)
    dataset = zbytes_from(tmp_path)
    assert len(dataset) < MB / 4
    status, _, body, pulled = asgi_post(client.app, _token(client),
                                        multipart_stream([("dataset", dataset), ("extra", (b"x", 50 * MB))]))
    assert status == 413 and body["code"] == "upload_too_large" and "NEPF_MAX_UPLOAD_MB" in body["detail"]
    assert pulled < 2 * MB
    assert leftover_files(data) == []


def test_junk_body_not_read_to_the_end(make_client):
    """A 200 MiB junk-only chunked body: refused after about the cap, not after 200 MiB."""
    client, svc, data = make_client(max_upload_mb=1)
    status, headers, body, pulled = asgi_post(client.app, _token(client),
                                              multipart_stream([("junk", (b"j", 200 * MB))]))
    assert status == 413 and body["code"] == "upload_too_large"
    assert headers["connection"] == "close"      # else uvicorn drains the rest to keep the connection
    assert pulled < 2 * MB
    assert leftover_files(data) == []


@contextmanager
def live_server(app):
    """uvicorn serving ``app`` on a free port in a thread of this process."""
    server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=free_port(), log_level="warning"))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    try:
        wait_for(lambda: server.started, 15, 0.02, what="uvicorn")
        yield f"http://127.0.0.1:{server.config.port}"
    finally:
        server.should_exit = True
        thread.join(15)


@pytest.mark.parametrize("authorized", [True, False], ids=["over_cap_413", "unauthorized_401"])
def test_live_server_stops_reading_a_junk_body(make_client, authorized):
    """Through uvicorn and a socket: the client's 200 MiB generator is pulled only as far as the
    kernel's socket buffers take it, whether the refusal is the cap (413) or the token (401)."""
    client, svc, data = make_client(max_upload_mb=1)
    pulled = 0

    def body():
        nonlocal pulled
        for chunk in multipart_stream([("junk", (b"j", 200 * MB))], chunk=MB):
            pulled += len(chunk)
            yield chunk

    headers = {"Content-Type": "multipart/form-data; boundary=B0undary"}
    if authorized:
        headers["Authorization"] = client.headers["Authorization"]
    with live_server(client.app) as base:
        try:
            r = httpx.post(f"{base}/jobs", content=body(), headers=headers, timeout=60)
            assert r.status_code == (413 if authorized else 401), r.text
        except httpx.TransportError:
            pass   # the server closed the socket before the client finished writing: also a refusal
    assert pulled < 64 * MB
    assert leftover_files(data) == []


def test_declared_content_length_over_the_cap_is_refused_unread(make_client):
    client, svc, data = make_client(max_upload_mb=1)
    status, _, body, pulled = asgi_post(client.app, _token(client), multipart_stream([("junk", (b"j", 10))]),
                                        content_length=5 * MB)
    assert status == 413 and body["code"] == "upload_too_large" and pulled == 0


def test_valid_chunked_upload_under_a_small_cap_is_accepted(make_client, tmp_path):
    client, svc, data = make_client(max_upload_mb=1)
    status, headers, body, _ = asgi_post(client.app, _token(client),
                                         multipart_stream([("dataset", zbytes_from(tmp_path)), ("config", b"{}")]))
    assert status == 202, body
    assert headers["location"] == f"/jobs/{body['id']}"


# ---------------------------------------------------------------- HTTP details
def test_openapi_declares_every_artifact_media_type(make_client):
    client, svc, data = make_client()
    doc = client.get("/openapi.json").json()
    declared = set(doc["paths"]["/jobs/{job_id}/artifacts/{path}"]["get"]["responses"]["200"]["content"])
    assert {"model/gltf-binary", "application/json", "application/x-ndjson"} <= declared
    served = {content_type_for(f"file{ext}").split(";")[0] for ext in CONTENT_TYPES}
    assert served <= declared, served - declared


@pytest.mark.parametrize("web", [False, True], ids=["api_only", "with_viewer"])
def test_405_lists_every_allowed_method(make_client, tmp_path, web):
    web_dir = tmp_path / ("web" if web else "no-web")
    if web:
        web_dir.mkdir()
        (web_dir / "index.html").write_text("<!doctype html>")
    client, svc, data = make_client(web_dir=web_dir)
    job = "0" * 32
    cases = {("DELETE", "/jobs"): "GET, POST", ("PUT", f"/jobs/{job}"): "DELETE, GET",
             ("DELETE", f"/jobs/{job}/cancel"): "POST", ("PATCH", "/healthz"): "GET"}
    if web:
        cases[("POST", "/index.html")] = "GET, HEAD"
    for (method, path), allow in cases.items():
        r = client.request(method, path)
        assert r.status_code == 405 and r.headers.get("allow") == allow, (method, path, r.headers, r.text)
        assert r.json()["code"] == "method_not_allowed"
        for other in allow.split(", "):       # every listed method is really answered (not a 405)
            assert client.request(other, path).status_code != 405, (other, path)
