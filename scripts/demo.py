"""Start NePF on its embedded default with a demo job on a scene the project generates.

    .venv/bin/python scripts/demo.py [--port 8000] [--preset fast] [--budget 300]

1. writes a synthetic glossy torus (``nepf make-scene``) under ``nepf-data/demo-scene``;
2. starts ``nepf serve`` (API + embedded worker, no Redis);
3. uploads the scene as a job with the local token and prints the viewer URL.
The server keeps running in the foreground (Ctrl-C stops it).
"""

from __future__ import annotations

import argparse
import io
import json
import os
import re
import signal
import subprocess
import sys
import time
import urllib.request
import zipfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--port", type=int, default=8000)
    ap.add_argument("--host", default="127.0.0.1")
    ap.add_argument("--preset", default="fast", choices=["tiny", "fast", "paper"])
    ap.add_argument("--budget", type=float, default=300.0, help="training time budget (s)")
    ap.add_argument("--data-dir", default=str(ROOT / "nepf-data"))
    a = ap.parse_args()
    data = Path(a.data_dir)
    scene = data / "demo-scene"
    if not (scene / "dtu" / "cameras.npz").exists():
        print("[demo] generating the demo scene (glossy torus, 64x64, 24 views)...", flush=True)
        subprocess.run([sys.executable, "-m", "nepf_core.cli", "make-scene", str(scene), "--shape", "torus",
                        "--material", "glossy", "--views", "24", "--test-views", "4", "--resolution", "64"], check=True)
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as z:
        for p in sorted((scene / "dtu").rglob("*")):
            if p.is_file():
                z.write(p, "demo/" + p.relative_to(scene / "dtu").as_posix())
    env = dict(os.environ, NEPF_DATA_DIR=str(data))
    srv = subprocess.Popen([sys.executable, "-m", "nepf_core.cli", "serve", "--host", a.host, "--port", str(a.port)],
                           env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, bufsize=1)
    # a SIGTERM (a closed terminal, a process manager) stops the server too, as Ctrl-C does
    signal.signal(signal.SIGTERM, _interrupt)
    try:
        return _run(a, srv, buf, scene)
    except KeyboardInterrupt:
        return 0
    finally:
        srv.terminate()
        try:
            srv.wait(15)
        except subprocess.TimeoutExpired:
            srv.kill()


def _interrupt(signum, frame):
    raise KeyboardInterrupt


def _run(a, srv: subprocess.Popen, buf: io.BytesIO, scene: Path) -> int:
    """Wait for the login URL, queue the demo job, then echo the server's output until it exits."""
    token, url = None, None
    deadline = time.time() + 120
    while time.time() < deadline and token is None:
        line = srv.stdout.readline()
        if not line:
            break
        print(line, end="", flush=True)
        m = re.search(r"(http\S+)/#token=(\S+)", line)
        if m:
            url, token = m.group(0), m.group(2)
    if token is None:
        print("[demo] the server did not print a login URL", file=sys.stderr)
        return 1
    base = f"http://{a.host}:{a.port}"
    for _ in range(120):
        try:
            urllib.request.urlopen(base + "/healthz", timeout=2)
            break
        except Exception:
            time.sleep(0.5)
    boundary = "nepfdemo"
    cfg = json.dumps({"preset": a.preset, "time_budget_s": a.budget, "name": "demo: glossy torus"})
    body = (f"--{boundary}\r\nContent-Disposition: form-data; name=\"config\"\r\n\r\n{cfg}\r\n"
            f"--{boundary}\r\nContent-Disposition: form-data; name=\"dataset\"; filename=\"demo.zip\"\r\n"
            f"Content-Type: application/zip\r\n\r\n").encode() + buf.getvalue() + f"\r\n--{boundary}--\r\n".encode()
    req = urllib.request.Request(base + "/jobs", data=body, method="POST", headers={
        "Authorization": f"Bearer {token}", "Content-Type": f"multipart/form-data; boundary={boundary}",
        "Idempotency-Key": "nepf-demo-" + str(scene.stat().st_mtime_ns)})
    try:
        job = json.loads(urllib.request.urlopen(req, timeout=60).read())
        print(f"[demo] queued job {job.get('id')} ({a.preset}, {a.budget:.0f} s budget).", flush=True)
    except Exception as e:  # the server stays up; the user can upload by hand
        print(f"[demo] could not queue the demo job: {e}", file=sys.stderr)
    print(f"[demo] open {url}", flush=True)
    for line in srv.stdout:
        print(line, end="", flush=True)
    return srv.wait()


if __name__ == "__main__":
    sys.exit(main())
