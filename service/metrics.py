"""Prometheus metrics: request counters/latency, jobs by state, queue depth,
stage durations. Job/queue/stage numbers are read from the shared store at
scrape time, so every API replica reports the same cluster-wide values."""

from __future__ import annotations

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
