"""Helpers for the service tests: tiny datasets, zips, a fake pipeline, server/worker/Redis
processes started on free loopback ports and stopped by PID."""

from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
import signal
import socket
import struct
import subprocess
import sys
import time
import zipfile
from pathlib import Path
from typing import Callable, Optional

import numpy as np
from PIL import Image

from nepf_core.pipeline import JobRequest
from nepf_core.resume import checkpoint_step, cut_metrics_to_checkpoint, write_checkpoint_info

REPO = Path(__file__).resolve().parent.parent
TESTS = Path(__file__).resolve().parent


# ------------------------------------------------------------------------ waiting
def wait_for(pred: Callable[[], object], timeout: float, interval: float = 0.1, what: str = "condition"):
    deadline = time.monotonic() + timeout
    last_exc = None
    while time.monotonic() < deadline:
        try:
            v = pred()
            if v:
                return v
        except Exception as exc:  # noqa: BLE001
            last_exc = exc
        time.sleep(interval)
    raise TimeoutError(f"timed out after {timeout}s waiting for {what}" + (f" (last error: {last_exc})" if last_exc else ""))


def worker_pids(output: str) -> list[int]:
    """Every embedded worker pid ``nepf serve`` announced in ``output`` ("[nepf serve] worker pid N",
    api/commands.py), oldest first. A regex, not the line's last word: the worker child writes to
    the same pipe, and its log can run on after serve's line before the newline."""
    return [int(p) for p in re.findall(r"worker pid (\d+)", output)]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


# ------------------------------------------------------------------------ datasets
def look_at_w2c(eye, target=(0, 0, 0), up=(0, 0, 1)):
    eye, target, up = (np.asarray(v, float) for v in (eye, target, up))
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-6:
        x = np.cross(z, (0, 1, 0))
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])          # rows: camera axes in world (OpenCV: x right, y down, z fwd)
    t = -R @ eye
    return R, t


def make_dtu_dir(root: Path, n: int = 6, size: int = 24, *, masks: bool = True) -> Path:
    """A minimal DTU folder: cameras.npz (world_mat_i = K[R|t], scale_mat_i), image/, mask/."""
    root = Path(root)
    (root / "image").mkdir(parents=True, exist_ok=True)
    if masks:
        (root / "mask").mkdir(parents=True, exist_ok=True)
    f = size * 1.2
    K = np.array([[f, 0, size / 2], [0, f, size / 2], [0, 0, 1]])
    cams = {}
    yy, xx = np.mgrid[0:size, 0:size]
    disc = ((xx - size / 2) ** 2 + (yy - size / 2) ** 2) < (size * 0.3) ** 2
    for i in range(n):
        a = 2 * np.pi * i / n
        R, t = look_at_w2c((3 * np.cos(a), 3 * np.sin(a), 1.0))
        P = np.eye(4)
        P[:3, :4] = K @ np.hstack([R, t[:, None]])
        cams[f"world_mat_{i}"] = P
        cams[f"scale_mat_{i}"] = np.eye(4)
        img = np.zeros((size, size, 3), np.uint8)
        img[disc] = (180, 90 + 10 * i, 60)
        Image.fromarray(img).save(root / "image" / f"{i:03d}.png")
        if masks:
            Image.fromarray((disc * 255).astype(np.uint8)).save(root / "mask" / f"{i:03d}.png")
    np.savez(root / "cameras.npz", **cams)
    return root


def zip_dir(src: Path, dst: Path, prefix: str = "") -> Path:
    with zipfile.ZipFile(dst, "w", zipfile.ZIP_DEFLATED) as z:
        for p in sorted(Path(src).rglob("*")):
            if p.is_file():
                z.write(p, prefix + p.relative_to(src).as_posix())
    return dst


def dataset_zip_bytes(tmp: Path, **kw) -> bytes:
    d = make_dtu_dir(tmp / "ds", **kw)
    z = zip_dir(d, tmp / "ds.zip", prefix="scan/")
    return z.read_bytes()


_REAL_ZIP: dict = {}


def real_scene_zip(tmp: Path) -> bytes:
    """A rendered scene for the real pipeline: ``nepf_core.data.synth.make_scene`` (its DTU folder)."""
    if "zip" not in _REAL_ZIP:
        from nepf_core.data.synth import make_scene  # only the real-pipeline tests need it

        out = tmp / "synth"
        make_scene(out, shape="sphere", material="diffuse", n_views=6, n_test=1, resolution=32,
                   supersample=1, write_mesh=False)
        _REAL_ZIP["zip"] = zip_dir(out / "dtu", tmp / "synth.zip", prefix="sphere/").read_bytes()
    return _REAL_ZIP["zip"]


#: environment for workers running the real pipeline in tests: CPU, small export
REAL_PIPELINE_ENV = {"NEPF_PIPELINE": "nepf_core.pipeline:run_pipeline", "NEPF_DEVICE": "cpu",
                     "NEPF_EXPORT_TEXTURE_SIZE": "64", "NEPF_EXPORT_MESH_RESOLUTION": "32",
                     "NEPF_EXPORT_MAX_FACES": "2000", "OMP_NUM_THREADS": "2"}
REAL_ITERS = 4


# ------------------------------------------------------------------------ fake pipeline
def _glb_bytes() -> bytes:
    """A minimal valid glTF-binary (one empty scene)."""
    js = json.dumps({"asset": {"version": "2.0"}, "scenes": [{"nodes": []}], "scene": 0}).encode()
    js += b" " * (-len(js) % 4)
    body = struct.pack("<II", len(js), 0x4E4F534A) + js
    return struct.pack("<4sII", b"glTF", 2, 12 + len(body)) + body


def fake_pipeline(request: JobRequest) -> dict:
    """Stands in for ``nepf_core.pipeline.run_pipeline`` in service tests (``NEPF_PIPELINE=
    service_fixtures:fake_pipeline``): same contract, no torch.

    Steps sleep ``NEPF_FAKE_STEP_S``; a checkpoint (``checkpoints/latest.json``, the file the core
    writes beside ``latest.pt``, by the core's own ``nepf_core.resume`` functions) every 5 steps;
    metrics.jsonl with train/sync/test records, cut back to the checkpoint on resume as the core
    does; export (asset.glb, previews, manifest) at the end. Like the core, it first reports ``loading`` at step 0 and
    then "loads" for ``NEPF_FAKE_LOAD_S`` seconds (default 0).
    """
    run, data_dir, callbacks, resume = Path(request.run_dir), request.data_dir, request.callbacks, request.resume
    (run / "checkpoints").mkdir(parents=True, exist_ok=True)
    total = int(request.iters or 40)
    step_s = float(os.environ.get("NEPF_FAKE_STEP_S", "0.05"))
    ck = run / "checkpoints" / "latest.json"
    start = (checkpoint_step(run) if resume else None) or 0
    if start:
        cut_metrics_to_checkpoint(run, start)
    if callbacks is not None:
        callbacks.progress({"step": 0, "total": 0, "fraction": 0.0, "stage": "loading", "eta_s": None, "wall_s": 0.0})
    time.sleep(float(os.environ.get("NEPF_FAKE_LOAD_S", "0")))
    assert Path(data_dir, "cameras.npz").exists() or any(Path(data_dir).iterdir())
    t0 = time.time()
    status = "succeeded"
    mf = open(run / "metrics.jsonl", "a")
    step = start
    for step in range(start + 1, total + 1):
        if callbacks is not None and callbacks.stop_requested():
            status = "cancelled"
            step -= 1
            break
        time.sleep(step_s)
        rec = {"step": step, "wall_s": time.time() - t0, "loss": 1.0 / step, "loss_r": 0.5 / step}
        mf.write(json.dumps(rec) + "\n")
        if step % 5 == 0:
            mf.write(json.dumps({"step": step, "wall_s": time.time() - t0, "kind": "sync", "psnr_r": 20 + step / 10,
                                 "psnr_surf": 19 + step / 10, "psnr_vol": 18 + step / 10}) + "\n")
            mf.flush()   # the records reach the file before the checkpoint names their step, as in the core
            write_checkpoint_info(run, step, time.time() - t0, mf.tell())
            if callbacks is not None:   # as the core does: the worker keeps it (object store)
                callbacks.checkpoint(step, str(ck))
        mf.flush()
        if callbacks is not None:
            callbacks.progress({"step": step, "total": total, "fraction": step / total, "stage": "train",
                                "eta_s": (total - step) * step_s, "wall_s": time.time() - t0})
    mf.write(json.dumps({"step": step, "wall_s": time.time() - t0, "kind": "test", "test_psnr": 21.0,
                         "chamfer": 0.01, "albedo_psnr": 18.0}) + "\n")
    mf.flush()
    write_checkpoint_info(run, step, time.time() - t0, mf.tell())
    mf.close()
    if callbacks is not None:
        callbacks.checkpoint(step, str(ck))
    (run / "report.json").write_text(json.dumps({"decisions": [
        {"decision": "ray_batch", "value": 256, "reason": "fake", "step": 0}]}))
    (run / "previews").mkdir(exist_ok=True)
    Image.fromarray(np.full((8, 8, 3), 128, np.uint8)).save(run / "previews" / "view_000.png")
    (run / "asset.glb").write_bytes(_glb_bytes())
    arts = []
    for kind, rel in (("glb", "asset.glb"), ("preview", "previews/view_000.png"), ("metrics", "metrics.jsonl")):
        b = (run / rel).read_bytes()
        arts.append({"kind": kind, "path": rel, "bytes": len(b), "sha256": hashlib.sha256(b).hexdigest()})
    (run / "manifest.json").write_text(json.dumps({"artifacts": arts}))
    with open(run / "completions.log", "a") as f:
        f.write(f"{os.getpid()} {status} {step}\n")
    return {"status": status, "step": step, "total": total, "wall_s": time.time() - t0,
            "manifest": str(run / "manifest.json"), "report": {"decisions": []}}


# ------------------------------------------------------------------------ processes
def service_env(data_dir: Path, **extra: str) -> dict:
    env = {k: v for k, v in os.environ.items() if not k.startswith("NEPF_")}
    env.update({"NEPF_DATA_DIR": str(data_dir), "PYTHONPATH": os.pathsep.join([str(REPO), str(TESTS)]),
                "PYTHONUNBUFFERED": "1", "OMP_NUM_THREADS": "1"})
    env.update({k: str(v) for k, v in extra.items()})
    return env


class Proc:
    """A child process with its output in a log file; stopped by PID."""

    def __init__(self, argv: list[str], env: dict, log: Path, cwd: Path = REPO) -> None:
        self.log = log
        self.fh = open(log, "ab")
        self.p = subprocess.Popen(argv, env=env, cwd=str(cwd), stdout=self.fh, stderr=subprocess.STDOUT,
                                  start_new_session=True)

    @property
    def pid(self) -> int:
        return self.p.pid

    def alive(self) -> bool:
        return self.p.poll() is None

    def kill9(self) -> None:
        os.kill(self.p.pid, signal.SIGKILL)
        self.p.wait(10)

    def stop(self, timeout: float = 10) -> None:
        if self.p.poll() is None:
            self.p.send_signal(signal.SIGTERM)
            try:
                self.p.wait(timeout)
            except subprocess.TimeoutExpired:
                self.p.kill()
                self.p.wait(5)
        # reap anything it left in its session (e.g. the embedded worker), by process group id
        try:
            os.killpg(self.p.pid, signal.SIGKILL)
        except (ProcessLookupError, PermissionError):
            pass
        self.fh.close()

    def output(self) -> str:
        self.fh.flush()
        return self.log.read_text(errors="replace")[-6000:]


def start_redis(tmp: Path, port: Optional[int] = None) -> tuple[Proc, int]:
    port = port or free_port()
    (tmp / "redis").mkdir(exist_ok=True)
    p = Proc(["/usr/bin/redis-server", "--port", str(port), "--bind", "127.0.0.1", "--save", "",
              "--appendonly", "no", "--dir", str(tmp / "redis")], os.environ.copy(), tmp / f"redis-{port}.log")
    import redis

    wait_for(lambda: redis.Redis(port=port, socket_timeout=1).ping(), 15, what="redis")
    return p, port


def start_api(env: dict, tmp: Path, port: Optional[int] = None, extra: Optional[list] = None,
              name: str = "api") -> tuple[Proc, str]:
    import httpx

    port = port or free_port()
    p = Proc([sys.executable, "-m", "api.commands", "serve", "--port", str(port), "--log-level", "warning"]
             + (extra or []), env, tmp / f"{name}-{port}.log")
    base = f"http://127.0.0.1:{port}"

    def ready():
        if not p.alive():
            raise RuntimeError("api exited:\n" + p.output())
        return httpx.get(base + "/readyz", timeout=2).status_code == 200
    wait_for(ready, 30, 0.2, what="api /readyz")
    return p, base


def start_worker(env: dict, tmp: Path, name: str = "worker") -> Proc:
    return Proc([sys.executable, "-m", "worker.commands", "--queues", "default,gpu", "--concurrency", "1",
                 "--loglevel", "INFO"], env, tmp / f"{name}-{time.monotonic_ns()}.log")


def local_token(data_dir: Path) -> str:
    return (Path(data_dir) / "local-token").read_text().strip()


def create_token(env: dict, name: str) -> str:
    out = subprocess.run([sys.executable, "-m", "api.commands", "token", "create", name], env=env,
                         cwd=str(REPO), capture_output=True, text=True, check=True)
    return out.stdout.strip().splitlines()[-1]


def leftover_files(data_dir: Path) -> list[str]:
    """Files under the upload staging and job folders (should be none after a rejection)."""
    out = []
    for sub in ("uploads", "jobs"):
        d = Path(data_dir) / sub
        if d.exists():
            out += [str(p.relative_to(data_dir)) for p in d.rglob("*")]
    return out


def rmtree(p: Path) -> None:
    shutil.rmtree(p, ignore_errors=True)


# ------------------------------------------------------------------------ HTTP helpers
def read_sse(base: str, path: str, headers: Optional[dict] = None, timeout: float = 60) -> list[tuple[str, dict]]:
    """Read an event stream until its ``end`` event; returns ``[(event, data), ...]``."""
    import httpx

    events, ev, data = [], None, []
    with httpx.stream("GET", base + path, headers=headers or {}, timeout=timeout) as r:
        assert r.status_code == 200, r.read()
        assert r.headers["content-type"].startswith("text/event-stream")
        for line in r.iter_lines():
            if line.startswith("event:"):
                ev = line[6:].strip()
            elif line.startswith("data:"):
                data.append(line[5:].strip())
            elif line == "" and ev is not None:
                events.append((ev, json.loads("\n".join(data))))
                if ev == "end":
                    break
                ev, data = None, []
    return events


def get_job(base: str, h: dict, job_id: str) -> dict:
    import httpx

    r = httpx.get(f"{base}/jobs/{job_id}", headers=h, timeout=10)
    assert r.status_code == 200, r.text
    return r.json()


def wait_status(base: str, h: dict, job_id: str, statuses, timeout: float) -> dict:
    statuses = {statuses} if isinstance(statuses, str) else set(statuses)
    return wait_for(lambda: (lambda j: j if j["status"] in statuses else None)(get_job(base, h, job_id)),
                    timeout, 0.1, what=f"job {job_id} in {statuses}")


def upload(base: str, h: dict, zbytes: bytes, config: Optional[dict] = None, extra_headers=None):
    import httpx

    data = {"config": json.dumps(config)} if config is not None else None
    return httpx.post(base + "/jobs", headers={**h, **(extra_headers or {})},
                      files={"dataset": ("dataset.zip", zbytes, "application/zip")}, data=data, timeout=120)


def pg_database(prefix: str = "nepf_t") -> tuple[str, Callable[[], None]]:
    """A fresh PostgreSQL database on 127.0.0.1:5432 (fails, not skips, when unreachable)."""
    import uuid

    import psycopg

    name = f"{prefix}_{uuid.uuid4().hex[:10]}"
    admin = "postgresql://postgres@127.0.0.1:5432/test"
    with psycopg.connect(admin, autocommit=True) as c:
        c.execute(f'CREATE DATABASE "{name}"')

    def drop():
        with psycopg.connect(admin, autocommit=True) as c:
            c.execute(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)')
    return f"postgresql+psycopg://postgres@127.0.0.1:5432/{name}", drop


def check_lifecycle(base: str, h: dict, zbytes: bytes, config: dict, timeout: float) -> dict:
    """Upload -> progress -> SSE -> metrics (with ?since=) -> artifacts -> GLB download."""
    import httpx

    r = upload(base, h, zbytes, config)
    assert r.status_code == 202, r.text
    job = r.json()
    jid = job["id"]
    # the 202 body is the job as the DB holds it after the enqueue: a free worker may already have
    # claimed it (seen with a separate Redis worker), so "running" is as valid as "queued" here
    assert r.headers["location"] == f"/jobs/{jid}" and job["status"] in ("queued", "running"), job["status"]
    # progress moves while it runs (or it is already done for very short jobs)
    seen = wait_for(lambda: (lambda j: j if (j["status"] == "running" and j["progress"]["step"] >= 1)
                             or j["status"] in ("succeeded", "failed") else None)(get_job(base, h, jid)),
                    timeout, 0.05, what="progress")
    assert seen["status"] != "failed", seen["error"]
    assert seen["started_at"] is not None
    # SSE with a ticket (what a browser EventSource does), until the end event
    t = httpx.post(f"{base}/jobs/{jid}/events/ticket", headers=h).json()
    events = read_sse(base, t["url"], timeout=timeout)
    kinds = [e for e, _ in events]
    assert kinds[-1] == "end" and events[-1][1]["status"] == "succeeded", events[-3:]
    assert "progress" in kinds and "metrics" in kinds
    final = wait_status(base, h, jid, ("succeeded", "failed"), 10)   # GET may lag by NEPF_POLL_CACHE_S
    assert final["status"] == "succeeded", final
    assert final["finished_at"] >= final["started_at"] >= final["created_at"]
    p = final["progress"]
    assert p["total"] and p["step"] == p["total"] and p["fraction"] == 1.0
    assert final["delivery"]["completions"] == 1
    # metrics: the full series, and increments with ?since=
    m = httpx.get(f"{base}/jobs/{jid}/metrics", headers=h).json()
    assert m["records"] and m["next_since"] == len(m["records"])
    assert all("step" in rec and "wall_s" in rec for rec in m["records"])
    sse_metrics = [d for e, d in events if e == "metrics"]
    assert sse_metrics == m["records"]
    half = len(m["records"]) // 2
    m1 = httpx.get(f"{base}/jobs/{jid}/metrics?since={half}", headers=h).json()
    assert m1["records"] == m["records"][half:] and m1["next_since"] == m["next_since"]
    assert httpx.get(f"{base}/jobs/{jid}/metrics?since={m['next_since']}", headers=h).json()["records"] == []
    # artifacts: manifest + GLB download with the right type and checksum
    arts = httpx.get(f"{base}/jobs/{jid}/artifacts", headers=h).json()
    assert arts["manifest"] is True
    glb = [a for a in arts["artifacts"] if a["path"].endswith(".glb")]
    assert glb, arts
    d = httpx.get(base + glb[0]["url"], headers=h)
    assert d.status_code == 200 and d.headers["content-type"] == "model/gltf-binary"
    assert d.content[:4] == b"glTF"
    if glb[0].get("sha256"):
        import hashlib
        assert hashlib.sha256(d.content).hexdigest() == glb[0]["sha256"]
    return final


def max_metric_step(data_dir: Path, job_id: str) -> int:
    """The last step written to metrics.jsonl (the DB progress lags by up to a heartbeat)."""
    p = Path(data_dir) / "jobs" / job_id / "run" / "metrics.jsonl"
    steps = []
    for line in p.read_text().splitlines():
        try:
            steps.append(int(json.loads(line).get("step", 0)))
        except ValueError:   # a line cut by the kill (JSONDecodeError is a ValueError)
            continue
    return max(steps) if steps else 0


def new_job(settings, Session, **values) -> str:
    """A job row (owner "w", preset tiny, 20 steps unless ``values`` say otherwise) with a small DTU
    dataset in its folder, written straight to the store (no API)."""
    from jobstore.models import Job

    values = {"config": {"preset": "tiny", "iters": 20}, **values}
    job = Job(owner="w", queue="default", attempt_log=[], **values)
    with Session() as s:
        s.add(job)
        s.commit()
        jid = job.id
    make_dtu_dir(settings.jobs_path / jid / "dataset", n=3, size=8)
    return jid
