"""``nepf serve`` and ``nepf token`` (plain functions; ``python -m api.commands serve|token ...``)."""

from __future__ import annotations

import argparse
import logging
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Optional

from jobstore.settings import get_settings, reset_settings_cache

REPO_ROOT = Path(__file__).resolve().parent.parent
LOCAL_OWNER = "local"
log = logging.getLogger("nepf.serve")


def _settings_with(data_dir: Optional[str]):
    if data_dir:
        os.environ["NEPF_DATA_DIR"] = str(Path(data_dir).expanduser().resolve())
    reset_settings_cache()
    return get_settings()


def ensure_local_token(settings) -> tuple[str, bool]:
    """The local owner's login token: created on first start, kept (0600) in DATA_DIR/local-token
    so that later starts can print the same login URL (the DB stores only its hash)."""
    from sqlalchemy import select

    from .auth import create_token, hash_token
    from jobstore.engine import session_factory
    from jobstore.models import Token

    settings.data_path.mkdir(parents=True, exist_ok=True)
    Session = session_factory(settings.db_url)
    path = settings.data_path / "local-token"
    if path.exists():
        tok = path.read_text().strip()
        with Session() as s:
            if s.execute(select(Token.id).where(Token.token_hash == hash_token(tok),
                                                Token.revoked == False)).first():  # noqa: E712
                return tok, False
    tok = create_token(Session, LOCAL_OWNER, "local (nepf serve)")
    settings.data_path.mkdir(parents=True, exist_ok=True)
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(tok + "\n")
    return tok, True


#: how long ``nepf serve`` waits for its worker to stop (the running job stops at its next step
#: and is re-queued) before it kills it (the job then resumes once its lease expires)
WORKER_STOP_GRACE_S = 60.0


class WorkerSupervisor(threading.Thread):
    """Keeps one local worker subprocess alive (embedded default); restarts it if it dies.

    The worker runs in its own process group, so a Ctrl-C in the terminal reaches ``nepf serve``
    alone, which then stops the worker in order (:meth:`stop`: SIGTERM, the running job is
    re-queued). It gets ``--parent-pid``: it stops by itself when serve dies, even by ``kill -9``
    (``worker/lifetime.py``). This thread starts the worker and outlives it: the parent-death
    signal fires when the thread that forked the worker exits.
    """

    def __init__(self, argv: list[str], env: dict, nice: int = 0) -> None:
        super().__init__(name="nepf-worker-supervisor", daemon=True)
        self.argv = argv
        self.env = env
        self.nice = nice
        self.proc: Optional[subprocess.Popen] = None
        self.stopping = threading.Event()
        self.restarts = 0
        self._spawn_lock = threading.Lock()   # stop() never misses a worker started at that moment

    def _prepare_child(self) -> None:
        os.setpgid(0, 0)          # own process group: the terminal's Ctrl-C goes to serve only
        if self.nice > 0:         # niced: on a shared machine the API stays responsive while it trains
            os.nice(self.nice)

    def run(self) -> None:
        backoff = 1.0
        while True:
            with self._spawn_lock:
                if self.stopping.is_set():
                    return
                started = time.monotonic()
                self.proc = subprocess.Popen(self.argv + ["--parent-pid", str(os.getpid())], env=self.env,
                                             cwd=str(REPO_ROOT), preexec_fn=self._prepare_child)
            print(f"[nepf serve] worker pid {self.proc.pid}", flush=True)
            self.proc.wait()
            if self.stopping.is_set():
                return
            backoff = 1.0 if time.monotonic() - started > 30 else min(backoff * 2, 30.0)
            print(f"[nepf serve] worker exited ({self.proc.returncode}); restarting in {backoff:g} s", flush=True)
            self.restarts += 1
            self.stopping.wait(backoff)

    def stop(self, grace: float = WORKER_STOP_GRACE_S) -> None:
        """SIGTERM (Celery's warm shutdown): a running job stops at its next step, goes back to the
        queue and resumes from its checkpoint at the next start. SIGKILL after ``grace`` s."""
        with self._spawn_lock:
            self.stopping.set()
            p = self.proc
        if p is not None and p.poll() is None:
            print(f"[nepf serve] stopping the worker (pid {p.pid}); a running job is re-queued", flush=True)
            p.send_signal(signal.SIGTERM)
            try:
                p.wait(grace)
            except subprocess.TimeoutExpired:
                print(f"[nepf serve] the worker did not stop in {grace:g} s: killing it", flush=True)
                self.kill_now()
                p.wait()
        if self.is_alive():
            self.join(timeout=5)

    def kill_now(self) -> None:
        """SIGKILL the worker (a second Ctrl-C); its job resumes once its lease expires. No wait
        here: it may run in a signal handler while :meth:`stop` is already waiting."""
        p = self.proc
        if p is not None and p.returncode is None:
            p.kill()


def serve_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="nepf serve", description="Run the NePF jobs API (and, without "
                                "NEPF_BROKER_URL, a local worker on an embedded SQLite broker).")
    p.add_argument("--host", default="127.0.0.1")
    p.add_argument("--port", type=int, default=8000)
    p.add_argument("--data-dir", default=None, help="overrides NEPF_DATA_DIR")
    p.add_argument("--no-worker", action="store_true", help="do not start the embedded worker")
    p.add_argument("--log-level", default="info")
    return p


def _stop_on_signal(signum, frame) -> None:
    """SIGTERM/SIGINT outside uvicorn's own handlers (before it starts, and the signal uvicorn
    re-raises after its graceful shutdown): leave ``serve_main`` through its ``finally``."""
    raise SystemExit(0)


def serve_main(argv: list[str] | None = None) -> int:
    args = serve_parser().parse_args(argv)
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, _stop_on_signal)
    settings = _settings_with(args.data_dir)
    logging.basicConfig(level=args.log_level.upper(), format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    from jobstore.storage import open_storage

    from .service import StartupError, check_secret
    try:
        check_secret(settings, open_storage(settings))
    except (StartupError, ValueError) as exc:
        print(f"nepf serve: {exc}", file=sys.stderr)
        return 2
    settings.data_path.mkdir(parents=True, exist_ok=True)
    from jobstore.engine import get_engine
    from jobstore.migrate import SchemaMismatch
    try:
        get_engine(settings.db_url)   # applies the job store migrations before the API or worker starts
    except SchemaMismatch as exc:
        print(f"nepf serve: {exc}", file=sys.stderr)
        return 2
    token, created = ensure_local_token(settings)
    shown_host = "127.0.0.1" if args.host in ("0.0.0.0", "::", "") else args.host
    base = settings.public_url or f"http://{shown_host}:{args.port}"
    print(("Created a local token. " if created else "") +
          f"Open the NePF viewer at:\n    {base.rstrip('/')}/#token={token}\n"
          f"API: {base.rstrip('/')}/docs   data dir: {settings.data_path}", flush=True)

    sup: Optional[WorkerSupervisor] = None
    if settings.embedded and settings.embedded_worker and not args.no_worker:
        env = dict(os.environ)
        env["NEPF_DATA_DIR"] = str(settings.data_path)
        env["PYTHONPATH"] = os.pathsep.join([str(REPO_ROOT)] + ([env["PYTHONPATH"]] if env.get("PYTHONPATH") else []))
        sup = WorkerSupervisor([sys.executable, "-m", "worker.commands", "--queues", "default,gpu",
                                "--concurrency", "1", "--loglevel", "INFO"], env, nice=settings.embedded_worker_nice)
        sup.start()
        print("[nepf serve] embedded broker: " + settings.effective_broker_url, flush=True)

    import uvicorn

    from .header_limit import uvicorn_options
    from .main import create_app

    app = create_app(settings)
    try:
        uvicorn.run(app, host=args.host, port=args.port, log_level=args.log_level.lower(),
                    timeout_graceful_shutdown=3, **uvicorn_options(settings.max_header_bytes))
    finally:
        if sup is not None:
            def force(signum, frame) -> None:
                print("[nepf serve] second signal: killing the worker now", flush=True)
                sup.kill_now()
            for sig in (signal.SIGINT, signal.SIGTERM):
                signal.signal(sig, force)
            sup.stop()
    return 0


def token_main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="nepf token", description="Manage API tokens (stored hashed).")
    sub = p.add_subparsers(dest="cmd", required=True)
    c = sub.add_parser("create", help="create a token and print it (shown once)")
    c.add_argument("name", help="the token's owner name; jobs belong to the owner")
    c.add_argument("--owner", default=None, help="owner, if different from NAME (several tokens, one owner)")
    sub.add_parser("list", help="list tokens (prefixes only)")
    r = sub.add_parser("revoke", help="revoke tokens by prefix")
    r.add_argument("prefix")
    p.add_argument("--data-dir", default=None)
    args = p.parse_args(argv)
    settings = _settings_with(args.data_dir)
    settings.data_path.mkdir(parents=True, exist_ok=True)
    from sqlalchemy import select, update

    from .auth import create_token
    from jobstore.engine import session_factory
    from jobstore.models import Token

    Session = session_factory(settings.db_url)
    if args.cmd == "create":
        print(create_token(Session, args.owner or args.name, args.name))
        return 0
    if args.cmd == "list":
        with Session() as s:
            for t in s.execute(select(Token).order_by(Token.id)).scalars():
                print(f"{t.prefix}...  owner={t.owner}  name={t.name}  created={t.created_at:%Y-%m-%d %H:%M}"
                      + ("  REVOKED" if t.revoked else ""))
        return 0
    with Session() as s:
        n = s.execute(update(Token).where(Token.prefix.startswith(args.prefix)).values(revoked=True)).rowcount
        s.commit()
    print(f"revoked {n} token(s)")
    return 0 if n else 1


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] not in ("serve", "token"):
        print("usage: python -m api.commands serve|token ...", file=sys.stderr)
        return 2
    return (serve_main if argv[0] == "serve" else token_main)(argv[1:])


if __name__ == "__main__":
    sys.exit(main())
