"""Retries after infrastructure errors back off: a job attempt that cannot store its
artifacts (storage at its quota) goes back to the queue with `next_attempt_at` set, and the next
attempt starts no sooner, in both modes (RQ's scheduler with Redis, the store in embedded mode)."""

from __future__ import annotations

import os
from datetime import datetime
from pathlib import Path

import grpc
import httpx
import pytest

from service.rpc.generated import alignment_pb2 as pb
from service.rpc.generated import alignment_pb2_grpc as pbg
from service.settings import Settings
from service.worker.execution import retry_delay
from tests.service.conftest import ALICE, service_env, start_api, start_worker, wait_until

pytestmark = pytest.mark.slow  # starts servers and worker processes

BASE_S = 1.6  # attempt 1 → 0.8..1.6 s, attempt 2 → 1.6..3.2 s
QUOTA = 64 * 1024 * 1024
GRPC_AUTH = (("authorization", ALICE["Authorization"]),)


def test_delay_is_exponential_capped_and_jittered():
    s = Settings(retry_backoff_base_s=2.0, retry_backoff_max_s=10.0)
    for attempt, full in ((1, 2.0), (2, 4.0), (3, 8.0), (4, 10.0), (9, 10.0)):
        seen = [retry_delay(s, attempt) for _ in range(200)]
        assert all(full / 2 <= d <= full for d in seen), (attempt, min(seen), max(seen))
        assert max(seen) - min(seen) > full / 10  # jittered, not one fixed delay
    assert retry_delay(Settings(retry_backoff_base_s=0), 3) == 0.0


def _ts(v: str | None) -> float | None:
    return None if v is None else datetime.fromisoformat(v.replace("Z", "+00:00")).timestamp()


def _used(root: Path) -> int:
    return sum(p.stat().st_size for p in root.rglob("*") if p.is_file())


@pytest.mark.parametrize("mode", ["redis", "embedded"])
def test_retries_after_a_full_storage_wait_for_their_back_off(tmp_path, pair, redis_url, mode):
    extra = dict(
        GSA_STORAGE_QUOTA_BYTES=QUOTA,
        GSA_TENANT_STORAGE_QUOTA_BYTES=0,  # the deployment's quota is the one filled here
        GSA_MIN_FREE_BYTES=1,
        GSA_RETRY_BACKOFF_BASE_S=BASE_S,
        GSA_RETRY_BACKOFF_MAX_S=60,
        GSA_MAX_ATTEMPTS=3,
    )
    if mode == "redis":
        extra.update(GSA_REDIS_URL=redis_url + "/7", GSA_QUEUE_NAME="backoff")
    env = service_env(tmp_path, **extra)
    api, url, gport = start_api(tmp_path, env, grpc=True, name=f"api-{mode}")
    worker = start_worker(tmp_path, env, name="worker-backoff") if mode == "redis" else None
    blobs = tmp_path / "data" / "blobs"
    channel = grpc.insecure_channel(f"127.0.0.1:{gport}")
    rpc = pbg.AlignmentServiceStub(channel)
    try:
        with httpx.Client(base_url=url, headers=ALICE, timeout=60) as c:
            ids = []
            for k in ("source", "target"):
                with open(pair[k], "rb") as fh:
                    r = c.post("/v1/assets", files={"file": (f"{k}.ply", fh)})
                assert r.status_code == 201, r.text
                ids.append(r.json()["id"])
            # Leave 100 bytes of the quota: the job's artifacts cannot be stored.
            filler = blobs / "cas" / "filler"
            filler.parent.mkdir(parents=True, exist_ok=True)
            filler.write_bytes(b"")
            os.truncate(filler, QUOTA - _used(blobs) - 100)
            r = c.post(
                "/v1/jobs",
                json={
                    "source": ids[0],
                    "target": ids[1],
                    "options": {"stages": ["coarse"], "outputs": ["result", "aligned"]},
                },
            )
            assert r.status_code == 202, r.text
            jid = r.json()["id"]

            def requeued(n):
                def check():
                    j = c.get(f"/v1/jobs/{jid}").json()
                    assert j["state"] != "failed", j
                    return j if j["state"] == "queued" and j["attempts"] == n else None

                return check

            waits, grpc_checked = [], 0
            for n in (1, 2):
                j = wait_until(requeued(n), 120, 0.02, f"attempt {n} to be requeued")
                failed_at, next_at = _ts(j["updated_at"]), _ts(j["next_attempt_at"])
                assert j["stage"] == "requeued" and next_at is not None, j
                full = BASE_S * 2 ** (n - 1)
                # The record's next attempt time is the back-off: half to all of base·2^(n-1).
                assert full / 2 - 0.05 <= next_at - failed_at <= full + 0.05, (n, next_at - failed_at, j)
                # gRPC clients see the same time (read while the job still waits for it).
                over_grpc = rpc.GetJob(pb.JobRef(job_id=jid), metadata=GRPC_AUTH)
                if over_grpc.state == pb.JOB_STATE_QUEUED:
                    grpc_checked += 1
                    assert over_grpc.HasField("next_attempt_at"), over_grpc
                    assert abs(over_grpc.next_attempt_at.ToNanoseconds() / 1e9 - next_at) < 1e-3
                if n == 2:
                    filler.unlink()  # room again: the third attempt can store its artifacts
                started = wait_until(
                    lambda n=n: (x := c.get(f"/v1/jobs/{jid}").json())["attempts"] == n + 1 and x, 60, 0.02
                )
                start = _ts(started["started_at"])
                # The next attempt waited for its time (never sooner; the scheduler and the
                # embedded worker look once a second, so at most ~1 s later).
                assert start >= next_at - 0.01, (n, start, next_at)
                assert start - next_at < 5.0, (n, start, next_at)
                waits.append(start - failed_at)
            done = wait_until(
                lambda: (x := c.get(f"/v1/jobs/{jid}").json())["state"] in ("succeeded", "failed") and x, 120
            )
            assert done["state"] == "succeeded" and done["attempts"] == 3, done
            assert done["next_attempt_at"] is None
            assert grpc_checked >= 1, "the back-off never outlasted one GetJob"
            assert not rpc.GetJob(pb.JobRef(job_id=jid), metadata=GRPC_AUTH).HasField("next_attempt_at")
            assert waits[0] >= BASE_S / 2 - 0.05 and waits[1] >= BASE_S - 0.05, waits
    finally:
        channel.close()
        if worker is not None:
            worker.stop()
        api.stop()
    # The delay is visible in the logs too, with the attempt's number.
    logs = "".join(p.read_text(errors="replace") for p in tmp_path.glob("*.log"))
    assert "next attempt in" in logs, logs[-3000:]
