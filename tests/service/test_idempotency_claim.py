"""An Idempotency-Key claimed by a request that never created its job (the API was
SIGKILLed, or Redis went away, between the claim and the job) lapses after
IDEM_PENDING_S instead of answering 409 "in progress" for a day (found by the chaos run)."""

from __future__ import annotations

import pytest
import redis as redislib

from service.backend import make_backend
from service.jobs.core import claim, create_job
from service.models import Asset
from service.problems import Problem
from service.settings import Settings
from service.stores import base as store
from service.stores import redis_store


def test_a_claim_without_its_job_lapses_and_a_created_job_keeps_its_key(redis_url, tmp_path):
    redislib.Redis.from_url(redis_url + "/5").flushdb()  # private test server, db 5
    b = make_backend(Settings(redis_url=redis_url + "/5", storage_root=tmp_path, queue_name="idem"))
    a = Asset(
        id="ast_1", owner="o", kind="ply", key="uploads/x/a.ply", size=1, content_type="x", sha256="0", created_at=0
    )
    key = b.store.p + "idem:o:k1"
    first, existing = claim(b, "o", "k1", "fp")
    assert existing is None and 0 < b.redis.ttl(key) <= redis_store.IDEM_PENDING_S
    with pytest.raises(Problem) as p:  # the first request is still (or was) storing its uploads
        claim(b, "o", "k1", "fp")
    assert p.value.status == 409
    b.redis.delete(key)  # what the pending TTL does once it has run out
    retry, existing = claim(b, "o", "k1", "fp")
    assert existing is None and retry != first
    create_job(b, "o", retry, [a], a, {}, None, "k1")
    assert b.redis.ttl(key) > redis_store.IDEM_PENDING_S  # the job's key lasts its full day
    again, existing = claim(b, "o", "k1", "fp")
    assert existing is not None and existing.id == retry


def test_embedded_store_claims_lapse_as_in_redis(tmp_path):
    b = make_backend(Settings(storage_root=tmp_path))  # no redis_url: the embedded SQLite store
    a = Asset(
        id="ast_1", owner="o", kind="ply", key="uploads/x/a.ply", size=1, content_type="x", sha256="0", created_at=0
    )
    first, existing = claim(b, "o", "k1", "fp")
    assert existing is None
    with pytest.raises(Problem) as p:
        claim(b, "o", "k1", "fp")
    assert p.value.status == 409
    b.store.db.execute("UPDATE idem SET at = at - ?", (store.IDEM_PENDING_S + 1,))  # its job never came
    retry, existing = claim(b, "o", "k1", "fp")
    assert existing is None and retry != first
    create_job(b, "o", retry, [a], a, {}, None, "k1")
    b.store.db.execute("UPDATE idem SET at = at - ?", (store.IDEM_PENDING_S + 1,))
    again, existing = claim(b, "o", "k1", "fp")  # a created job keeps its key past the pending time
    assert existing is not None and existing.id == retry
    b.store.db.execute("UPDATE idem SET at = at - ?", (store.IDEM_TTL_S,))
    later, existing = claim(b, "o", "k1", "fp")  # and gives it up after its full day
    assert existing is None and later not in (first, retry)
