"""The embedded default: ``nepf serve`` with no NEPF_BROKER_URL runs the API plus a local worker
on a SQLite broker in the data dir. Real processes, real HTTP."""

from __future__ import annotations


import httpx
import pytest

from service_fixtures import (REAL_ITERS, REAL_PIPELINE_ENV, max_metric_step, real_scene_zip, check_lifecycle, dataset_zip_bytes, get_job, local_token, service_env, start_api,
                              upload, wait_for, wait_status, worker_pids)

FAST = dict(NEPF_PIPELINE="service_fixtures:fake_pipeline", NEPF_LEASE_S="3", NEPF_HEARTBEAT_S="0.3",
            NEPF_RECONCILE_INTERVAL_S="1")


@pytest.fixture
def embedded(tmp_path):
    data = tmp_path / "data"
    api, base = start_api(service_env(data, NEPF_FAKE_STEP_S="0.04", **FAST), tmp_path)
    h = {"Authorization": f"Bearer {local_token(data)}"}
    yield base, h, data, api
    api.stop()


def test_serve_prints_login_url_and_keeps_token(embedded):
    base, h, data, api = embedded
    out = api.output()
    assert f"{base}/#token={local_token(data)}" in out
    assert (data / "local-token").stat().st_mode & 0o077 == 0
    assert httpx.get(base + "/jobs", headers=h).status_code == 200
    assert httpx.get(base + "/").status_code == 200          # viewer mount (or its placeholder)
    assert httpx.get(base + "/openapi.json").json()["info"]["title"]


def test_embedded_lifecycle_fake_pipeline(embedded, tmp_path):
    """The same life cycle with the fake pipeline, which also writes sync and test records."""
    base, h, data, api = embedded
    final = check_lifecycle(base, h, dataset_zip_bytes(tmp_path), {"preset": "tiny", "iters": 30}, 60)
    assert final["delivery"]["attempts"] == 1
    assert final["decisions"] and final["decisions"][0]["decision"] == "ray_batch"
    recs = httpx.get(f"{base}/jobs/{final['id']}/metrics", headers=h).json()["records"]
    assert any(r.get("kind") == "sync" and {"psnr_r", "psnr_surf", "psnr_vol"} <= set(r) for r in recs)
    assert any(r.get("kind") == "test" and "test_psnr" in r for r in recs)


def test_embedded_lifecycle_real_tiny_pipeline(tmp_path):
    """The full life cycle on the embedded default, training with the real core (`tiny`, CPU)."""
    data = tmp_path / "data"
    api, base = start_api(service_env(data, NEPF_LEASE_S="30", **REAL_PIPELINE_ENV), tmp_path, name="real")
    try:
        h = {"Authorization": f"Bearer {local_token(data)}"}
        final = check_lifecycle(base, h, real_scene_zip(tmp_path), {"preset": "tiny", "iters": REAL_ITERS}, 240)
        assert final["delivery"]["attempts"] == 1 and final["progress"]["step"] == REAL_ITERS
        assert final["decisions"] and all("decision" in d for d in final["decisions"])
        arts = httpx.get(f"{base}/jobs/{final['id']}/artifacts", headers=h).json()["artifacts"]
        previews = [a for a in arts if a["content_type"] == "image/png"]
        assert previews and httpx.get(base + previews[0]["url"], headers=h).content[:4] == b"\x89PNG"
    finally:
        api.stop()


def test_embedded_worker_kill9_resumes(tmp_path):
    """kill -9 the embedded worker mid-job: `nepf serve` restarts it, the reconciler re-queues the job
    once its lease expires, and the job resumes from its checkpoint and completes exactly once.

    Issue 37: each step is listed once in the metrics (the records after the checkpoint are
    dropped on resume), the resumed attempt's progress is `resuming` at the checkpoint's step and
    never drops to the pipeline's `loading` step 0, and `first_step` is the checkpoint step + 1."""
    data = tmp_path / "data"
    # the fake "loads" for 1 s, as the core does, reporting step 0 meanwhile
    api, base = start_api(service_env(data, NEPF_FAKE_STEP_S="0.04", NEPF_FAKE_LOAD_S="1", **FAST), tmp_path)
    try:
        h = {"Authorization": f"Bearer {local_token(data)}"}
        _kill9_and_resume(base, h, data, api, tmp_path)
    finally:
        api.stop()


def _kill9_and_resume(base, h, data, api, tmp_path):
    import os
    import signal
    import time

    r = upload(base, h, dataset_zip_bytes(tmp_path), {"preset": "tiny", "iters": 120})
    jid = r.json()["id"]
    wait_for(lambda: get_job(base, h, jid)["progress"]["step"] >= 32, 30, what="step 32")
    pid = worker_pids(api.output())[-1]
    os.kill(pid, signal.SIGKILL)
    data_dir = data
    killed_at = max_metric_step(data_dir, jid)
    seen = []                           # (attempts, step, stage) polled while the job resumes
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        job = get_job(base, h, jid)
        seen.append((job["delivery"]["attempts"], job["progress"]["step"], job["progress"]["stage"]))
        if job["status"] in ("succeeded", "failed"):
            break
        time.sleep(0.05)
    final = wait_status(base, h, jid, ("succeeded", "failed"), 10)
    # the error and the delivery log first: pytest cuts a long dict, and CI once showed only "failed"
    assert final["status"] == "succeeded", (final.get("error"), final.get("delivery"), api.output()[-3000:])
    log = final["delivery"]["attempt_log"]
    assert final["delivery"]["attempts"] == 2 and len(log) == 2
    assert 1 < log[1]["first_step"] <= killed_at + 1, log       # resumed from a checkpoint, not from zero
    resumed_from = log[1]["first_step"] - 1
    assert resumed_from % 5 == 0, log                            # the fake checkpoints every 5 steps
    assert final["delivery"]["completions"] == 1
    done = (data / "jobs" / jid / "run" / "completions.log").read_text().splitlines()
    assert len(done) == 1 and done[0].split()[1:] == ["succeeded", "120"]
    recs = httpx.get(f"{base}/jobs/{jid}/metrics", headers=h).json()["records"]
    train_steps = [r["step"] for r in recs if "kind" not in r]
    assert train_steps == list(range(1, 121)), [s for s in set(train_steps) if train_steps.count(s) > 1]
    second = [(step, stage) for attempts, step, stage in seen if attempts == 2]
    assert second and all(step >= resumed_from for step, _ in second), second     # never back to 0
    steps = [step for step, _ in second]
    assert steps == sorted(steps), second                                        # never backwards
    assert ("resuming" in {stage for _, stage in second}), second                # seen during the 1 s load
