"""Request/response models: the public HTTP contract (and its OpenAPI)."""

from __future__ import annotations

import logging
from datetime import UTC, datetime
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from service.api.results import JobResult
from service.jobs.options import AlignOptionsIn, hint_field
from service.models import Asset, Job, JobState

log = logging.getLogger("gsa.api")


# The extension members the service puts in its problems (service.problems.Problem's **extra),
# declared so that generated clients type them; each is present only where it applies. Declared in
# the schema only, not as model fields: a job's stored `error` is served as stored, without nulls.
PROBLEM_EXTENSIONS: dict[str, dict[str, Any]] = {
    "errors": {
        "type": "array",
        "description": "validation-error: each failed check (loc: where, msg: what, type: the check)",
        "items": {
            "type": "object",
            "properties": {
                "loc": {"type": "array", "items": {"anyOf": [{"type": "string"}, {"type": "integer"}]}},
                "msg": {"type": "string"},
                "type": {"type": "string"},
            },
        },
    },
    "option": {"type": "string", "description": "the job option (or request field) that was refused"},
    "value": {"description": "the refused value (e.g. the predicted memory in MB for option 'memory')"},
    "minimum": {"type": "number", "description": "the option's smallest allowed value"},
    "exclusive_minimum": {"type": "number", "description": "the option must be above this"},
    "maximum": {"type": "number", "description": "the option's largest allowed value"},
    "allowed": {"type": "array", "items": {}, "description": "the values the option may take"},
    "expected": {"type": "string", "description": "the shape a guidance option must have"},
    "conflicts_with": {"type": "string", "description": "the option this one may not be given with"},
    "job_id": {"type": "string", "description": "asset-in-use: the queued or running job that reads the asset"},
    "limit": {"type": "number", "description": "rate-limited: requests a second; too-many-jobs: active jobs"},
    "active": {"type": "integer", "description": "too-many-jobs: the tenant's queued and running jobs"},
    "quota": {"type": "integer", "description": "storage-quota-exceeded: the tenant's quota in bytes"},
    "used": {"type": "integer", "description": "storage-quota-exceeded: the bytes the tenant stores"},
    "retry_after": {"type": "integer", "description": "429: seconds until a retry may succeed (as Retry-After)"},
    "checks": {
        "type": "object",
        "additionalProperties": {"type": "boolean"},
        "description": "not-ready: each readiness check and whether it passed",
    },
}


def _problem_schema(schema: dict[str, Any]) -> None:
    schema["properties"].update(PROBLEM_EXTENSIONS)


class Problem(BaseModel):
    """RFC 9457 problem details (media type application/problem+json): `type`, `title`,
    `status`, `detail`, `instance` and the service's extension members."""

    model_config = ConfigDict(extra="allow", json_schema_extra=_problem_schema)
    type: str = Field(examples=["https://gsa.dev/problems/not-found"])
    title: str
    status: int
    detail: str | None = None
    instance: str | None = None


class RefineIn(BaseModel):
    """POST /v1/jobs/{id}:refine: where the follow-up job starts (exactly one of alternative,
    init_transform, point_pairs) and, optionally, new up_axes / front_axes / fixed_scale (null
    drops the parent's; new up_axes without front_axes drop the parent's fronts). Checked by service.jobs.core.refine_options and service.jobs.options (422 naming the field)."""

    model_config = ConfigDict(extra="forbid")
    alternative: Any = Field(None, description="index into the parent result's metrics.alternatives", examples=[0])
    init_transform: Any = hint_field("init_transform", "start from this pose")
    point_pairs: Any = hint_field("point_pairs", "start from these picked pairs")
    up_axes: Any = hint_field("up_axes", "keep these up axes aligned")
    front_axes: Any = hint_field("front_axes", "with up_axes: turn about up only where these fronts agree")
    fixed_scale: Any = Field(None, description="the answer's scale (null: free)", json_schema_extra={"type": "number"})


class WebhookIn(BaseModel):
    url: str = Field(description="called with POST {job_id, state, ...} when the job reaches a final state")
    secret: str | None = Field(None, description="HMAC-SHA256 key for X-GSA-Signature (else the server's)")


class JobCreate(BaseModel):
    """JSON form of POST /v1/jobs: previously uploaded asset ids."""

    model_config = ConfigDict(extra="forbid")
    source: str | None = Field(None, description="source asset id (pair job)")
    sources: list[str] | None = Field(None, description="N source asset ids aligned to one target (multi-model)")
    target: str = Field(description="target (reference) asset id")
    options: AlignOptionsIn = Field(default_factory=AlignOptionsIn)
    webhook: WebhookIn | None = None


class ArtifactOut(BaseModel):
    name: str
    size: int
    content_type: str
    href: str


class JobOut(BaseModel):
    id: str
    state: JobState
    stage: str | None
    progress: float = Field(description="0..1")
    created_at: datetime
    updated_at: datetime
    started_at: datetime | None
    finished_at: datetime | None
    attempts: int
    max_attempts: int
    next_attempt_at: datetime | None = Field(
        None,
        description="a job waiting to be retried after an infrastructure error (back-off): "
        "the earliest time its next attempt starts",
    )
    cancel_requested: bool
    sources: list[str] = Field(description="source asset ids")
    target: str = Field(description="target asset id")
    options: dict[str, Any]
    error: Problem | None = None
    result: JobResult | None = Field(
        None,
        description="when succeeded: transform (4x4 row-major, x_t = s R x_s + t), scale, rotation (3x3), "
        "quaternion (wxyz), translation, metrics, timings; `results` lists one entry per source",
    )
    artifacts: list[ArtifactOut] = Field(default_factory=list)
    parent_job: str | None = Field(None, description="the job this one refines (POST /v1/jobs/{id}:refine)")
    children: list[str] = Field(default_factory=list, description="the jobs that refine this one, oldest first")
    links: dict[str, str]

    @classmethod
    def from_job(cls, job: Job) -> JobOut:
        def ts(t):
            return None if t is None else datetime.fromtimestamp(t, UTC)

        base = f"/v1/jobs/{job.id}"
        return cls(
            id=job.id,
            state=job.state,
            stage=job.stage,
            progress=job.progress,
            created_at=ts(job.created_at),
            updated_at=ts(job.updated_at),
            started_at=ts(job.started_at),
            finished_at=ts(job.finished_at),
            attempts=job.attempts,
            max_attempts=job.max_attempts,
            next_attempt_at=ts(job.next_attempt_at) if job.state == JobState.queued else None,
            cancel_requested=job.cancel_requested,
            sources=[s.asset_id for s in job.sources],
            target=job.target.asset_id,
            options=job.options,
            error=job.error,
            result=_result(job),
            artifacts=[
                ArtifactOut(
                    name=a.name,
                    size=a.size,
                    content_type=a.content_type,
                    href=f"{base}/artifacts/{a.name}",
                )
                for a in job.artifacts
            ],
            parent_job=job.parent_job,
            children=job.children,
            links={
                "self": base,
                "cancel": f"{base}:cancel",
                "refine": f"{base}:refine",
                **({"parent": f"/v1/jobs/{job.parent_job}"} if job.parent_job else {}),
            },
        )


def _result(job: Job) -> JobResult | None:
    if job.result is None:
        return None
    try:
        return JobResult.model_validate(job.result)
    except ValidationError:  # a result stored by another library version: shown as stored
        log.warning("job %s: stored result does not match the JobResult schema", job.id)
        return JobResult.model_construct(**job.result)


class JobList(BaseModel):
    items: list[JobOut]
    next_cursor: str | None = Field(None, description="pass as ?cursor= for the next page; null at the end")


class AssetOut(BaseModel):
    id: str
    kind: Literal["ply", "images"]
    size: int
    filename: str | None
    content_type: str
    sha256: str
    n_gaussians: int | None = None
    n_images: int | None = None
    created_at: datetime

    @classmethod
    def from_asset(cls, a: Asset) -> AssetOut:
        return cls(
            id=a.id,
            kind=a.kind,
            size=a.size,
            filename=a.filename,
            content_type=a.content_type,
            sha256=a.sha256,
            n_gaussians=a.n_gaussians,
            n_images=a.n_images,
            created_at=datetime.fromtimestamp(a.created_at, UTC),
        )


class AssetList(BaseModel):
    items: list[AssetOut]
    next_cursor: str | None = Field(None, description="pass as ?cursor= for the next page; null at the end")


class Health(BaseModel):
    status: str
    checks: dict[str, bool] = Field(default_factory=dict)
