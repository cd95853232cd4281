"""The embedded broker is created once, whoever starts first (``jobstore.queue.prepare_embedded_broker``).

kombu's SQLAlchemy transport creates its tables and queue rows lazily in every process; two
processes starting on a fresh data dir (``nepf serve`` and its worker) raced, and the loser got
"table kombu_queue already exists" or "UNIQUE constraint failed: kombu_queue.name" (the inferred
cause of a worker that died at its start in CI). These tests start processes at one barrier, as serve and its worker do.
"""

from __future__ import annotations

import multiprocessing as mp
import sqlite3

from jobstore.queue import QUEUES, declare_queues, make_celery, prepare_embedded_broker
from jobstore.settings import Settings

ROUNDS = 8


def _start_like_a_process(data_dir: str, barrier, results, prepare: bool) -> None:
    """What the API and the worker do first: (prepare, then) declare every queue on the broker."""
    settings = Settings(data_dir=data_dir)
    settings.data_path.mkdir(parents=True, exist_ok=True)      # serve makes it before either starts
    barrier.wait()
    try:
        if prepare:
            prepare_embedded_broker(settings)
        declare_queues(make_celery(settings, "race"))
        results.put("ok")
    except Exception as exc:  # noqa: BLE001 - the parent reports what the child hit
        results.put(f"{type(exc).__name__}: {str(exc).splitlines()[0]}")


def _race(tmp_path, prepare: bool) -> list[str]:
    ctx = mp.get_context("fork")
    outcomes = []
    for i in range(ROUNDS):
        barrier, results = ctx.Barrier(2), ctx.Queue()
        procs = [ctx.Process(target=_start_like_a_process, args=(str(tmp_path / f"d{i}"), barrier, results, prepare))
                 for _ in range(2)]
        for p in procs:
            p.start()
        for p in procs:
            p.join(60)
        outcomes += [results.get(timeout=5) for _ in procs]
    return outcomes


def test_two_processes_starting_together_both_get_a_working_broker(tmp_path):
    outcomes = _race(tmp_path, prepare=True)
    assert outcomes == ["ok"] * (2 * ROUNDS), outcomes
    con = sqlite3.connect(tmp_path / "d0" / "broker.sqlite3")
    try:
        names = sorted(r[0] for r in con.execute("SELECT name FROM kombu_queue"))
    finally:
        con.close()
    assert names == sorted(QUEUES)          # one row per queue, none twice


def test_the_race_is_real_without_the_lock(tmp_path):
    """The control: kombu's lazy creation alone fails in at least one of the rounds, so the test
    above would catch a prepare step that lost its lock."""
    outcomes = _race(tmp_path, prepare=False)
    assert any("already exists" in o or "UNIQUE constraint" in o for o in outcomes), outcomes


def test_an_external_broker_is_left_alone(tmp_path):
    settings = Settings(data_dir=tmp_path, broker_url="redis://127.0.0.1:1/0")
    prepare_embedded_broker(settings)       # no connection attempted: the port would refuse it
    assert not (tmp_path / "broker.sqlite3").exists()
