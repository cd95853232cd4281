"""Malformed uploads: each is a 4xx with a specific code and message, and leaves nothing on disk."""

from __future__ import annotations

import io
import json
import struct
import zipfile
import zlib
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient
from PIL import Image
from sqlalchemy import func, select

from api.auth import create_token
from api.main import create_app
from api.settings import Settings
from jobstore.engine import dispose_engines
from jobstore.models import Job
from service_fixtures import leftover_files, make_dtu_dir, zip_dir


@pytest.fixture
def make_client(tmp_path, monkeypatch):
    for k in list(__import__("os").environ):
        if k.startswith("NEPF_"):
            monkeypatch.delenv(k)
    made = []

    def make(**overrides):
        data = tmp_path / f"data{len(made)}"
        settings = Settings(data_dir=data, reconcile_interval_s=0, **overrides)
        app = create_app(settings)
        svc = app.state.service
        token = create_token(svc.Session, "alice")
        client = TestClient(app)
        client.headers["Authorization"] = f"Bearer {token}"
        made.append(client)
        return client, svc, data

    yield make
    for c in made:
        c.close()
    dispose_engines()


def post(client, zbytes: bytes, config=None, headers=None, filename="ds.zip"):
    data = {"config": json.dumps(config)} if config is not None else None
    return client.post("/jobs", files={"dataset": (filename, zbytes, "application/zip")}, data=data,
                       headers=headers or {})


# ---------------------------------------------------------------- builders
def zbytes_from(tmp: Path, mutate=None, prefix="scan/", **kw) -> bytes:
    d = make_dtu_dir(tmp / "ds", **kw)
    if mutate:
        mutate(d)
    return zip_dir(d, tmp / "ds.zip", prefix=prefix).read_bytes()


def raw_zip(entries) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as z:
        for e in entries:
            if isinstance(e, zipfile.ZipInfo):
                z.writestr(e, b"target")
            else:
                name, data = e
                z.writestr(name, data)
    return buf.getvalue()


def cams_edit(fn):
    def mutate(d: Path):
        cams = dict(np.load(d / "cameras.npz"))
        fn(cams)
        np.savez(d / "cameras.npz", **cams)
    return mutate


def png_header_only(w: int, h: int) -> bytes:
    def chunk(kind, data):
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(b"\0" * 64)) + chunk(b"IEND", b""))


def symlink_zip() -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as z:
        z.writestr("scan/cameras.npz", b"x")
        zi = zipfile.ZipInfo("scan/image/000.png")
        zi.create_system = 3
        zi.external_attr = (0o120777 << 16)
        z.writestr(zi, "/etc/passwd")
    return buf.getvalue()


def bomb_zip() -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as z:
        z.writestr("scan/cameras.npz", b"\0" * (30 * 1024 * 1024))
    return buf.getvalue()


def truncate_png(d: Path):
    p = d / "image" / "002.png"
    b = p.read_bytes()
    p.write_bytes(b[: len(b) // 2])


def resize_one(d: Path):
    Image.new("RGB", (20, 16), (10, 20, 30)).save(d / "image" / "003.png")


def black_mask(d: Path):
    Image.new("L", (24, 24), 0).save(d / "mask" / "001.png")


def jpeg_named_png(d: Path):
    Image.new("RGB", (24, 24), (1, 2, 3)).save(d / "image" / "001.png", format="JPEG")


def noise_image(d: Path):
    rng = np.random.default_rng(0)
    Image.fromarray(rng.integers(0, 255, (256, 256, 3), dtype=np.uint8)).save(d / "image" / "noise.png")


def bmp_image(d: Path):
    Image.new("RGB", (24, 24)).save(d / "image" / "006.bmp")


# (id, builder(tmp) -> bytes, settings overrides, expected status, expected code(s), a word the message names)
CASES = [
    ("zip_slip_dotdot", lambda t: raw_zip([("scan/cameras.npz", b"x"), ("../../evil.txt", b"pwned")]), {},
     422, {"zip_slip"}, "evil.txt"),
    ("zip_slip_absolute", lambda t: raw_zip([("/tmp/evil.txt", b"pwned")]), {}, 422, {"zip_slip"}, "evil.txt"),
    ("zip_symlink", lambda t: symlink_zip(), {}, 422, {"zip_symlink"}, "000.png"),
    ("zip_bomb_ratio", lambda t: bomb_zip(), {}, 422, {"zip_bomb"}, "ratio"),
    ("zip_bomb_total", lambda t: zbytes_from(t), {"max_unzipped_mb": 0.001}, 422, {"zip_bomb"}, "NEPF_MAX_UNZIPPED_MB"),
    ("too_many_entries", lambda t: zbytes_from(t), {"max_zip_entries": 5}, 422, {"too_many_entries"}, "entries"),
    ("image_bomb", lambda t: zbytes_from(t, lambda d: (d / "image" / "000.png").write_bytes(png_header_only(40000, 40000))),
     {}, 422, {"image_bomb"}, "000.png"),
    ("not_a_zip", lambda t: b"this is not a zip file at all" * 10, {}, 422, {"not_a_zip"}, "zip"),
    ("empty_zip", lambda t: raw_zip([]), {}, 422, {"empty_zip"}, "no files"),
    ("missing_cameras", lambda t: zbytes_from(t, lambda d: (d / "cameras.npz").unlink()), {},
     422, {"unknown_layout"}, None),
    ("nan_pose", lambda t: zbytes_from(t, cams_edit(lambda c: c["world_mat_2"].__setitem__((0, 3), np.nan))), {},
     422, {"nonfinite_camera"}, "cameras.npz"),
    ("singular_pose", lambda t: zbytes_from(t, cams_edit(lambda c: c.__setitem__("world_mat_1", np.zeros((4, 4))))),
     {}, 422, {"singular_camera", "invalid_camera"}, "cameras.npz"),
    ("count_mismatch", lambda t: zbytes_from(t, lambda d: (d / "image" / "005.png").unlink()), {},
     422, {"count_mismatch"}, None),
    ("size_mismatch", lambda t: zbytes_from(t, resize_one), {}, 422, {"size_mismatch"}, "003.png"),
    ("corrupt_png", lambda t: zbytes_from(t, truncate_png), {}, 422, {"corrupt_image"}, "002.png"),
    ("all_black_mask", lambda t: zbytes_from(t, black_mask), {}, 422, {"empty_mask"}, "001.png"),
    ("too_large_upload", lambda t: zbytes_from(t, noise_image), {"max_upload_mb": 0.05}, 413,
     {"upload_too_large"}, "NEPF_MAX_UPLOAD_MB"),
    ("unknown_layout", lambda t: raw_zip([("stuff/readme.txt", b"hello"), ("stuff/notes.json", b"{}")]), {},
     422, {"unknown_layout"}, None),
    ("unsupported_image_format", lambda t: zbytes_from(t, bmp_image), {}, 422, {"unsupported_image_format"}, ".bmp"),
    ("format_mismatch", lambda t: zbytes_from(t, jpeg_named_png), {}, 422, {"image_format_mismatch"}, "001.png"),
]


@pytest.mark.parametrize("case", CASES, ids=[c[0] for c in CASES])
def test_malformed_upload_rejected_and_nothing_left(case, make_client, tmp_path):
    name, build, overrides, status, codes, word = case
    client, svc, data = make_client(**overrides)
    r = post(client, build(tmp_path))
    assert r.status_code == status, r.text
    body = r.json()
    assert body["code"] in codes, body
    assert body["detail"] and isinstance(body["detail"], str)
    if word is not None:
        assert word in body["detail"] or any(word in (e.get("file") or "") for e in body["errors"]), body
    if body["errors"]:
        assert all({"code", "message", "file", "view"} <= set(e) for e in body["errors"])
    assert leftover_files(data) == []
    with svc.Session() as s:
        assert s.execute(select(func.count()).select_from(Job)).scalar_one() == 0
    assert not list(tmp_path.glob("evil.txt")) and not Path("/tmp/evil.txt").exists()


def test_dataset_errors_name_file_and_view(make_client, tmp_path):
    """The 422 body carries the loader's error list (same as the CLI): code, message, file, view."""
    client, svc, data = make_client()
    r = post(client, zbytes_from(tmp_path, cams_edit(lambda c: c["world_mat_3"].__setitem__((1, 1), np.inf))))
    assert r.status_code == 422
    err = r.json()["errors"][0]
    assert err["code"] == "nonfinite_camera" and err["file"] == "cameras.npz" and err["view"] == 3


@pytest.mark.parametrize("body,ctype,status,code", [
    (b'{"dataset": "x"}', "application/json", 415, "unsupported_media_type"),
    (b"--B\r\nContent-Disposition: form-data; name=\"config\"\r\n\r\n{}\r\n--B--\r\n",
     "multipart/form-data; boundary=B", 422, "missing_dataset"),
])
def test_request_shape_errors(make_client, body, ctype, status, code):
    client, svc, data = make_client()
    r = client.post("/jobs", content=body, headers={"Content-Type": ctype})
    assert r.status_code == status and r.json()["code"] == code
    assert leftover_files(data) == []


@pytest.mark.parametrize("config", [{"preset": "huge"}, {"iters": -3}, {"iters": "ten"}, {"bogus": 1},
                                    {"time_budget_s": 0}, [1, 2]])
def test_bad_config_rejected(make_client, tmp_path, config):
    client, svc, data = make_client()
    r = post(client, zbytes_from(tmp_path), config=config)
    assert r.status_code == 422 and r.json()["code"] == "invalid_config", r.text
    assert leftover_files(data) == []


def test_valid_upload_queues_job_with_location(make_client, tmp_path):
    client, svc, data = make_client()
    r = post(client, zbytes_from(tmp_path), config={"preset": "tiny", "iters": 7, "name": "my scan"})
    assert r.status_code == 202, r.text
    job = r.json()
    assert r.headers["location"] == f"/jobs/{job['id']}"
    assert job["status"] == "queued" and job["config"] == {"preset": "tiny", "iters": 7, "time_budget_s": None,
                                                           "name": "my scan", "max_image_side": None,
                                                           "texture_size": None, "max_faces": None,
                                                           "holdout_every": 0, "up_axis": None}   # 6 views: none held out; up from the cameras
    assert job["dataset"]["format"] == "dtu" and job["dataset"]["n_views"] == 6
    assert (data / "jobs" / job["id"] / "dataset" / "cameras.npz").is_file()
    assert list((data / "uploads").iterdir()) == []


def test_idempotency_key_replays_and_rejects_reuse(make_client, tmp_path):
    client, svc, data = make_client()
    z = zbytes_from(tmp_path)
    h = {"Idempotency-Key": "upload-42"}
    r1 = post(client, z, config={"preset": "tiny"}, headers=h)
    r2 = post(client, z, config={"preset": "tiny"}, headers=h)
    assert r1.status_code == 202 and r2.status_code == 202
    assert r1.json()["id"] == r2.json()["id"] and r2.headers.get("idempotent-replayed") == "true"
    with svc.Session() as s:
        assert s.execute(select(func.count()).select_from(Job)).scalar_one() == 1
    r3 = post(client, z, config={"preset": "fast"}, headers=h)
    assert r3.status_code == 409 and r3.json()["code"] == "idempotency_key_reused"
    assert len(list((data / "jobs").iterdir())) == 1 and list((data / "uploads").iterdir()) == []
