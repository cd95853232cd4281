"""Upload validation against issue 23's dataset findings: frames pointing outside the upload
(another user's job included), the decoded-pixel cap, the working-resolution ceiling, the
image-bomb and camera-file messages, and no absolute server path in any answer."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient
from PIL import Image

from api.auth import create_token
from api.main import create_app
from api.settings import Settings
from jobstore.engine import dispose_engines
from service_fixtures import leftover_files, look_at_w2c, make_dtu_dir, zip_dir


@pytest.fixture
def service(tmp_path, monkeypatch):
    """``make(**settings) -> (clients {user: TestClient}, svc, data dir)`` for users alice and bob."""
    for k in list(os.environ):
        if k.startswith("NEPF_"):
            monkeypatch.delenv(k)
    made = []

    def make(**overrides):
        data = tmp_path / f"data{len(made)}"
        app = create_app(Settings(data_dir=data, reconcile_interval_s=0, **overrides))
        svc = app.state.service
        clients = {}
        for user in ("alice", "bob"):
            c = TestClient(app)
            c.headers["Authorization"] = f"Bearer {create_token(svc.Session, user)}"
            clients[user] = c
            made.append(c)
        return clients, svc, data

    yield make
    for c in made:
        c.close()
    dispose_engines()


def post(client, zbytes: bytes, config=None):
    data = {"config": json.dumps(config)} if config is not None else None
    return client.post("/jobs", files={"dataset": ("ds.zip", zbytes, "application/zip")}, data=data)


def dtu_zip(tmp: Path, mutate=None, **kw) -> bytes:
    d = make_dtu_dir(tmp / "dtu", **kw)
    if mutate:
        mutate(d)
    return zip_dir(d, tmp / "dtu.zip", prefix="scan/").read_bytes()


def ingp_zip(tmp: Path, file_paths: dict[int, str], n: int = 6, size: int = 24) -> bytes:
    """An instant-ngp upload (``transforms.json`` + ``images/``) whose frames ``file_paths``
    name other files, as written."""
    root = tmp / "ingp"
    make_dtu_dir(root, n=n, size=size, masks=False)     # for its images
    (root / "cameras.npz").unlink()
    (root / "image").rename(root / "images")
    frames = []
    for i in range(n):
        a = 2 * np.pi * i / n
        R, t = look_at_w2c((3 * np.cos(a), 3 * np.sin(a), 1.0))
        c2w = np.eye(4)
        c2w[:3, :3], c2w[:3, 3] = R.T, -R.T @ t
        c2w_gl = c2w @ np.diag([1.0, -1.0, -1.0, 1.0])
        frames.append({"file_path": file_paths.get(i, f"images/{i:03d}.png"),
                       "transform_matrix": c2w_gl.tolist()})
    f = size * 1.2
    meta = {"fl_x": f, "fl_y": f, "cx": size / 2, "cy": size / 2, "w": size, "h": size, "frames": frames}
    (root / "transforms.json").write_text(json.dumps(meta))
    return zip_dir(root, tmp / "ingp.zip", prefix="capture/").read_bytes()


def test_frames_pointing_at_another_users_job_are_refused(service, tmp_path):
    clients, svc, data = service()
    r = post(clients["alice"], dtu_zip(tmp_path))
    assert r.status_code == 202, r.text
    victim = data / "jobs" / r.json()["id"] / "dataset" / "image" / "000.png"
    assert victim.is_file()
    assert post(clients["bob"], ingp_zip(tmp_path / "ok", {})).status_code == 202   # the layout is fine
    before = sorted(leftover_files(data))
    # bob's zip unpacks into <data>/uploads/<staging>/extract/capture: four levels below <data>
    relative = os.path.relpath(victim, data / "uploads" / "s" / "extract" / "capture")
    assert relative.startswith("../../../../jobs/")
    for k, written in enumerate((str(victim), relative, str(victim.with_suffix("")))):
        r = post(clients["bob"], ingp_zip(tmp_path / f"b{k}", {2: written}))
        assert r.status_code == 422, r.text
        body = r.json()
        assert body["code"] == "path_outside_dataset", body
        assert written in body["detail"] and "points outside the dataset folder" in body["detail"]
        assert (body["errors"][0]["file"], body["errors"][0]["view"]) == ("transforms.json", 2)
        if not os.path.isabs(written):
            assert str(data) not in r.text and str(data.resolve()) not in r.text
    assert sorted(leftover_files(data)) == before      # nothing left behind, no job made for bob
    jobs = clients["bob"].get("/jobs").json()
    assert jobs["total"] == 1


def test_decoded_pixel_cap_refuses_before_decoding_and_names_the_limit(service, tmp_path):
    clients, svc, data = service(max_total_pixels=3 * 1000 * 1000 - 1)
    z = dtu_zip(tmp_path, n=3, size=1000)     # three 1000x1000 PNGs, compressible: a ~20 KB zip
    assert len(z) < 200_000
    r = post(clients["alice"], z)
    assert r.status_code == 422, r.text
    body = r.json()
    assert body["code"] == "too_many_pixels"
    assert "NEPF_MAX_TOTAL_PIXELS" in body["detail"] and f"{3 * 1000 * 1000 - 1:,}" in body["detail"]
    assert leftover_files(data) == []


def test_working_size_is_reported_and_capped_by_the_ceiling(service, tmp_path):
    clients, svc, data = service(max_total_pixels=3 * 1000 * 1000, max_image_side=800)
    z = dtu_zip(tmp_path, n=3, size=1000)
    r = post(clients["alice"], z, config={"max_image_side": 500})
    assert r.status_code == 202, r.text
    job = r.json()
    assert job["config"]["max_image_side"] == 500
    assert (job["dataset"]["width"], job["dataset"]["working_width"], job["dataset"]["working_height"]) == (
        1000, 500, 500)
    r = post(clients["alice"], z)                                  # no ask: the ceiling
    assert r.status_code == 202 and r.json()["dataset"]["working_width"] == 800
    assert svc.settings.job_max_side(None) == 800 and svc.settings.job_max_side(500) == 500
    # a job that asks nothing trains at the default side, capped by the ceiling
    from api.settings import Settings
    assert Settings(max_image_side=1600, default_image_side=800).job_max_side(None) == 800
    assert Settings(max_image_side=600, default_image_side=800).job_max_side(None) == 600
    assert Settings(max_image_side=1600, default_image_side=0).job_max_side(None) == 1600
    assert Settings(max_image_side=0, default_image_side=800).job_max_side(None) == 800
    assert Settings(max_image_side=0, default_image_side=0).job_max_side(None) == 0
    r = post(clients["alice"], z, config={"max_image_side": 801})
    assert r.status_code == 422 and r.json()["code"] == "invalid_config"
    assert "NEPF_MAX_IMAGE_SIDE" in r.json()["detail"] and "800" in r.json()["detail"]
    for bad in (4, "big", True, 512.5):
        r = post(clients["alice"], z, config={"max_image_side": bad})
        assert r.status_code == 422 and r.json()["code"] == "invalid_config", bad


def test_image_bomb_message_states_the_limit_in_force(service, tmp_path):
    """Pillow refuses images over twice its limit itself, with its own number; the message
    must state the setting (here 1,000,000), whichever check fires."""
    from test_api_uploads import png_header_only
    clients, svc, data = service(max_image_pixels=1_000_000)
    for w, h in ((1200, 1000), (3000, 3000)):          # ours (1.2 Mpx), then Pillow's (> 2 Mpx)
        r = post(clients["alice"], dtu_zip(tmp_path / f"{w}", lambda d: (d / "image" / "000.png").write_bytes(
            png_header_only(w, h))))
        assert r.status_code == 422 and r.json()["code"] == "image_bomb", r.text
        assert "1000000" in r.json()["detail"] and "2000000" not in r.json()["detail"]


def test_garbage_camera_file_is_not_a_valid_npz(service, tmp_path):
    clients, svc, data = service()
    r = post(clients["alice"], dtu_zip(tmp_path, lambda d: (d / "cameras.npz").write_bytes(b"garbage" * 10)))
    assert r.status_code == 422 and r.json()["code"] == "unreadable_cameras", r.text
    assert "not a valid .npz" in r.json()["detail"] and "pickle" not in r.json()["detail"]


def test_job_answers_hold_no_absolute_server_path(service, tmp_path):
    clients, svc, data = service()
    r = post(clients["alice"], dtu_zip(tmp_path))
    assert r.status_code == 202
    jid = r.json()["id"]
    texts = [r.text] + [clients["alice"].get(u).text for u in (f"/jobs/{jid}", "/jobs")]
    for t in texts:
        assert str(data) not in t and str(data.resolve()) not in t and str(tmp_path) not in t


def test_a_failed_jobs_error_holds_no_absolute_server_path(service, tmp_path):
    from worker.runner import JobRunner
    clients, svc, data = service()
    jid = post(clients["alice"], dtu_zip(tmp_path)).json()["id"]

    def pipeline(request):
        open(Path(request.run_dir) / "missing" / "checkpoint.pt")   # FileNotFoundError naming the path

    JobRunner(svc.settings, svc.Session, jid, "w1", pipeline=pipeline).run()
    job = clients["alice"].get(f"/jobs/{jid}").json()
    assert job["status"] == "failed" and "checkpoint.pt" in job["error"]
    assert str(data.resolve()) not in job["error"] and str(data) not in job["error"]


def test_small_images_pass_unchanged(service, tmp_path):
    clients, svc, data = service()
    r = post(clients["alice"], dtu_zip(tmp_path))
    d = r.json()["dataset"]
    assert (d["width"], d["height"], d["working_width"], d["working_height"]) == (24, 24, 24, 24)
    assert d["total_pixels"] == 6 * 24 * 24
    img = np.asarray(Image.open(data / "jobs" / r.json()["id"] / "dataset" / "image" / "000.png"))
    assert img.shape == (24, 24, 3)


def test_worker_passes_the_jobs_working_side_to_the_pipeline(service, tmp_path):
    from worker.runner import JobRunner
    clients, svc, data = service(max_image_side=800)
    seen = {}

    def pipeline(request):
        seen[request.data_dir.parent.name] = request.max_side
        return {"status": "succeeded", "step": 1, "total": 1}

    asked = post(clients["alice"], dtu_zip(tmp_path / "a"), config={"max_image_side": 300}).json()["id"]
    default = post(clients["alice"], dtu_zip(tmp_path / "b")).json()["id"]
    for jid in (asked, default):
        assert JobRunner(svc.settings, svc.Session, jid, "w1", pipeline=pipeline).run() == "succeeded"
    assert seen == {asked: 300, default: 800}
