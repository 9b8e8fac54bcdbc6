"""Deleting jobs and assets, and the retention sweep that does it on a schedule.

A job is deleted only once it is final (queued and running jobs answer 409:
cancel first), with every attempt's artifacts. An asset is deleted only while
no queued or running job uses it (409), and its bytes go with the last asset
that references them (uploads are content-addressed, see service.jobs.core.blob_key).

Retention (settings.retention_days > 0): finished jobs older than that, and
assets older than that which no remaining job refers to, are deleted by a
sweep every retention_sweep_interval_s. It runs in the API process (both
modes have one); several API replicas sweeping at once is harmless, every
step is idempotent.
"""

from __future__ import annotations

import logging
import threading
import time

from service.backend import Backend
from service.jobs import core, quotas
from service.models import Job, JobState
from service.problems import Problem, infrastructure_problem

log = logging.getLogger("gsa.retention")


def delete_job(b: Backend, owner: str, job_id: str) -> None:
    job = core.get_job(b, owner, job_id)
    if not job.terminal:
        raise Problem(
            409,
            "job-not-finished",
            "Job not finished",
            f"job {job_id} is {job.state.value}; cancel it first (POST /v1/jobs/{job_id}:cancel), "
            "then delete it once it is cancelled",
        )
    _remove_job(b, job)


def _remove_job(b: Backend, job: Job) -> None:
    # Artifacts first: if this fails the record stays and the DELETE can be retried.
    b.storage.delete_prefix(f"jobs/{job.id}")
    quotas.forget(b, job.owner, f"job:{job.id}")
    b.store.delete(job.id)


def _job_using(b: Backend, asset_id: str) -> str | None:
    """A queued or running job that reads this asset, if any."""
    live = [b.store.get(i) for i in b.store.queued_ids()] + b.store.running()
    for job in live:
        if job is not None and not job.terminal and asset_id in _asset_ids(job):
            return job.id
    return None


def _asset_ids(job: Job) -> set[str]:
    return {ref.asset_id for ref in job.sources} | {job.target.asset_id}


def _in_use(asset_id: str, job_id: str) -> Problem:
    return Problem(
        409,
        "asset-in-use",
        "Asset in use",
        f"asset {asset_id} is an input of job {job_id}, which has not finished; "
        "cancel the job or wait for it, then delete the asset",
        job_id=job_id,
    )


def delete_asset(b: Backend, owner: str, asset_id: str) -> None:
    asset = core.get_asset(b, owner, asset_id)
    if (user := _job_using(b, asset_id)) is not None:
        raise _in_use(asset_id, user)
    b.store.delete_asset(asset_id)
    # A job created between the check and the delete found the asset: put it back.
    if (user := _job_using(b, asset_id)) is not None:
        b.store.put_asset(asset)
        raise _in_use(asset_id, user)
    core.release_blob(b, asset)


def sweep(b: Backend, now: float | None = None) -> dict[str, int]:
    """One retention pass: {"jobs": n, "assets": n} deleted."""
    days = b.settings.retention_days
    if not days or days <= 0:
        return {"jobs": 0, "assets": 0}
    cutoff = (now or time.time()) - days * 86400
    removed = {"jobs": 0, "assets": 0}
    referenced: set[str] = set()
    for job in b.store.jobs():
        ended = job.finished_at or job.updated_at
        if job.state in (JobState.succeeded, JobState.failed, JobState.cancelled) and ended < cutoff:
            _remove_job(b, job)
            removed["jobs"] += 1
        else:
            referenced |= _asset_ids(job)
    for asset_id in b.store.asset_ids():
        if asset_id in referenced:
            continue
        asset = b.store.get_asset(asset_id)
        if asset is None or asset.created_at >= cutoff or _job_using(b, asset_id) is not None:
            continue
        b.store.delete_asset(asset_id)
        core.release_blob(b, asset)
        removed["assets"] += 1
    if removed["jobs"] or removed["assets"]:
        log.info("retention: deleted %d job(s) and %d asset(s) older than %g days", *removed.values(), days)
    return removed


def start_retention(b: Backend, stop: threading.Event) -> threading.Thread | None:
    """The sweep thread (None when retention is off): a pass at start, then every interval."""
    if not b.settings.retention_days or b.settings.retention_days <= 0:
        return None

    def loop():
        while True:
            try:
                sweep(b)
            except Exception as exc:  # last resort: the sweep thread outlives any one failed pass
                if infrastructure_problem(exc) is not None:  # Redis down, disk trouble: next pass
                    log.warning("retention sweep failed: %s: %s", type(exc).__name__, exc)
                else:
                    log.exception("retention sweep failed")
            if stop.wait(b.settings.retention_sweep_interval_s):
                return

    t = threading.Thread(target=loop, name="gsa-retention", daemon=True)
    t.start()
    return t
