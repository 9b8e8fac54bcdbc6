"""Per-tenant limits (so no tenant takes what all share): request rate, active jobs, stored bytes.

One tenant must not be able to take what every tenant shares: the API's request capacity
(429 `rate-limited`), the queue (429 `too-many-jobs` past `GSA_TENANT_MAX_ACTIVE_JOBS` queued
or running jobs) and the storage (507 `storage-quota-exceeded` past the tenant's quota, while
the others can still store). A tenant is an owner: the value `GSA_API_KEYS` maps its keys to.

The rate limiter is a token bucket per owner: in Redis mode one bucket in Redis shared by every
API process (a Lua script reading Redis' clock, so processes need no synchronised clocks),
in embedded mode one in this process. Stored bytes are a ledger per owner in the job store
(service.stores.base: `set_usage` / `drop_usage` / `usage`) keyed by what holds the bytes (an
upload's blob key, `job:<id>` for a job's artifacts): setting an entry twice counts it once,
so a retried write never counts double.

Every refusal is counted where it is raised, per tenant and reason (service.metrics:
`gsa_tenant_refusals_total{tenant, reason}`), for HTTP and gRPC alike.
"""

from __future__ import annotations

import logging
import math
import threading
import time

from service.problems import Problem, store_errors

log = logging.getLogger("gsa.quotas")

# KEYS[1]: the owner's bucket. ARGV: rate (tokens/s), burst. Returns the seconds to wait
# ("0": allowed, a token taken) as a string, as Redis truncates Lua numbers to integers.
_BUCKET = """
local t = redis.call('TIME')
local now = tonumber(t[1]) + tonumber(t[2]) / 1000000
local rate, burst = tonumber(ARGV[1]), tonumber(ARGV[2])
local s = redis.call('HMGET', KEYS[1], 'tokens', 'ts')
local tokens = tonumber(s[1]) or burst
local ts = tonumber(s[2]) or now
tokens = math.min(burst, tokens + math.max(0, now - ts) * rate)
local wait = 0
if tokens >= 1 then tokens = tokens - 1 else wait = (1 - tokens) / rate end
redis.call('HSET', KEYS[1], 'tokens', tostring(tokens), 'ts', tostring(now))
redis.call('PEXPIRE', KEYS[1], math.ceil(burst / rate * 1000) + 1000)
return tostring(wait)
"""


class MemoryRateLimiter:
    """Embedded mode: one process serves every request, so its own buckets are the truth."""

    def __init__(self, rate: float, burst: float):
        self.rate, self.burst = rate, max(burst, 1.0)
        self.buckets: dict[str, tuple[float, float]] = {}
        self.lock = threading.Lock()

    def acquire(self, owner: str) -> float:
        """Take a token: 0.0 if allowed, else the seconds until one is free."""
        now = time.monotonic()
        with self.lock:
            tokens, ts = self.buckets.get(owner, (self.burst, now))
            tokens = min(self.burst, tokens + max(0.0, now - ts) * self.rate)
            wait = 0.0
            if tokens >= 1:
                tokens -= 1
            else:
                wait = (1 - tokens) / self.rate
            self.buckets[owner] = (tokens, now)
            if len(self.buckets) > 100_000:  # owners idle long enough to be full again
                full = [o for o, (t, at) in self.buckets.items() if t + (now - at) * self.rate >= self.burst]
                for o in full:
                    del self.buckets[o]
            return wait


class RedisRateLimiter:
    """Redis mode: the bucket lives in Redis, so N API replicas allow one tenant the rate, not N×."""

    def __init__(self, redis_client, rate: float, burst: float, prefix: str = "gsa:"):
        self.rate, self.burst, self.p = rate, max(burst, 1.0), prefix
        self._bucket = redis_client.register_script(_BUCKET)

    def acquire(self, owner: str) -> float:
        return float(self._bucket(keys=[f"{self.p}rate:{owner}"], args=[self.rate, self.burst]))


def make_rate_limiter(settings, redis_client=None):
    """None when GSA_TENANT_RATE_PER_S is 0 (no limit)."""
    if not settings.tenant_rate_per_s or settings.tenant_rate_per_s <= 0:
        return None
    if redis_client is not None:
        return RedisRateLimiter(redis_client, settings.tenant_rate_per_s, settings.tenant_rate_burst)
    return MemoryRateLimiter(settings.tenant_rate_per_s, settings.tenant_rate_burst)


def _retry_after(p: Problem, seconds: float) -> Problem:
    s = max(math.ceil(seconds), 1)
    p.headers["Retry-After"] = str(s)
    p.extra["retry_after"] = s  # gRPC clients have no headers: the problem carries it too
    return p


def _refused(b, owner: str, reason: str) -> None:
    """Count a refusal (service.metrics.REFUSAL_REASONS) on the API's metrics, if it has them."""
    metrics = getattr(b, "metrics", None)
    if metrics is not None:
        metrics.refused(owner, reason)


_made = threading.Lock()


def rate_limiter(b):
    """The backend's limiter, made on first use from its settings and Redis client (None: no limit)."""
    if not hasattr(b, "_rate_limiter"):
        with _made:
            if not hasattr(b, "_rate_limiter"):
                b._rate_limiter = make_rate_limiter(b.settings, b.redis)
    return b._rate_limiter


def check_rate(b, owner: str) -> None:
    """429 `rate-limited` with Retry-After once the owner's bucket is empty."""
    limiter = rate_limiter(b)
    if limiter is None:
        return
    try:
        wait = limiter.acquire(owner)
    except store_errors() as exc:  # Redis down: the request's own store access answers 503
        log.debug("rate limiter unavailable: %s", exc)
        return
    if wait > 0:
        s = b.settings
        _refused(b, owner, "rate_limited")
        raise _retry_after(
            Problem(
                429,
                "rate-limited",
                "Too many requests",
                f"more than {s.tenant_rate_per_s:g} requests a second (burst {s.tenant_rate_burst}) "
                "with this tenant's keys; retry after the time in Retry-After",
                limit=s.tenant_rate_per_s,
            ),
            wait,
        )


def tenant_storage_quota(settings) -> int:
    """Bytes one owner may store (0: no limit). Unset: half the global quota, if there is one."""
    q = settings.tenant_storage_quota_bytes
    if q is None:
        return settings.storage_quota_bytes // 2 if settings.storage_quota_bytes > 0 else 0
    return max(q, 0)


def check_storage(b, owner: str, incoming: int = 0) -> None:
    """507 `storage-quota-exceeded` when the owner's stored bytes plus `incoming` pass its
    quota (with incoming 0: once it is reached). No Retry-After: waiting frees nothing,
    deleting the owner's jobs or assets does."""
    quota = tenant_storage_quota(b.settings)
    if not quota:
        return
    used = b.store.usage(owner)
    if used + incoming > quota or (incoming == 0 and used >= quota):
        _refused(b, owner, "storage_quota")
        raise Problem(
            507,
            "storage-quota-exceeded",
            "Storage quota exceeded",
            f"this tenant stores {used} bytes of its quota of {quota} (GSA_TENANT_STORAGE_QUOTA_BYTES)"
            + (f"; this upload of {incoming} bytes does not fit" if incoming else "")
            + ": delete jobs or assets to make room",
            quota=quota,
            used=used,
        )


def check_active_jobs(b, owner: str) -> None:
    """429 `too-many-jobs` with Retry-After while the owner has its limit of queued or running jobs."""
    limit = b.settings.tenant_max_active_jobs
    if not limit or limit <= 0:
        return
    active = b.store.active_jobs(owner)
    if active >= limit:
        _refused(b, owner, "active_jobs")
        raise _retry_after(
            Problem(
                429,
                "too-many-jobs",
                "Too many jobs",
                f"this tenant has {active} queued or running jobs, its limit (GSA_TENANT_MAX_ACTIVE_JOBS) "
                f"is {limit}: retry once some have finished",
                limit=limit,
                active=active,
            ),
            b.settings.tenant_jobs_retry_after_s,
        )


def record(b, owner: str, item: str, nbytes: int) -> None:
    """Count `nbytes` held by `item` (a blob key, job:<id>) against the owner; idempotent."""
    b.store.set_usage(owner, item, int(nbytes))


def forget(b, owner: str, item: str) -> None:
    """The item's bytes are gone; never hides the caller's own error."""
    try:
        b.store.drop_usage(owner, item)
    except store_errors() as exc:
        log.warning("could not update %s's storage usage for %s: %s", owner, item, exc)
