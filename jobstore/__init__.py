"""The NePF job store: the tables (``models``), engines and sessions (``engine``), schema
migrations (``migrate``, Alembic scripts in ``migrations/``), the service settings (``settings``),
every job state change (``state``), the Celery wiring both sides share (``queue``) and the
reconciler (``reconcile``).

Both the API and the worker import it; it never imports torch, FastAPI, ``api`` or ``worker``,
nor ``nepf_core`` beyond its stdlib-only constants ``nepf_core.limits`` (the settings' defaults).
"""

import logging

# Alembic announces each of its plugins at INFO when it is imported (every process start); the
# store logs what its migrations change instead (jobstore.migrate.upgrade).
logging.getLogger("alembic.runtime.plugins").setLevel(logging.WARNING)
