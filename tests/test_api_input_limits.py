"""Issue 37, findings 1-3, through the ASGI app (``POST /jobs``): every JSON the service reads
goes through one bounded parser (``nepf_json``), camera files are read member by member with
each ``.npy`` header checked before its data, and no malformed file ends as ``internal_error``
(nor as a 500)."""

from __future__ import annotations

import io
import json
import os
import stat
import sys
import tracemalloc
import zipfile
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient

from service_fixtures import leftover_files, make_dtu_dir
from test_api_dataset_limits import dtu_zip, ingp_zip, post, service  # noqa: F401 - service is a fixture

# ------------------------------------------------------------------ config part (finding 1)
DEEP = "[" * 2000 + "]" * 2000


def post_config(client, zbytes: bytes, raw: str):
    return client.post("/jobs", files={"dataset": ("ds.zip", zbytes, "application/zip")}, data={"config": raw})


@pytest.mark.parametrize("raw, words", [
    ('{"preset":"tiny","name":' + DEEP + '}', ("nesting", "32")),          # was RecursionError, 500
    ('{"iters": 1' + "0" * 5000 + '}', ("number", "5001", "100")),          # was ValueError (4300 digits), 500
    ('{"iters":30,"iters":40}', ('"iters"', "twice")),                       # was silently 40
    ('{"name": "' + "x" * 5000 + '"}', ("string", "4096")),
])
def test_config_json_out_of_limits_is_a_422_naming_the_part_and_the_limit(service, tmp_path, raw, words):
    clients, svc, data = service()
    r = post_config(clients["alice"], dtu_zip(tmp_path), raw)
    assert r.status_code == 422 and r.json()["code"] == "invalid_config", r.text
    detail = r.json()["detail"]
    assert detail.startswith("'config'") and all(w in detail for w in words), detail
    assert "Traceback" not in r.text and "Error:" not in detail
    assert not leftover_files(data)


# ------------------------------------------------------------------ transforms.json (findings 1, 3)
def ingp_zip_with(tmp: Path, edit) -> bytes:
    """An instant-ngp upload whose ``transforms.json`` text is passed through ``edit``."""
    zb = ingp_zip(tmp, {})
    src = zipfile.ZipFile(io.BytesIO(zb))
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w", zipfile.ZIP_DEFLATED) as z:
        for info in src.infolist():
            body = src.read(info)
            if info.filename.endswith("transforms.json"):
                body = edit(body.decode()).encode()
            z.writestr(info.filename, body)
    return out.getvalue()


@pytest.mark.parametrize("edit, words", [
    (lambda t: t.replace('{"fl_x"', '{"extra": ' + DEEP + ', "fl_x"', 1), ("nesting", "32")),
    (lambda t: t.replace('{"fl_x"', '{"extra": 1' + "0" * 50_000 + ', "fl_x"', 1), ("number", "100")),
    (lambda t: t.replace('{"fl_x"', '{"fl_x": 1.0, "fl_x"', 1), ('"fl_x"', "twice")),
])
def test_transforms_json_out_of_limits_is_bad_json_naming_the_file(service, tmp_path, edit, words):
    clients, svc, data = service()
    r = post(clients["alice"], ingp_zip_with(tmp_path, edit))
    body = r.json()
    assert r.status_code == 422 and body["code"] == "bad_json", r.text           # was internal_error / accepted
    assert body["errors"][0]["file"] == "transforms.json"
    assert all(w in body["detail"] for w in words), body["detail"]
    assert "Error" not in body["detail"]
    assert not leftover_files(data)


def test_transforms_json_within_limits_still_accepted(service, tmp_path):
    clients, svc, data = service()
    assert post(clients["alice"], ingp_zip_with(tmp_path, lambda t: t)).status_code == 202


# ------------------------------------------------------------------ camera files (findings 2, 3)
def npy_bytes(descr: str, shape: tuple, data: bytes) -> bytes:
    """A ``.npy`` member whose header says ``descr`` / ``shape``, followed by ``data`` as is."""
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(buf, {"descr": descr, "fortran_order": False, "shape": shape})
    return buf.getvalue() + data


def with_members(d: Path, members: dict[str, bytes], compress: bool = True) -> None:
    """Rewrite ``d/cameras.npz``: its arrays, with ``members`` (name -> .npy bytes) added or replacing."""
    with np.load(d / "cameras.npz") as z:
        arrays = {k: z[k] for k in z.files}
    with zipfile.ZipFile(d / "cameras.npz", "w", zipfile.ZIP_DEFLATED if compress else zipfile.ZIP_STORED) as z:
        for k, v in arrays.items():
            if k not in members:
                buf = io.BytesIO()
                np.save(buf, v)
                z.writestr(k + ".npy", buf.getvalue())
        for k, b in members.items():
            z.writestr(k + ".npy", b)


HUGE = ("<f8", (100_000, 100_000))      # 74.5 GiB declared, a few bytes held


def test_a_member_no_loader_needs_is_never_read(service, tmp_path):
    """The junk member declares 74.5 GiB: reading it was a MemoryError (422 internal_error); now
    the loader never opens it, and the upload is accepted."""
    clients, svc, data = service()
    zb = dtu_zip(tmp_path, lambda d: with_members(d, {"junk": npy_bytes(*HUGE, b"\0" * 64)}))
    r = post(clients["alice"], zb)
    assert r.status_code == 202, r.text


@pytest.mark.parametrize("member, code, words", [
    (npy_bytes(*HUGE, b"\0" * 64), "invalid_camera", ("world_mat_0", "(100000, 100000)", "4x4")),
    (npy_bytes("<c16", (4, 4), np.eye(4, dtype=np.complex128).tobytes()), "unsupported_dtype", ("complex128",)),
    (npy_bytes("<U8", (4, 4), b"\0" * (16 * 32)), "unsupported_dtype", ("<U8", "string")),
    (npy_bytes("|O", (4, 4), b"\0" * 64), "unsupported_dtype", ("object",)),
    (npy_bytes("<f8", (4, 4), b"\0" * 8), "unreadable_cameras", ("declares 128 bytes",)),
    (b"\x93NUMPY\x01\x00garbage", "unreadable_cameras", ("world_mat_0", "not a readable .npy")),
])
def test_camera_member_header_checked_before_its_data(service, tmp_path, member, code, words):
    clients, svc, data = service()
    r = post(clients["alice"], dtu_zip(tmp_path, lambda d: with_members(d, {"world_mat_0": member})))
    body = r.json()
    assert r.status_code == 422 and body["code"] == code, r.text
    assert body["errors"][0]["file"] == "cameras.npz" and body["errors"][0]["view"] == 0
    assert all(w in body["detail"] for w in words), body["detail"]
    assert "MemoryError" not in r.text and "internal_error" not in r.text
    assert not leftover_files(data)


def test_parse_dtu_reads_only_the_camera_members(tmp_path):
    """The worker's loader (``load_dtu`` -> ``parse_dtu``) with a 128 MiB compressed-zeros member:
    it allocates nothing near that size (``np.load`` decompressed every member: 3.85 GB for the
    probe's 3 * 2**27 floats)."""
    from nepf_core.data.dtu import parse_dtu

    d = make_dtu_dir(tmp_path / "dtu")
    n = 2 ** 24
    with_members(d, {"junk": npy_bytes("<f8", (n,), bytes(8 * n))})
    assert (d / "cameras.npz").stat().st_size < 2 * 1024 * 1024
    tracemalloc.start()
    try:
        specs, scale, _ = parse_dtu(d)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert len(specs) == 6 and scale is not None
    assert peak < 8 * 1024 * 1024, peak


# ------------------------------------------------------------------ internal errors (finding 3)
def test_a_validator_bug_is_a_500_internal_error_without_its_text(service, tmp_path, caplog):
    """A crash of the validator (exit 3, a traceback on stderr) is a real bug: 500 ``internal_error``
    whose answer holds no Python text; the traceback is in the server's log."""
    fake = tmp_path / "python-with-a-bug"
    fake.write_text("#!/bin/sh\necho 'Traceback (most recent call last):' >&2\n"
                    "echo 'KeyError: secret-detail' >&2\n"
                    "echo '{\"ok\": false, \"errors\": [{\"code\": \"internal_error\"}]}'\nexit 3\n")
    fake.chmod(fake.stat().st_mode | stat.S_IXUSR)
    clients, svc, data = service(python_executable=str(fake))
    with caplog.at_level("ERROR", logger="nepf.api"):
        r = post(clients["alice"], dtu_zip(tmp_path))
    assert r.status_code == 500 and r.json()["code"] == "internal_error", r.text
    assert "secret-detail" not in r.text and "Traceback" not in r.text
    assert "secret-detail" in caplog.text
    assert not leftover_files(data)


def test_validator_main_keeps_the_traceback_out_of_its_json(tmp_path, monkeypatch, capsys):
    from nepf_core.data import validate

    def boom(*a, **k):
        raise KeyError("secret-detail")
    monkeypatch.setattr(validate, "validate_dataset", boom)
    assert validate.main([str(tmp_path)]) == validate.EXIT_INTERNAL_ERROR
    out, err = capsys.readouterr()
    result = json.loads(out.strip().splitlines()[-1])
    assert result["errors"][0]["code"] == "internal_error" and "secret" not in out
    assert "Traceback" in err and "secret-detail" in err


def test_an_unhandled_exception_is_a_500_in_the_error_shape(tmp_path, monkeypatch):
    from api.main import create_app
    from api.settings import Settings
    from jobstore.engine import dispose_engines

    for k in list(os.environ):
        if k.startswith("NEPF_"):
            monkeypatch.delenv(k)
    app = create_app(Settings(data_dir=tmp_path / "data", web_dir=tmp_path / "none", reconcile_interval_s=0))

    @app.get("/boom")
    def boom():
        raise RuntimeError("secret-detail")
    with TestClient(app, raise_server_exceptions=False) as c:
        r = c.get("/boom")
    dispose_engines()
    assert r.status_code == 500 and r.json() == {"detail": "internal server error (logged on the server)",
                                                 "code": "internal_error", "errors": []}


if __name__ == "__main__":
    sys.exit(pytest.main([__file__, "-q"]))
