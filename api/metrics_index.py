"""Moved to :mod:`jobstore.storage.metrics_index` (the local storage backend reads with it)."""

from jobstore.storage.metrics_index import METRICS, MetricsIndex  # noqa: F401
