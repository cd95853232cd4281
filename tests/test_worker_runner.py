"""Worker delivery semantics against the real job store (SQLite and PostgreSQL): claim, lease,
redelivery cap, exactly-once completion, cancel, error mapping, and the reconciler."""

from __future__ import annotations

import datetime as dt
import threading
import time

import pytest
from sqlalchemy import update

from api.settings import Settings
from jobstore.engine import dispose_engines, session_factory
from jobstore.models import Job, utcnow
from jobstore.reconcile import reconcile_once
from nepf_core.data.errors import DatasetError
from nepf_core.pipeline import JobRequest, load_pipeline
from service_fixtures import fake_pipeline, new_job, pg_database
from worker.runner import JobRunner


@pytest.fixture(params=["sqlite", "postgresql"])
def store(request, tmp_path, monkeypatch):
    monkeypatch.setenv("NEPF_FAKE_STEP_S", "0.01")
    drop = None
    if request.param == "sqlite":
        url = f"sqlite:///{tmp_path / 'jobs.sqlite3'}"
    else:
        url, drop = pg_database("nepf_w")
    settings = Settings(data_dir=tmp_path / "data", database_url=url, lease_s=1.0, heartbeat_s=0.1,
                        max_deliveries=2)
    Session = session_factory(url)
    yield settings, Session
    dispose_engines()
    if drop:
        drop()


def get(Session, jid) -> Job:
    with Session() as s:
        return s.get(Job, jid)


def test_claim_is_exclusive_and_finished_jobs_are_dropped(store):
    settings, Session = store
    jid = new_job(settings, Session)
    a = JobRunner(settings, Session, jid, "A", pipeline=fake_pipeline)
    assert a.claim() == "claimed"
    assert JobRunner(settings, Session, jid, "B").claim() == "held"      # live lease elsewhere
    assert a.finish("succeeded", None, {"status": "succeeded", "step": 20, "total": 20}) == "succeeded"
    assert JobRunner(settings, Session, jid, "C").claim() == "finished"  # a late duplicate message
    j = get(Session, jid)
    assert j.status == "succeeded" and j.completions == 1 and j.attempts == 1 and j.lease_owner is None


def test_expired_lease_lets_another_worker_take_over_and_only_one_completes(store):
    settings, Session = store
    jid = new_job(settings, Session)
    a = JobRunner(settings, Session, jid, "A")
    assert a.claim() == "claimed"
    with Session() as s:   # A stalls: its lease runs out
        s.execute(update(Job).where(Job.id == jid).values(lease_expires=utcnow() - dt.timedelta(seconds=1)))
        s.commit()
    b = JobRunner(settings, Session, jid, "B")
    assert b.claim() == "claimed"
    assert a.finish("succeeded", None, None) == "lease_lost"
    assert b.finish("succeeded", None, None) == "succeeded"
    j = get(Session, jid)
    assert j.completions == 1 and j.attempts == 2 and [x["worker"] for x in j.attempt_log] == ["A", "B"]


def test_redelivery_cap_fails_the_job(store):
    settings, Session = store
    jid = new_job(settings, Session, attempts=settings.max_deliveries)
    assert JobRunner(settings, Session, jid, "A").claim() == "gave_up"
    j = get(Session, jid)
    assert j.status == "failed" and "NEPF_MAX_DELIVERIES=2" in j.error and j.completions == 1


def test_cancel_before_claim(store):
    settings, Session = store
    jid = new_job(settings, Session, cancel_requested=True, status="running")
    assert JobRunner(settings, Session, jid, "A").claim() == "cancelled"
    assert get(Session, jid).status == "cancelled"


def test_full_run_progress_and_cooperative_cancel(store):
    settings, Session = store
    jid = new_job(settings, Session, config={"preset": "tiny", "iters": 100000})
    r = JobRunner(settings, Session, jid, "A", pipeline=fake_pipeline)
    out = {}
    t = threading.Thread(target=lambda: out.update(res=r.run()))
    t.start()
    deadline = time.monotonic() + 20
    while get(Session, jid).step < 10 and time.monotonic() < deadline:
        time.sleep(0.05)
    assert get(Session, jid).status == "running" and get(Session, jid).total == 100000
    with Session() as s:
        s.execute(update(Job).where(Job.id == jid).values(cancel_requested=True))
        s.commit()
    t.join(20)
    assert out["res"] == "cancelled"
    j = get(Session, jid)
    assert j.status == "cancelled" and 10 <= j.step < 100000 and j.finished_at is not None
    assert (settings.jobs_path / jid / "run" / "asset.glb").exists()     # partial export kept


@pytest.mark.parametrize("exc,expect", [
    (DatasetError("pose is singular", file="cameras.npz", view=2, code="singular_camera"),
     "invalid dataset: [file cameras.npz, view 2] pose is singular"),
    (RuntimeError("CUDA out of memory. Tried to allocate 2 GiB"), "out of memory"),
    (ValueError("bad thing"), "training failed: ValueError: bad thing"),
])
def test_exceptions_become_failed_with_a_human_message(store, exc, expect):
    settings, Session = store
    jid = new_job(settings, Session)

    def boom(request: JobRequest) -> dict:
        raise exc
    assert JobRunner(settings, Session, jid, "A", pipeline=boom).run() == "failed"
    j = get(Session, jid)
    assert j.status == "failed" and expect in j.error and j.completions == 1



def test_pipeline_gets_one_request_from_job_config_and_settings(store):
    """The pipeline is called once, with a JobRequest holding the job's config and the
    worker's settings; its summary becomes the job's result."""
    settings, Session = store
    settings = settings.model_copy(update=dict(device="cpu", checkpoint_every=7, export_texture_size=64,
                                               export_mesh_resolution=32, export_max_faces=900))
    jid = new_job(settings, Session, config={"preset": "paper", "iters": 12, "time_budget_s": 30.5})
    calls = []

    def record(request: JobRequest) -> dict:
        calls.append(request)
        request.callbacks.progress({"step": 3, "total": 12, "fraction": 0.25, "stage": "train"})
        return {"status": "succeeded", "step": 12, "total": 12, "wall_s": 1.5}

    assert JobRunner(settings, Session, jid, "A", pipeline=record).run() == "succeeded"
    (req,) = calls
    assert (req.data_dir, req.run_dir) == (settings.jobs_path / jid / "dataset", settings.jobs_path / jid / "run")
    assert (req.preset, req.iters, req.time_budget_s, req.device, req.resume) == ("paper", 12, 30.5, "cpu", True)
    assert (req.checkpoint_every, req.texture_size, req.mesh_resolution, req.max_faces) == (7, 64, 32, 900)
    assert req.callbacks.stop_requested() is False
    j = get(Session, jid)
    assert j.step == 12 and j.wall_s == 1.5 and j.result["status"] == "succeeded"
    # the first step this attempt trained: 1 on a fresh start, whichever step it reported first
    # (issue 37: it was the first step reported, which after a resume was the checkpoint's step)
    assert j.attempt_log[-1]["first_step"] == 1


def test_pipeline_setting_names_the_function(store, monkeypatch):
    """NEPF_PIPELINE is resolved when a job runs; a wrong one fails the job with a message naming it."""
    settings, Session = store
    monkeypatch.setenv("NEPF_FAKE_STEP_S", "0")
    ok = new_job(settings, Session, config={"preset": "tiny", "iters": 5})
    named = settings.model_copy(update={"pipeline": "service_fixtures:fake_pipeline"})
    assert JobRunner(named, Session, ok, "A").run() == "succeeded"
    assert get(Session, ok).step == 5 and (settings.jobs_path / ok / "run" / "asset.glb").exists()
    bad = new_job(settings, Session)
    missing = settings.model_copy(update={"pipeline": "nepf_no_such_module:run"})
    assert JobRunner(missing, Session, bad, "A").run() == "failed"
    assert "NEPF_PIPELINE='nepf_no_such_module:run': cannot import module" in get(Session, bad).error


def test_load_pipeline_and_setting_format():
    from pydantic import ValidationError

    from nepf_core.pipeline import run_pipeline

    assert load_pipeline("nepf_core.pipeline:run_pipeline") is run_pipeline
    assert Settings().pipeline == "nepf_core.pipeline:run_pipeline"
    with pytest.raises(ValueError, match=r"NEPF_PIPELINE='nepf_core.pipeline': expected 'package.module:function'"):
        load_pipeline("nepf_core.pipeline")
    with pytest.raises(ValueError, match="has no function 'nope'"):
        load_pipeline("nepf_core.pipeline:nope")
    with pytest.raises(ValidationError, match="pipeline"):
        Settings(pipeline="nepf_core.pipeline.run_pipeline")   # a dot where the colon goes

def test_reconciler_requeues_orphans_only(store):
    """Re-sent: a running job whose lease expired, a queued job unclaimed past NEPF_RESEND_AFTER_S
    (doubled by each earlier re-send), a job never sent. Not: a live lease, a job sent recently, a
    finished job. The broker is never inspected."""
    settings, Session = store
    assert settings.resend_after_s == 120
    now = utcnow()
    old, older = now - dt.timedelta(seconds=30), now - dt.timedelta(seconds=200)
    orphan_running = new_job(settings, Session, status="running", lease_owner="dead",
                             lease_expires=now - dt.timedelta(seconds=5), enqueued_at=old, enqueue_count=1)
    live_running = new_job(settings, Session, status="running", lease_owner="alive",
                           lease_expires=now + dt.timedelta(seconds=60), enqueued_at=old, enqueue_count=1)
    lost_queued = new_job(settings, Session, status="queued", enqueued_at=older, enqueue_count=1)
    waiting_queued = new_job(settings, Session, status="queued", enqueued_at=old, enqueue_count=1)
    backed_off = new_job(settings, Session, status="queued", enqueued_at=older, enqueue_count=2)  # waits 240 s
    fresh_queued = new_job(settings, Session, status="queued", enqueued_at=now, enqueue_count=1)
    never_sent = new_job(settings, Session, status="queued", enqueued_at=None, created_at=old)
    done = new_job(settings, Session, status="succeeded", enqueued_at=old, enqueue_count=1)

    sent = []
    got = reconcile_once(settings, Session, lambda jid, q: sent.append(jid))
    assert sorted(got) == sorted(sent) == sorted([orphan_running, lost_queued, never_sent])
    j = get(Session, orphan_running)
    assert j.status == "queued" and j.lease_owner is None and j.stage == "requeued" and j.enqueue_count == 2
    assert get(Session, live_running).status == "running" and get(Session, done).status == "succeeded"
    assert get(Session, lost_queued).enqueue_count == 2
    # a second pass right away sends nothing (the re-sends are reserved)
    assert reconcile_once(settings, Session, lambda jid, q: sent.append(jid)) == []
    assert not {waiting_queued, backed_off, fresh_queued} & set(sent)


def test_reconciler_send_failure_is_not_counted_and_retried(store):
    settings, Session = store
    old = utcnow() - dt.timedelta(seconds=200)
    lost = new_job(settings, Session, status="queued", enqueued_at=old, created_at=old, enqueue_count=1)

    def down(jid, q):
        raise ConnectionError("broker down")
    assert reconcile_once(settings, Session, down) == []
    j = get(Session, lost)
    assert j.enqueue_count == 1 and j.enqueued_at is None          # not a send; due again at once
    assert reconcile_once(settings, Session, lambda jid, q: None) == [lost]
    assert get(Session, lost).enqueue_count == 2


def test_lease_lost_mid_run_stops_without_result(store):
    """A worker that stalled past its lease (another took over) stops at its next step and writes nothing."""
    settings, Session = store
    jid = new_job(settings, Session, config={"preset": "tiny", "iters": 100000})
    r = JobRunner(settings, Session, jid, "A", pipeline=fake_pipeline)
    out = {}
    t = threading.Thread(target=lambda: out.update(res=r.run()))
    t.start()
    deadline = time.monotonic() + 20
    while get(Session, jid).step < 5 and time.monotonic() < deadline:
        time.sleep(0.05)
    with Session() as s:   # B took the job over
        s.execute(update(Job).where(Job.id == jid).values(lease_owner="B", lease_expires=utcnow() + dt.timedelta(seconds=60)))
        s.commit()
    t.join(20)
    assert out["res"] == "lease_lost"
    j = get(Session, jid)
    assert j.status == "running" and j.lease_owner == "B" and j.completions == 0
    assert not (settings.jobs_path / jid / "run" / "asset.glb").exists()     # no export into B's folder


def test_a_resumed_attempt_shows_resuming_at_the_checkpoint_and_first_step_after_it(store):
    """Issue 37: the resumed attempt's progress stands at the checkpoint's step with stage
    ``resuming`` from the claim on; the pipeline's ``loading`` report at step 0 (the core reloads
    its data) does not pull it back to 0; ``first_step`` is the checkpoint step + 1 (it was the
    checkpoint step: the core reports that step once before it trains the next)."""
    from nepf_core.resume import write_checkpoint_info

    settings, Session = store
    jid = new_job(settings, Session)
    with Session() as s:   # what the killed attempt left: step 130 of 260, a checkpoint at 100
        s.execute(update(Job).where(Job.id == jid).values(step=130, total=260, stage="requeued", attempts=1))
        s.commit()
    run_dir = settings.jobs_path / jid / "run"
    write_checkpoint_info(run_dir, 100, 40.0)
    (run_dir / "checkpoints" / "latest.pt").write_bytes(b"stand-in")
    seen = []

    def core_like(request):
        cb = request.callbacks
        seen.append((get(Session, jid).step, get(Session, jid).stage))          # right after the claim
        cb.progress({"step": 0, "total": 0, "fraction": 0.0, "stage": "loading", "eta_s": None, "wall_s": 0.0})
        time.sleep(0.3)                                                         # three heartbeats
        seen.append((get(Session, jid).step, get(Session, jid).stage))
        for step in (100, 101, 102):                                           # the core's first reports
            cb.progress({"step": step, "total": 260, "fraction": step / 260, "stage": "training",
                         "eta_s": 1.0, "wall_s": 40.0})
        time.sleep(0.3)
        return {"status": "succeeded", "step": 260, "total": 260, "wall_s": 50.0}

    assert JobRunner(settings, Session, jid, "B", pipeline=core_like).run() == "succeeded"
    assert seen[0] == (100, "resuming") and seen[1] == (100, "resuming"), seen
    job = get(Session, jid)
    assert job.attempt_log[-1]["first_step"] == 101, job.attempt_log
