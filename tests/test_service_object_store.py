"""Two "machines" that share no disk: the API (`nepf serve --no-worker --data-dir A`) and workers
(`nepf worker --data-dir B...`), with PostgreSQL, a private Redis and a private SeaweedFS S3
server (`NEPF_STORAGE_URL`). Covers the life cycle through the store, resume on a fresh worker
after kill -9, SSE tickets across two API processes, downloads (streamed, Range, 304,
presigned), authorisation, DELETE, and the store unreachable at a job's start and mid-job.
"""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys

import httpx
import pytest

from service_fixtures import (REAL_ITERS, REAL_PIPELINE_ENV, REPO, Proc, check_lifecycle, create_token,
                              dataset_zip_bytes, get_job, pg_database, real_scene_zip, service_env, start_api,
                              start_redis, upload, wait_for, wait_status)
from storage_fixtures import BUCKET, Seaweed

PREFIX = "deploy1"
SECRET = "shared-secret-for-the-replicas-0123456789"


@pytest.fixture(scope="module")
def stack(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("object_store")
    weed = Seaweed(tmp).start()
    redis_proc, port = start_redis(tmp)
    db_url, drop_db = pg_database()
    a = tmp / "A"
    env = service_env(a, NEPF_BROKER_URL=f"redis://127.0.0.1:{port}/0", NEPF_DATABASE_URL=db_url,
                      NEPF_STORAGE_URL=f"s3://{BUCKET}/{PREFIX}", NEPF_SECRET_KEY=SECRET,
                      NEPF_PIPELINE="service_fixtures:fake_pipeline", NEPF_FAKE_STEP_S="0.04",
                      NEPF_LEASE_S="3", NEPF_HEARTBEAT_S="0.3", NEPF_RECONCILE_INTERVAL_S="1",
                      NEPF_STORAGE_SYNC_S="0.5", **weed.env)
    api, base = start_api(env, tmp, extra=["--no-worker", "--data-dir", str(a)])
    h = {"Authorization": f"Bearer {create_token(env, 'carol')}"}
    st = {"tmp": tmp, "env": env, "base": base, "h": h, "a": a, "weed": weed, "api": api}
    yield st
    api.stop()
    redis_proc.stop()
    weed.stop()
    drop_db()


@pytest.fixture
def worker(stack):
    procs = []

    def start(name: str, **env) -> Proc:
        data = stack["tmp"] / f"B-{name}"
        p = Proc([sys.executable, "-m", "worker.commands", "--queues", "default,gpu", "--concurrency", "1",
                  "--data-dir", str(data)], {**stack["env"], "NEPF_DATA_DIR": str(data), **env},
                 stack["tmp"] / f"worker-{name}.log")
        p.data = data
        procs.append(p)
        return p
    yield start
    for p in procs:
        p.stop()


def job_keys(stack, jid: str) -> list[str]:
    return stack["weed"].keys(f"{PREFIX}/jobs/{jid}/")


def files_under(path) -> list[str]:
    return sorted(str(p.relative_to(path)) for p in path.rglob("*") if p.is_file()) if path.exists() else []


def test_real_tiny_job_through_the_object_store(stack, worker):
    """Upload -> worker on B (its own data dir) -> charts, artifacts, GLB through the API on A;
    A keeps no dataset or run file; DELETE empties the job's prefix."""
    base, h = stack["base"], stack["h"]
    w = worker("real", NEPF_LEASE_S="30", **REAL_PIPELINE_ENV)
    final = check_lifecycle(base, h, real_scene_zip(stack["tmp"]), {"preset": "tiny", "iters": REAL_ITERS}, 300)
    jid = final["id"]
    assert final["delivery"]["attempts"] == 1 and final["progress"]["step"] == REAL_ITERS
    keys = job_keys(stack, jid)
    assert any(k.endswith("/dataset/cameras.npz") for k in keys), keys
    assert any(k.endswith("/run/asset.glb") for k in keys) and any(k.endswith("/run/manifest.json") for k in keys)
    assert any(k.endswith("/run/checkpoints/latest.pt") for k in keys)
    # machine A: the login token only, no dataset, no run files, no staging left
    assert files_under(stack["a"]) == ["local-token"], files_under(stack["a"])
    wait_for(lambda: not (w.data / "work" / jid).exists(), 10, what="B's scratch removed")
    assert w.alive()
    r = httpx.delete(f"{base}/jobs/{jid}", headers=h)
    assert r.status_code == 204
    assert job_keys(stack, jid) == []
    assert httpx.get(f"{base}/jobs/{jid}", headers=h).status_code == 404


def test_kill9_worker_resumes_on_a_fresh_worker_from_the_stored_checkpoint(stack, worker):
    base, h, weed = stack["base"], stack["h"], stack["weed"]
    w1 = worker("w1")
    jid = upload(base, h, dataset_zip_bytes(stack["tmp"] / "k"), {"preset": "tiny", "iters": 150}).json()["id"]
    ck_key = f"{PREFIX}/jobs/{jid}/run/checkpoints/latest.json"
    wait_for(lambda: json.loads(weed.read(ck_key))["step"] >= 30, 60, what="a stored checkpoint at step >= 30")
    w1.kill9()
    stored = json.loads(weed.read(ck_key))["step"]
    assert get_job(base, h, jid)["status"] in ("running", "queued")
    w2 = worker("w2")                                     # another machine: a fresh data dir
    assert not w2.data.exists() or not (w2.data / "work").exists()
    final = wait_status(base, h, jid, ("succeeded", "failed"), 120)
    assert final["status"] == "succeeded", final
    log = final["delivery"]["attempt_log"]
    assert final["delivery"]["attempts"] == 2 and len(log) == 2, log
    assert stored + 1 <= log[1]["first_step"] <= 150, (log, stored)   # from the stored checkpoint, not 1
    assert (log[1]["first_step"] - 1) % 5 == 0, log       # a checkpoint step (every 5) + 1
    assert final["progress"]["step"] == 150 and final["delivery"]["completions"] == 1
    # every step listed once, through the API (the metrics come from the store)
    recs = httpx.get(f"{base}/jobs/{jid}/metrics", headers=h).json()["records"]
    train = [r["step"] for r in recs if "kind" not in r]
    assert train == list(range(1, 151)), [s for s in set(train) if train.count(s) > 1]
    done = weed.read(f"{PREFIX}/jobs/{jid}/run/completions.log").decode().splitlines()
    assert len(done) == 1, done                                      # exactly one final result
    assert files_under(stack["a"]) == ["local-token"]



def test_sigterm_worker_stores_its_checkpoint_and_the_job_moves_to_another_machine(stack, worker):
    """A worker stopped with SIGTERM (docker compose stop) re-queues its job after its last
    checkpoint reached the bucket; a worker on another data dir resumes it from there."""
    base, h, weed = stack["base"], stack["h"], stack["weed"]
    w1 = worker("term1")
    jid = upload(base, h, dataset_zip_bytes(stack["tmp"] / "t"), {"preset": "tiny", "iters": 150}).json()["id"]
    wait_for(lambda: get_job(base, h, jid)["progress"]["step"] >= 30, 60, what="step 30")
    w1.stop(timeout=60)
    j = wait_status(base, h, jid, "queued", 10)
    assert j["progress"]["stage"] == "interrupted", j
    stored = json.loads(weed.read(f"{PREFIX}/jobs/{jid}/run/checkpoints/latest.json"))["step"]
    assert stored >= 30
    assert not (w1.data / "work" / jid).exists()          # the scratch copy went with the worker
    worker("term2")
    final = wait_status(base, h, jid, ("succeeded", "failed"), 120)
    assert final["status"] == "succeeded", final
    log = final["delivery"]["attempt_log"]
    assert log[0].get("interrupted") == "worker shutdown" and log[1]["first_step"] == stored + 1, log
    recs = httpx.get(f"{base}/jobs/{jid}/metrics", headers=h).json()["records"]
    assert [r["step"] for r in recs if "kind" not in r] == list(range(1, 151))

def test_downloads_authorisation_and_tickets_across_two_api_processes(stack, worker):
    """A second API process (other data dir, same NEPF_SECRET_KEY, presigned downloads) accepts the
    first one's SSE ticket; streamed downloads answer Range and If-None-Match; checkpoints are
    never served; another owner gets 404; a presigned URL names one object and expires."""
    base, h, env = stack["base"], stack["h"], stack["env"]
    worker("dl")
    jid = upload(base, h, dataset_zip_bytes(stack["tmp"] / "d"), {"preset": "tiny", "iters": 20}).json()["id"]
    a2 = stack["tmp"] / "A2"
    api2, base2 = start_api({**env, "NEPF_DATA_DIR": str(a2), "NEPF_STORAGE_PRESIGN_DOWNLOADS": "true"},
                            stack["tmp"], extra=["--no-worker"], name="api2")
    try:
        t = httpx.post(f"{base}/jobs/{jid}/events/ticket", headers=h).json()
        with httpx.stream("GET", base2 + t["url"], timeout=60) as r:
            assert r.status_code == 200
            text = "".join(r.iter_text())
        assert "event: end" in text and '"succeeded"' in text
        wait_status(base, h, jid, "succeeded", 30)
        glb = httpx.get(f"{base}/jobs/{jid}/artifacts/asset.glb", headers=h)
        assert glb.status_code == 200 and glb.content[:4] == b"glTF"
        assert glb.headers["content-type"] == "model/gltf-binary" and "attachment" in glb.headers["content-disposition"]
        part = httpx.get(f"{base}/jobs/{jid}/artifacts/asset.glb", headers={**h, "Range": "bytes=0-3"})
        assert part.status_code == 206 and part.content == b"glTF"
        assert part.headers["content-range"] == f"bytes 0-3/{len(glb.content)}"
        same = httpx.get(f"{base}/jobs/{jid}/artifacts/asset.glb", headers={**h, "If-None-Match": glb.headers["etag"]})
        assert same.status_code == 304
        for bad in ("checkpoints/latest.json", "checkpoints/latest.pt", "../dataset/cameras.npz", "nope.glb"):
            assert httpx.get(f"{base}/jobs/{jid}/artifacts/{bad}", headers=h).status_code == 404, bad
        other = {"Authorization": f"Bearer {create_token(env, 'mallory')}"}
        for path in (f"/jobs/{jid}/artifacts/asset.glb", f"/jobs/{jid}/artifacts", f"/jobs/{jid}/metrics"):
            assert httpx.get(base + path, headers=other).status_code == 404
        red = httpx.get(f"{base2}/jobs/{jid}/artifacts/asset.glb", headers=h)
        assert red.status_code == 307
        url = red.headers["location"]
        assert f"/{BUCKET}/{PREFIX}/jobs/{jid}/run/asset.glb?" in url and "X-Amz-Expires=300" in url
        got = httpx.get(url)
        assert got.status_code == 200 and hashlib.sha256(got.content).digest() == hashlib.sha256(glb.content).digest()
        assert "attachment" in got.headers.get("content-disposition", "")
        assert files_under(a2) == ["local-token"]
    finally:
        api2.stop()


def test_the_api_refuses_to_start_without_a_shared_secret(stack):
    env = {k: v for k, v in stack["env"].items() if k != "NEPF_SECRET_KEY"}
    out = subprocess.run([sys.executable, "-m", "api.commands", "serve", "--no-worker", "--port", "9",
                          "--data-dir", str(stack["tmp"] / "A3")], env=env, cwd=str(REPO),
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 2 and "NEPF_SECRET_KEY" in out.stderr, out.stderr


def test_store_unreachable_at_job_start_waits_then_runs(stack, worker):
    base, h, weed = stack["base"], stack["h"], stack["weed"]
    jid = upload(base, h, dataset_zip_bytes(stack["tmp"] / "s"), {"preset": "tiny", "iters": 20}).json()["id"]
    weed.stop()
    try:
        r = upload(base, h, dataset_zip_bytes(stack["tmp"] / "s2"), {"preset": "tiny", "iters": 20})
        assert r.status_code == 503 and r.json()["code"] == "storage_unavailable", r.text
        worker("start")
        j = wait_for(lambda: (lambda j: j if j["progress"]["stage"] == "waiting_for_storage" else None)(
            get_job(base, h, jid)), 60, what="waiting_for_storage")
        assert j["status"] == "running" and "waiting for the object store" in (j["error"] or "")
        assert "invalid dataset" not in (j["error"] or "")
    finally:
        weed.start()
    final = wait_status(base, h, jid, ("succeeded", "failed"), 90)
    assert final["status"] == "succeeded" and final["error"] is None, final
    arts = httpx.get(f"{base}/jobs/{jid}/artifacts", headers=h).json()
    assert arts["manifest"] and any(a["path"] == "asset.glb" for a in arts["artifacts"])


def test_store_unreachable_mid_job_the_job_goes_on_and_ends_when_it_returns(stack, worker):
    base, h, weed = stack["base"], stack["h"], stack["weed"]
    worker("mid")
    jid = upload(base, h, dataset_zip_bytes(stack["tmp"] / "m"), {"preset": "tiny", "iters": 100}).json()["id"]
    wait_for(lambda: get_job(base, h, jid)["progress"]["step"] >= 20, 60, what="step 20")
    weed.stop()
    try:
        # training goes on without the store; the job cannot end before its results are stored
        wait_for(lambda: get_job(base, h, jid)["progress"]["step"] >= 100, 60, what="the last step")
        assert get_job(base, h, jid)["status"] == "running"
        r = httpx.get(f"{base}/jobs/{jid}/metrics", headers=h)
        assert r.status_code == 503 and r.json()["code"] == "storage_unavailable"
    finally:
        weed.start()
    final = wait_status(base, h, jid, ("succeeded", "failed"), 90)
    assert final["status"] == "succeeded", final
    recs = httpx.get(f"{base}/jobs/{jid}/metrics", headers=h).json()["records"]
    assert [r["step"] for r in recs if "kind" not in r] == list(range(1, 101))
    assert httpx.get(f"{base}/jobs/{jid}/artifacts/asset.glb", headers=h).status_code == 200


def test_kill9_real_pipeline_resumes_from_the_stored_checkpoint(stack, worker):
    """The same crash with the real core (`tiny`, CPU): worker 2, on a fresh data dir, downloads
    `checkpoints/latest.pt` from the bucket and continues; each step's record appears once."""
    base, h, weed = stack["base"], stack["h"], stack["weed"]
    env = dict(REAL_PIPELINE_ENV, NEPF_CHECKPOINT_EVERY="2", NEPF_LEASE_S="4")
    w1 = worker("real-w1", **env)
    iters = 200
    jid = upload(base, h, real_scene_zip(stack["tmp"]), {"preset": "tiny", "iters": iters, "holdout_every": 0}).json()["id"]
    ck_key = f"{PREFIX}/jobs/{jid}/run/checkpoints/latest.json"
    wait_for(lambda: json.loads(weed.read(ck_key))["step"] >= 4, 240, what="a stored checkpoint")
    w1.kill9()
    stored = json.loads(weed.read(ck_key))["step"]
    assert stored < iters
    worker("real-w2", **env)
    final = wait_status(base, h, jid, ("succeeded", "failed"), 420)
    assert final["status"] == "succeeded", final
    log = final["delivery"]["attempt_log"]
    assert final["delivery"]["attempts"] == 2 and len(log) == 2, log
    assert stored + 1 <= log[1]["first_step"] <= iters and log[1]["first_step"] % 2 == 1, (log, stored)
    recs = httpx.get(f"{base}/jobs/{jid}/metrics", headers=h).json()["records"]
    train = [r["step"] for r in recs if r.get("kind") == "train"]
    assert train == list(range(5, iters + 1, 5)), [s for s in set(train) if train.count(s) > 1]
    arts = httpx.get(f"{base}/jobs/{jid}/artifacts", headers=h).json()
    assert any(a["path"].endswith(".glb") for a in arts["artifacts"])
    assert files_under(stack["a"]) == ["local-token"]
