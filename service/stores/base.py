"""What a job store must do: the contract the Redis and SQLite stores both meet.

Every state change is a compare-and-set (`update` with `states`/`token`), so
the API, workers and reapers can write the same job without locks of their own.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import AbstractContextManager
from typing import Protocol

from service.models import Asset, Job, JobState

# An Idempotency-Key is claimed before its job exists (the request's uploads are stored in
# between). If the API process dies or the store goes away in that window, the claim must
# not answer "in progress" for a day: it lives IDEM_PENDING_S until create() gives it
# IDEM_TTL_S. (A request whose uploads take longer than that to store may, retried
# meanwhile, make a second job.) Found by the chaos run: a key stuck after an API SIGKILL.
IDEM_PENDING_S = 120
IDEM_TTL_S = 24 * 3600


class JobStore(Protocol):
    """Jobs, assets, idempotency keys and stage timings; see RedisJobStore and SQLiteJobStore."""

    def create(self, job: Job) -> None: ...

    def get(self, job_id: str) -> Job | None: ...

    def update(
        self,
        job_id: str,
        *,
        states: set[JobState] | None = None,
        token: str | None = None,
        **fields,
    ) -> bool:
        """Set fields iff the job is in one of `states` (any if None) and, if given,
        holds run_token `token`; False when the condition (or the job) is missing."""
        ...

    def list(
        self,
        owner: str,
        state: JobState | None,
        limit: int,
        cursor: tuple[float, str] | None,
    ) -> list[Job]:
        """The owner's jobs, newest first, after `cursor` (created_at, id)."""
        ...

    def running(self) -> list[Job]: ...

    def queued_ids(self) -> list[str]: ...

    def counts(self) -> dict[str, int]:
        """Jobs per state (every state present)."""
        ...

    def claim_idempotency(self, owner: str, key: str, body_hash: str, job_id: str) -> tuple[str, str] | None:
        """Reserve `key` for job_id; if it was taken: (earlier job id, its body hash)."""
        ...

    def release_idempotency(self, owner: str, key: str) -> None: ...

    def delete(self, job_id: str) -> bool:
        """Remove the job record (its owner index, state set and idempotency key with it);
        False if it was not there. Artifacts are the caller's (service.jobs.retention)."""
        ...

    def jobs(self) -> Iterator[Job]:
        """Every job, in no particular order (retention sweeps)."""
        ...

    def asset_ids(self) -> list[str]: ...

    def add_blob_ref(self, key: str, asset_id: str) -> int:
        """Record that asset_id uses the stored blob `key`; returns the number of users."""
        ...

    def remove_blob_ref(self, key: str, asset_id: str) -> int:
        """Forget that asset_id uses `key`; returns how many users remain (0: delete the blob)."""
        ...

    def blob_ref_ids(self, key: str) -> list[str]: ...

    def blob_lock(self, key: str) -> AbstractContextManager:
        """Held while a blob's references are changed together with its bytes (the last
        reference dropped and the blob deleted; a reference added and the blob checked),
        so an upload reusing a blob and a delete of its last other user cannot interleave."""
        ...

    def put_asset(self, asset: Asset) -> None: ...

    def delete_asset(self, asset_id: str) -> None: ...

    def get_asset(self, asset_id: str) -> Asset | None: ...

    def list_assets(self, owner: str, limit: int, cursor: tuple[float, str] | None) -> list[Asset]:
        """The owner's assets, newest first, after `cursor` (created_at, id), as `list` pages jobs:
        a tenant finds (and can free) an asset whose id it lost."""
        ...

    def active_jobs(self, owner: str) -> int:
        """The owner's queued and running jobs (service.jobs.quotas: GSA_TENANT_MAX_ACTIVE_JOBS)."""
        ...

    def set_usage(self, owner: str, item: str, nbytes: int) -> int:
        """Count `nbytes` stored for `item` (a blob key, job:<id>) against the owner, replacing
        what the item counted before (so a retried write counts once); returns the owner's total."""
        ...

    def drop_usage(self, owner: str, item: str) -> int:
        """The item's bytes are gone; returns the owner's total."""
        ...

    def usage(self, owner: str) -> int:
        """Bytes the owner stores (what set_usage counted, less what drop_usage removed)."""
        ...

    def record_stage(self, stage: str, seconds: float) -> None: ...

    def stage_stats(self) -> dict[str, tuple[int, float]]:
        """{stage: (count, total seconds)}"""
        ...

    def ping(self) -> bool: ...
