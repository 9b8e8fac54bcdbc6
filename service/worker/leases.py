"""Who owns a running job: leases, heartbeats, progress reports, the reaper.

Delivery is at-least-once. A worker claims a queued job by compare-and-set
(state queued -> running, attempts + 1, a fresh run_token, a lease) and keeps
renewing the lease from a heartbeat thread. If the worker dies (SIGKILL, OOM,
machine lost) the lease expires and any reaper (every API process and every
worker runs one) puts the job back in the queue, or fails it once
max_attempts is spent, so no job stays "running" forever. Every write a worker
makes is conditional on its run_token, so a worker that was presumed dead but
comes back cannot overwrite the job's newer attempt.
"""

from __future__ import annotations

import logging
import os
import re
import shutil
import socket
import tempfile
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager, nullcontext
from pathlib import Path

from service.backend import Backend, notify_webhook
from service.jobs import quotas
from service.models import Job, JobState
from service.problems import Problem, infrastructure_problem, store_errors
from service.worker.interrupt import Interrupter

log = logging.getLogger("gsa.worker")


class JobCancelled(Exception):
    """The client cancelled the job: stop the attempt, mark it cancelled."""


class LeaseLost(Exception):
    """This attempt no longer owns the job (lease expired, newer attempt): stop, write nothing."""


class JobTimeout(Exception):
    """The attempt ran past job_timeout_s: stop and fail the job (504)."""


def worker_name() -> str:
    return f"{socket.gethostname()}:{os.getpid()}"


# Where each library stage sits in a job's overall 0..1 progress (the library
# reports a fraction per stage); unknown stages hold the current value, so the
# published progress never goes backwards.
STAGE_SPAN = {
    "loading": (0.0, 0.05), "features": (0.05, 0.2), "hypotheses": (0.2, 0.4), "coarse": (0.4, 0.7),
    "refine": (0.7, 0.8), "semantic": (0.8, 0.97), "fine": (0.8, 0.97), "writing": (0.97, 0.99), "renders": (0.97, 0.99), "done": (0.97, 0.99),
    "storing": (0.99, 0.999),
}  # fmt: skip


# Image-set inputs: gsa.recon's stages ("recon:sfm:features" -> "sfm") come first.
RECON_SPAN = {
    "images": (0.0, 0.02),
    "sfm": (0.02, 0.1),
    "masks": (0.1, 0.12),
    "train": (0.12, 0.4),
}


class JobProgress:
    """The progress callback handed to align(): writes stage/progress (throttled),
    records stage durations, and raises to abort on cancel/lease loss/timeout."""

    def __init__(
        self,
        backend: Backend,
        job: Job,
        token: str,
        lost: threading.Event,
        n_parts: int,
    ):
        self.b, self.job_id, self.token, self.lost = backend, job.id, token, lost
        self.n = n_parts
        self.part = 0
        self.started = time.monotonic()
        self.stage: str | None = None
        self.stage_t0 = time.monotonic()
        self.last_write = 0.0
        self.last_check = 0.0
        self.overall = 0.0
        # Shown before the stage while set: a many job's "edge 2/3" (service.jobs.many).
        self.label: str | None = None
        # The heartbeat's stop of the job's thread (service.worker.interrupt), kept out of this
        # callback's store I/O.
        self.interrupter: Interrupter | None = None

    def _shielded(self):
        return self.interrupter.shielded() if self.interrupter is not None else nullcontext()

    def check(self, force: bool = False) -> None:
        with self._shielded():
            self._check(force)

    def _check(self, force: bool) -> None:
        if self.lost.is_set():
            raise LeaseLost()
        if time.monotonic() - self.started > self.b.settings.job_timeout_s:
            raise JobTimeout()
        now = time.monotonic()
        if force or now - self.last_check > 0.2:
            self.last_check = now
            job = self.b.store.get(self.job_id)
            if job is None or job.run_token != self.token:
                raise LeaseLost()
            if job.cancel_requested or job.state == JobState.cancelled:
                raise JobCancelled()

    def set_stage(self, stage: str) -> None:
        if stage != self.stage:
            now = time.monotonic()
            if self.stage is not None:
                self.b.store.record_stage(self.stage, now - self.stage_t0)
            self.stage, self.stage_t0 = stage, now

    def __call__(self, stage: str, fraction: float) -> None:
        with self._shielded():
            self._report(stage, fraction)

    def _report(self, stage: str, fraction: float) -> None:
        changed = stage != self.stage
        self.set_stage(stage)
        self.check(force=changed)
        now = time.monotonic()
        if changed or now - self.last_write > 0.2:
            self.last_write = now
            f = max(0.0, min(1.0, float(fraction)))
            key = stage.split(":")[1] if stage.startswith("recon:") else stage
            span = RECON_SPAN if stage.startswith("recon:") else STAGE_SPAN
            lo, hi = span.get(key, (None, None))
            within = (lo + f * (hi - lo)) if lo is not None else (self.overall * self.n - self.part)
            # 1.0 is kept for "succeeded"; a running job's progress stays below it.
            self.overall = min(max(self.overall, (self.part + within) / self.n), 0.999)
            # A progress report renews the lease too: a second renewer besides the heartbeat thread.
            self.b.store.update(
                self.job_id,
                states={JobState.running},
                token=self.token,
                stage=f"{self.label}: {stage}" if self.label else stage,
                progress=self.overall,
                lease_until=time.time() + self.b.settings.lease_s,
            )

    def finish(self) -> None:
        self.set_stage("__end__")


# How often the heartbeat reads a running job's record for a cancel (the lease renews less often).
CANCEL_POLL_S = 0.5


def heartbeat(
    backend: Backend,
    job_id: str,
    token: str,
    lost: threading.Event,
    stop: threading.Event,
    interrupter: Interrupter | None = None,
    deadline: float | None = None,
) -> None:
    """Thread body: renew the lease every lease_s/3 until `stop`; set `lost` once
    the store refuses (another attempt owns the job now). A failed renewal (store
    unreachable for a moment) is retried after a tenth of the lease, not a third.
    With an `interrupter`, also read the job every CANCEL_POLL_S and stop the job's
    thread on a cancel, a lost lease, or past `deadline` (time.monotonic()): where the
    library reports no progress for seconds, the progress callback cannot (service.worker.interrupt)."""
    lease = backend.settings.lease_s
    renew_every = lease / 3
    next_renewal = time.monotonic() + renew_every
    tick = CANCEL_POLL_S if interrupter is not None else renew_every
    while not stop.wait(min(tick, max(0.0, next_renewal - time.monotonic()))):
        if interrupter is not None and interrupter.requested is None:
            reason = _stop_reason(backend, job_id, token, deadline)
            if reason is not None:
                interrupter.interrupt(reason)
        if time.monotonic() < next_renewal:
            continue
        try:
            ok = backend.store.update(
                job_id,
                states={JobState.running},
                token=token,
                lease_until=time.time() + lease,
            )
        except store_errors() as exc:  # transient store error: the lease has slack for a few quick retries
            log.warning("lease renewal failed for %s: %s: %s", job_id, type(exc).__name__, exc)
            next_renewal = time.monotonic() + lease / 10
            continue
        next_renewal = time.monotonic() + renew_every
        if not ok:
            lost.set()
            if interrupter is not None:
                interrupter.interrupt(LeaseLost)
            return


def _stop_reason(backend: Backend, job_id: str, token: str, deadline: float | None) -> type[Exception] | None:
    """Why the attempt must stop now (JobTimeout, LeaseLost, JobCancelled), or None; a store
    that cannot answer is no reason (the lease renewal copes with that)."""
    if deadline is not None and time.monotonic() > deadline:
        return JobTimeout
    try:
        job = backend.store.get(job_id)
    except store_errors():
        return None
    if job is None or job.run_token != token:
        return LeaseLost
    if job.cancel_requested or job.state == JobState.cancelled:
        return JobCancelled
    return None


def finish_attempt(backend: Backend, job_id: str, token: str, state: JobState, **fields) -> bool:
    """End this attempt in `state`; False if the attempt no longer owns the job.
    An error's worker temp paths become the names of the client's assets."""
    if isinstance(fields.get("error"), dict):
        from service.jobs.inputs import redact_problem  # lazy: inputs loads numpy

        job = backend.store.get(job_id)
        if job is not None:
            fields["error"] = redact_problem(fields["error"], job)
    ok = backend.store.update(
        job_id,
        states={JobState.running},
        token=token,
        state=state,
        finished_at=time.time(),
        lease_until=None,
        **fields,
    )
    if ok and fields.get("artifacts"):
        # The artifacts count against their owner's storage quota (service.jobs.quotas) until the job is deleted.
        job = backend.store.get(job_id)
        if job is not None:
            try:
                quotas.record(backend, job.owner, f"job:{job_id}", sum(a.size for a in job.artifacts))
            except store_errors():  # never fails a finished job; the tenant's count is short by this job
                log.warning("could not count job %s's artifacts against %s's quota", job_id, job.owner)
    return ok


# ------------------------------------------------------------------ reaper
def reap(backend: Backend, *, force: bool = False) -> list[str]:
    """Requeue (or fail, when attempts are spent) running jobs whose lease expired.

    force=True treats every running job as lost: embedded mode at startup, where
    the only possible worker was the previous process.
    """
    now = time.time()
    touched = []
    for job in backend.store.running():
        if not force and job.lease_until is not None and job.lease_until > now:
            continue
        common = dict(
            states={JobState.running},
            token=job.run_token,
            lease_until=None,
            worker=None,
        )
        if job.cancel_requested:
            ok = backend.store.update(job.id, state=JobState.cancelled, finished_at=now, **common)
        elif job.attempts >= job.max_attempts:
            err = Problem(
                500,
                "worker-lost",
                "Job failed",
                f"the worker running this job was lost {job.attempts} times; giving up",
            ).to_dict()
            ok = backend.store.update(job.id, state=JobState.failed, finished_at=now, error=err, **common)
        else:
            ok = backend.store.update(
                job.id,
                state=JobState.queued,
                stage="requeued",
                run_token=None,
                **common,
            )
            if ok:
                backend.queue.enqueue(job.id)
        if ok:
            log.warning(
                "reaped job %s (attempt %d, worker %s)",
                job.id,
                job.attempts,
                job.worker,
            )
            touched.append(job.id)
            _discard_lost_artifacts(backend, job.id, job.run_token)
            if job.cancel_requested or job.attempts >= job.max_attempts:
                notify_webhook(backend, job.id)
    return touched


def attempt_artifacts(job_id: str, token: str) -> str:
    """The storage prefix one attempt (run token) of a job stores its artifacts under."""
    return f"jobs/{job_id}/{token}"


def _discard_lost_artifacts(backend: Backend, job_id: str, token: str | None) -> None:
    """What a lost attempt stored before it died goes with it: an attempt removes its own set
    when it does not succeed, but one killed between storing its artifacts and finishing cannot,
    and the next attempt's set would then be the job's second (seen once in the chaos test: a
    worker SIGKILLed in that window). An attempt still alive past its lease removes what it
    stores later itself: its finish fails on the token."""
    if not token:
        return
    try:
        backend.storage.delete_prefix(attempt_artifacts(job_id, token))
    except Exception:  # storage down: the set stays, the job is requeued all the same
        log.exception("job %s: could not remove the lost attempt's artifacts", job_id)


def _requeue(backend: Backend, job_id: str) -> None:
    ref = backend.queue.enqueue(job_id)
    backend.store.update(job_id, queue_ref=ref, enqueued_at=time.time())


def resend_lost(backend: Backend) -> list[str]:
    """Queued jobs whose queue message is gone (e.g. the worker died between
    dequeuing and claiming) or was never sent (the API SIGKILLed between creating
    the job and enqueuing it: the client's retry with its Idempotency-Key finds that
    job, so nothing else would ever send it) are enqueued again. Duplicates are
    harmless: the claim is a compare-and-set, so only one delivery ever runs the job."""
    now = time.time()
    grace = 2 * backend.settings.lease_s
    out = []
    for job_id in backend.store.queued_ids():
        job = backend.store.get(job_id)
        if job is None or job.state != JobState.queued:
            continue
        if now - (job.enqueued_at or job.created_at) < grace:
            continue
        if job.next_attempt_at is not None and job.next_attempt_at > now:
            continue  # waiting out a back-off (its message is scheduled)
        if backend.queue.lost(job.queue_ref):
            log.warning("re-sending lost queue message for job %s", job_id)
            _requeue(backend, job_id)
            out.append(job_id)
    return out


WORKSPACE_PREFIX = "gsa-job-"


@contextmanager
def job_workspace(job_id: str, token: str) -> Iterator[Path]:
    """The attempt's temp folder, <tmp>/gsa-job-<job id>-<token[:12]>-<random>, removed
    on every way out (success, failure, cancel, lease lost, timeout, and SIGTERM of
    the work horse, which run_job turns into SystemExit). What a SIGKILL leaves behind
    is swept by service.worker.leases.sweep_workspaces (its name says whose it was)."""
    d = Path(tempfile.mkdtemp(prefix=f"{WORKSPACE_PREFIX}{job_id}-{token[:12]}-"))
    try:
        yield d
    finally:
        shutil.rmtree(d, ignore_errors=True)


_WORKSPACE = re.compile(rf"^{re.escape(WORKSPACE_PREFIX)}(job_[0-9a-f]+)-([0-9a-f]{{12}})-")


def sweep_workspaces(backend: Backend, root: str | os.PathLike | None = None) -> list[Path]:
    """Remove job temp folders (<tmp>/gsa-job-*) that no live attempt owns: left by
    a work horse or worker that was SIGKILLed, or a process that died mid-job.

    A folder is stale once it is older than the lease and its attempt (job id and
    run token in its name) no longer runs the job (reaped, finished); a folder whose
    job this store does not know (another deployment on the machine, an older
    naming) only after job_timeout_s + lease_s. Runs at worker start-up
    and on every reaper pass."""
    s = backend.settings
    now = time.time()
    removed = []
    for d in Path(root or tempfile.gettempdir()).glob(f"{WORKSPACE_PREFIX}*"):
        try:
            age = now - d.stat().st_mtime
        except OSError:
            continue
        if age < s.lease_s or not d.is_dir():
            continue
        m = _WORKSPACE.match(d.name)
        job = backend.store.get(m.group(1)) if m else None
        if job is not None:
            # Still this attempt's job: leave it, even with a lapsed lease (a heartbeat
            # late under load renews it). A dead worker's job is reaped soon (fresh
            # token or a final state), and then its folder goes.
            if job.state == JobState.running and (job.run_token or "").startswith(m.group(2)):
                continue
        elif age < s.job_timeout_s + s.lease_s:
            # Not a job of this store (another deployment sharing the machine's temp
            # folder, or an older naming): only once no attempt can still be running.
            continue
        shutil.rmtree(d, ignore_errors=True)
        log.warning("removed stale job workspace %s", d)
        removed.append(d)
    return removed


def start_reaper(backend: Backend, stop: threading.Event) -> threading.Thread:
    def loop():
        while not stop.wait(backend.settings.reaper_interval_s):
            try:
                reap(backend)
                resend_lost(backend)
                sweep_workspaces(backend)
            except Exception as exc:  # last resort: the reaper thread outlives any one failed pass
                if infrastructure_problem(exc) is not None:  # Redis down, disk trouble: one line, not a traceback
                    log.warning("reaper pass failed: %s: %s", type(exc).__name__, exc)
                else:
                    log.exception("reaper pass failed")

    t = threading.Thread(target=loop, name="gsa-reaper", daemon=True)
    t.start()
    return t
