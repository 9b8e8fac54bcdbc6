"""Per-tenant metrics: a real `gsa serve` over HTTP with two tenants (the test stack's
alice, an operator in GSA_METRICS_OWNERS, and bob), a low request rate, a small storage quota and
a limit of one active job. Bob is driven into 429 (request rate; in Redis mode also active jobs)
and 507 (storage quota); alice's /metrics scrape then shows exactly those refusals, requests and
jobs for bob and none for alice, with the stored bytes and active jobs read from the shared store.
Redis mode runs two API replicas: the counters are per process (their sum is what bob saw), the
store-read gauges the same on both. No API key ever appears in the scrape."""

from __future__ import annotations

from collections import Counter

import httpx
import pytest
from prometheus_client.parser import text_string_to_metric_families

from tests.service.conftest import ALICE, BOB, assert_problem, service_env, start_api

_REASON = {"rate-limited": "rate_limited", "too-many-jobs": "active_jobs", "storage-quota-exceeded": "storage_quota"}


def _samples(text: str) -> dict[tuple[str, tuple], float]:
    """{(sample name, sorted labels): value} of a Prometheus text exposition."""
    out = {}
    for fam in text_string_to_metric_families(text):
        for s in fam.samples:
            out[(s.name, tuple(sorted(s.labels.items())))] = s.value
    return out


def _get(samples: dict, name: str, **labels) -> float | None:
    return samples.get((name, tuple(sorted(labels.items()))))


def _upload(c: httpx.Client, path) -> httpx.Response:
    with open(path, "rb") as fh:
        return c.post("/v1/assets", files={"file": (path.name, fh)})


def _deploy(tmp_path, redis_url, mode: str, size: int) -> tuple[list, list[str]]:
    """One API (embedded) or two API replicas on one Redis database and no worker (redis)."""
    env = dict(
        GSA_TENANT_RATE_PER_S=0.02,  # a token back every 50 s: the burst is what the test spends
        GSA_TENANT_RATE_BURST=12,
        GSA_TENANT_STORAGE_QUOTA_BYTES=int(size * 2.5),  # source + target fit, a third upload does not
        GSA_TENANT_MAX_ACTIVE_JOBS=1,
    )
    apis = 1
    if mode == "redis":
        import redis as redislib

        redislib.Redis.from_url(redis_url + "/15").flushdb()  # private test server, db 15
        # no worker: an accepted job stays queued, so the active-jobs limit holds
        env.update(GSA_REDIS_URL=redis_url + "/15", GSA_QUEUE_NAME="tenant-metrics")
        apis = 2
    e = service_env(tmp_path, **env)
    procs, urls = [], []
    for i in range(apis):
        proc, url, _ = start_api(tmp_path, e, name=f"api{i}")
        procs.append(proc)
        urls.append(url)
    return procs, urls


def _drive_bob(urls: list[str], pair, mode: str) -> tuple[list[httpx.Response], int]:
    """Bob's requests, spread over the replicas, into 429 and 507: (his responses, his stored bytes)."""
    bob = [httpx.Client(base_url=u, headers=BOB, timeout=60) for u in urls]
    seen: list[httpx.Response] = []

    def call(r: httpx.Response) -> httpx.Response:
        seen.append(r)
        return r

    try:
        ids = [call(_upload(bob[0], pair[k])).json()["id"] for k in ("source", "target")]
        assert [r.status_code for r in seen] == [201, 201], [r.text for r in seen]
        if mode == "redis":
            job = {"source": ids[0], "target": ids[1], "options": {"stages": ["coarse"]}}
            assert call(bob[0].post("/v1/jobs", json=job)).status_code == 202
            assert_problem(call(bob[-1].post("/v1/jobs", json=job)), 429, "too-many-jobs")
        used = assert_problem(call(_upload(bob[-1], pair["source2"])), 507, "storage-quota-exceeded")["used"]
        assert_problem(call(_upload(bob[0], pair["source2"])), 507, "storage-quota-exceeded")
        # GETs until his bucket is empty; then one more refusal on each replica.
        for i in range(20):
            if call(bob[i % len(bob)].get("/v1/jobs")).status_code == 429:
                break
        assert seen[-1].status_code == 429, [r.status_code for r in seen]
        for c in bob:
            assert_problem(call(c.get("/v1/jobs")), 429, "rate-limited")
        # A key nobody configured is no tenant: its 401 adds no label.
        assert bob[0].get("/v1/jobs", headers={"Authorization": "Bearer key-mallory"}).status_code == 401
    finally:
        for c in bob:
            c.close()
    return seen, used


@pytest.mark.parametrize("mode", ["embedded", "redis"])
def test_refusals_requests_and_usage_are_counted_per_tenant(tmp_path, pair, redis_url, mode):
    size = pair["source"].stat().st_size  # the target has the same layout and count
    procs, urls = _deploy(tmp_path, redis_url, mode, size)
    try:
        seen, used = _drive_bob(urls, pair, mode)
        with httpx.Client(headers=ALICE, timeout=60) as alice:
            assert alice.get(urls[0] + "/v1/jobs").status_code == 200  # alice is well within her limits
            texts = [alice.get(u + "/metrics") for u in urls]
        assert all(r.status_code == 200 for r in texts), [r.text for r in texts]
        texts = [r.text for r in texts]
    finally:
        for p in procs:
            p.stop()
    assert used == 2 * size
    refusals = Counter(_REASON[r.json()["type"].rsplit("/", 1)[-1]] for r in seen if r.status_code in (429, 507))
    classes = Counter(f"{r.status_code // 100}xx" for r in seen)
    assert refusals["rate_limited"] == len(urls) + 1 and refusals["storage_quota"] == 2, refusals
    jobs = 1 if mode == "redis" else 0
    assert refusals["active_jobs"] == jobs, refusals
    scrapes = [_samples(t) for t in texts]

    def total(name: str, **labels) -> float:
        return sum(_get(s, name, **labels) or 0 for s in scrapes)

    for reason in ("rate_limited", "active_jobs", "storage_quota"):
        assert total("gsa_tenant_refusals_total", tenant="bob", reason=reason) == refusals[reason], reason
        for s in scrapes:  # every configured tenant's series exist, at 0 until a refusal
            assert _get(s, "gsa_tenant_refusals_total", tenant="alice", reason=reason) == 0, reason
    for cls in ("2xx", "4xx", "5xx"):
        assert total("gsa_tenant_http_requests_total", tenant="bob", status_class=cls) == classes[cls], cls
    assert total("gsa_tenant_http_requests_total", tenant="alice", status_class="2xx") >= 1
    assert total("gsa_tenant_http_requests_total", tenant="alice", status_class="4xx") == 0
    assert total("gsa_tenant_jobs_created_total", tenant="bob", api="http") == jobs
    assert total("gsa_tenant_jobs_created_total", tenant="alice", api="http") == 0
    # From the shared store: every replica reports the same cluster-wide numbers.
    for s in scrapes:
        assert _get(s, "gsa_tenant_storage_bytes", tenant="bob") == used
        assert _get(s, "gsa_tenant_storage_bytes", tenant="alice") == 0
        assert _get(s, "gsa_tenant_active_jobs", tenant="bob") == jobs
        assert _get(s, "gsa_tenant_active_jobs", tenant="alice") == 0
    tenants = {dict(k[1]).get("tenant") for s in scrapes for k in s} - {None}
    assert tenants == {"alice", "bob"}, tenants
    for t in texts:
        assert "key-alice" not in t and "key-bob" not in t and "mallory" not in t


def test_tenant_labels_never_hold_a_key():
    """The `tenant` label is the configured owner; an owner that is (a prefix of) its own key, as
    `GSA_API_KEYS=key` without `:owner` makes it, is labelled by a hash of the key instead."""
    from service.metrics import tenant_labels
    from service.settings import Settings

    s = Settings(api_keys="s3cretkey-1234567890:ops,s3cretkey-abcdefghij", auth_disabled=False)
    labels = tenant_labels(s)
    assert labels["ops"] == "ops"
    unnamed = labels["s3cretke"]  # the owner the shell form made from the key's first 8 characters
    assert unnamed.startswith("key-") and "s3cret" not in unnamed and len(unnamed) == 16
    assert tenant_labels(Settings(auth_disabled=True)) == {"anonymous": "anonymous"}
