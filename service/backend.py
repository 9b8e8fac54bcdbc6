"""Wires settings into a store, a storage and a queue: the one place that
decides between distributed mode (Redis + RQ) and embedded mode (SQLite +
in-process worker thread)."""

from __future__ import annotations

import logging
import shutil
import tempfile
import threading
import time
import uuid
from dataclasses import dataclass, field
from datetime import timedelta
from pathlib import Path

from service.settings import Settings, get_settings
from service.storage import Storage, make_storage
from service.stores.base import JobStore
from service.stores.redis_store import RedisJobStore
from service.stores.sqlite_store import SQLiteJobStore
from service.webhooks.delivery import deliver_with_retries

log = logging.getLogger("gsa.worker")


class RQQueue:
    """RQ on Redis. Chosen over Celery/Dramatiq: Redis-only (no broker zoo),
    small, mature, plain functions as tasks, fork-per-job work horses (a job's
    GPU/CPU memory is returned to the OS when it ends)."""

    def __init__(self, redis_conn, settings: Settings):
        import rq  # lazy: embedded mode runs without RQ installed or loaded

        self.settings = settings
        self.q = rq.Queue(settings.queue_name, connection=redis_conn)
        self.hooks = rq.Queue(settings.queue_name + "-webhooks", connection=redis_conn)

    def enqueue(self, job_id: str, delay_s: float = 0.0) -> str:
        """Send the job to the workers, now or (a retry's back-off) after delay_s, through
        RQ's scheduler, which every `gsa worker` runs (the message is "scheduled" meanwhile,
        which the reaper does not count as lost)."""
        ref = f"{job_id}-{uuid.uuid4().hex[:8]}"
        kw = dict(job_id=ref, **self.task_options())
        task = "service.worker.run_job"  # by name: workers of any version resolve it
        if delay_s > 0:
            self.q.enqueue_in(timedelta(seconds=delay_s), task, job_id, **kw)
        else:
            self.q.enqueue(task, job_id, **kw)
        return ref

    def task_options(self) -> dict:
        """RQ options of a job's tasks (the job itself, a many job's edges)."""
        # Our own lease/reaper does retries; RQ's timeout is only the backstop.
        return dict(job_timeout=int(self.settings.job_timeout_s + 120), result_ttl=600, failure_ttl=24 * 3600)

    def lost(self, ref: str | None) -> bool:
        """True if RQ no longer holds a live message for this ref (dropped, failed,
        or "started" by a worker that died before claiming the job), or none was ever
        sent (ref None: the API died, or Redis went, between creating the job and
        enqueuing it), or a retry's delayed message is long overdue (see below)."""
        from rq.exceptions import NoSuchJobError  # lazy: see RQQueue.__init__
        from rq.job import Job as RQJob

        if ref is None:
            return True
        try:
            status = RQJob.fetch(ref, connection=self.q.connection).get_status(refresh=False)
        except NoSuchJobError:
            return True
        status = str(getattr(status, "value", status))
        if status == "queued":
            # A worker on several queues (ours: webhooks + jobs) dequeues with BLPOP; one
            # killed before it marks the message started leaves it "queued" in no list.
            r = self.q.connection
            return r.lpos(self.q.key, ref) is None and r.lpos(self.q.intermediate_queue_key, ref) is None
        if status == "scheduled":
            # RQ's scheduler runs in one worker holding a lock that lapses 61 s after that
            # worker dies (SIGKILL, OOM), and the others retry taking it every 10 s
            # (service.worker.runners): meanwhile a retry's back-off message stays "scheduled"
            # past its time. One overdue by more than two leases is re-sent now (a duplicate
            # delivery is harmless: the claim is a compare-and-set).
            due = self.q.connection.zscore(self.q.scheduled_job_registry.key, ref)
            return due is None or due < time.time() - 2 * self.settings.lease_s
        return status != "deferred"

    def enqueue_webhook(self, job_id: str) -> None:
        from rq import Retry  # lazy: see RQQueue.__init__

        n = max(self.settings.webhook_max_attempts - 1, 0)
        self.hooks.enqueue(
            "service.webhooks.deliver_job",
            job_id,
            retry=Retry(max=n, interval=[1, 5, 30, 120, 600][: max(n, 1)]) if n else None,
            job_timeout=60,
            result_ttl=600,
        )

    def depth(self) -> int:
        return len(self.q)


class EmbeddedQueue:
    """The SQLite store is the queue; this only wakes the worker thread."""

    def __init__(self, store: JobStore, settings: Settings):
        self.store, self.settings = store, settings
        self.wake = threading.Event()

    def enqueue(self, job_id: str, delay_s: float = 0.0) -> str | None:
        # A delayed job waits in the store: its next_attempt_at keeps the workers off it.
        self.wake.set()
        return None

    def lost(self, ref: str | None) -> bool:
        return False  # the store is the queue: nothing to lose

    def enqueue_webhook(self, job_id: str) -> None:
        threading.Thread(
            target=deliver_with_retries,
            args=(self.store, job_id, self.settings),
            daemon=True,
        ).start()

    def depth(self) -> int:
        return len(self.store.queued_ids())


@dataclass
class Backend:
    settings: Settings
    store: JobStore
    storage: Storage
    queue: RQQueue | EmbeddedQueue
    redis: object | None = None
    threads: list = field(default_factory=list)

    def ready(self) -> dict[str, bool]:
        return {"store": self.store.ping(), "storage": self.storage.ping(), "disk_space": self.disk_space_ok()}

    def disk_space_ok(self) -> bool:
        """Free space on the local disks a job writes to (job workspaces in the temp
        folder; blobs too with local storage) is at least settings.min_free_bytes: a
        full disk should take the instance out of rotation before jobs fail on it."""
        folders = {Path(tempfile.gettempdir())}
        if self.settings.storage_backend != "s3":
            folders.add(Path(self.settings.storage_root))
        try:
            if not all(shutil.disk_usage(_existing(f)).free >= self.settings.min_free_bytes for f in folders):
                return False
            # With a storage quota (GSA_STORAGE_QUOTA_BYTES), what is left of it counts too.
            quota_free = getattr(self.storage, "free_bytes", lambda: None)()
            return quota_free is None or quota_free >= min(self.settings.min_free_bytes, self.storage.quota // 10)
        except OSError:
            return False


def _existing(folder: Path) -> Path:
    while not folder.exists() and folder != folder.parent:
        folder = folder.parent
    return folder


def make_backend(settings: Settings | None = None) -> Backend:
    settings = settings or get_settings()
    storage = make_storage(settings)
    if settings.redis_url:
        import redis  # lazy: embedded mode needs no Redis client

        r = redis.Redis.from_url(settings.redis_url, health_check_interval=30)
        store = RedisJobStore(r)
        return Backend(settings, store, storage, RQQueue(r, settings), redis=r)
    store = SQLiteJobStore(settings.sqlite_file)
    return Backend(settings, store, storage, EmbeddedQueue(store, settings))


_process_backend: Backend | None = None


def process_backend(settings: Settings | None = None) -> Backend:
    """The backend of this process, made on first use from `settings` (default: the
    environment's): what RQ tasks (job runs, webhook deliveries) use, since RQ passes
    them only ids. `gsa worker` makes it from its flags before it forks work horses,
    which inherit it."""
    global _process_backend
    if _process_backend is None:
        _process_backend = make_backend(settings)
    return _process_backend


def notify_webhook(backend: Backend, job_id: str) -> None:
    """Queue the job's completion webhook, if it asked for one."""
    job = backend.store.get(job_id)
    if job is not None and job.webhook:
        try:
            backend.queue.enqueue_webhook(job_id)
        except Exception:  # a webhook problem never fails a job
            log.exception("could not enqueue webhook for %s", job_id)
