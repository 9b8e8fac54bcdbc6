"""Request/response models: the public HTTP contract (and its OpenAPI)."""

from __future__ import annotations

import logging
from datetime import UTC, datetime
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from service.api.results import JobResult
from service.models import Asset, Job, JobState
from service.options import GUIDANCE_SHAPES, OPTION_BOUNDS, OutputName, check_option_values

log = logging.getLogger("gsa.api")


class Problem(BaseModel):
    """RFC 9457 problem details (media type application/problem+json)."""

    model_config = ConfigDict(extra="allow")
    type: str = Field(examples=["https://gsa.dev/problems/not-found"])
    title: str
    status: int
    detail: str | None = None
    instance: str | None = None


def _bounded(name: str, description: str | None = None, **kw):
    """A field whose documented bounds come from service.options (which enforces them)."""
    return Field(None, description=description, json_schema_extra=OPTION_BOUNDS[name].json_schema(), **kw)


_HINT_SCHEMAS: dict[str, dict[str, Any]] = {
    "init_transform": {
        "type": "array",
        "items": {"type": "array", "items": {"type": "number"}, "minItems": 4, "maxItems": 4},
        "minItems": 4,
        "maxItems": 4,
    },
    "point_pairs": {
        "type": "object",
        "properties": {
            k: {"type": "array", "items": {"type": "array", "items": {"type": "number"}, "minItems": 3, "maxItems": 3}}
            for k in ("source", "target")
        },
        "required": ["source", "target"],
    },
    "up_axes": {
        "type": "array",
        "items": {"type": "array", "items": {"type": "number"}, "minItems": 3, "maxItems": 3},
        "minItems": 2,
        "maxItems": 2,
    },
}


def _hint(name: str, description: str):
    """A guidance field: documented in OpenAPI, checked by service.options.check_guidance_options."""
    return Field(None, description=f"{description}; {GUIDANCE_SHAPES[name]}", json_schema_extra=_HINT_SCHEMAS[name])


class AlignOptionsIn(BaseModel):
    """Alignment options; fields not listed (e.g. fine_*) pass through to the
    library's AlignOptions and are rejected with 422 if it does not know them.
    Types, bounds and choices are checked by service.options (422 invalid-input
    naming the option and its bound)."""

    model_config = ConfigDict(extra="allow")
    stages: list[str] | None = Field(None, examples=[["coarse", "fine"]], description="auto | coarse | coarse,fine")
    features: str | None = Field(None, description="feature backend: auto | canonical | spheremap | dinov2")
    tau_f: float | None = _bounded("tau_f", "feature-match threshold τ_f")
    coarse_iterations: int | None = _bounded("coarse_iterations")
    seed: int | None = _bounded("seed")
    fine_views: int | None = _bounded("fine_views", "fine stage: rendered views")
    fine_image_size: int | None = _bounded("fine_image_size", "fine stage: render size in pixels (square)")
    fine_iterations: int | None = _bounded(
        "fine_iterations",
        "fine stage: optimiser steps; fine_views × fine_image_size² × fine_iterations is also capped "
        "per job (GSA_MAX_FINE_WORK)",
    )
    renders: bool | None = Field(None, description="produce before/after renders (default true)")
    outputs: list[OutputName] | None = Field(None, description="artifacts wanted (default: all)")
    recon_iterations: int | None = _bounded("recon_iterations", "3DGS training iterations for image-set inputs")
    # Guidance (docs/service.md "Guided alignment"), in the input files' own coordinates. Typed
    # loosely here: their shapes are checked by the library's check_guidance (422 naming the option).
    init_transform: Any = _hint("init_transform", "start from this pose; only a local refinement runs")
    point_pairs: Any = _hint("point_pairs", "picked point pairs: their Sim(3), then a local refinement")
    up_axes: Any = _hint("up_axes", "every pose keeps these up axes aligned")
    fixed_scale: float | None = _bounded("fixed_scale", "the answer's scale, kept through every stage")

    @model_validator(mode="after")
    def _check(self):
        check_option_values(self.to_dict())  # raises a 422 Problem (not a pydantic error)
        return self

    def to_dict(self) -> dict[str, Any]:
        return self.model_dump(exclude_none=True)


class RefineIn(BaseModel):
    """POST /v1/jobs/{id}:refine: where the follow-up job starts (exactly one of alternative,
    init_transform, point_pairs) and, optionally, new up_axes / fixed_scale (null drops the
    parent's). Checked by service.core.refine_options and service.options (422 naming the field)."""

    model_config = ConfigDict(extra="forbid")
    alternative: Any = Field(None, description="index into the parent result's metrics.alternatives", examples=[0])
    init_transform: Any = _hint("init_transform", "start from this pose")
    point_pairs: Any = _hint("point_pairs", "start from these picked pairs")
    up_axes: Any = _hint("up_axes", "keep these up axes aligned")
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


class Health(BaseModel):
    status: str
    checks: dict[str, bool] = Field(default_factory=dict)
