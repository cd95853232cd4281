"""Artifact downloads (issue 34): ``Content-Disposition: attachment`` named ``<job name>-<artifact>``
(RFC 6266: an ASCII ``filename`` and a UTF-8 ``filename*``, RFC 8187), with ETag and Range still
answered (Starlette's FileResponse: 206, If-Range, multipart ranges)."""

from __future__ import annotations

import json
from urllib.parse import unquote

import pytest

from api.downloads import MAX_NAME, content_disposition, download_name
from test_api_dataset_limits import dtu_zip, post, service  # noqa: F401 - the fixture


def parse_disposition(value: str) -> dict:
    """RFC 6266 as a browser reads it: the type, ``filename*`` (RFC 8187: ``UTF-8''`` +
    percent-encoded UTF-8) when present, and the quoted ASCII ``filename``. The header's values
    hold no ``;`` (the ASCII name keeps them out, ``filename*`` percent-encodes them)."""
    kind, *params = [p.strip() for p in value.split(";")]
    got = {"type": kind}
    for p in params:
        key, _, val = p.partition("=")
        if key == "filename":
            assert val.startswith('"') and val.endswith('"') and '"' not in val[1:-1] and "\\" not in val
            got["ascii"] = val[1:-1]
        elif key == "filename*":
            charset, _, rest = val.partition("''")
            assert charset == "UTF-8"
            got["filename"] = unquote(rest, encoding="utf-8", errors="strict")
    return got


@pytest.mark.parametrize("name, path, exact, ascii_", [
    ("fox scan", "asset.glb", "fox scan-asset.glb", "fox scan-asset.glb"),
    (None, "textures/orm.png", "nepf-0123abcd-textures-orm.png", "nepf-0123abcd-textures-orm.png"),
    ('Kürbis "groß"', "asset.glb", "Kürbis _groß_-asset.glb", "Kurbis _gro__-asset.glb"),
    ("日本の狐", "previews/thumb.png", "日本の狐-previews-thumb.png", "____-previews-thumb.png"),
    ("../..\\etc:passwd", "lights.json", "_.._etc_passwd-lights.json", "_.._etc_passwd-lights.json"),
    ("50% off; x", "asset.glb", "50% off; x-asset.glb", "50_ off_ x-asset.glb"),
])
def test_names_and_the_header_round_trip(name, path, exact, ascii_):
    assert download_name(name, "0123abcd" * 4, path) == exact
    header = content_disposition(name, "0123abcd" * 4, path)
    assert header.isascii()
    got = parse_disposition(header)
    assert got == {"type": "attachment", "filename": exact, "ascii": ascii_}
    assert unquote(header.split("filename*=UTF-8''", 1)[1]) == exact


def test_long_names_keep_their_extension():
    n = download_name("x" * 500, "0" * 32, "asset.glb")
    assert len(n) == MAX_NAME and n.endswith(".glb")


def _job_with_files(clients, svc, tmp_path, name):
    r = post(clients["alice"], dtu_zip(tmp_path / "ds", n=6), config={"name": name, "preset": "tiny"})
    assert r.status_code == 202, r.text
    job_id = r.json()["id"]
    run = svc.settings.jobs_path / job_id / "run"
    (run / "textures").mkdir(parents=True, exist_ok=True)
    glb = bytes(range(256)) * 40   # 10,240 bytes
    (run / "asset.glb").write_bytes(glb)
    (run / "textures" / "orm.png").write_bytes(b"\x89PNG" + b"\0" * 60)
    (run / "manifest.json").write_text(json.dumps({"artifacts": [
        {"kind": "glb", "path": "asset.glb", "bytes": len(glb)},
        {"kind": "texture", "path": "textures/orm.png", "bytes": 64}]}))
    return job_id, glb


def test_download_is_an_attachment_named_after_the_job_with_etag_and_range(service, tmp_path):  # noqa: F811
    clients, svc, _ = service()
    job_id, glb = _job_with_files(clients, svc, tmp_path, "Fuchs – Wald")
    c = clients["alice"]
    r = c.get(f"/jobs/{job_id}/artifacts/asset.glb")
    assert r.status_code == 200 and r.content == glb
    assert r.headers["content-type"] == "model/gltf-binary"
    got = parse_disposition(r.headers["content-disposition"])
    assert got == {"type": "attachment", "filename": "Fuchs – Wald-asset.glb", "ascii": "Fuchs _ Wald-asset.glb"}
    etag = r.headers["etag"]
    assert etag.startswith('"') and r.headers["accept-ranges"] == "bytes" and r.headers["last-modified"]
    tex = c.get(f"/jobs/{job_id}/artifacts/textures/orm.png")
    assert parse_disposition(tex.headers["content-disposition"])["filename"] == "Fuchs – Wald-textures-orm.png"

    part = c.get(f"/jobs/{job_id}/artifacts/asset.glb", headers={"Range": "bytes=100-199"})
    assert part.status_code == 206 and part.content == glb[100:200]
    assert part.headers["content-range"] == f"bytes 100-199/{len(glb)}"
    assert part.headers["etag"] == etag and "content-disposition" in part.headers
    tail = c.get(f"/jobs/{job_id}/artifacts/asset.glb", headers={"Range": "bytes=-24"})
    assert tail.status_code == 206 and tail.content == glb[-24:]
    # If-Range: a matching ETag resumes; a stale one gets the whole file
    assert c.get(f"/jobs/{job_id}/artifacts/asset.glb", headers={"Range": "bytes=0-9", "If-Range": etag}).status_code == 206
    full = c.get(f"/jobs/{job_id}/artifacts/asset.glb", headers={"Range": "bytes=0-9", "If-Range": '"stale"'})
    assert full.status_code == 200 and full.content == glb
    assert c.get(f"/jobs/{job_id}/artifacts/asset.glb", headers={"Range": f"bytes={len(glb)}-"}).status_code == 416


def test_a_job_without_a_name_downloads_under_its_id(service, tmp_path):  # noqa: F811
    clients, svc, _ = service()
    r = post(clients["alice"], dtu_zip(tmp_path / "ds", n=6))
    job_id = r.json()["id"]
    run = svc.settings.jobs_path / job_id / "run"
    (run / "lights.json").write_text("{}")
    got = clients["alice"].get(f"/jobs/{job_id}/artifacts/lights.json")
    assert got.status_code == 200
    assert parse_disposition(got.headers["content-disposition"])["filename"] == f"nepf-{job_id[:8]}-lights.json"
