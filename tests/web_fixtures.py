"""Helpers for the browser tests of the web viewer (``tests/test_web_*.py``).

* :func:`ensure_web_built` builds ``web/dist`` (``npm ci`` when ``node_modules`` is missing,
  ``npm run build`` when ``dist`` is older than the sources).
* :class:`Backend` runs the real service the way a user does, ``nepf serve`` with its embedded
  default (SQLite job store, SQLite broker, one local worker that runs the real pipeline,
  ``nepf_core.pipeline.run_pipeline``, with smaller export sizes: :data:`WEB_TEST_EXPORT`) on a free
  loopback port, reads the login URL it prints, and stops it (and the worker it started) by
  process-group id.
* :func:`make_sphere_dtu` renders a small DTU-layout dataset (a shaded sphere, masks,
  ``cameras.npz``) with numpy, so the tests need no ``../shared``.
* :func:`invalid_dataset_zip` is a DTU zip with one corrupt image (the API rejects it and
  names the file).
* :func:`chromium_path` finds Debian's Chromium; the tests fail (not skip) without it.
"""

from __future__ import annotations

import io
import json
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import time
import zipfile
from pathlib import Path
from typing import Callable, Optional

import numpy as np
from PIL import Image

REPO = Path(__file__).resolve().parent.parent
WEB = REPO / "web"
DIST = WEB / "dist"
ARTIFACTS = REPO / "test-artifacts" / "web"

CHROMIUM_CANDIDATES = ("/usr/bin/chromium", "/usr/bin/chromium-browser", "/usr/lib/chromium/chromium")
CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
                 "--disable-component-update", "--use-angle=swiftshader", "--enable-unsafe-swiftshader"]


# ------------------------------------------------------------------------------ waiting
def wait_for(pred: Callable[[], object], timeout: float, interval: float = 0.2, what: str = "condition"):
    """Poll ``pred`` until it returns a truthy value (returned) or ``timeout`` seconds pass."""
    deadline = time.monotonic() + timeout
    last_exc: Optional[BaseException] = None
    while time.monotonic() < deadline:
        try:
            v = pred()
            if v:
                return v
        except Exception as exc:  # noqa: BLE001 - keep polling, report the last error
            last_exc = exc
        time.sleep(interval)
    raise TimeoutError(f"timed out after {timeout:g}s waiting for {what}"
                       + (f" (last error: {last_exc!r})" if last_exc else ""))


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


# ------------------------------------------------------------------------------ browser
def chromium_path() -> str:
    """Debian's Chromium (``apt-get install chromium``); ``NEPF_CHROMIUM`` overrides."""
    cands = [os.environ.get("NEPF_CHROMIUM")] + list(CHROMIUM_CANDIDATES)
    for c in cands:
        if c and Path(c).is_file() and os.access(c, os.X_OK):
            return c
    found = shutil.which("chromium") or shutil.which("chromium-browser")
    if found:
        return found
    raise RuntimeError("Chromium not found: install Debian's `chromium` (apt-get install -y chromium) "
                       "or set NEPF_CHROMIUM; the web tests need a real browser")


# ------------------------------------------------------------------------------ web build
def _newest_mtime(paths) -> float:
    m = 0.0
    for p in paths:
        p = Path(p)
        if p.is_dir():
            for q in p.rglob("*"):
                if q.is_file():
                    m = max(m, q.stat().st_mtime)
        elif p.exists():
            m = max(m, p.stat().st_mtime)
    return m


def ensure_web_built() -> Path:
    """``web/dist`` up to date with ``web/src`` (build here when needed; CI builds it first)."""
    index = DIST / "index.html"
    srcs = [WEB / "src", WEB / "index.html", WEB / "package.json", WEB / "vite.config.js"]
    if index.exists() and index.stat().st_mtime >= _newest_mtime(srcs):
        return DIST
    npm = shutil.which("npm")
    if npm is None:
        raise RuntimeError("web/dist is missing or stale and npm is not installed: run "
                           "`cd web && npm ci && npm run build`")
    if not (WEB / "node_modules" / ".package-lock.json").exists():
        subprocess.run([npm, "ci", "--no-audit", "--no-fund"], cwd=WEB, check=True, timeout=600)
    subprocess.run([npm, "run", "build"], cwd=WEB, check=True, timeout=300)
    assert index.exists(), "npm run build did not produce web/dist/index.html"
    return DIST


# ------------------------------------------------------------------------------ datasets
def _look_at_w2c(eye, target=(0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0)):
    eye, target, up = (np.asarray(v, float) for v in (eye, target, up))
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])  # rows: camera axes in world (OpenCV: x right, y down, z forward)
    return R, -R @ eye


def make_sphere_dtu(root: Path, n_views: int = 12, size: int = 48, radius: float = 0.7,
                    light=(2.0, 1.5, 2.5), light_intensity: float = 6.0) -> Path:
    """Render a DTU-layout dataset of a Lambertian sphere lit by a point light.

    World frame, Z up; sphere of ``radius`` at the origin with albedo ``0.25 + 0.5 * (n+1)/2``
    per channel (spatially varying, so the albedo texture is not flat); cameras on a ring at
    distance 3 and heights alternating +-0.8, focal ``1.4 * size``. Pixel colour (linear):
    ``albedo / pi * I / d^2 * max(n.l, 0) + 0.03 * albedo`` (small ambient), stored as sRGB.
    Writes ``cameras.npz`` (``world_mat_i = K [R|t]`` as 4x4, ``scale_mat_i = I``), ``image/``
    and ``mask/``.
    """
    root = Path(root)
    (root / "image").mkdir(parents=True, exist_ok=True)
    (root / "mask").mkdir(parents=True, exist_ok=True)
    f = 1.4 * size
    K = np.array([[f, 0, (size - 1) / 2], [0, f, (size - 1) / 2], [0, 0, 1]])
    Lp = np.asarray(light, float)
    cams = {}
    for i in range(n_views):
        a = 2 * np.pi * i / n_views
        eye = np.array([3 * np.cos(a), 3 * np.sin(a), 0.8 if i % 2 == 0 else -0.8])
        R, t = _look_at_w2c(eye)
        P = np.eye(4)
        P[:3, :4] = K @ np.hstack([R, t[:, None]])
        cams[f"world_mat_{i}"] = P
        cams[f"scale_mat_{i}"] = np.eye(4)
        # rays through pixel centres (OpenCV: integer coordinates)
        v, u = np.mgrid[0:size, 0:size].astype(float)
        d_cam = np.stack([(u - K[0, 2]) / f, (v - K[1, 2]) / f, np.ones_like(u)], -1)
        d = d_cam @ R  # camera -> world: R^T d  (row vectors)
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        b = (d * eye).sum(-1)
        c = eye @ eye - radius ** 2
        disc = b * b - c
        hit = disc > 0
        tt = -b - np.sqrt(np.where(hit, disc, 0))
        x = eye + tt[..., None] * d
        n = x / radius
        albedo = 0.25 + 0.5 * (n + 1) / 2
        lv = Lp - x
        dist2 = (lv * lv).sum(-1, keepdims=True)
        l = lv / np.sqrt(dist2)
        ndl = np.clip((n * l).sum(-1, keepdims=True), 0, None)
        lin = albedo / np.pi * light_intensity / dist2 * ndl + 0.03 * albedo
        lin = np.where(hit[..., None], np.clip(lin, 0, 1), 0.0)
        srgb = np.where(lin <= 0.0031308, 12.92 * lin, 1.055 * np.power(lin, 1 / 2.4) - 0.055)
        Image.fromarray((srgb * 255 + 0.5).astype(np.uint8)).save(root / "image" / f"{i:03d}.png")
        Image.fromarray((hit * 255).astype(np.uint8)).save(root / "mask" / f"{i:03d}.png")
    np.savez(root / "cameras.npz", **cams)
    return root


def zip_dir_bytes(src: Path, prefix: str = "") -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as z:
        for p in sorted(Path(src).rglob("*")):
            if p.is_file():
                z.write(p, prefix + p.relative_to(src).as_posix())
    return buf.getvalue()


def invalid_dataset_zip(tmp: Path, bad_file: str = "image/002.png") -> bytes:
    """A DTU zip whose ``bad_file`` is not an image (the validator names it)."""
    d = make_sphere_dtu(Path(tmp) / "invalid_ds", n_views=6, size=24)
    (d / bad_file).write_bytes(b"this is not a PNG file")
    return zip_dir_bytes(d, prefix="broken_scan/")


# ------------------------------------------------------------------------------ backend
# Export sizes for the jobs of the browser tests. The presets' defaults (1024² textures,
# 100k faces, a 256³ SDF grid) take minutes on a 2-core CPU; the viewer's behaviour does not
# depend on them. Training, export code paths, artifacts and manifest are the real ones.
# ``NEPF_WEB_TEST_FULL_EXPORT=1`` runs the worker's default pipeline unchanged.
WEB_TEST_EXPORT = {"texture_size": 256, "max_faces": 5000, "mesh_resolution": 64}


def pipeline_small_export(request):
    """The real :func:`nepf_core.pipeline.run_pipeline` with :data:`WEB_TEST_EXPORT` (the
    worker's ``NEPF_PIPELINE`` setting names this function in the browser tests)."""
    from dataclasses import replace

    from nepf_core.pipeline import run_pipeline

    iters = request.iters
    if iters is None and request.time_budget_s:
        # a budgeted upload without an iteration count would stop at tiny's 100 steps (~5 s),
        # before a browser test can watch and cancel it: train until the budget or a cancel
        iters = 100_000
    return run_pipeline(replace(request, iters=iters, **WEB_TEST_EXPORT))


def pipeline_held_out_standin(request):
    """Stands in for the training in the browser test of the held-out split (no torch, ~15 s).

    Like ``fit()`` with held-out views, it writes a ``kind: "test"`` record (wall-clock
    schedule: every :data:`STANDIN_EVAL_EVERY` steps, and a final one) only when the job's
    ``request.holdout_every`` reached it and is > 0, with ``test_views`` the number held out
    (``ceil(n_views / K)``, ``n_views`` counted in the dataset's ``image/``). Train records
    carry a loss; no export."""
    from nepf_core.holdout_preview import write_holdout_preview   # numpy + Pillow only

    run = Path(request.run_dir)
    every = int(request.holdout_every or 0)
    n_views = len(list(Path(request.data_dir, "image").glob("*.png")))
    held = -(-n_views // every) if every else 0
    total, t0 = STANDIN_STEPS, time.time()
    status = "succeeded"
    with open(run / "metrics.jsonl", "a") as f:
        for step in range(1, total + 1):
            if request.callbacks.stop_requested():
                status = "cancelled"
                break
            time.sleep(STANDIN_STEP_S)
            wall = round(time.time() - t0, 3)
            f.write(json.dumps({"kind": "train", "step": step, "wall_s": wall, "loss": 1.0 / step}) + "\n")
            if held and (step % STANDIN_EVAL_EVERY == 0 or step == total):
                # the real picture writer, on a render that approaches the truth as the steps go
                truth = np.linspace(0.0, 1.0, 16 * 16 * 3).reshape(16, 16, 3)
                preview = write_holdout_preview(run, truth * min(1.0, step / total), truth)
                f.write(json.dumps({"kind": "test", "step": step, "wall_s": wall, "test_views": held,
                                    "test_psnr": 12.0 + step / 10, "test_psnr_full": 10.0 + step / 10,
                                    "test_psnr_radiance": 13.0 + step / 10, "final": step == total,
                                    "preview": preview}) + "\n")
            f.flush()
            request.callbacks.progress({"step": step, "total": total, "fraction": step / total, "stage": "training",
                                        "eta_s": (total - step) * STANDIN_STEP_S, "wall_s": wall})
            if step == STANDIN_HOLD_STEP and os.environ.get(STANDIN_HOLD_ENV) == "1":
                _hold_until_released(request, run)
    return {"status": status, "step": step, "total": total, "wall_s": time.time() - t0, "manifest": None,
            "split": {"holdout_every": every, "n_test": held, "n_train": n_views - held}}


#: the stand-in's schedule: 150 steps of 0.1 s, a held-out evaluation every 10 steps
STANDIN_STEPS, STANDIN_STEP_S, STANDIN_EVAL_EVERY = 150, 0.1, 10
#: with ``WEB_TEST_STANDIN_HOLD=1`` in the server's environment, the stand-in holds after this step
#: (its second held-out record) until :func:`release_standin`, so that a test sees the job training
#: while its chart shows points, on a machine of any speed
STANDIN_HOLD_STEP, STANDIN_HOLD_ENV = 2 * STANDIN_EVAL_EVERY, "WEB_TEST_STANDIN_HOLD"
STANDIN_HOLDING, STANDIN_RELEASE, STANDIN_MAX_HOLD_S = "standin-holding", "standin-release", 120.0


def _hold_until_released(request, run: Path) -> None:
    """Say so in ``RUN/standin-holding``, then wait for ``RUN/standin-release`` (or a stop, or
    STANDIN_MAX_HOLD_S)."""
    (run / STANDIN_HOLDING).touch()
    deadline = time.time() + STANDIN_MAX_HOLD_S
    while not (run / STANDIN_RELEASE).exists() and time.time() < deadline:
        if request.callbacks.stop_requested():
            return
        time.sleep(0.05)


def standin_holding(data_dir: Path, job_id: str) -> bool:
    """Whether a stand-in job (``pipeline_held_out_standin``) reached its hold."""
    return (Path(data_dir) / "jobs" / job_id / "run" / STANDIN_HOLDING).exists()


def release_standin(data_dir: Path, job_id: str) -> None:
    """Let a held stand-in job train on."""
    (Path(data_dir) / "jobs" / job_id / "run" / STANDIN_RELEASE).touch()


class Backend:
    """``nepf serve`` (API + embedded broker + one local worker) on a free port."""

    def __init__(self, data_dir: Path, log_path: Path, env_extra: Optional[dict] = None) -> None:
        self.data_dir = Path(data_dir)
        self.port = free_port()
        self.base = f"http://127.0.0.1:{self.port}"
        env = {k: v for k, v in os.environ.items() if not k.startswith("NEPF_")}
        env.update({
            "NEPF_DATA_DIR": str(self.data_dir),
            "NEPF_WEB_DIR": str(DIST),
            "NEPF_DEVICE": "cpu",
            "PYTHONPATH": os.pathsep.join([str(REPO), str(REPO / "tests")]
                                          + ([env["PYTHONPATH"]] if env.get("PYTHONPATH") else [])),
            "PYTHONUNBUFFERED": "1",
        })
        if os.environ.get("NEPF_WEB_TEST_FULL_EXPORT") != "1":
            env["NEPF_PIPELINE"] = "web_fixtures:pipeline_small_export"
        env.update(env_extra or {})
        self.log_path = Path(log_path)
        self.log = open(self.log_path, "ab")
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "api.commands", "serve", "--port", str(self.port), "--log-level", "warning"],
            cwd=str(REPO), env=env, stdout=self.log, stderr=subprocess.STDOUT, start_new_session=True)
        try:
            self.login_url = wait_for(self._login_url, 60, 0.2, what="the login URL printed by `nepf serve`")
            m = re.search(r"#token=([^\s&]+)", self.login_url)
            assert m, self.login_url
            self.token = m.group(1)
            import httpx

            wait_for(lambda: httpx.get(self.base + "/readyz", timeout=2).status_code == 200, 60, 0.3,
                     what="GET /readyz")
        except BaseException:
            self.stop()
            raise

    def _login_url(self) -> Optional[str]:
        if self.proc.poll() is not None:
            raise RuntimeError(f"nepf serve exited ({self.proc.returncode}):\n{self.output()}")
        self.log.flush()
        m = re.search(r"(http://\S+/#token=\S+)", self.log_path.read_text(errors="replace"))
        return m.group(1) if m else None

    def output(self) -> str:
        try:
            self.log.flush()
        except ValueError:
            pass
        return self.log_path.read_text(errors="replace")[-8000:]

    # -- API helpers (the tests compare the UI against these) --
    def client(self):
        import httpx

        return httpx.Client(base_url=self.base, headers={"Authorization": f"Bearer {self.token}"}, timeout=30)

    def submit(self, zip_bytes: bytes, config: dict, name: str = "dataset.zip") -> dict:
        with self.client() as c:
            r = c.post("/jobs", files={"dataset": (name, zip_bytes, "application/zip")},
                       data={"config": json.dumps(config)})
        assert r.status_code == 202, r.text
        return r.json()

    def job(self, job_id: str) -> dict:
        with self.client() as c:
            r = c.get(f"/jobs/{job_id}")
        r.raise_for_status()
        return r.json()

    def wait_status(self, job_id: str, statuses: tuple[str, ...], timeout: float) -> dict:
        def done():
            j = self.job(job_id)
            if j["status"] in statuses:
                return j
            if j["status"] in ("failed", "cancelled", "succeeded"):
                raise AssertionError(f"job {job_id} ended {j['status']}: {j.get('error')}\n{self.output()}")
            return None
        try:
            return wait_for(done, timeout, 0.5, what=f"job {job_id} to reach {statuses}")
        except TimeoutError as e:
            raise TimeoutError(f"{e}; last state: {self.job(job_id)}\n--- serve log ---\n{self.output()}") from None

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(15)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)
        # the embedded worker runs in serve's session: reap it by process-group id
        try:
            os.killpg(self.proc.pid, signal.SIGKILL)
        except (ProcessLookupError, PermissionError):
            pass
        try:
            self.log.close()
        except Exception:  # noqa: BLE001
            pass


# ------------------------------------------------------------------------------ images
def png_stats(png: bytes) -> np.ndarray:
    """PNG bytes -> float RGB array in [0, 1]."""
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=np.float32) / 255.0


def asset_change(a: bytes, b: bytes, background, fg_thr: float = 0.04, diff_thr: float = 0.03) -> float:
    """Fraction of the asset's pixels (not ``background`` in either PNG) whose colour changed
    by more than ``diff_thr`` (max over RGB): a size-independent "did the picture change"."""
    x, y = png_stats(a), png_stats(b)
    assert x.shape == y.shape, (x.shape, y.shape)
    bg = np.asarray(background, np.float32)
    fg = (np.abs(x - bg).max(-1) > fg_thr) | (np.abs(y - bg).max(-1) > fg_thr)
    if not fg.any():
        return 0.0
    return float((np.abs(x - y).max(-1) > diff_thr)[fg].mean())
