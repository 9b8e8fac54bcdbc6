#!/usr/bin/env python
"""How long `:cancel` takes to stop a running job, at moments spread over its stages, on a large
model (docs/service.md, "Cancel and leases").

A real deployment (`gsa serve` and, with --redis, its own redis-server and one `gsa worker`, whose
work horses run the jobs; else embedded: the API's worker thread runs them) and a bus of
N Gaussians against a 3,000-Gaussian car (other objects: a doubtful answer, so the semantic
stage, the frame snap and the relabelling choice run too). For each cancel moment a fresh job is
submitted; once it runs, the script waits that many seconds, notes the job's stage, POSTs
`:cancel` and polls every 20 ms until the job is `cancelled`. Prints one row per moment.

    .venv/bin/python -m benchmarks.service.measure_cancel --redis --gaussians 300000 --at 5 20 40 70 100
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import httpx

ROOT = Path(__file__).resolve().parents[2]  # the repository
sys.path.insert(0, str(ROOT))
from benchmarks.service.bench_service import free_port, start, wait_http  # noqa: E402

KEY = {"Authorization": "Bearer k"}


def write_pair(d: Path, n: int) -> tuple[Path, Path]:
    from gsa.io.ply import write_ply
    from gsa.synth import make_object

    write_ply(make_object("bus", seed=1, n_gaussians=n), d / "source.ply")
    write_ply(make_object("car", seed=3, n_gaussians=3000), d / "target.ply")
    return d / "source.ply", d / "target.ply"


def cancel_at(c: httpx.Client, assets: dict, seconds: float) -> dict:
    body = {"source": assets["source"], "target": assets["target"], "options": {"outputs": ["result"]}}
    jid = c.post("/v1/jobs", json=body).json()["id"]
    while c.get(f"/v1/jobs/{jid}").json()["state"] == "queued":
        time.sleep(0.05)
    time.sleep(seconds)
    job = c.get(f"/v1/jobs/{jid}").json()
    if job["state"] != "running":
        return {"at_s": seconds, "stage": job.get("stage"), "state": job["state"], "cancel_s": None}
    t = time.monotonic()
    c.post(f"/v1/jobs/{jid}:cancel")
    while (state := c.get(f"/v1/jobs/{jid}").json()["state"]) == "running":
        time.sleep(0.02)
    return {
        "at_s": seconds,
        "stage": job.get("stage"),
        "progress": round(job.get("progress") or 0.0, 3),
        "state": state,
        "cancel_s": round(time.monotonic() - t, 2),
    }


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--gaussians", type=int, default=300_000)
    ap.add_argument("--at", type=float, nargs="+", default=[5, 20, 40, 70])
    ap.add_argument("--redis", action="store_true", help="Redis and a gsa worker (else embedded)")
    a = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="gsa-cancel-") as tmp:
        d = Path(tmp)
        src, tgt = write_pair(d, a.gaussians)
        env = {k: v for k, v in os.environ.items() if not k.startswith("GSA_")}
        env.update(
            PYTHONPATH=str(ROOT),
            GSA_STORAGE_ROOT=str(d / "data"),
            GSA_API_KEYS=json.dumps({"k": "me"}),
            GSA_MAX_UPLOAD_BYTES=str(2 * 1024**3),
        )
        procs = []
        if a.redis:
            redis_port = free_port()
            procs.append(start(["redis-server", "--port", str(redis_port), "--save", ""], env, d / "redis.log"))
            env["GSA_REDIS_URL"] = f"redis://127.0.0.1:{redis_port}/0"
            time.sleep(0.5)
            procs.append(start([sys.executable, "-m", "service.cli", "worker"], env, d / "worker.log"))
        port = free_port()
        procs.append(start([sys.executable, "-m", "service.cli", "serve", "--port", str(port)], env, d / "api.log"))
        try:
            url = f"http://127.0.0.1:{port}"
            wait_http(url + "/healthz", 120)
            with httpx.Client(base_url=url, headers=KEY, timeout=120) as c:
                assets = {}
                for k, p in (("source", src), ("target", tgt)):
                    with open(p, "rb") as fh:
                        assets[k] = c.post("/v1/assets", files={"file": (p.name, fh)}).json()["id"]
                for seconds in a.at:
                    print(json.dumps(cancel_at(c, assets, seconds)), flush=True)
        finally:
            for p in reversed(procs):
                p.terminate()
                p.wait(30)


if __name__ == "__main__":
    main()
