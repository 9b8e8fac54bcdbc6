#!/usr/bin/env python
"""A scene-size pair through a real service end to end: upload, job, artifacts.

    .venv/bin/python -m benchmarks.service.bench_service_scene [--gaussians 2000000] [--sh-degree 0]
        [--mode redis|embedded] [--seed 0]

Generates a room (gsa.synth.make_scene) and two partial captures of it with their own Sim(3)
(gsa.synth.scene_captures, exactly --gaussians each plus 1-5 % floaters), writes both as PLY,
starts a deployment of its own in a temp folder — `gsa serve` plus `gsa worker` on a private
redis-server on a free loopback port (never the Redis on 6379), or `gsa serve` alone with its
embedded worker — uploads both files over HTTP (POST /v1/assets), submits a job asking for the
aligned and merged models (POST /v1/jobs), polls it (printing every stage it reports), downloads
the aligned and merged artifacts, reads them back and checks the transform against the truth
(RRE, translation error at the source's centroid in % of the room's diagonal, scale error).
Prints the upload, job and download times and the peak resident memory (VmHWM) of the API
process and of the worker (the `gsa worker` process and its forked work horse, sampled).
"""

from __future__ import annotations

import argparse
import json
import os
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

KEY = "scene-bench-key"
HEADERS = {"Authorization": f"Bearer {KEY}"}


def make_pair(d: Path, n: int, sh_degree: int, seed: int):
    """Two captures of one room, n Gaussians each (+ floaters), written as PLY."""
    from gsa.io.ply import write_ply
    from gsa.synth import make_scene, scene_captures

    rng = np.random.default_rng([seed, 18])
    # Each half-space keeps >= 60 % of the room, so n / 0.6 room Gaussians give n per capture.
    scene = make_scene(seed=1800 + seed, n_gaussians=int(n / 0.6) + 1, sh_degree=sh_degree)
    cap = scene_captures(scene, rng, sizes=(n, n))
    del scene
    src, tgt = write_ply(cap.source, d / "source.ply"), write_ply(cap.target, d / "target.ply")
    centre = cap.source.means.mean(axis=0, dtype=np.float64)
    info = {
        "truth": cap.truth,
        "extent_target": cap.extent_target,
        "source_centre": centre,
        "n_source": len(cap.source),
        "n_target": len(cap.target),
        "overlap": cap.overlap,
    }
    return src, tgt, info


def service_env(tmp: Path, **extra) -> dict:
    env = {k: v for k, v in os.environ.items() if not k.startswith("GSA_")}
    env.update(
        PYTHONPATH=str(ROOT),
        GSA_STORAGE_ROOT=str(tmp / "data"),
        GSA_API_KEYS=json.dumps({KEY: "bench"}),
    )
    env.update({k: str(v) for k, v in extra.items()})
    return env


class PeakSampler:
    """Highest VmHWM seen of a process and its descendants (an RQ work horse lives only for
    its job, so its high-water mark is read while it runs, every `interval` seconds)."""

    def __init__(self, proc: Proc, interval: float = 0.1):
        self.proc, self.interval = proc, interval
        self.peak: dict[str, int] = {}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def __enter__(self) -> PeakSampler:
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()

    def sample(self) -> None:
        pids = [self.proc.p.pid, *self.proc.descendants()]
        for pid in pids:
            role = "main" if pid == self.proc.p.pid else "child"
            self.peak[role] = max(self.peak.get(role, 0), rss_bytes(pid, "VmHWM"))

    def _run(self) -> None:
        while not self._stop.wait(self.interval):
            self.sample()


def upload(c: httpx.Client, path: Path) -> tuple[dict, float]:
    t0 = time.perf_counter()
    with open(path, "rb") as fh:  # httpx streams the file part; nothing holds it whole
        r = c.post("/v1/assets", files={"file": (path.name, fh, "application/x-ply")})
    seconds = time.perf_counter() - t0
    if r.status_code != 201:
        raise SystemExit(f"upload of {path.name} failed: {r.status_code} {r.text}")
    return r.json(), seconds


def download(c: httpx.Client, href: str, dest: Path) -> tuple[int, float]:
    t0 = time.perf_counter()
    size = 0
    with c.stream("GET", href) as r, open(dest, "wb") as fh:
        if r.status_code != 200:
            raise SystemExit(f"download of {href} failed: {r.status_code} {r.read()[:500]!r}")
        for chunk in r.iter_bytes(1 << 20):
            fh.write(chunk)
            size += len(chunk)
    return size, time.perf_counter() - t0


def run(args) -> dict:
    from gsa.io.ply import read_ply
    from gsa.metrics import rre_deg
    from gsa.sim3 import Sim3

    tmp = Path(tempfile.mkdtemp(prefix="gsa-scene-bench-"))
    t0 = time.perf_counter()
    src_path, tgt_path, info = make_pair(tmp, args.gaussians, args.sh_degree, args.seed)
    build_s = time.perf_counter() - t0
    file_mb = (src_path.stat().st_size + tgt_path.stat().st_size) / 2 / 2**20
    print(
        f"pair: {info['n_source']:,} vs {info['n_target']:,} Gaussians, SH {args.sh_degree}, "
        f"{file_mb:.0f} MB per PLY, overlap {info['overlap']:.2f}, built in {build_s:.1f} s",
        flush=True,
    )
    redis = None
    extra = {}
    if args.mode == "redis":
        redis = RedisServer(tmp / "redis")
        redis.start()
        extra["GSA_REDIS_URL"] = redis.url
    env = service_env(tmp, **extra)
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    api = Proc(
        [sys.executable, "-m", "service.cli", "serve", "--port", str(port), "--log-level", "warning"],
        env,
        tmp / "api.log",
    )
    worker = None
    try:
        wait_until(lambda: api_up(url, api), 120, 0.1, "API to start")
        if redis is not None:
            worker = Proc(
                [sys.executable, "-m", "service.cli", "worker", "--name", f"scene-{time.time_ns()}"],
                env,
                tmp / "worker.log",
            )
            wait_until(lambda: "warm-up took" in worker.tail(20000), 180, 0.2, "worker warm-up")
        api_rss_idle = rss_bytes(api.p.pid)
        with httpx.Client(base_url=url, headers=HEADERS, timeout=600) as c:
            a_src, up_src = upload(c, src_path)
            a_tgt, up_tgt = upload(c, tgt_path)
            api_peak_upload = rss_bytes(api.p.pid, "VmHWM")
            print(
                f"upload: source {up_src:.2f} s, target {up_tgt:.2f} s "
                f"({2 * file_mb / (up_src + up_tgt):.0f} MB/s); API VmHWM {api_peak_upload / 2**20:.0f} MB "
                f"(idle RSS {api_rss_idle / 2**20:.0f} MB)",
                flush=True,
            )
            options = {"outputs": ["result", "aligned", "merged"], "seed": args.seed}
            sampler = PeakSampler(worker if worker is not None else api)
            with sampler:
                t_submit = time.perf_counter()
                r = c.post("/v1/jobs", json={"source": a_src["id"], "target": a_tgt["id"], "options": options})
                if r.status_code != 202:
                    raise SystemExit(f"submit failed: {r.status_code} {r.text}")
                job_id = r.json()["id"]
                stages, last = [], None
                while True:
                    j = c.get(f"/v1/jobs/{job_id}").json()
                    seen = (j.get("stage") or j["state"], round(float(j.get("progress") or 0), 3))
                    if seen != last:
                        last = seen
                        stages.append((time.perf_counter() - t_submit, *seen))
                        print(f"  {stages[-1][0]:7.2f} s  {seen[0]:<12} {seen[1]:.3f}", flush=True)
                    if j["state"] in ("succeeded", "failed", "cancelled"):
                        break
                    time.sleep(0.25)
                job_s = time.perf_counter() - t_submit
                sampler.sample()
            api_peak_job = rss_bytes(api.p.pid, "VmHWM")
            if j["state"] != "succeeded":
                raise SystemExit(f"job ended {j['state']}: {json.dumps(j.get('error'))}")
            arts = {a["name"]: a for a in j["artifacts"]}
            dl = {}
            for name in ("aligned.ply", "merged.ply", "result.json"):
                dl[name] = download(c, arts[name]["href"], tmp / f"out-{name}")
        api_peak = rss_bytes(api.p.pid, "VmHWM")
        res = j["result"]
        est = Sim3(float(res["scale"]), np.array(res["rotation"]), np.array(res["translation"]))
        truth = info["truth"]
        centre = info["source_centre"]
        t_err = float(np.linalg.norm(est.apply(centre) - truth.apply(centre)) / info["extent_target"] * 100)
        rre = rre_deg(est.rotation, truth.rotation)
        scale_err = abs(est.scale / truth.scale - 1) * 100
        aligned = read_ply(tmp / "out-aligned.ply")
        merged = read_ply(tmp / "out-merged.ply")
        assert len(aligned) == info["n_source"], (len(aligned), info["n_source"])
        assert len(merged) == info["n_source"] + info["n_target"], len(merged)
        # The aligned artifact is the source moved by the job's transform: its centroid lands
        # where the truth puts the source's.
        moved = float(np.linalg.norm(aligned.means.mean(axis=0, dtype=np.float64) - truth.apply(centre)))
        out = {
            "mode": args.mode,
            "gaussians": args.gaussians,
            "n_source": info["n_source"],
            "n_target": info["n_target"],
            "sh_degree": args.sh_degree,
            "file_mb": file_mb,
            "overlap": info["overlap"],
            "upload_seconds": [up_src, up_tgt],
            "job_seconds": job_s,
            "job_timings": res.get("timings"),
            "stages": stages,
            "download_seconds": {k: v[1] for k, v in dl.items()},
            "download_mb": {k: v[0] / 2**20 for k, v in dl.items()},
            "rre_deg": rre,
            "translation_error_pct_extent": t_err,
            "scale_error_pct": scale_err,
            "aligned_centroid_error_pct_extent": moved / info["extent_target"] * 100,
            "success": bool(rre < 2.0 and t_err < 2.0),
            "doubtful": res.get("metrics", {}).get("doubtful"),
            "api_peak_mb": api_peak / 2**20,
            "api_peak_after_upload_mb": api_peak_upload / 2**20,
            "api_peak_after_job_mb": api_peak_job / 2**20,
            "attempts": j["attempts"],
            "worker_peak_mb": {k: v / 2**20 for k, v in sampler.peak.items()},
            "load_average": os.getloadavg(),
        }
        return out
    finally:
        if worker is not None:
            worker.stop()
        api.stop()
        if redis is not None:
            redis.stop()
        if not args.keep:
            import shutil

            shutil.rmtree(tmp, ignore_errors=True)
        else:
            print(f"kept {tmp}")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--gaussians", type=int, default=2_000_000, help="per capture (floaters come on top)")
    p.add_argument("--sh-degree", type=int, default=0)
    p.add_argument("--mode", choices=("redis", "embedded"), default="redis")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--keep", action="store_true", help="keep the temp folder (files, logs)")
    p.add_argument("--json", action="store_true")
    args = p.parse_args(argv)
    print(f"load average before: {' '.join(f'{x:.2f}' for x in os.getloadavg())}", flush=True)
    r = run(args)
    dl = r["download_seconds"]
    print(
        f"result: RRE {r['rre_deg']:.3f} deg, translation error {r['translation_error_pct_extent']:.3f} % of the "
        f"room's diagonal, scale error {r['scale_error_pct']:.3f} % -> {'success' if r['success'] else 'FAILURE'}"
        f" (doubtful: {r['doubtful']})"
    )
    print(
        f"times: upload {sum(r['upload_seconds']):.1f} s ({r['upload_seconds'][0]:.1f} + {r['upload_seconds'][1]:.1f}), "
        f"job {r['job_seconds']:.1f} s (submit -> succeeded), download aligned {dl['aligned.ply']:.1f} s "
        f"({r['download_mb']['aligned.ply']:.0f} MB) + merged {dl['merged.ply']:.1f} s "
        f"({r['download_mb']['merged.ply']:.0f} MB)"
    )
    wp = r["worker_peak_mb"]
    print(
        f"peak RSS (VmHWM): API {r['api_peak_mb']:.0f} MB (after both uploads {r['api_peak_after_upload_mb']:.0f} MB, "
        f"after the job {r['api_peak_after_job_mb']:.0f} MB); "
        + ", ".join(f"worker {k} {v:.0f} MB" for k, v in sorted(wp.items()))
    )
    print(f"attempts: {r['attempts']}")
    print(f"library timings: {json.dumps({k: round(v, 2) for k, v in (r['job_timings'] or {}).items()})}")
    print(f"load average after: {' '.join(f'{x:.2f}' for x in r['load_average'])}")
    if args.json:
        print(json.dumps({k: v for k, v in r.items() if k != "stages"}, indent=2, default=str))
    return 0 if r["success"] else 1


if __name__ == "__main__":
    sys.exit(main())
