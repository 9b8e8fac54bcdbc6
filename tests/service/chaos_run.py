"""A chaos run against a real deployment (redis-server, `gsa serve`, several
`gsa worker`s): small jobs are submitted while faults are injected — workers
SIGKILLed at random moments (with their work horses), Redis restarted, the API
SIGKILLed and restarted, the storage filled to its quota — and afterwards every
job must have ended exactly once in a final state.

Evidence for "exactly once": a monitor polls every job and flags any job whose
final state (state, finished_at, attempts) changes once seen; a webhook
receiver flags a job reported final twice with different contents; the job
list must hold one job per logical submission (client retries carry an
Idempotency-Key). Used by tests/service/test_chaos_service.py and
benchmarks/service/chaos_service.py."""

from __future__ import annotations

import json
import random
import threading
import time
from dataclasses import dataclass, field
from datetime import datetime
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import httpx

from tests.service.conftest import ALICE, free_port, service_env
from tests.service.harness import Deployment, RedisServer

FINAL = {"succeeded", "failed", "cancelled"}
QUOTA = 256 * 2**20


class WebhookSink:
    """Receives the service's webhooks: job id -> the distinct final reports."""

    def __init__(self):
        self.reports: dict[str, set[tuple]] = {}
        self.deliveries = 0
        sink = self

        class Handler(BaseHTTPRequestHandler):
            def do_POST(self):  # noqa: N802 (http.server's naming)
                body = json.loads(self.rfile.read(int(self.headers.get("Content-Length", 0))))
                sink.deliveries += 1
                report = (body["state"], body["finished_at"])
                sink.reports.setdefault(body["job_id"], set()).add(report)
                self.send_response(200)
                self.end_headers()

            def log_message(self, *a):
                pass

        self.server = ThreadingHTTPServer(("127.0.0.1", free_port()), Handler)
        self.url = f"http://127.0.0.1:{self.server.server_address[1]}/hook"
        threading.Thread(target=self.server.serve_forever, daemon=True).start()

    def close(self):
        self.server.shutdown()


@dataclass
class Fault:
    kind: str
    started: float
    ended: float = 0.0
    recovered: float | None = None  # first job finished after the fault ended
    note: str = ""

    def recovery_s(self) -> float | None:
        return None if self.recovered is None else round(self.recovered - self.ended, 2)


@dataclass
class Report:
    submitted: int = 0
    submit_retries: int = 0
    jobs_on_server: int = 0
    final: dict[str, int] = field(default_factory=dict)
    lost: list[str] = field(default_factory=list)
    # What the store and RQ held for each lost job at the end: why it never finished
    lost_detail: dict[str, dict] = field(default_factory=dict)
    duplicated: list[str] = field(default_factory=list)
    missing_webhooks: list[str] = field(default_factory=list)
    # succeeded jobs whose storage holds artifacts of more than one attempt (a second
    # run that got as far as storing its results) or none
    artifact_sets_not_one: list[str] = field(default_factory=list)
    faults: list[dict] = field(default_factory=list)
    attempts_max: int = 0
    errors: dict[str, int] = field(default_factory=dict)
    wall_s: float = 0.0


def _ts(v: str | None) -> float | None:
    return None if v is None else datetime.fromisoformat(v.replace("Z", "+00:00")).timestamp()


class ChaosRun:
    def __init__(
        self,
        tmp: Path,
        pair: dict,
        jobs: int = 50,
        workers: int = 3,
        seed: int = 0,
        gap_s: float = 4.0,
        webhook_wait_s: float = 0.0,
    ):
        self.tmp, self.pair, self.n_jobs, self.n_workers = tmp, pair, jobs, workers
        self.rng = random.Random(seed)
        self.gap_s = gap_s
        # A webhook delivery killed with its worker is retried by RQ once its 60 s task
        # timeout has passed, at the next maintenance pass (30 s): ~1.5-2 min late.
        self.webhook_wait_s = webhook_wait_s
        self.sink = WebhookSink()
        self.redis = RedisServer(tmp / "redis")
        self.redis.start()
        env = service_env(
            tmp,
            GSA_REDIS_URL=self.redis.url,
            GSA_STORAGE_QUOTA_BYTES=QUOTA,
            GSA_MIN_FREE_BYTES=2**20,
            GSA_MAX_ATTEMPTS=20,  # enough to ride out every fault; each fault costs running jobs one
            GSA_WORKER_RECONNECT_MIN_S=0.2,
            GSA_WORKER_RECONNECT_MAX_S=1,
            GSA_UNAVAILABLE_RETRY_AFTER_S=1,
            GSA_LEASE_S=3,
            # Faults last seconds here: a short back-off (0.5-1 s, doubling to 4 s at most)
            # keeps up to 20 retried attempts within the run's time.
            GSA_RETRY_BACKOFF_BASE_S=1,
            GSA_RETRY_BACKOFF_MAX_S=4,
        )
        self.dep = Deployment(tmp, env, self.redis)
        self.ids: dict[int, str] = {}  # logical submission -> job id
        self.seen_final: dict[str, tuple] = {}
        self.finished_at: list[float] = []  # monotonic times jobs were first seen final
        self.changed_after_final: set[str] = set()
        self.retries = 0
        self.stop = threading.Event()

    # -- clients ------------------------------------------------------------------------------
    def _submit_all(self, assets: list[str], interval: float) -> None:
        options = {"stages": ["coarse"], "outputs": ["result"], "coarse_iterations": 10}
        spec = {"source": assets[0], "target": assets[1], "options": options, "webhook": {"url": self.sink.url}}
        for i in range(self.n_jobs):
            while not self.stop.is_set():
                try:
                    r = httpx.post(
                        self.dep.url + "/v1/jobs",
                        json=spec,
                        headers={**ALICE, "Idempotency-Key": f"chaos-{i}"},
                        timeout=10,
                    )
                    if r.status_code == 202:
                        self.ids[i] = r.json()["id"]
                        break
                    # Only outages may refuse a good job, and an earlier try with this key that
                    # the API (or Redis) lost mid-request: 409 "in progress" until its claim lapses.
                    assert r.status_code in (503, 507) or "idempotency-in-progress" in r.text, r.text
                except httpx.HTTPError:
                    pass
                self.retries += 1
                time.sleep(0.3)
            time.sleep(interval)

    def _monitor(self) -> None:
        while not self.stop.is_set():
            try:
                jobs = httpx.get(self.dep.url + "/v1/jobs?limit=200", headers=ALICE, timeout=5).json()["items"]
            except (httpx.HTTPError, ValueError, KeyError):  # API down, or an error answer (no items)
                jobs = []
            now = time.monotonic()
            for j in jobs:
                if j["state"] not in FINAL:
                    if j["id"] in self.seen_final:
                        self.changed_after_final.add(j["id"])
                    continue
                key = (j["state"], j["finished_at"], j["attempts"])
                if j["id"] not in self.seen_final:
                    self.seen_final[j["id"]] = key
                    self.finished_at.append(now)
                elif self.seen_final[j["id"]] != key:
                    self.changed_after_final.add(j["id"])
            time.sleep(0.2)

    # -- faults -------------------------------------------------------------------------------
    def _kill_worker(self, f: Fault) -> None:
        victim = self.rng.choice(self.dep.workers)
        if self.rng.random() < 0.7:  # mostly mid-job: wait (briefly) for a work horse
            deadline = time.monotonic() + 3
            while not victim.descendants() and time.monotonic() < deadline:
                time.sleep(0.05)
        horses = victim.kill_tree()
        self.dep.workers.remove(victim)
        f.note = f"{len(horses)} work horse(s) killed with it"
        self.dep.add_worker()

    def _restart_redis(self, f: Fault) -> None:
        kill = self.rng.random() < 0.5
        self.redis.stop(kill=kill)
        f.note = "SIGKILL" if kill else "SIGTERM"
        time.sleep(2)
        self.redis.start()

    def _restart_api(self, f: Fault) -> None:
        self.dep.stop_api(kill=True)
        time.sleep(1)
        self.dep.start_api()

    def _fill_disk(self, f: Fault) -> None:
        blobs = self.tmp / "data" / "blobs"
        filler = blobs / "chaos-filler"
        used = sum(p.stat().st_size for p in blobs.rglob("*") if p.is_file())
        with open(filler, "wb") as fh:
            fh.truncate(max(QUOTA - used, 0))  # sparse: the quota counts sizes, the disk keeps its space
        f.note = "storage at its quota"
        time.sleep(3)
        filler.unlink()

    def _chaos(self, kinds: list[str]) -> list[Fault]:
        act = {
            "kill_worker": self._kill_worker,
            "redis_restart": self._restart_redis,
            "api_restart": self._restart_api,
            "disk_full": self._fill_disk,
        }
        faults = []
        for kind in kinds:
            time.sleep(self.gap_s * (0.5 + self.rng.random()))
            if self.stop.is_set():
                break
            f = Fault(kind, time.monotonic())
            act[kind](f)
            f.ended = time.monotonic()
            faults.append(f)
        return faults

    # -- the run ------------------------------------------------------------------------------
    def run(self, kinds: list[str], deadline_s: float = 240) -> Report:
        t0 = time.monotonic()
        self.dep.start_api()
        for _ in range(self.n_workers):
            self.dep.add_worker()
        with httpx.Client(base_url=self.dep.url, headers=ALICE, timeout=60) as c:
            assets = []
            for k in ("source", "target"):
                with open(self.pair[k], "rb") as fh:
                    assets.append(c.post("/v1/assets", files={"file": (k + ".ply", fh)}).json()["id"])
        # Spread the submissions over the faults.
        interval = max(self.gap_s * len(kinds) / self.n_jobs, 0.05)
        submitter = threading.Thread(target=self._submit_all, args=(assets, interval), daemon=True)
        monitor = threading.Thread(target=self._monitor, daemon=True)
        submitter.start()
        monitor.start()
        faults = self._chaos(kinds)
        end = t0 + deadline_s
        submitter.join(max(end - time.monotonic(), 1))
        while time.monotonic() < end and len(self.seen_final) < self.n_jobs:
            time.sleep(0.3)
        # Webhooks are at-least-once with backoff (1, 5, 30 s...): one that failed during a
        # fault comes later. Wait for them (and keep watching for late changes meanwhile).
        hooks_by = time.monotonic() + self.webhook_wait_s
        while time.monotonic() < hooks_by and set(self.ids.values()) - set(self.sink.reports):
            time.sleep(0.3)
        time.sleep(1.5)  # a last look for late changes (a job finishing twice)
        self.stop.set()
        monitor.join(10)
        return self._report(faults, time.monotonic() - t0)

    def _report(self, faults: list[Fault], wall: float) -> Report:
        rep = Report(submitted=len(self.ids), submit_retries=self.retries, wall_s=round(wall, 1))
        with httpx.Client(base_url=self.dep.url, headers=ALICE, timeout=30) as c:
            jobs = c.get("/v1/jobs?limit=200").json()["items"]
        rep.jobs_on_server = len(jobs)
        by_id = {j["id"]: j for j in jobs}
        for jid in self.ids.values():
            j = by_id.get(jid)
            if j is None or j["state"] not in FINAL:
                rep.lost.append(jid)
                rep.lost_detail[jid] = self._inside(jid)
                continue
            rep.final[j["state"]] = rep.final.get(j["state"], 0) + 1
            rep.attempts_max = max(rep.attempts_max, j["attempts"])
            if j["error"]:
                kind = j["error"]["type"].rsplit("/", 1)[-1]
                rep.errors[kind] = rep.errors.get(kind, 0) + 1
            folder = self.tmp / "data" / "blobs" / "jobs" / jid
            if j["state"] == "succeeded" and (not folder.is_dir() or len(list(folder.iterdir())) != 1):
                rep.artifact_sets_not_one.append(jid)
            if len(self.sink.reports.get(jid, ())) > 1:
                rep.duplicated.append(jid)
            elif jid not in self.sink.reports:
                rep.missing_webhooks.append(jid)
        rep.duplicated = sorted(set(rep.duplicated) | self.changed_after_final)
        for f in faults:
            after = [t for t in self.finished_at if t >= f.ended]
            f.recovered = min(after) if after else None
            rep.faults.append({"fault": f.kind, "recovery_s": f.recovery_s(), "note": f.note})
        return rep

    def _inside(self, job_id: str) -> dict:
        """The stored job's queue fields and its RQ message's status (a lost job's diagnosis)."""
        import redis
        from rq.exceptions import NoSuchJobError
        from rq.job import Job as RQJob

        from service.stores.redis_store import RedisJobStore

        conn = redis.Redis.from_url(self.redis.url)
        try:
            job = RedisJobStore(conn).get(job_id)
            if job is None:
                return {"stored": None}
            fields = (
                "state",
                "stage",
                "attempts",
                "queue_ref",
                "enqueued_at",
                "next_attempt_at",
                "lease_until",
                "worker",
            )
            out = {k: getattr(job, k) for k in fields} | {"now": time.time()}
            try:
                out["rq_status"] = str(RQJob.fetch(job.queue_ref, connection=conn).get_status(refresh=False))
            except (NoSuchJobError, TypeError, ValueError) as exc:
                out["rq_status"] = repr(exc)
            return out
        except redis.RedisError as exc:
            return {"error": repr(exc)}
        finally:
            conn.close()

    def close(self) -> None:
        self.stop.set()
        self.dep.close()
        self.sink.close()


DEFAULT_FAULTS = [
    "kill_worker",
    "redis_restart",
    "kill_worker",
    "api_restart",
    "disk_full",
    "kill_worker",
    "redis_restart",
    "kill_worker",
    "api_restart",
    "kill_worker",
]
