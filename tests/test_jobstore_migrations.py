"""Job store migrations (jobstore/migrate.py) on SQLite and PostgreSQL: an empty database goes to
head with exactly the models' schema, a database made by the old ``create_all`` is stamped and
keeps its rows, a foreign unversioned schema is refused, concurrent starts do not collide, and
``nepf serve`` migrates before it starts."""

from __future__ import annotations

import threading

import pytest
from alembic.autogenerate import compare_metadata
from alembic.runtime.migration import MigrationContext
from alembic.script import ScriptDirectory
from sqlalchemy import Column, Integer, MetaData, String, Table, inspect, select

from jobstore.engine import make_engine
from jobstore.migrate import (INITIAL_REVISION, LEGACY_COLUMNS, VERSION_TABLE, SchemaMismatch,
                              alembic_config, current_revision, upgrade)
from jobstore.models import Base, Job, Token
from service_fixtures import pg_database


@pytest.fixture(params=["sqlite", "postgresql"])
def db_url(request, tmp_path):
    if request.param == "sqlite":
        yield f"sqlite:///{tmp_path / 'store.sqlite3'}"
        return
    url, drop = pg_database("nepf_mig")
    try:
        yield url
    finally:
        drop()


@pytest.fixture
def engine(db_url):
    eng = make_engine(db_url)
    yield eng
    eng.dispose()


def head_revision() -> str:
    heads = ScriptDirectory.from_config(alembic_config(None)).get_heads()
    assert len(heads) == 1, f"the migrations must have one head, not {heads}"
    return heads[0]


def schema_diff(eng) -> list:
    """What autogenerate would change to make the database match jobstore.models (empty: same)."""
    with eng.connect() as conn:
        ctx = MigrationContext.configure(conn, opts={"version_table": VERSION_TABLE, "compare_type": True})
        return compare_metadata(ctx, Base.metadata)


def test_empty_database_goes_to_head_with_the_models_schema(engine):
    assert upgrade(engine) == (None, head_revision())
    assert schema_diff(engine) == []
    names = set(inspect(engine).get_table_names())
    assert names == {"nepf_jobs", "nepf_tokens", VERSION_TABLE}
    assert upgrade(engine) == (head_revision(), head_revision())          # idempotent


def test_initial_revision_is_the_pre_migration_schema(engine):
    """LEGACY_COLUMNS (used to recognise create_all databases) is what revision 0001 creates,
    and what create_all makes from today's models."""
    upgrade(engine, INITIAL_REVISION)
    insp = inspect(engine)
    assert {t: frozenset(c["name"] for c in insp.get_columns(t)) for t in LEGACY_COLUMNS} == LEGACY_COLUMNS
    assert {t.name: frozenset(t.columns.keys()) for t in Base.metadata.sorted_tables} == LEGACY_COLUMNS


def test_create_all_database_is_stamped_and_keeps_its_rows(engine):
    Base.metadata.create_all(engine)                 # how NePF made the store before migrations
    with engine.begin() as conn:
        conn.execute(Token.__table__.insert().values(owner="ann", name="laptop", token_hash="h" * 64,
                                                     prefix="nepf_abc", revoked=False))
        conn.execute(Job.__table__.insert().values(
            id="a" * 32, owner="ann", status="running", config={"preset": "tiny", "iters": 7},
            dataset={"n_views": 3}, queue="default", attempt_log=[{"worker": "w1"}], step=5,
            fraction=0.5, cancel_requested=False, attempts=1, enqueue_count=1, completions=0))
    with engine.connect() as conn:
        before_rows = [conn.execute(select(t)).all() for t in (Token.__table__, Job.__table__)]

    assert upgrade(engine) == (None, head_revision())
    with engine.connect() as conn:
        assert current_revision(conn) == head_revision()
        after_rows = [conn.execute(select(t)).all() for t in (Token.__table__, Job.__table__)]
    assert after_rows == before_rows and len(after_rows[1]) == 1
    assert after_rows[1][0].config == {"preset": "tiny", "iters": 7}
    assert schema_diff(engine) == []


def test_unversioned_tables_of_another_shape_are_refused(engine):
    md = MetaData()
    Table("nepf_jobs", md, Column("id", String(32), primary_key=True), Column("owner", String(128)))
    md.create_all(engine)
    with pytest.raises(SchemaMismatch) as exc:
        upgrade(engine)
    msg = str(exc.value)
    assert "table nepf_tokens is missing" in msg and "'status'" in msg and "NEPF_DATABASE_URL" in msg
    names = set(inspect(engine).get_table_names())
    assert names == {"nepf_jobs"}, "a refused database must be left as it was"


def test_concurrent_first_starts_migrate_once(db_url):
    """API, worker and token command may open a new store at the same moment."""
    engines = [make_engine(db_url) for _ in range(4)]
    barrier = threading.Barrier(len(engines))
    results, errors = [], []

    def start(eng):
        barrier.wait()
        try:
            results.append(upgrade(eng))
        except Exception as exc:  # noqa: BLE001 - collected and asserted below
            errors.append(exc)

    threads = [threading.Thread(target=start, args=(e,)) for e in engines]
    for t in threads:
        t.start()
    for t in threads:
        t.join(60)
    for e in engines:
        e.dispose()
    assert errors == []
    head = head_revision()
    assert sorted(results, key=str) == sorted([(None, head)] + [(head, head)] * 3, key=str)


def test_serve_refuses_a_foreign_schema_before_starting(tmp_path, monkeypatch, capsys):
    from api.commands import serve_main

    for k in [k for k in __import__("os").environ if k.startswith("NEPF_")]:
        monkeypatch.delenv(k)
    data = tmp_path / "data"
    data.mkdir()
    eng = make_engine(f"sqlite:///{data / 'nepf.sqlite3'}")
    md = MetaData()
    Table("nepf_tokens", md, Column("id", Integer, primary_key=True))
    md.create_all(eng)
    eng.dispose()
    assert serve_main(["--data-dir", str(data), "--no-worker", "--port", "1"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("nepf serve: the job store has NePF tables but no schema version")
    assert "Traceback" not in err
