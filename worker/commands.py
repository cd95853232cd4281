"""``nepf worker``: a Celery worker for NePF jobs (``worker_main(argv)``; ``python -m worker.commands``)."""

from __future__ import annotations

import argparse
import logging
import os
import sys


def worker_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="nepf worker", description="Run a NePF Celery worker. It must share "
                                "NEPF_DATABASE_URL and NEPF_DATA_DIR with the API; NEPF_BROKER_URL picks the "
                                "broker (unset: the embedded SQLite broker in the data dir).")
    p.add_argument("--queues", default="default,gpu", help="comma-separated queues to consume (default, gpu)")
    p.add_argument("--concurrency", type=int, default=1, help="jobs at once (default 1: one job per device)")
    p.add_argument("--pool", default=None, choices=["solo", "prefork", "threads"],
                   help="Celery pool (default: solo for concurrency 1, else prefork)")
    p.add_argument("--loglevel", default="INFO")
    p.add_argument("--data-dir", default=None, help="overrides NEPF_DATA_DIR")
    return p


def worker_main(argv: list[str] | None = None) -> int:
    args = worker_parser().parse_args(argv)
    if args.data_dir:
        os.environ["NEPF_DATA_DIR"] = args.data_dir
    logging.basicConfig(level=args.loglevel.upper(), format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    from api.settings import reset_settings_cache
    reset_settings_cache()
    from .tasks import app

    pool = args.pool or ("solo" if args.concurrency == 1 else "prefork")
    app.worker_main(["worker", "-Q", args.queues, "-c", str(args.concurrency), "-P", pool,
                     "-l", args.loglevel, "-n", f"nepf-{os.getpid()}@%h", "--without-gossip",
                     "--without-mingle", "--without-heartbeat"])
    return 0


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv and argv[0] == "worker":
        argv = argv[1:]
    return worker_main(argv)


if __name__ == "__main__":
    sys.exit(main())
