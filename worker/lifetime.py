"""How long a worker process lives: one worker per data dir, and never longer than its ``nepf serve``.

* **Data-dir lock.** A worker on the embedded broker (no ``NEPF_BROKER_URL``) holds an exclusive
  ``flock`` on ``DATA_DIR/worker.lock`` for its whole life, taken *before* it consumes any message.
  A second worker on the same data dir waits (printing who holds the lock) and takes over when
  the first exits: two embedded workers never run jobs at the same time. The kernel releases an
  ``flock`` when its holder dies, even by ``kill -9``, so a restart never finds a stale lock.
* **Parent death.** ``nepf serve``'s embedded worker gets ``--parent-pid``: on Linux
  ``prctl(PR_SET_PDEATHSIG, SIGTERM)`` makes the kernel send SIGTERM when serve dies (even by
  ``kill -9``), and a thread polls ``os.getppid()`` as a fallback (other systems, and the window
  between ``fork`` and ``prctl``). SIGTERM is the worker's ordinary shutdown: the running job
  stops at its next step and is re-queued (``worker/tasks.py``).

PDEATHSIG fires when the parent *thread* that forked the worker exits, not only the parent
process: serve's supervisor thread, which starts the worker, outlives it by design.
"""

from __future__ import annotations

import ctypes
import fcntl
import os
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Callable, TextIO

LOCK_NAME = "worker.lock"
_PR_SET_PDEATHSIG = 1


def hold_data_dir_lock(data_dir: Path, *, poll_s: float = 0.5, out: TextIO = sys.stdout,
                       sleep: Callable[[float], None] = time.sleep) -> int:
    """Block until this process holds the exclusive lock of ``data_dir``; returns the lock's fd.

    The fd must stay open for the worker's life (closing it releases the lock). The holder's pid
    is written into the file, only to name it in the message a waiting worker prints.
    """
    data_dir.mkdir(parents=True, exist_ok=True)
    path = data_dir / LOCK_NAME
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)     # not inherited by children (O_CLOEXEC)
    announced = False
    while True:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            break
        except BlockingIOError:
            if not announced:
                holder = os.pread(fd, 32, 0).decode("ascii", "replace").strip() or "unknown"
                print(f"[nepf worker] another NePF worker (pid {holder}) holds {path}: waiting for it to "
                      "exit (one worker per data dir on the embedded broker)", file=out, flush=True)
                announced = True
            sleep(poll_s)
    os.ftruncate(fd, 0)
    os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
    if announced:
        print(f"[nepf worker] took over {path}", file=out, flush=True)
    return fd


def exit_with_parent(parent_pid: int, *, poll_s: float = 1.0) -> None:
    """Send this process SIGTERM when ``parent_pid`` (the process that started it) is gone."""
    if sys.platform.startswith("linux"):
        try:
            libc = ctypes.CDLL(None, use_errno=True)
            libc.prctl(_PR_SET_PDEATHSIG, int(signal.SIGTERM), 0, 0, 0)
        except (OSError, AttributeError):
            pass                                           # the poll below still covers it
    if os.getppid() != parent_pid:                         # it died before prctl: leave now
        raise SystemExit(f"[nepf worker] the process that started this worker ({parent_pid}) is gone")

    def watch() -> None:
        while os.getppid() == parent_pid:
            time.sleep(poll_s)
        os.kill(os.getpid(), signal.SIGTERM)

    threading.Thread(target=watch, name="nepf-parent-watch", daemon=True).start()
