#!/usr/bin/env python
"""The first job of embedded mode (`gsa serve` without Redis) vs a warm one.

    PYTHONPATH=. python scripts/bench_embedded_first_job.py [--cold-cache] [--delay 0] [--warm 3] [--gaussians 3000]

Starts `gsa serve` (no Redis: SQLite and an in-process worker; `python -m service.cli serve`, so a
PYTHONPATH given in front picks the service code to measure) in a temp dir, with no GSA_/NUMBA_/OMP_
tuning in its environment, uploads one small pair as assets once /healthz answers, then submits
the first job (all outputs: renders and preview included) --delay seconds after /healthz answered,
and --warm sequential jobs after it. --cold-cache: an empty numba cache (NUMBA_CACHE_DIR in the
temp dir), as in a fresh container. Prints start -> /healthz, the first job's submit -> succeeded
(with its queue -> start and start -> end split), the warm jobs' median and the server's warm-up
log line, if any.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import httpx

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "scripts"))
from bench_service import free_port, make_pair, wait_http  # noqa: E402
from bench_workers import one_job, phases  # noqa: E402

KEY = "bench-key"


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--cold-cache", action="store_true", help="an empty numba cache, as in a fresh container")
    ap.add_argument("--delay", type=float, default=0.0, help="seconds after /healthz before the first job")
    ap.add_argument("--warm", type=int, default=3)
    ap.add_argument("--gaussians", type=int, default=3000)
    ap.add_argument("--keep", action="store_true", help="keep the temp folder (the server's log)")
    a = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="gsa-bench-embedded-"))
    proc = None
    try:
        src, tgt = make_pair(tmp, a.gaussians)
        env = {k: v for k, v in os.environ.items() if not k.startswith(("GSA_", "NUMBA_", "OMP_"))}
        env.update(GSA_STORAGE_ROOT=str(tmp / "data"), GSA_API_KEYS=json.dumps({KEY: "bench"}))
        env["PYTHONPATH"] = os.pathsep.join(p for p in (env.get("PYTHONPATH"), str(ROOT)) if p)
        if a.cold_cache:
            env["NUMBA_CACHE_DIR"] = str(tmp / "numba-cache")
        port = free_port()
        url = f"http://127.0.0.1:{port}"
        t0 = time.perf_counter()
        # Run from the temp dir: `python -m` puts the working directory first on sys.path.
        proc = subprocess.Popen(
            [sys.executable, "-m", "service.cli", "serve", "--port", str(port), "--log-level", "info"],
            env=env,
            cwd=tmp,
            stdout=open(tmp / "api.log", "wb"),
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
        wait_http(url + "/healthz")
        up = time.perf_counter() - t0
        with httpx.Client(base_url=url, headers={"Authorization": f"Bearer {KEY}"}, timeout=60) as c:
            ids = []
            for p in (src, tgt):
                with open(p, "rb") as fh:
                    ids.append(c.post("/v1/assets", files={"file": (p.name, fh)}).json()["id"])
            time.sleep(max(0.0, a.delay - (time.perf_counter() - t0 - up)))
            first, job = one_job(c, ids, {})
            assert job["state"] == "succeeded", job
            first_phases = phases(job)
            warm = []
            for _ in range(a.warm):
                dt, job = one_job(c, ids, {})
                assert job["state"] == "succeeded", job
                warm.append(dt)
        warm_med = statistics.median(warm)
        print(
            f"embedded gaussians={a.gaussians} outputs=all cold_cache={a.cold_cache} delay={a.delay:g} s "
            f"cores={os.cpu_count()} load(1 min)={os.getloadavg()[0]:.2f}"
        )
        print(f"serve start -> /healthz:                   {up:6.2f} s")
        print(f"first job (submit->result):               {1e3 * first:7.0f} ms ({first_phases})")
        print(f"warm job, median of {a.warm} (submit->result):  {1e3 * warm_med:7.0f} ms")
        print(f"first / warm:                             {first / warm_med:6.2f}x")
        for line in (tmp / "api.log").read_text(errors="replace").splitlines():
            if "warm-up" in line:
                print(f"  server: {line.split(': ', 1)[-1]}")
        return 0
    finally:
        if proc is not None:
            try:
                os.killpg(proc.pid, signal.SIGTERM)
                proc.wait(10)
            except (ProcessLookupError, subprocess.TimeoutExpired):
                pass
        if a.keep:
            print(f"log kept in {tmp}")
        else:
            shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    sys.exit(main())
