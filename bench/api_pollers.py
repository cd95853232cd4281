"""Load benchmark of the jobs API (not a test).

Default mode: with a job training, N concurrent pollers each ``GET /jobs/{id}`` for D seconds;
reports p50/p99/max latency, throughput and the error count (target: p99 <= 50 ms, 0 errors).

    python -m bench.api_pollers                      # spawns `nepf serve` (embedded) + a real tiny job
    python -m bench.api_pollers --fake               # the job is the service tests' fake pipeline
    python -m bench.api_pollers --base URL --token T --job ID   # an existing server and job
    python -m bench.api_pollers --mode enqueue-latency          # embedded broker: enqueue -> claim

Pollers wait ``--interval`` seconds (+-20 % jitter) between requests, as a browser tab or a
script polling a job does; ``--interval 0`` is a closed loop (measures saturation instead).
Results are written as JSON to ``bench/results/``.
"""

from __future__ import annotations

import argparse
import asyncio
import datetime as dt
import json
import os
import random
import statistics
import sys
import tempfile
import time
from pathlib import Path

import httpx

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO / "tests"))


def percentile(xs: list[float], q: float) -> float:
    if not xs:
        return float("nan")
    xs = sorted(xs)
    k = (len(xs) - 1) * q
    lo, hi = int(k), min(int(k) + 1, len(xs) - 1)
    return xs[lo] + (xs[hi] - xs[lo]) * (k - lo)


class RawConn:
    """A minimal HTTP/1.1 keep-alive client (one connection per poller, like separate browser tabs).

    httpx costs ~2.5 ms of client CPU per request, four times what the server spends, so on a
    2-core machine it measured the client; this costs a small fraction of that."""

    def __init__(self, host: str, port: int, token: str) -> None:
        self.host, self.port, self.token = host, port, token
        self.reader = self.writer = None

    async def get(self, path: str) -> tuple[int, bytes]:
        if self.writer is None:
            self.reader, self.writer = await asyncio.open_connection(self.host, self.port)
        req = (f"GET {path} HTTP/1.1\r\nHost: {self.host}:{self.port}\r\n"
               f"Authorization: Bearer {self.token}\r\nAccept: application/json\r\n\r\n").encode()
        try:
            self.writer.write(req)
            head = await self.reader.readuntil(b"\r\n\r\n")
            status = int(head.split(b" ", 2)[1])
            length = 0
            for line in head.split(b"\r\n")[1:]:
                k, _, v = line.partition(b":")
                if k.strip().lower() == b"content-length":
                    length = int(v)
            body = await self.reader.readexactly(length)
            return status, body
        except Exception:
            await self.close()
            raise

    async def close(self) -> None:
        if self.writer is not None:
            self.writer.close()
            self.writer = self.reader = None


async def poll(base: str, token: str, job_id: str, n: int, duration: float, interval: float) -> dict:
    from urllib.parse import urlsplit

    u = urlsplit(base)
    lat: list[float] = []
    errors: dict[str, int] = {}
    stop = time.perf_counter() + duration

    async def one(i: int):
        conn = RawConn(u.hostname, u.port or 80, token)
        await asyncio.sleep(random.random() * max(interval, 0.01))   # spread the start
        while time.perf_counter() < stop:
            t0 = time.perf_counter()
            try:
                status, body = await asyncio.wait_for(conn.get(f"/jobs/{job_id}"), 10)
                if status != 200:
                    errors[str(status)] = errors.get(str(status), 0) + 1
                else:
                    lat.append(time.perf_counter() - t0)
            except Exception as exc:  # noqa: BLE001
                errors[type(exc).__name__] = errors.get(type(exc).__name__, 0) + 1
            if interval > 0:
                await asyncio.sleep(interval * random.uniform(0.8, 1.2))
        await conn.close()

    t0 = time.perf_counter()
    cpu0 = time.process_time()
    await asyncio.gather(*(one(i) for i in range(n)))
    wall = time.perf_counter() - t0
    ms = [x * 1000 for x in lat]
    return {"pollers": n, "duration_s": duration, "interval_s": interval, "requests": len(lat),
            "errors": sum(errors.values()), "error_kinds": errors, "rps": len(lat) / wall,
            "p50_ms": percentile(ms, 0.5), "p90_ms": percentile(ms, 0.9), "p99_ms": percentile(ms, 0.99),
            "max_ms": max(ms) if ms else None, "mean_ms": statistics.fmean(ms) if ms else None,
            "client_cpu_ms_per_req": (time.process_time() - cpu0) * 1000 / max(len(lat), 1)}


def spawn(tmp: Path, fake: bool, iters: int):
    from service_fixtures import dataset_zip_bytes, local_token, service_env, start_api, upload, wait_for

    extra = {"NEPF_RECONCILE_INTERVAL_S": "5"}
    if fake:
        extra.update(NEPF_PIPELINE="service_fixtures:fake_pipeline", NEPF_FAKE_STEP_S="0.05")
    else:
        extra.update(NEPF_EXPORT_TEXTURE_SIZE="64", NEPF_EXPORT_MESH_RESOLUTION="32", NEPF_EXPORT_MAX_FACES="2000")
    data = tmp / "data"
    api, base = start_api(service_env(data, **extra), tmp, name="bench-api")
    token = local_token(data)
    h = {"Authorization": f"Bearer {token}"}
    r = upload(base, h, dataset_zip_bytes(tmp), {"preset": "tiny", "iters": iters})
    r.raise_for_status()
    job_id = r.json()["id"]
    wait_for(lambda: httpx.get(f"{base}/jobs/{job_id}", headers=h).json()["progress"]["step"] >= 1, 120,
             what="training started")
    return api, base, token, job_id


def enqueue_latency(tmp: Path, n: int) -> dict:
    """Embedded broker: time from the API's enqueue (``enqueued_at``) to the worker's claim."""
    from service_fixtures import dataset_zip_bytes, local_token, service_env, start_api, upload, wait_for

    data = tmp / "data"
    api, base = start_api(service_env(data, NEPF_PIPELINE="service_fixtures:fake_pipeline",
                                      NEPF_FAKE_STEP_S="0.001"), tmp, name="lat-api")
    h = {"Authorization": f"Bearer {local_token(data)}"}
    z = dataset_zip_bytes(tmp)
    lat = []
    try:
        time.sleep(2)   # worker ready
        for _ in range(n):
            jid = upload(base, h, z, {"preset": "tiny", "iters": 2}).json()["id"]
            j = wait_for(lambda: (lambda j: j if j["status"] == "succeeded" else None)(
                httpx.get(f"{base}/jobs/{jid}", headers=h).json()), 30)
            from sqlalchemy import create_engine, text
            eng = create_engine(f"sqlite:///{data / 'nepf.sqlite3'}")
            with eng.connect() as c:
                enq = c.execute(text("SELECT enqueued_at FROM nepf_jobs WHERE id=:i"), {"i": jid}).scalar()
            eng.dispose()
            claimed = dt.datetime.fromisoformat(j["delivery"]["attempt_log"][0]["claimed_at"].rstrip("Z"))
            enq = dt.datetime.fromisoformat(str(enq))
            lat.append((claimed - enq).total_seconds() * 1000)
    finally:
        api.stop()
    return {"mode": "enqueue-latency", "broker": "embedded sqlite (kombu sqla, poll 0.1 s)", "n": n,
            "p50_ms": percentile(lat, 0.5), "max_ms": max(lat), "min_ms": min(lat), "samples_ms": lat}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--mode", choices=["pollers", "enqueue-latency"], default="pollers")
    p.add_argument("--pollers", type=int, default=200)
    p.add_argument("--duration", type=float, default=30.0)
    p.add_argument("--interval", type=float, default=1.0)
    p.add_argument("--base")
    p.add_argument("--token")
    p.add_argument("--job")
    p.add_argument("--fake", action="store_true", help="train with the tests' fake pipeline (no torch)")
    p.add_argument("--iters", type=int, default=100000)
    p.add_argument("--n", type=int, default=10, help="jobs for enqueue-latency")
    p.add_argument("--out", default=str(REPO / "bench" / "results"))
    args = p.parse_args(argv)
    tmp = Path(tempfile.mkdtemp(prefix="nepf-bench-"))
    print(f"load average before: {os.getloadavg()}", file=sys.stderr)
    if args.mode == "enqueue-latency":
        res = enqueue_latency(tmp, args.n)
    else:
        api = None
        if args.base:
            base, token, job_id = args.base, args.token, args.job
        else:
            api, base, token, job_id = spawn(tmp, args.fake, args.iters)
        h = {"Authorization": f"Bearer {token}"}
        try:
            before = httpx.get(f"{base}/jobs/{job_id}", headers=h).json()
            res = asyncio.run(poll(base, token, job_id, args.pollers, args.duration, args.interval))
            after = httpx.get(f"{base}/jobs/{job_id}", headers=h).json()
            res["job_status_after"] = after["status"]
            res["job_steps_during"] = [before["progress"]["step"], after["progress"]["step"]]
        finally:
            if api is not None:
                api.stop()
        res.update(mode="pollers", pipeline="fake" if args.fake else "real tiny", cpus=os.cpu_count())
    res["when"] = dt.datetime.now(dt.timezone.utc).isoformat()
    res["loadavg_after"] = os.getloadavg()
    try:
        import httptools  # noqa: F401
        import uvloop  # noqa: F401
        res["uvicorn"] = "httptools+uvloop"
    except ImportError:
        res["uvicorn"] = "h11+asyncio"
    print(json.dumps(res, indent=2))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / f"api_{res['mode']}.json").write_text(json.dumps(res, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
