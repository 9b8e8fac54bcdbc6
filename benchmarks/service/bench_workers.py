#!/usr/bin/env python
"""Throughput of `gsa worker` as documented: N workers, a batch of small jobs.

    python -m benchmarks.service.bench_workers [--workers 2] [--jobs 20] [--gaussians 3000] [--outputs all] [--keep]

Starts its own redis-server (free loopback port), `gsa serve` and `gsa worker`
processes (the installed entry point, with no tuning environment) in a temp dir.
Uploads one small pair as assets, then:

1. waits until every worker has registered with RQ (ready to take jobs), and
   measures the first job's submit -> succeeded time ("first job after start");
2. runs --warm sequential jobs on the now-warm workers (median submit -> succeeded);
3. submits --jobs jobs at once and reports jobs/min from the first submission
   to the last job's end.

With --many N it instead runs one many job (POST /v1/many-jobs) over N partial captures of one
generated car (--gaussians each, coarse stage) and reports its wall time, edges, seconds per
edge and which workers ran the edges: run it with --workers 1 and --workers 2 to compare.
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

ROOT = Path(__file__).resolve().parents[2]  # the repository
sys.path.insert(0, str(ROOT))
from benchmarks.service.bench_service import free_port, make_pair, start, wait_http  # noqa: E402

KEY = "bench-key"
# --profile: each job's work in the horse (service.worker.execution.execute) under cProfile, one
# stats file per job; installed by a sitecustomize on the workers' PYTHONPATH, so the service runs
# as documented otherwise.
PROFILE_HOOK = """
import cProfile, os, time
import service.worker.runners as runners

_execute = runners.execute

def execute(job_id, backend, **kw):
    prof = cProfile.Profile()
    try:
        return prof.runcall(_execute, job_id, backend, **kw)
    finally:
        prof.dump_stats(os.path.join(os.environ["GSA_BENCH_PROFILE"], f"{time.time_ns()}-{job_id}.prof"))

runners.execute = execute
"""
FINAL = ("succeeded", "failed", "cancelled")


def gsa_exe() -> str:
    exe = Path(sys.executable).with_name("gsa")
    return str(exe) if exe.exists() else shutil.which("gsa") or "gsa"


POLL_S = 0.05  # one request per poll: 20 a second, a fifth of the tenant's default rate (100/s)


def request(c: httpx.Client, method: str, path: str, **kw) -> httpx.Response:
    """One API call that waits out the service's pushback instead of failing on it: a 429
    (the tenant's rate limit or job quota) or 503 is retried after its Retry-After, else
    after a back-off that doubles from 0.1 s up to 5 s."""
    backoff = 0.1
    while True:
        r = c.request(method, path, **kw)
        if r.status_code not in (429, 503):
            r.raise_for_status()
            return r
        try:
            wait = float(r.headers.get("Retry-After", backoff))
        except ValueError:
            wait = backoff
        time.sleep(max(wait, backoff))
        backoff = min(2 * backoff, 5.0)


def wait_final(c: httpx.Client, ids: list[str], timeout: float = 600) -> dict[str, dict]:
    """The jobs' final records. One request per poll, whatever the batch size: the job itself
    while one is pending, else the tenant's job list (every job of this run fits in a page)."""
    done: dict[str, dict] = {}
    deadline = time.monotonic() + timeout
    while len(done) < len(ids):
        if time.monotonic() > deadline:
            raise TimeoutError(f"{len(ids) - len(done)} jobs not finished")
        pending = [j for j in ids if j not in done]
        if len(pending) == 1 or len(ids) > 200:  # a page holds 200 (the newest)
            seen = [request(c, "GET", f"/v1/jobs/{j}").json() for j in pending[:1]]
        else:
            seen = request(c, "GET", "/v1/jobs", params={"limit": 200}).json()["items"]
        for j in seen:
            if j["id"] in pending and j["state"] in FINAL:
                done[j["id"]] = j
        if len(done) < len(ids):
            time.sleep(POLL_S)
    return done


def submit(c: httpx.Client, ids: list[str], options: dict) -> str:
    r = request(c, "POST", "/v1/jobs", json={"source": ids[0], "target": ids[1], "options": options})
    return r.json()["id"]


def one_job(c: httpx.Client, ids: list[str], options: dict) -> tuple[float, dict]:
    t = time.perf_counter()
    jid = submit(c, ids, options)
    job = wait_final(c, [jid])[jid]
    return time.perf_counter() - t, job


def phases(job: dict) -> str:
    """created -> started (queue, fork) and started -> finished (the attempt), from the job record."""
    from datetime import datetime

    def ts(v):
        return datetime.fromisoformat(v.replace("Z", "+00:00")).timestamp()

    wait = ts(job["started_at"]) - ts(job["created_at"])
    run = ts(job["finished_at"]) - ts(job["started_at"])
    return f"queue->start {1e3 * wait:.0f} ms, start->end {1e3 * run:.0f} ms"


def cpu_split(pid: int) -> tuple[float, float, float, int]:
    """(own user+system s, reaped children's user s, their system s, their minor page faults)."""
    f = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    tick = os.sysconf("SC_CLK_TCK")
    return (int(f[11]) + int(f[12])) / tick, int(f[13]) / tick, int(f[14]) / tick, int(f[8])


def cpu_seconds(pid: int) -> float:
    """CPU time of a process and its reaped children (RQ's work horses): utime, stime,
    cutime, cstime from /proc/<pid>/stat."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return sum(int(x) for x in fields[11:15]) / os.sysconf("SC_CLK_TCK")


def registered_workers(redis_url: str) -> int:
    import redis
    from rq import Worker

    return len(Worker.all(connection=redis.Redis.from_url(redis_url)))


def many_captures(tmp: Path, n: int, gaussians: int) -> list[Path]:
    """N partial captures (70-90 % kept) of one generated car, each under its own random Sim(3)."""
    import numpy as np

    from gsa.io.ply import write_ply
    from gsa.synth import make_object, random_sim3
    from gsa.synth.variants import cut_by_plane

    rng = np.random.default_rng([0, 30, n])
    paths = []
    for k in range(n):
        m = make_object("car", seed=0, n_gaussians=gaussians, sample_seed=k)
        m = cut_by_plane(m, rng, keep=(0.7, 0.9))
        paths.append(tmp / f"capture{k}.ply")
        write_ply(m.transformed(random_sim3(rng, scale_range=(0.5, 2.0))), paths[-1])
    return paths


def many_job(c: httpx.Client, paths: list[Path], workers: int) -> int:
    ids = []
    for p in paths:
        with open(p, "rb") as fh:
            ids.append(c.post("/v1/assets", files={"file": (p.name, fh)}).json()["id"])
    t0 = time.perf_counter()
    r = c.post("/v1/many-jobs", json={"assets": ids, "options": {"stages": ["coarse"], "seed": 0}})
    assert r.status_code == 202, r.text
    job = wait_final(c, [r.json()["id"]], timeout=7200)[r.json()["id"]]
    wall = time.perf_counter() - t0
    assert job["state"] == "succeeded", job
    res = job["result"]
    edges = res["edges"]
    by_worker: dict[str, int] = {}
    for e in edges:
        by_worker[e["worker"]] = by_worker.get(e["worker"], 0) + 1
    print(
        f"many job: N={len(paths)} workers={workers} edges={len(edges)} edge_tasks={int(res['timings']['edge_tasks'])} "
        f"wall (submit->result) {wall:.1f} s, edges phase {res['timings']['pairwise']:.1f} s, "
        f"{res['timings']['per_edge']:.2f} s per edge (mean of its own time), global step incl.: total "
        f"{res['timings']['total']:.1f} s; edges per worker: {sorted(by_worker.values(), reverse=True)}; "
        f"pruned {len(res['pruned'])}, corrected {len(res['corrected'])}"
    )
    return 0


def profiled_env(env: dict, tmp: Path, out: Path) -> dict:
    """The workers' environment with PROFILE_HOOK installed, stats written into `out`."""
    out.mkdir(parents=True, exist_ok=True)
    (tmp / "hook").mkdir()
    (tmp / "hook" / "sitecustomize.py").write_text(PROFILE_HOOK)
    path = os.pathsep.join([str(tmp / "hook"), str(ROOT), env.get("PYTHONPATH", "")])
    return {**env, "PYTHONPATH": path, "GSA_BENCH_PROFILE": str(out.resolve())}


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--jobs", type=int, default=20)
    ap.add_argument("--warm", type=int, default=5)
    ap.add_argument("--gaussians", type=int, default=3000)
    ap.add_argument("--outputs", default="all", help="comma list, or 'all' (the service default)")
    ap.add_argument("--keep", action="store_true", help="keep the temp folder (logs) for a look")
    ap.add_argument("--profile", type=Path, help="write each job's cProfile stats here (the batch's jobs summed)")
    ap.add_argument("--many", type=int, default=0, help="run one many job over this many captures instead")
    ap.add_argument(
        "--cold-cache",
        action="store_true",
        help="an empty numba cache (NUMBA_CACHE_DIR in the temp dir), as in a fresh container",
    )
    a = ap.parse_args()
    options = {} if a.outputs == "all" else {"outputs": a.outputs.split(",")}
    tmp = Path(tempfile.mkdtemp(prefix="gsa-bench-workers-"))
    procs: list[subprocess.Popen] = []
    try:
        src, tgt = make_pair(tmp, a.gaussians)
        rport = free_port()
        procs.append(
            subprocess.Popen(
                [shutil.which("redis-server"), "--port", str(rport), "--bind", "127.0.0.1"]
                + ["--save", "", "--appendonly", "no", "--dir", str(tmp)],
                stdout=subprocess.DEVNULL,
                start_new_session=True,
            )
        )
        redis_url = f"redis://127.0.0.1:{rport}/0"
        # The documented environment only: no NUMBA_* or other tuning variables.
        env = {k: v for k, v in os.environ.items() if not k.startswith(("GSA_", "NUMBA_", "OMP_"))}
        env.update(GSA_STORAGE_ROOT=str(tmp / "data"), GSA_API_KEYS=json.dumps({KEY: "bench"}))
        env["GSA_REDIS_URL"] = redis_url
        if a.cold_cache:
            env["NUMBA_CACHE_DIR"] = str(tmp / "numba-cache")
        worker_env = profiled_env(env, tmp, a.profile) if a.profile else env
        port = free_port()
        url = f"http://127.0.0.1:{port}"
        procs.append(start([gsa_exe(), "serve", "--port", str(port), "--log-level", "warning"], env, tmp / "api.log"))
        wait_http(url + "/healthz")
        with httpx.Client(base_url=url, headers={"Authorization": f"Bearer {KEY}"}, timeout=60) as c:
            ids = []
            for p in (src, tgt):
                with open(p, "rb") as fh:
                    ids.append(c.post("/v1/assets", files={"file": (p.name, fh)}).json()["id"])
            t_start = time.perf_counter()
            for i in range(a.workers):
                procs.append(start([gsa_exe(), "worker"], worker_env, tmp / f"worker{i}.log"))
            deadline = time.monotonic() + 300
            while registered_workers(redis_url) < a.workers:
                if time.monotonic() > deadline:
                    raise TimeoutError("workers did not register")
                time.sleep(0.05)
            ready = time.perf_counter() - t_start
            if a.many:
                print(f"workers={a.workers} gaussians={a.gaussians} cores={os.cpu_count()} load={os.getloadavg()}")
                return many_job(c, many_captures(tmp, a.many, a.gaussians), a.workers)
            first, job = one_job(c, ids, options)
            assert job["state"] == "succeeded", job
            first_phases = phases(job)
            warm = []
            for _ in range(a.warm):
                dt, job = one_job(c, ids, options)
                assert job["state"] == "succeeded", job
                warm.append(dt)
            warm_phases = phases(job)
            workers = procs[-a.workers :]
            cpu0 = sum(cpu_seconds(p.pid) for p in workers)
            split0 = [sum(x) for x in zip(*(cpu_split(p.pid) for p in workers))]
            t0 = time.perf_counter()
            batch = [submit(c, ids, options) for _ in range(a.jobs)]
            done = wait_final(c, batch)
            elapsed = time.perf_counter() - t0
            time.sleep(0.5)  # the last horse reaped
            cpu_per_job = (sum(cpu_seconds(p.pid) for p in workers) - cpu0) / a.jobs
            split = [sum(x) / a.jobs for x in zip(*(cpu_split(p.pid) for p in workers))]
            split = [x - y / a.jobs for x, y in zip(split, split0)]
        ok = sum(j["state"] == "succeeded" for j in done.values())
        warm_med = statistics.median(warm)
        try:
            load = " ".join(f"{x:.2f}" for x in os.getloadavg())
        except OSError:
            load = "n/a"
        print(
            f"workers={a.workers} jobs={a.jobs} gaussians={a.gaussians} outputs={a.outputs} "
            f"cores={os.cpu_count()} cold_cache={a.cold_cache} load(1/5/15 min)={load}"
        )
        print(f"worker start -> registered with RQ:      {ready:6.2f} s")
        print(f"first job after start (submit->result):  {1e3 * first:7.0f} ms ({first_phases})")
        print(f"warm job, median of {a.warm} (submit->result): {1e3 * warm_med:7.0f} ms (last: {warm_phases})")
        print(f"first / warm:                             {first / warm_med:6.2f}x")
        print(f"batch: {ok}/{a.jobs} succeeded in {elapsed:.2f} s = {60 * a.jobs / elapsed:.1f} jobs/min")
        print(
            f"worker CPU per job (parents + horses): {cpu_per_job:.2f} s -> "
            f"{60 * (os.cpu_count() or 1) / cpu_per_job:.0f} jobs/min if the workers had all {os.cpu_count()} cores"
        )
        print(
            f"  of which: worker parents {split[0]:.2f} s, horses user {split[1]:.2f} s + system {split[2]:.2f} s, "
            f"horses' minor page faults {split[3]:,.0f} a job"
        )
        for i in range(a.workers):
            for line in (tmp / f"worker{i}.log").read_text(errors="replace").splitlines():
                if "warm-up" in line:
                    print(f"  worker{i}: {line.split(': ', 1)[-1]}")
        return 0 if ok == a.jobs else 1
    finally:
        for p in reversed(procs):
            try:
                os.killpg(p.pid, signal.SIGTERM)
                p.wait(10)
            except (ProcessLookupError, subprocess.TimeoutExpired):  # gone already, or slow: stop the rest
                pass
        if a.keep:
            print(f"logs kept in {tmp}")
        else:
            shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    sys.exit(main())
