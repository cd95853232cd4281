"""Alembic environment: runs on the connection ``jobstore.migrate`` passes in (no ini, no URL here)."""

from alembic import context

from jobstore.migrate import VERSION_TABLE
from jobstore.models import Base

connection = context.config.attributes.get("connection")
if connection is None:
    raise RuntimeError("run the job store migrations through jobstore.migrate "
                       "(python -m jobstore.migrate upgrade URL)")
context.configure(connection=connection, target_metadata=Base.metadata, version_table=VERSION_TABLE,
                  render_as_batch=connection.dialect.name == "sqlite", compare_type=True)
with context.begin_transaction():
    context.run_migrations()
