"""Worker liveness for container healthchecks: ``nepf worker --check``.

A running worker touches ``$TMPDIR/nepf-worker-<pid>.alive`` every ``HEARTBEAT_S`` from a
daemon thread (started when Celery reports the worker ready). The check passes when some worker
process on this host is alive and touched its file within ``max_age_s``, *and* the broker
answers from here. Why not ``celery inspect ping``: with the default solo pool (one job per
device) the worker answers control messages only between jobs, so a ping fails for the whole of
every training run.
"""

from __future__ import annotations

import os
import tempfile
import threading
import time
from pathlib import Path
from typing import Optional

HEARTBEAT_S = 10.0
PREFIX = "nepf-worker-"


def heartbeat_dir() -> Path:
    return Path(tempfile.gettempdir())


class Heartbeat(threading.Thread):
    """Touches this process's ``.alive`` file every ``interval_s`` until ``stop()``."""

    def __init__(self, directory: Optional[Path] = None, interval_s: float = HEARTBEAT_S) -> None:
        super().__init__(name="nepf-worker-heartbeat", daemon=True)
        self.path = (directory or heartbeat_dir()) / f"{PREFIX}{os.getpid()}.alive"
        self.interval_s = interval_s
        self.stopping = threading.Event()

    def run(self) -> None:
        while True:
            self.path.touch()
            if self.stopping.wait(self.interval_s):
                break
        self.path.unlink(missing_ok=True)

    def stop(self) -> None:
        self.stopping.set()
        if self.is_alive():
            self.join(timeout=2)
        self.path.unlink(missing_ok=True)


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:   # alive, another user's
        return True
    return True


def live_workers(directory: Optional[Path] = None, max_age_s: float = 3 * HEARTBEAT_S) -> list[int]:
    """Pids of worker processes that are alive and touched their file within ``max_age_s``
    (files of processes that are gone are removed)."""
    now = time.time()
    pids = []
    for f in (directory or heartbeat_dir()).glob(f"{PREFIX}*.alive"):
        pid_text = f.name[len(PREFIX):-len(".alive")]
        try:
            fresh = now - f.stat().st_mtime <= max_age_s
        except FileNotFoundError:   # its worker just stopped
            continue
        if not pid_text.isdigit():
            continue
        if not _pid_alive(int(pid_text)):   # left by a killed worker
            f.unlink(missing_ok=True)
        elif fresh:
            pids.append(int(pid_text))
    return sorted(pids)


def check(settings, directory: Optional[Path] = None, max_age_s: float = 3 * HEARTBEAT_S) -> list[str]:
    """Problems found (empty: healthy): no live worker on this host, or the broker unreachable."""
    from jobstore.queue import make_celery, ping_broker

    problems = []
    if not live_workers(directory, max_age_s):
        problems.append(f"no NePF worker on this host has reported alive in the last {max_age_s:g} s")
    try:
        ping_broker(make_celery(settings, "nepf-check"))
    except Exception as exc:  # noqa: BLE001 - reported, not raised
        problems.append(f"broker unreachable: {type(exc).__name__}: {exc}"[:300])
    return problems


def check_main(settings) -> int:
    problems = check(settings)
    for p in problems:
        print(f"nepf worker --check: {p}")
    if not problems:
        print(f"nepf worker --check: ok (worker pid {', '.join(map(str, live_workers()))})")
    return 1 if problems else 0
