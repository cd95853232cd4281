"""`nepf worker --check` (worker/health.py): a worker's heartbeat file, read back by the check
together with a broker ping; stale files, dead pids and an unreachable broker fail it."""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import time

from api.settings import Settings
from service_fixtures import free_port, wait_for
from worker.health import Heartbeat, check, live_workers


def test_heartbeat_marks_this_process_alive_until_stopped(tmp_path):
    beat = Heartbeat(tmp_path, interval_s=0.05)
    beat.start()
    wait_for(lambda: beat.path.exists(), 5, what="heartbeat file")
    first = beat.path.stat().st_mtime_ns
    wait_for(lambda: beat.path.stat().st_mtime_ns > first, 5, interval=0.02, what="a second touch")
    assert beat.path.name == f"nepf-worker-{os.getpid()}.alive"
    assert live_workers(tmp_path) == [os.getpid()]
    beat.stop()
    assert not beat.path.exists() and live_workers(tmp_path) == []


def test_stale_files_and_dead_pids_do_not_count(tmp_path):
    stale = tmp_path / f"nepf-worker-{os.getpid()}.alive"
    stale.touch()
    old = time.time() - 100
    os.utime(stale, (old, old))
    assert live_workers(tmp_path, max_age_s=30) == []
    assert live_workers(tmp_path, max_age_s=300) == [os.getpid()]
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    stale.unlink()
    (tmp_path / f"nepf-worker-{int(dead.stdout)}.alive").touch()
    (tmp_path / "nepf-worker-notapid.alive").touch()
    assert live_workers(tmp_path) == []
    assert [p.name for p in tmp_path.iterdir()] == ["nepf-worker-notapid.alive"]   # the dead one is swept


def test_check_needs_a_live_worker_and_a_reachable_broker(tmp_path):
    beats = tmp_path / "beats"
    beats.mkdir()
    down = Settings(data_dir=tmp_path / "data", broker_url=f"redis://127.0.0.1:{free_port()}/0")
    problems = check(down, directory=beats)
    assert len(problems) == 2
    assert problems[0].startswith("no NePF worker on this host") and problems[1].startswith("broker unreachable")

    (tmp_path / "data").mkdir()
    embedded = Settings(data_dir=tmp_path / "data")
    beat = Heartbeat(beats, interval_s=0.05)
    beat.start()
    try:
        wait_for(lambda: beat.path.exists(), 5, what="heartbeat file")
        assert check(embedded, directory=beats) == []
    finally:
        beat.stop()
    assert check(embedded, directory=beats) == [
        "no NePF worker on this host has reported alive in the last 30 s"]


def test_nepf_worker_check_exit_status(tmp_path, monkeypatch, capsys):
    from worker.commands import worker_main

    for k in [k for k in os.environ if k.startswith("NEPF_")]:
        monkeypatch.delenv(k)
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    (tmp_path / "data").mkdir()
    args = ["--check", "--data-dir", str(tmp_path / "data")]
    assert worker_main(args) == 1
    assert "no NePF worker on this host" in capsys.readouterr().out
    beat = Heartbeat(interval_s=0.05)
    assert beat.path.parent == tmp_path
    beat.start()
    try:
        wait_for(lambda: beat.path.exists(), 5, what="heartbeat file")
        assert worker_main(args) == 0
        assert capsys.readouterr().out.strip() == f"nepf worker --check: ok (worker pid {os.getpid()})"
    finally:
        beat.stop()
