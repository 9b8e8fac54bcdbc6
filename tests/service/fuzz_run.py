"""One fuzzing session against a real deployment (redis-server, `gsa serve`, an
optional `gsa worker`): the baseline it stores first, the generated requests,
the checks on every answer and the integrity check at the end.

Used by tests/service/test_fuzz_service.py (a few hundred requests) and
benchmarks/service/fuzz_service.py (thousands, with numbers)."""

from __future__ import annotations

import hashlib
import json
import re
import time
from dataclasses import dataclass, field
from pathlib import Path

from tests.service.conftest import ALICE, BOB, KEYS, service_env, wait_job
from tests.service.fuzz_requests import (
    Req,
    Resp,
    Targets,
    build_corpus,
    dump_http,
    option_names,
    problems_with,
    send,
)
from tests.service.harness import Deployment, RedisServer

MAX_UPLOAD = 4 * 1024 * 1024  # the fuzz deployment's per-file cap (the "big" requests pass it)


@dataclass
class Stats:
    requests: int = 0
    by_status: dict[int, int] = field(default_factory=dict)
    by_kind: dict[str, int] = field(default_factory=dict)
    unexpected_5xx: int = 0
    hangs: int = 0
    no_answer: int = 0
    other: int = 0
    max_latency_s: float = 0.0
    rss_start: int = 0
    rss_peak: int = 0
    failures: list[str] = field(default_factory=list)

    def record(self, req: Req, resp: Resp, problems: list[str], bound_s: float) -> None:
        self.requests += 1
        self.by_status[resp.status] = self.by_status.get(resp.status, 0) + 1
        self.by_kind[req.kind] = self.by_kind.get(req.kind, 0) + 1
        self.max_latency_s = max(self.max_latency_s, resp.elapsed)
        if resp.status == 0:
            self.no_answer += 1
        if resp.elapsed > bound_s:
            self.hangs += 1
        if any(p.startswith("5") for p in problems):
            self.unexpected_5xx += 1
        elif problems and resp.status and resp.elapsed <= bound_s:
            self.other += 1
        if problems and len(self.failures) < 50:
            self.failures.append(f"{req.kind} {req.method} {req.target[:120]!r} -> {'; '.join(problems)}")


def _blob_digests(root: Path) -> dict[str, str]:
    return {
        str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*"))
        if p.is_file() and not p.name.startswith(".part-")
    }


class FuzzSession:
    def __init__(
        self, tmp: Path, ply_bytes: bytes, worker: bool = False, bound_s: float = 10.0, save_dir: Path | None = None
    ):
        """save_dir: where each request that broke the contract is written (one .http file,
        fuzz_requests.dump_http), ready to join tests/service/corpus/."""
        self.tmp, self.bound_s, self.save_dir = tmp, bound_s, save_dir
        env = service_env(
            tmp,
            GSA_MAX_UPLOAD_BYTES=MAX_UPLOAD,
            GSA_MAX_FINE_WORK=50_000_000,  # fuzzed jobs that run must stay small
            GSA_JOB_TIMEOUT_S=120,
            GSA_UNAVAILABLE_RETRY_AFTER_S=1,
        )
        # Fuzzed jobs carry fuzzed webhook URLs: the deployment must refuse every host
        # outside loopback at submission, and never look names up (no server-side requests leave the machine).
        assert env.get("GSA_WEBHOOK_LOOPBACK_ONLY") == "true", "fuzz deployments are loopback-only"
        self.redis = RedisServer(tmp / "redis")
        self.redis.start()
        env["GSA_REDIS_URL"] = self.redis.url
        self.dep = Deployment(tmp, env, self.redis)
        self.corpus = build_corpus(ply_bytes)
        self.names = option_names()
        self.stats = Stats()
        self.outage = False
        self.keep_worker = worker
        self.dep.start_api()
        self.host, self.port = self.dep.url.removeprefix("http://").split(":")
        self.port = int(self.port)

    # -- baseline: what must be unchanged after the fuzzing ---------------------------------
    def store_baseline(self, source: Path, target: Path) -> Targets:
        worker = self.dep.add_worker()
        made = {}
        for who, headers in (("alice", ALICE), ("bob", BOB)):
            with self.dep.client(headers, timeout=60) as c:
                ids = []
                for p in (source, target):
                    with open(p, "rb") as fh:
                        r = c.post("/v1/assets", files={"file": (p.name, fh)})
                    assert r.status_code == 201, r.text
                    ids.append(r.json()["id"])
                r = c.post(
                    "/v1/jobs", json={"source": ids[0], "target": ids[1], "options": {"outputs": ["result", "aligned"]}}
                )
                assert r.status_code == 202, r.text
                job = wait_job(c, r.json()["id"], timeout=180)
                assert job["state"] == "succeeded", (job, self.dep.logs())
                made[who] = (job["id"], ids[0], [a["name"] for a in job["artifacts"]])
        if not self.keep_worker:
            worker.kill()
            self.dep.workers.remove(worker)
        self.baseline = self.snapshot(made)
        self.made = made
        self.stats.rss_start = self.dep.api_rss()
        self.stats.rss_peak = self.dep.api_rss("VmHWM")
        targets = Targets(made["alice"][0], made["alice"][1], made["bob"][0], made["bob"][1], made["alice"][2])
        with self.dep.client(ALICE) as c:
            for n in targets.artifacts:
                targets.etags[n] = c.get(f"/v1/jobs/{made['alice'][0]}/artifacts/{n}").headers["etag"]
        return targets

    def snapshot(self, made: dict) -> dict:
        snap = {"blobs": _blob_digests(self.tmp / "data" / "blobs")}
        for who, headers in (("alice", ALICE), ("bob", BOB)):
            job_id, asset_id, names = made[who]
            with self.dep.client(headers) as c:
                snap[who] = {
                    "job": c.get(f"/v1/jobs/{job_id}").json(),
                    "asset": c.get(f"/v1/assets/{asset_id}").json(),
                    "artifacts": {n: c.get(f"/v1/jobs/{job_id}/artifacts/{n}").content for n in names},
                }
        return snap

    def changed(self) -> list[str]:
        """Differences between the stored baseline and now ([] = byte-identical)."""
        now = self.snapshot(self.made)
        out = []
        for rel, digest in self.baseline["blobs"].items():
            if now["blobs"].get(rel) != digest:
                out.append(f"blob {rel} {'changed' if rel in now['blobs'] else 'gone'}")
        for who in ("alice", "bob"):
            for part in ("job", "asset"):
                if now[who][part] != self.baseline[who][part]:
                    out.append(f"{who}'s {part}: {self.baseline[who][part]} -> {now[who][part]}")
            for n, data in self.baseline[who]["artifacts"].items():
                if now[who]["artifacts"][n] != data:
                    out.append(f"{who}'s artifact {n} changed")
        return out

    # -- one generated request ---------------------------------------------------------------
    def run(self, req: Req) -> list[str]:
        resp = send(self.host, self.port, req, timeout=self.bound_s + 20)
        problems = problems_with(req, resp, self.bound_s, self.outage)
        problems += self._artifact_oracle(req, resp)
        self.stats.record(req, resp, problems, self.bound_s)
        if problems and self.save_dir is not None:
            self.save(req, problems)
        self.stats.rss_peak = max(self.stats.rss_peak, self.dep.api_rss("VmHWM"))
        return problems

    def save(self, req: Req, problems: list[str]) -> Path:
        self.save_dir.mkdir(parents=True, exist_ok=True)
        digest = hashlib.sha256(req.method.encode() + req.target + req.body).hexdigest()[:12]
        path = self.save_dir / f"{req.kind}-{digest}.http"
        why = "; ".join(problems).replace("\r", " ").replace("\n", " ")[:300]
        note = {"found": f"benchmarks/service/fuzz_service.py {time.strftime('%Y-%m-%d')}: {why}", "expect": "4xx"}
        path.write_bytes(dump_http(req, note))
        return path

    def _artifact_oracle(self, req: Req, resp: Resp) -> list[str]:
        """A 200/206 for a baseline artifact must carry exactly its bytes (or the range asked for)."""
        m = re.fullmatch(rb"/v1/jobs/([^/]+)/artifacts/(.+)", req.target)
        if req.kind != "artifact" or req.method != "GET" or not m or resp.status not in (200, 206):
            return []
        job_id, name = m.group(1).decode(errors="replace"), m.group(2).decode(errors="replace")
        if job_id != self.made["alice"][0] or name not in self.baseline["alice"]["artifacts"]:
            return []
        full = self.baseline["alice"]["artifacts"][name]
        if resp.status == 200:
            return [] if resp.body == full else ["200 body differs from the artifact"]
        cr = re.fullmatch(r"bytes (\d+)-(\d+)/(\d+)", resp.headers.get("content-range", ""))
        if not cr or int(cr.group(3)) != len(full):
            return [f"bad Content-Range {resp.headers.get('content-range')!r}"]
        a, z = int(cr.group(1)), int(cr.group(2))
        out = [] if resp.body == full[a : z + 1] else ["206 body is not the range it names"]
        if_range = {k.lower(): v for k, v in req.headers}.get(b"if-range")
        if if_range is not None and if_range.decode(errors="replace") != resp.headers.get("etag"):
            out.append(f"206 for a stale If-Range {if_range!r}")
        return out

    def fuzzed_job_outcomes(self, timeout_s: float = 180) -> dict[str, int]:
        """With a worker: wait for the jobs the fuzzer created, then count them by final
        state and error type. A job the API accepted must never fail as the service's
        fault (alignment-failed, 500): bad input is refused at submission, or fails 422."""
        from tests.service.conftest import wait_until

        baseline = {self.made["alice"][0]}

        def jobs():
            out, cursor = [], None
            with self.dep.client(ALICE) as c:
                while True:
                    page = c.get("/v1/jobs", params={"limit": 200, **({"cursor": cursor} if cursor else {})}).json()
                    out += [j for j in page["items"] if j["id"] not in baseline]
                    cursor = page.get("next_cursor")
                    if not cursor:
                        return out

        def settled():
            js = jobs()
            return js if all(j["state"] in ("succeeded", "failed", "cancelled") for j in js) else None

        try:
            found = wait_until(settled, timeout_s, 1.0, "fuzzed jobs to finish")
        except TimeoutError:
            found = jobs()
        counts: dict[str, int] = {}
        for j in found:
            key = j["state"] + (
                f" ({j['error']['status']} {j['error']['type'].rsplit('/', 1)[-1]})" if j["error"] else ""
            )
            counts[key] = counts.get(key, 0) + 1
        return dict(sorted(counts.items()))

    # -- outages -----------------------------------------------------------------------------
    def redis_down(self) -> None:
        self.outage = True
        self.redis.stop()

    def redis_up(self) -> None:
        self.redis.start()
        time.sleep(0.5)  # answers already in flight may still be 503
        self.outage = False

    def summary(self) -> dict:
        s = self.stats
        return {
            "requests": s.requests,
            "unexpected_5xx": s.unexpected_5xx,
            "hangs": s.hangs,
            "no_answer": s.no_answer,
            "other_contract_breaks": s.other,
            "max_latency_s": round(s.max_latency_s, 2),
            "rss_start_mib": round(s.rss_start / 2**20, 1),
            "rss_peak_mib": round(s.rss_peak / 2**20, 1),
            "by_status": dict(sorted(s.by_status.items())),
            "by_kind": dict(sorted(s.by_kind.items())),
        }

    def close(self) -> None:
        self.dep.close()


def dumps(d: dict) -> str:
    return json.dumps(d, indent=1, default=str)


__all__ = ["FuzzSession", "KEYS", "MAX_UPLOAD", "dumps"]
