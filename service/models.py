"""Job and asset records: what the stores keep and the front ends describe."""

from __future__ import annotations

import uuid
from enum import Enum
from typing import Any

from pydantic import BaseModel, Field


class JobState(str, Enum):  # noqa: UP042 - StrEnum would change str(member) in stored records and logs
    queued = "queued"
    running = "running"
    succeeded = "succeeded"
    failed = "failed"
    cancelled = "cancelled"


TERMINAL = {JobState.succeeded, JobState.failed, JobState.cancelled}


class InputRef(BaseModel):
    asset_id: str
    key: str
    kind: str  # "ply" | "images"
    filename: str | None = None


class Artifact(BaseModel):
    name: str
    key: str
    size: int
    content_type: str


class Job(BaseModel):
    id: str
    owner: str
    state: JobState = JobState.queued
    stage: str | None = None
    progress: float = 0.0
    created_at: float
    updated_at: float
    started_at: float | None = None
    finished_at: float | None = None
    attempts: int = 0
    max_attempts: int = 3
    sources: list[InputRef]
    target: InputRef
    options: dict[str, Any] = Field(default_factory=dict)
    webhook: dict[str, Any] | None = None
    idempotency_key: str | None = None
    error: dict[str, Any] | None = None
    result: dict[str, Any] | None = None
    artifacts: list[Artifact] = Field(default_factory=list)
    cancel_requested: bool = False
    run_token: str | None = None
    lease_until: float | None = None
    worker: str | None = None
    # The queue's own handle (RQ job id) and when it was last enqueued: lets the
    # reaper notice a queue message lost before any worker claimed the job.
    queue_ref: str | None = None
    enqueued_at: float | None = None
    # A retry after an infrastructure error waits (exponential back-off with jitter): the
    # earliest time its next attempt may start; None when it may start at once.
    next_attempt_at: float | None = None
    # Guided alignment: the job this one refines (POST /v1/jobs/{id}:refine) and the jobs that refine this one.
    parent_job: str | None = None
    children: list[str] = Field(default_factory=list)
    version: int = 0

    @property
    def terminal(self) -> bool:
        return self.state in TERMINAL


class Asset(BaseModel):
    id: str
    owner: str
    kind: str
    key: str
    size: int
    filename: str | None = None
    content_type: str
    n_gaussians: int | None = None
    n_images: int | None = None
    sha256: str
    created_at: float


def new_id(prefix: str) -> str:
    return f"{prefix}_{uuid.uuid4().hex}"
