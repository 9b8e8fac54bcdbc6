"""A queue message taken by a worker that died before marking it started: RQ still
says "queued", but no list holds it any more. The reaper must send it again (found
by the chaos run: one job of 100 stayed queued for good). Nor may a job whose message
was never sent stay queued (the API SIGKILLed between creating and enqueuing it), nor
a retry whose delayed message RQ's scheduler does not move (its worker died holding the
scheduler's lock)."""

from __future__ import annotations

import time

import redis as redislib

from service.backend import make_backend
from service.jobs.core import create_job
from service.models import Asset
from service.settings import Settings
from service.worker.leases import resend_lost


def test_a_queued_message_no_list_holds_is_resent(redis_url, tmp_path):
    redislib.Redis.from_url(redis_url + "/4").flushdb()  # private test server, db 4
    b = make_backend(Settings(redis_url=redis_url + "/4", storage_root=tmp_path, queue_name="blpop", lease_s=1))
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
    job = create_job(b, "o", "job_blpop", [a], a, {}, None, None)
    ref = b.store.get(job.id).queue_ref
    b.store.update(job.id, enqueued_at=time.time() - 10)
    assert resend_lost(b) == []  # still in the queue: a backlog, not a loss
    b.redis.lpop(b.queue.q.key)  # what BLPOP does for a worker that is then SIGKILLed
    assert b.queue.q.fetch_job(ref).get_status(refresh=True).value == "queued"
    assert resend_lost(b) == [job.id]
    new_ref = b.store.get(job.id).queue_ref
    assert new_ref != ref and b.queue.q.job_ids == [new_ref]


def _asset() -> Asset:
    return Asset(
        id="ast_1", owner="o", kind="ply", key="uploads/x/a.ply", size=1, content_type="x", sha256="0", created_at=0
    )


def _queued_job(redis_url: str, tmp_path, db: int, name: str):
    """A backend on the private test server's database `db` (emptied) and one queued job."""
    redislib.Redis.from_url(f"{redis_url}/{db}").flushdb()
    b = make_backend(Settings(redis_url=f"{redis_url}/{db}", storage_root=tmp_path, queue_name=name, lease_s=1))
    a = _asset()
    return b, create_job(b, "o", f"job_{name}", [a], a, {}, None, None)


def test_a_job_whose_message_was_never_sent_is_sent(redis_url, tmp_path):
    b, job = _queued_job(redis_url, tmp_path, 5, "unsent")
    # What the store holds when the API died right after creating the record: no message.
    b.redis.delete(b.queue.q.key)
    b.store.update(job.id, queue_ref=None, enqueued_at=None)
    assert resend_lost(b) == []  # within the grace a submission may still be enqueuing
    b.store.update(job.id, created_at=time.time() - 10)
    b.store.update(job.id, next_attempt_at=time.time() + 60)
    assert resend_lost(b) == []  # waiting out a back-off is not lost
    b.store.update(job.id, next_attempt_at=None)
    assert resend_lost(b) == [job.id]
    ref = b.store.get(job.id).queue_ref
    assert ref is not None and b.queue.q.job_ids == [ref]
    assert resend_lost(b) == []  # sent now: not sent again


def test_a_retry_message_the_scheduler_left_overdue_is_resent(redis_url, tmp_path):
    b, job = _queued_job(redis_url, tmp_path, 6, "overdue")
    b.redis.delete(b.queue.q.key)
    # A retry's back-off message: "scheduled" in RQ's registry, due in 1 s; no scheduler runs here.
    ref = b.queue.enqueue(job.id, delay_s=1.0)
    b.store.update(job.id, queue_ref=ref, enqueued_at=time.time() - 10, next_attempt_at=time.time() - 0.5)
    assert b.queue.q.fetch_job(ref).get_status(refresh=True).value == "scheduled"
    assert resend_lost(b) == []  # due moments ago: the scheduler's next pass moves it
    registry = b.queue.q.scheduled_job_registry
    b.redis.zadd(registry.key, {ref: time.time() - 5})  # now overdue by more than two leases
    assert resend_lost(b) == [job.id]
    new_ref = b.store.get(job.id).queue_ref
    assert new_ref != ref and b.queue.q.job_ids == [new_ref]
