"""Prometheus metrics: request counters/latency, jobs by state, queue depth,
stage durations. Job/queue/stage numbers are read from the shared store at
scrape time, so every API replica reports the same cluster-wide values.

Per tenant: refusals by reason (429 request rate, 429 active jobs, 507 storage
quota), HTTP requests by status class and jobs created are counters of this process (summed
over replicas by Prometheus); stored bytes and queued + running jobs are read from the shared
store at scrape time. The `tenant` label is the owner GSA_API_KEYS names (or `anonymous` with
auth off), never a key: an owner that is a prefix of its own key (`GSA_API_KEYS=key` without
`:owner` names the owner by the key's first 8 characters) is labelled `key-<sha256 of the
key, 12 hex>` instead. Labels come only from the configured owners, so their number is bounded
by the configuration; a request without a valid key counts for no tenant."""

from __future__ import annotations

import hashlib

from prometheus_client import CollectorRegistry, Counter, Histogram
from prometheus_client.core import GaugeMetricFamily, SummaryMetricFamily

from service.problems import store_errors


class _StoreCollector:
    def __init__(self, backend):
        self.b = backend

    # While the store or the queue cannot answer, its families go out without samples: the
    # scrape itself still answers (and /readyz tells why).
    def collect(self):
        jobs = GaugeMetricFamily("gsa_jobs", "Jobs by state", labels=["state"])
        try:
            for state, n in self.b.store.counts().items():
                jobs.add_metric([state], n)
        except store_errors():
            pass
        yield jobs
        depth = GaugeMetricFamily("gsa_queue_depth", "Jobs waiting in the queue")
        try:
            depth.add_metric([], self.b.queue.depth())
        except store_errors():
            pass
        yield depth
        stages = SummaryMetricFamily(
            "gsa_stage_duration_seconds",
            "Time spent per pipeline stage",
            labels=["stage"],
        )
        try:
            for stage, (n, secs) in sorted(self.b.store.stage_stats().items()):
                stages.add_metric([stage], n, secs)
        except store_errors():
            pass
        yield stages


# Why a tenant was refused (service.jobs.quotas): 429 rate-limited, 429 too-many-jobs, 507
# storage-quota-exceeded.
REFUSAL_REASONS = ("rate_limited", "active_jobs", "storage_quota")
ANONYMOUS = "anonymous"


def tenant_labels(settings) -> dict[str, str]:
    """owner -> its `tenant` label, for every owner the settings configure."""
    if settings.auth_disabled:
        return {ANONYMOUS: ANONYMOUS}
    out: dict[str, str] = {}
    for key, owner in sorted(settings.api_keys.items()):
        if not owner or key.startswith(owner):  # the owner's name would be (part of) the key
            out.setdefault(owner, "key-" + hashlib.sha256(key.encode()).hexdigest()[:12])
        else:
            out.setdefault(owner, owner)
    return out


class _TenantCollector:
    """Per configured tenant, from the shared store at scrape time: the bytes it stores (the
    ledger its storage quota is checked against) and its queued + running jobs (the count its
    active-jobs limit is checked against). Both are per-owner point reads in either store."""

    def __init__(self, backend, labels: dict[str, str]):
        self.b = backend
        self.labels = labels

    def collect(self):
        used = GaugeMetricFamily(
            "gsa_tenant_storage_bytes", "Bytes of uploads and job artifacts a tenant stores", labels=["tenant"]
        )
        active = GaugeMetricFamily("gsa_tenant_active_jobs", "A tenant's queued and running jobs", labels=["tenant"])
        try:
            for owner, label in sorted(self.labels.items(), key=lambda kv: kv[1]):
                used.add_metric([label], self.b.store.usage(owner))
                active.add_metric([label], self.b.store.active_jobs(owner))
        except store_errors():
            # as _StoreCollector: the families go out, without samples, while the store cannot answer
            used = GaugeMetricFamily(used.name, used.documentation, labels=["tenant"])
            active = GaugeMetricFamily(active.name, active.documentation, labels=["tenant"])
        yield used
        yield active


class Metrics:
    def __init__(self, backend):
        self.registry = CollectorRegistry()
        self.requests = Counter(
            "gsa_http_requests",
            "HTTP requests",
            ["method", "route", "status"],
            registry=self.registry,
        )
        self.latency = Histogram(
            "gsa_http_request_duration_seconds",
            "HTTP request latency",
            ["method", "route"],
            registry=self.registry,
            buckets=(
                0.001,
                0.0025,
                0.005,
                0.01,
                0.025,
                0.05,
                0.1,
                0.25,
                0.5,
                1,
                2.5,
                10,
            ),
        )
        self.jobs_created = Counter("gsa_jobs_created", "Jobs created", ["api"], registry=self.registry)
        self.registry.register(_StoreCollector(backend))
        self.tenants = tenant_labels(backend.settings)
        self.tenant_requests = Counter(
            "gsa_tenant_http_requests",
            "HTTP requests of a tenant (a valid key) by status class",
            ["tenant", "status_class"],
            registry=self.registry,
        )
        self.tenant_refusals = Counter(
            "gsa_tenant_refusals",
            "Requests refused by a tenant limit: rate_limited (429), active_jobs (429), storage_quota (507)",
            ["tenant", "reason"],
            registry=self.registry,
        )
        self.tenant_jobs_created = Counter(
            "gsa_tenant_jobs_created", "Jobs a tenant created", ["tenant", "api"], registry=self.registry
        )
        # Every configured tenant's series exist from the start (at 0), so a first refusal is an
        # increase Prometheus' rate()/increase() can see.
        for label in self.tenants.values():
            for reason in REFUSAL_REASONS:
                self.tenant_refusals.labels(label, reason)
        self.registry.register(_TenantCollector(backend, self.tenants))
        # service.jobs.quotas counts refusals where it raises them, through the backend.
        backend.metrics = self

    def tenant(self, owner: str) -> str | None:
        """The `tenant` label of an owner; None for one the settings do not configure."""
        return self.tenants.get(owner)

    def refused(self, owner: str, reason: str) -> None:
        label = self.tenant(owner)
        if label is not None:
            self.tenant_refusals.labels(label, reason).inc()

    def request_done(self, owner: str, status: int) -> None:
        label = self.tenant(owner)
        if label is not None:
            self.tenant_requests.labels(label, f"{status // 100}xx").inc()

    def job_created(self, api: str, owner: str) -> None:
        """A job was created (not an Idempotency-Key replay): service-wide and per tenant."""
        self.jobs_created.labels(api).inc()
        label = self.tenant(owner)
        if label is not None:
            self.tenant_jobs_created.labels(label, api).inc()
