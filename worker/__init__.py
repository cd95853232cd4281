"""NePF Celery worker: thin glue between the job store and ``nepf_core.jobs.run_job``."""
