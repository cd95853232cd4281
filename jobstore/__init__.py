"""The NePF job store: the tables (``models``), engines and sessions (``engine``), schema
migrations (``migrate``, Alembic scripts in ``migrations/``), the Celery wiring both sides share
(``queue``) and the reconciler (``reconcile``).

Both the API and the worker import it; it never imports torch, ``nepf_core``, FastAPI, ``api``
or ``worker`` (settings objects are passed in).
"""

import logging

# Alembic announces each of its plugins at INFO when it is imported (every process start); the
# store logs what its migrations change instead (jobstore.migrate.upgrade).
logging.getLogger("alembic.runtime.plugins").setLevel(logging.WARNING)
