"""The README's first command ends in ``scripts/demo.py``: it generates the demo scene, starts
``nepf serve`` on the embedded default and queues the scene as a job. Run it for real (the
``tiny`` preset and a 3 s budget instead of the default ``fast`` / 300 s)."""

from __future__ import annotations

import os
import re
import signal
import sys

import httpx

from service_fixtures import (REAL_PIPELINE_ENV, REPO, Proc, free_port, service_env, wait_for, wait_status,
                              worker_pids)


def _start_demo(data, tmp_path, port, name):
    argv = [sys.executable, str(REPO / "scripts" / "demo.py"), "--port", str(port), "--preset", "tiny",
            "--budget", "3", "--data-dir", str(data)]
    return Proc(argv, service_env(data, **REAL_PIPELINE_ENV), tmp_path / f"{name}.log")


def _stop_and_check_gone(demo: Proc, base: str) -> None:
    """SIGTERM to the demo alone (not its process group): it must stop the server and its worker."""
    out = demo.output()
    pids = worker_pids(out)
    os.kill(demo.pid, signal.SIGTERM)
    demo.p.wait(30)
    assert demo.p.returncode == 0, demo.output()

    def port_closed():
        try:
            httpx.get(base + "/healthz", timeout=1)
            return False
        except httpx.TransportError:
            return True
    wait_for(port_closed, 15, what="the demo's server to stop")
    for pid in pids:
        def gone(pid=pid):
            try:
                os.kill(pid, 0)
            except ProcessLookupError:
                return True
            with open(f"/proc/{pid}/stat") as f:       # a zombie left for init to reap is gone too
                return f.read().split(")")[-1].split()[0] == "Z"
        wait_for(gone, 15, what=f"the embedded worker {pid} to exit")


def test_demo_generates_a_scene_serves_it_and_trains_it_once(tmp_path):
    data = tmp_path / "data"
    port = free_port()
    base = f"http://127.0.0.1:{port}"
    demo = _start_demo(data, tmp_path, port, "demo1")
    try:
        wait_for(lambda: "[demo] open " in demo.output() or not demo.alive(), 120, 0.2, what="the demo's login URL")
        out = demo.output()
        assert demo.alive(), out
        url = re.search(r"\[demo\] open (\S+)", out).group(1)
        assert url.startswith(base + "/#token=")
        h = {"Authorization": f"Bearer {url.split('#token=')[1]}"}
        job_id = re.search(r"\[demo\] queued job ([0-9a-f]{32})", out).group(1)
        assert (data / "demo-scene" / "dtu" / "cameras.npz").exists()
        final = wait_status(base, h, job_id, ("succeeded", "failed", "cancelled"), 180)
        assert final["status"] == "succeeded", (final.get("error"), demo.output()[-3000:])
        assert final["name"] == "demo: glossy torus"
        arts = httpx.get(f"{base}/jobs/{job_id}/artifacts", headers=h).json()["artifacts"]
        glb = [a for a in arts if a["url"].endswith(".glb")]
        assert glb and httpx.get(base + glb[0]["url"], headers=h).content[:4] == b"glTF"
        _stop_and_check_gone(demo, base)
    finally:
        demo.stop()

    # a second start on the same data dir reuses the scene and does not queue the demo twice
    demo = _start_demo(data, tmp_path, port, "demo2")
    try:
        wait_for(lambda: "[demo] open " in demo.output() or not demo.alive(), 120, 0.2, what="the second login URL")
        out = demo.output()
        assert "generating the demo scene" not in out
        assert re.search(r"\[demo\] queued job ([0-9a-f]{32})", out).group(1) == job_id
        assert [j["id"] for j in httpx.get(base + "/jobs", headers=h).json()["items"]] == [job_id]
    finally:
        demo.stop()
