"""At-least-once: a worker killed with SIGKILL mid-job; the job finishes on another."""

from __future__ import annotations

import time

import httpx
import pytest

from tests.service.conftest import (
    ALICE,
    service_env,
    start_api,
    start_worker,
    submit_slow_job,
    wait_job,
)

pytestmark = pytest.mark.slow  # starts servers and worker processes


def test_sigkilled_worker_job_finishes_elsewhere(tmp_path, redis_url, pair):
    env = service_env(tmp_path, GSA_REDIS_URL=redis_url + "/1", GSA_QUEUE_NAME="killtest")
    api, url, _ = start_api(tmp_path, env, name="api-kill")
    victim = start_worker(tmp_path, env, name="victim")
    rescuer = None
    try:
        with httpx.Client(base_url=url, headers=ALICE, timeout=60) as http:
            job, _ = submit_slow_job(http, pair, copies=4)
            running = wait_job(http, job["id"], states=("running",), timeout=60)
            assert running["attempts"] == 1
            horses = victim.kill_tree()  # SIGKILL the worker and its forked work horse
            assert victim.p.returncode == -9 and horses, "the job should be running in a work horse"
            # nobody is running it now; the job must not stay "running" forever
            rescuer = start_worker(tmp_path, env, name="rescuer")
            done = wait_job(http, job["id"], timeout=120)
            assert done["state"] == "succeeded", (done, rescuer.tail())
            assert done["attempts"] == 2
            assert len(done["result"]["results"]) == 4
            assert {a["name"] for a in done["artifacts"]} == {f"s{i}/result.json" for i in range(4)}
            # only the successful attempt's artifacts exist in storage
            attempts_dirs = list((tmp_path / "data" / "blobs" / "jobs" / job["id"]).iterdir())
            assert len(attempts_dirs) == 1
    finally:
        for p in (victim, rescuer, api):
            if p is not None:
                p.stop()


def test_lost_job_is_failed_when_attempts_are_spent(tmp_path):
    import time

    from service.backend import make_backend
    from service.models import JobState
    from service.settings import Settings
    from service.worker.leases import reap

    b = make_backend(Settings(storage_root=tmp_path, max_attempts=2))
    now = time.time()
    for jid, attempts in (("j1", 1), ("j2", 2)):
        _running_job(b, jid, attempts, now - 1, max_attempts=2)
    _running_job(b, "j3", 1, now + 60)
    assert sorted(reap(b)) == ["j1", "j2"]
    assert b.store.get("j1").state == JobState.queued and b.store.get("j1").run_token is None
    j2 = b.store.get("j2")
    assert j2.state == JobState.failed and j2.error["type"].endswith("/worker-lost")
    assert b.store.get("j3").state == JobState.running  # lease still valid
    # a stale worker holding the old token can no longer write
    assert not b.store.update("j1", token="t", states={JobState.running}, progress=0.5)


def test_lost_queue_message_is_resent(redis_url, tmp_path):
    """A worker that dies between dequeuing and claiming leaves the job queued in
    the store with no live queue message; the reaper sends it again."""
    import redis as redislib
    from rq.job import Job as RQJob

    from service.backend import make_backend
    from service.jobs.core import create_job
    from service.models import Asset
    from service.settings import Settings
    from service.worker.leases import resend_lost

    redislib.Redis.from_url(redis_url + "/3").flushdb()  # private test server, db 3
    b = make_backend(
        Settings(
            redis_url=redis_url + "/3",
            storage_root=tmp_path,
            queue_name="losttest",
            lease_s=1,
        )
    )
    a = Asset(
        id="ast_1",
        owner="o",
        kind="ply",
        key="uploads/x/a.ply",
        size=1,
        content_type="x",
        sha256="0",
        created_at=0,
    )
    job = create_job(b, "o", "job_lost", [a], a, {}, None, None)
    ref = b.store.get(job.id).queue_ref
    assert ref and b.queue.q.job_ids == [ref]
    assert resend_lost(b) == []  # a live message within the grace period: left alone
    b.queue.q.remove(ref)  # the message vanishes (dequeued by a worker that then died)
    RQJob.fetch(ref, connection=b.redis).delete()
    b.store.update(job.id, enqueued_at=time.time() - 10)
    assert resend_lost(b) == [job.id]
    new_ref = b.store.get(job.id).queue_ref
    assert new_ref != ref and b.queue.q.job_ids == [new_ref]


def test_the_reaper_removes_what_a_lost_attempt_stored(tmp_path):
    # An attempt SIGKILLed between storing its artifacts and finishing cannot remove them; the
    # retry's set would then be the job's second (the chaos test saw it once).
    import io
    import time

    from service.backend import make_backend
    from service.models import JobState
    from service.settings import Settings
    from service.worker.leases import attempt_artifacts, reap

    b = make_backend(Settings(storage_root=tmp_path, max_attempts=3))
    now = time.time()
    for jid, lease in (("lost", now - 1), ("alive", now + 60)):
        _running_job(b, jid, 1, lease)
        b.storage.put(attempt_artifacts(jid, "t") + "/result.json", io.BytesIO(b"{}"))
    assert reap(b) == ["lost"]
    assert b.store.get("lost").state == JobState.queued
    assert not b.storage.exists(attempt_artifacts("lost", "t") + "/result.json")
    assert b.storage.exists(attempt_artifacts("alive", "t") + "/result.json")  # its lease still holds


def _running_job(b, jid: str, attempts: int, lease_until: float, **fields) -> None:
    """A job record as a worker's claim leaves it: running on run token "t" (or fields'), leased."""
    import time

    from service.models import InputRef, Job, JobState

    ref = InputRef(asset_id="a", key="uploads/x/y", kind="ply")
    now = time.time()
    b.store.create(
        Job(
            id=jid,
            owner="o",
            created_at=now,
            updated_at=now,
            sources=[ref],
            target=ref,
            state=JobState.running,
            attempts=attempts,
            run_token="t",
            lease_until=lease_until,
            **fields,
        )
    )
