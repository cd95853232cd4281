"""Alembic environment and revision scripts of the job store (run through ``jobstore.migrate``)."""
