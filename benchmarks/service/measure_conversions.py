#!/usr/bin/env python
"""The API process's memory and /healthz latency while artifacts convert (on request, in child processes).

    .venv/bin/python -m benchmarks.service.measure_conversions [--gaussians 3000000]
        [--sh-degree 0] [--mode redis|embedded] [--concurrent 5] [--root PATH]

Generates a pair of models of --gaussians/2 each (gsa.synth.make_object), starts a deployment
of its own in a temp folder (`gsa serve` + `gsa worker` on a private redis-server on a free
loopback port, or `gsa serve` alone), uploads the pair, runs one job asking for the merged
model (--gaussians in all), then:

1. --concurrent clients GET `merged.ply?format=splat` at once (the conversion probe), each body
   read to the end, while /healthz is polled every 50 ms;
2. the same request once more (a service that keeps conversions serves it from storage);
3. --concurrent clients at once, each asking for another format (splat, ksplat, spz,
   compressed-ply, glb).

For each it prints the answers' status codes, the wall time, the API process's peak RSS
(VmHWM, reset before each step through /proc/<pid>/clear_refs, so the job's own peak in
embedded mode does not count) against its RSS before, and /healthz's latency (median, max).
--root runs the service from another checkout (e.g. `git archive` of an older commit) to
compare: the client side (this script) stays the same.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import httpx
import numpy as np

ROOT = Path(__file__).resolve().parents[2]  # the repository
sys.path.insert(0, str(ROOT))

from tests.service.conftest import Proc, api_up, free_port, wait_until  # noqa: E402
from tests.service.harness import RedisServer, rss_bytes  # noqa: E402

KEY = "conversion-bench-key"
HEADERS = {"Authorization": f"Bearer {KEY}"}
FORMATS = ["splat", "ksplat", "spz", "compressed-ply", "glb"]


def make_pair(d: Path, n: int, sh_degree: int) -> tuple[Path, Path]:
    from gsa.io.ply import write_ply
    from gsa.sim3 import Sim3
    from gsa.synth import make_object

    m = make_object("bus", seed=5, n_gaussians=n, sh_degree=sh_degree)
    src = write_ply(m, d / "source.ply")
    tgt = write_ply(m.transformed(Sim3(1.3, np.eye(3), np.array([0.5, -0.1, 0.2]))), d / "target.ply")
    return src, tgt


class InTree(Proc):
    """A service process run from `cwd` (python -m puts the working folder first on sys.path,
    so that is where its code comes from)."""

    def __init__(self, args, env, log: Path, cwd: Path):
        self.log, self.fh = log, open(log, "ab")
        self.p = subprocess.Popen(
            args, env=env, cwd=cwd, stdout=self.fh, stderr=subprocess.STDOUT, start_new_session=True
        )


class Healthz:
    """Polls /healthz every 50 ms on its own connection and records each latency."""

    def __init__(self, url: str):
        self.url, self.times, self._stop = url, [], threading.Event()
        self._t = threading.Thread(target=self._run, daemon=True)

    def __enter__(self):
        self._t.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._t.join()

    def _run(self):
        with httpx.Client(timeout=60) as c:
            while not self._stop.is_set():
                t = time.perf_counter()
                c.get(self.url + "/healthz")
                self.times.append(time.perf_counter() - t)
                self._stop.wait(0.05)


def fetch(url: str, href: str, fmt: str) -> tuple[int, int, float]:
    """(status, body bytes, seconds), the body read to its end in 1 MiB pieces."""
    t = time.perf_counter()
    size = 0
    with httpx.Client(base_url=url, headers=HEADERS, timeout=1800) as c:
        with c.stream("GET", href, params={"format": fmt}) as r:
            for chunk in r.iter_bytes(1 << 20):
                size += len(chunk)
            return r.status_code, size, time.perf_counter() - t


def step(name: str, url: str, pid: int, href: str, fmts: list[str]) -> dict:
    Path(f"/proc/{pid}/clear_refs").write_text("5")  # VmHWM := VmRSS now
    rss0 = rss_bytes(pid)
    out: list = [None] * len(fmts)
    t0 = time.perf_counter()
    with Healthz(url) as hz:
        threads = [
            threading.Thread(target=lambda i=i: out.__setitem__(i, fetch(url, href, fmts[i]))) for i in range(len(fmts))
        ]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
    wall = time.perf_counter() - t0
    peak = rss_bytes(pid, "VmHWM")
    lat = hz.times or [0.0]
    row = {
        "step": name,
        "codes": [o[0] for o in out],
        "bytes": [o[1] for o in out],
        "wall_s": round(wall, 2),
        "api_rss_before_mb": round(rss0 / 2**20),
        "api_peak_mb": round(peak / 2**20),
        "healthz_p50_ms": round(statistics.median(lat) * 1000, 1),
        "healthz_max_ms": round(max(lat) * 1000, 1),
        "healthz_polls": len(hz.times),
    }
    print(
        f"{name}: {row['codes']} in {wall:.1f} s; API RSS {row['api_rss_before_mb']} MB → peak "
        f"{row['api_peak_mb']} MB; /healthz p50 {row['healthz_p50_ms']} ms, max {row['healthz_max_ms']} ms "
        f"({row['healthz_polls']} polls)",
        flush=True,
    )
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--gaussians", type=int, default=3_000_000, help="of the merged model (half a model)")
    ap.add_argument("--sh-degree", type=int, default=0)
    ap.add_argument("--mode", choices=["redis", "embedded"], default="redis")
    ap.add_argument("--concurrent", type=int, default=5)
    ap.add_argument("--root", type=Path, default=ROOT, help="the service's code (PYTHONPATH of its processes)")
    args = ap.parse_args()

    tmp = Path(tempfile.mkdtemp(prefix="gsa-conv-bench-"))
    t = time.perf_counter()
    src, tgt = make_pair(tmp, args.gaussians // 2, args.sh_degree)
    print(
        f"pair: 2 × {args.gaussians // 2:,} Gaussians, SH {args.sh_degree}, "
        f"{src.stat().st_size / 2**20:.0f} MB per PLY ({time.perf_counter() - t:.1f} s); service from {args.root}",
        flush=True,
    )
    env = {k: v for k, v in os.environ.items() if not k.startswith("GSA_")}
    env.update(
        PYTHONPATH=str(args.root.resolve()),
        GSA_STORAGE_ROOT=str(tmp / "data"),
        GSA_API_KEYS=json.dumps({KEY: "bench"}),
        GSA_MAX_UPLOAD_BYTES=str(4 * 2**30),
        GSA_WORKER_MEMORY_MB="0",
    )
    redis = None
    if args.mode == "redis":
        redis = RedisServer(tmp / "redis")
        redis.start()
        env["GSA_REDIS_URL"] = redis.url
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    cwd = args.root.resolve()
    api = InTree([sys.executable, "-m", "service.cli", "serve", "--port", str(port)], env, tmp / "api.log", cwd)
    worker = None
    try:
        wait_until(lambda: api_up(url, api), 120, 0.1, "API to start")
        if redis is not None:
            worker = InTree([sys.executable, "-m", "service.cli", "worker"], env, tmp / "worker.log", cwd)
        with httpx.Client(base_url=url, headers=HEADERS, timeout=1800) as c:
            ids = []
            for p in (src, tgt):
                with open(p, "rb") as fh:
                    r = c.post("/v1/assets", files={"file": (p.name, fh)})
                assert r.status_code == 201, r.text
                ids.append(r.json()["id"])
            t = time.perf_counter()
            options = {"stages": ["coarse"], "outputs": ["merged"]}
            r = c.post("/v1/jobs", json={"source": ids[0], "target": ids[1], "options": options})
            assert r.status_code == 202, r.text
            jid = r.json()["id"]
            job = wait_until(
                lambda: (j := c.get(f"/v1/jobs/{jid}").json())["state"] in ("succeeded", "failed") and j, 1800, 0.5
            )
            assert job["state"] == "succeeded", job
            merged = next(a for a in job["artifacts"] if a["name"] == "merged.ply")
            print(f"job: {time.perf_counter() - t:.1f} s, merged.ply {merged['size'] / 2**20:.0f} MB", flush=True)
        href = merged["href"]
        n = args.concurrent
        rows = [
            step(f"{n} × splat at once", url, api.p.pid, href, ["splat"] * n),
            step("splat once more", url, api.p.pid, href, ["splat"]),
            step(f"{n} formats at once", url, api.p.pid, href, (FORMATS * n)[:n]),
        ]
        print(json.dumps({"gaussians": args.gaussians, "mode": args.mode, "root": str(cwd), "steps": rows}))
    finally:
        if worker is not None:
            worker.stop()
        api.stop()
        if redis is not None:
            redis.stop()


if __name__ == "__main__":
    main()
