"""``nepf worker``: a Celery worker for NePF jobs (``worker_main(argv)``; ``python -m worker.commands``)."""

from __future__ import annotations

import argparse
import logging
import os
import sys

from .lifetime import exit_with_parent, hold_data_dir_lock


def worker_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="nepf worker", description="Run a NePF Celery worker. It must share "
                                "NEPF_DATABASE_URL with the API, and NEPF_DATA_DIR unless NEPF_STORAGE_URL "
                                "names an S3 bucket (then the data dir is its own scratch); NEPF_BROKER_URL "
                                "picks the broker (unset: the embedded SQLite broker in the data dir).")
    p.add_argument("--queues", default="default,gpu", help="comma-separated queues to consume (default, gpu)")
    p.add_argument("--concurrency", type=int, default=1, help="jobs at once (default 1: one job per device)")
    p.add_argument("--pool", default=None, choices=["solo", "prefork", "threads"],
                   help="Celery pool (default: solo for concurrency 1, else prefork)")
    p.add_argument("--loglevel", default="INFO")
    p.add_argument("--data-dir", default=None, help="overrides NEPF_DATA_DIR")
    p.add_argument("--parent-pid", type=int, default=None,
                   help="stop (re-queueing the running job) when this process exits; nepf serve sets it")
    p.add_argument("--check", action="store_true", help="healthcheck: exit 0 if a worker on this host "
                   "is alive and the broker answers, else print why and exit 1 (worker/health.py)")
    return p


def worker_main(argv: list[str] | None = None) -> int:
    args = worker_parser().parse_args(argv)
    if args.data_dir:
        os.environ["NEPF_DATA_DIR"] = args.data_dir
    logging.basicConfig(level=args.loglevel.upper(), format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    if args.parent_pid is not None:
        exit_with_parent(args.parent_pid)
    from jobstore.settings import get_settings, reset_settings_cache
    reset_settings_cache()
    settings = get_settings()
    if args.check:
        from .health import check_main
        return check_main(settings)
    # on the embedded broker, one worker per data dir: held until this process exits
    lock_fd = hold_data_dir_lock(settings.data_path) if settings.embedded else None
    from jobstore.queue import prepare_embedded_broker

    from .tasks import app
    prepare_embedded_broker(settings)

    pool = args.pool or ("solo" if args.concurrency == 1 else "prefork")
    try:
        app.worker_main(["worker", "-Q", args.queues, "-c", str(args.concurrency), "-P", pool,
                         "-l", args.loglevel, "-n", f"nepf-{os.getpid()}@%h", "--without-gossip",
                         "--without-mingle", "--without-heartbeat"])
    finally:
        if lock_fd is not None:
            os.close(lock_fd)
    return 0


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv and argv[0] == "worker":
        argv = argv[1:]
    return worker_main(argv)


if __name__ == "__main__":
    sys.exit(main())
