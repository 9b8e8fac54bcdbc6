#!/usr/bin/env python
"""Service benchmark: submit-to-result overhead vs a direct library call, and
GET /v1/jobs/{id} latency under concurrent pollers.

    python -m benchmarks.service.bench_service [--mode redis|embedded] [--runs 10] [--pollers 50] [--seconds 10]

Starts its own redis-server (free loopback port), API process and worker
process in a temp dir; needs redis-server on PATH for --mode redis.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import shutil
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import httpx
import numpy as np

ROOT = Path(__file__).resolve().parents[2]  # the repository
# Same numba threading layer as `gsa worker` uses (gsa.kernels), so "direct" and "service" run the same kernels.
from gsa.kernels import use_workqueue_layer  # noqa: E402

use_workqueue_layer()
KEY = "bench-key"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def start(args, env, log):
    return subprocess.Popen(
        args,
        env=env,
        cwd=ROOT,
        stdout=open(log, "wb"),
        stderr=subprocess.STDOUT,
        start_new_session=True,
    )


def wait_http(url, timeout=60):
    t = time.monotonic()
    while time.monotonic() - t < timeout:
        try:
            if httpx.get(url, timeout=1).status_code == 200:
                return
        except httpx.HTTPError:
            pass
        time.sleep(0.1)
    raise TimeoutError(url)


def pct(xs, q):
    return float(np.percentile(np.asarray(xs), q))


def make_pair(d: Path, n: int):
    from scipy.spatial.transform import Rotation

    from gsa.io.ply import write_ply
    from gsa.sim3 import Sim3
    from gsa.synth import make_object

    src = make_object("car", seed=3, n_gaussians=n)
    gt = Sim3(
        1.4,
        Rotation.from_euler("xyz", [35, 80, -20], degrees=True).as_matrix(),
        np.array([0.4, -0.2, 0.7]),
    )
    write_ply(src, d / "source.ply")
    write_ply(src.transformed(gt), d / "target.ply")
    return d / "source.ply", d / "target.ply"


def direct(src, tgt, out: Path, outputs) -> float:
    """What a worker does, minus the service: read, align, write outputs."""
    from gsa.align.outputs import write_outputs
    from gsa.align.pipeline import AlignOptions, align
    from gsa.io.ply import read_ply

    t = time.perf_counter()
    s, g = read_ply(src), read_ply(tgt)
    res = align(s, g, AlignOptions(), progress=lambda *_: None)
    write_outputs(res, s, g, out, outputs=set(outputs))
    return time.perf_counter() - t


def submit_and_wait(c: httpx.Client, src, tgt, outputs) -> tuple[float, float, dict]:
    t = time.perf_counter()
    with open(src, "rb") as a, open(tgt, "rb") as b:
        r = c.post(
            "/v1/jobs",
            files=[("source", ("s.ply", a)), ("target", ("t.ply", b))],
            data={"options": json.dumps({"outputs": outputs})},
        )
    r.raise_for_status()
    accepted = time.perf_counter() - t
    jid, etag = r.json()["id"], None
    while True:
        h = {"If-None-Match": etag} if etag else {}
        g = c.get(f"/v1/jobs/{jid}", headers=h)
        if g.status_code == 200:
            etag, job = g.headers["etag"], g.json()
            if job["state"] in ("succeeded", "failed", "cancelled"):
                return accepted, time.perf_counter() - t, job
        time.sleep(0.01)


async def pollers(url, job_id, n, seconds, etag=None):
    """n keep-alive connections, each polling as fast as answers come back.

    A minimal HTTP/1.1 client on raw asyncio streams: httpx's per-request CPU
    cost on a 2-core box would otherwise dominate the numbers being measured
    (the client shares the CPU with the server)."""
    host, port = url.split("//")[1].split(":")
    req = (
        f"GET /v1/jobs/{job_id} HTTP/1.1\r\nHost: {host}\r\nAuthorization: Bearer {KEY}\r\n"
        + (f"If-None-Match: {etag}\r\n" if etag else "")
        + "\r\n"
    ).encode()
    lat: list[float] = []
    errors = 0
    stop = time.monotonic() + seconds

    async def one():
        nonlocal errors
        reader, writer = await asyncio.open_connection(host, int(port))
        try:
            while time.monotonic() < stop:
                t = time.perf_counter()
                writer.write(req)
                head = await reader.readuntil(b"\r\n\r\n")
                status = int(head.split(b" ", 2)[1])
                length = 0
                for line in head.split(b"\r\n"):
                    if line.lower().startswith(b"content-length:"):
                        length = int(line.split(b":")[1])
                if length:
                    await reader.readexactly(length)
                lat.append(time.perf_counter() - t)
                if status not in (200, 304):
                    errors += 1
        finally:
            writer.close()

    await asyncio.gather(*(one() for _ in range(n)))
    return lat, errors


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--mode", choices=["redis", "embedded"], default="redis")
    ap.add_argument("--runs", type=int, default=10)
    ap.add_argument("--gaussians", type=int, default=3000)
    ap.add_argument("--pollers", type=int, default=50)
    ap.add_argument("--seconds", type=float, default=10)
    ap.add_argument("--outputs", default="result,aligned,merged")
    a = ap.parse_args()
    outputs = a.outputs.split(",")
    tmp = Path(tempfile.mkdtemp(prefix="gsa-bench-"))
    procs = []
    try:
        src, tgt = make_pair(tmp, a.gaussians)
        env = {k: v for k, v in os.environ.items() if not k.startswith("GSA_")}
        env.update(
            PYTHONPATH=str(ROOT),
            GSA_STORAGE_ROOT=str(tmp / "data"),
            GSA_API_KEYS=json.dumps({KEY: "bench"}),
            # 50 pollers of one tenant measure the server, not the per-tenant rate limit (100/s)
            GSA_TENANT_RATE_PER_S="0",
        )
        if a.mode == "redis":
            rport = free_port()
            procs.append(
                subprocess.Popen(
                    [
                        shutil.which("redis-server"),
                        "--port",
                        str(rport),
                        "--bind",
                        "127.0.0.1",
                        "--save",
                        "",
                        "--appendonly",
                        "no",
                        "--dir",
                        str(tmp),
                    ],
                    stdout=subprocess.DEVNULL,
                    start_new_session=True,
                )
            )
            env["GSA_REDIS_URL"] = f"redis://127.0.0.1:{rport}/0"
        port = free_port()
        url = f"http://127.0.0.1:{port}"
        procs.append(
            start(
                [
                    sys.executable,
                    "-m",
                    "service.cli",
                    "serve",
                    "--port",
                    str(port),
                    "--log-level",
                    "warning",
                ],
                env,
                tmp / "api.log",
            )
        )
        if a.mode == "redis":
            procs.append(
                start(
                    [sys.executable, "-m", "service.cli", "worker"],
                    env,
                    tmp / "worker.log",
                )
            )
        wait_http(url + "/healthz")

        direct(src, tgt, tmp / "warm", outputs)  # warm imports/caches
        d_times = [direct(src, tgt, tmp / f"d{i}", outputs) for i in range(a.runs)]
        with httpx.Client(base_url=url, headers={"Authorization": f"Bearer {KEY}"}, timeout=60) as c:
            submit_and_wait(c, src, tgt, outputs)  # warm
            runs = [submit_and_wait(c, src, tgt, outputs) for _ in range(a.runs)]
            job = runs[-1][2]
            assert job["state"] == "succeeded", job
            etag = c.get(f"/v1/jobs/{job['id']}").headers["etag"]
        s_times = [r[1] for r in runs]
        from datetime import datetime

        def ts(v):
            return datetime.fromisoformat(v.replace("Z", "+00:00")).timestamp()

        wait_q = [ts(r[2]["started_at"]) - ts(r[2]["created_at"]) for r in runs]
        run_t = [ts(r[2]["finished_at"]) - ts(r[2]["started_at"]) for r in runs]
        acc = [r[0] for r in runs]
        print(f"mode={a.mode} gaussians={a.gaussians} outputs={outputs} runs={a.runs} cores={os.cpu_count()}")
        print(f"direct library (read+align+write):  median {1e3 * statistics.median(d_times):7.1f} ms")
        print(
            f"service submit->result:             median {1e3 * statistics.median(s_times):7.1f} ms "
            f"(p90 {1e3 * pct(s_times, 90):.1f} ms); POST accepted in median {1e3 * statistics.median(acc):.1f} ms"
        )
        print(
            f"  of which created->started (queue, fork) median {1e3 * statistics.median(wait_q):.1f} ms; "
            f"started->finished (load, align, write, store) median {1e3 * statistics.median(run_t):.1f} ms"
        )
        print(
            f"overhead:                            median {1e3 * (statistics.median(s_times) - statistics.median(d_times)):7.1f} ms"
        )
        for label, tag in (("200 (full body)", None), ("304 (If-None-Match)", etag)):
            lat, errors = asyncio.run(pollers(url, job["id"], a.pollers, a.seconds, tag))
            print(
                f"GET /v1/jobs/{{id}} {label}, {a.pollers} concurrent pollers, {a.seconds:.0f} s: "
                f"n={len(lat)} ({len(lat) / a.seconds:.0f} req/s) p50 {1e3 * pct(lat, 50):.1f} ms "
                f"p99 {1e3 * pct(lat, 99):.1f} ms errors={errors}"
            )
    finally:
        for p in reversed(procs):
            try:
                os.killpg(p.pid, signal.SIGTERM)
                p.wait(10)
            except (ProcessLookupError, subprocess.TimeoutExpired):  # gone already, or slow: stop the rest
                pass
        shutil.rmtree(tmp, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
