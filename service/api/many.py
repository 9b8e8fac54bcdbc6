"""Many jobs (N-way registration): N previously uploaded models into one reference frame
(service.jobs.many; the job is then read, cancelled, deleted and its artifacts fetched as any job's
under /v1/jobs/{id})."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Header, Request
from fastapi.concurrency import run_in_threadpool
from pydantic import BaseModel, ConfigDict, Field

from service.api.deps import AppBackend, Owner
from service.api.jobs import _job_response
from service.api.openapi import problem_responses
from service.api.schemas import JobOut, WebhookIn
from service.jobs import many
from service.jobs.options import AlignOptionsIn

router = APIRouter()


class ManyJobCreate(BaseModel):
    """POST /v1/many-jobs: every model's Sim(3) into the reference's frame (gsa align-many)."""

    model_config = ConfigDict(extra="forbid")
    assets: list[str] = Field(
        description="asset ids of the 3DGS models (2..GSA_MAX_MANY_MODELS, each once); all pairs are "
        "aligned up to 8 models, each model with its 3 most similar plus a spanning tree beyond",
        examples=[["ast_a", "ast_b", "ast_c"]],
    )
    reference: str | None = Field(None, description="the asset whose frame all go into (default: the first)")
    edges: str = Field("auto", description="auto (all pairs up to 8 models, sparse beyond), all or sparse")
    merged: bool = Field(False, description="also write every model in the reference frame as one merged.ply")
    merge: str = Field("concat", description="concat, or dedup: drop Gaussians duplicated across models")
    options: AlignOptionsIn = Field(
        default_factory=AlignOptionsIn,
        description="align() options for every edge (stages, seed, coarse_iterations, …); not outputs, "
        "renders or guidance",
    )
    webhook: WebhookIn | None = None


@router.post(
    "/v1/many-jobs",
    operation_id="createManyJob",
    status_code=202,
    response_model=JobOut,
    tags=["jobs"],
    summary="Create an N-way registration job (many models into one frame)",
    description="Aligns every pair of the given models (sparse beyond 8) and solves for each model's Sim(3) "
    "into the reference's frame consistently around the cycles (gsa.align.many). Answers 202 with Location "
    "/v1/jobs/{id}; the job's stage names the edge running (`edge 2/3: coarse`), its result is many.json's "
    "content and its artifacts many.json and, with `merged`, merged.ply. 422 for fewer than 2 or more than "
    "GSA_MAX_MANY_MODELS assets, a repeated asset, a reference not among them, an image set, or an option a "
    "many job does not take; 404 for an asset that is not yours. `Idempotency-Key` as for createJob.",
    responses=problem_responses(401, 404, 422, 507),
)
async def create_many_job(
    spec: ManyJobCreate,
    request: Request,
    owner: Owner,
    b: AppBackend,
    idempotency_key: Annotated[str | None, Header(alias="Idempotency-Key")] = None,
):
    req = request_from(spec)
    job, created = await run_in_threadpool(many.submit_many, b, owner, req, idempotency_key, "http")
    if created:
        request.app.state.metrics.job_created("http", owner)
    return _job_response(job, created)


def request_from(spec: ManyJobCreate) -> many.ManyRequest:
    webhook: dict[str, Any] | None = spec.webhook.model_dump(exclude_none=True) if spec.webhook else None
    return many.ManyRequest(
        assets=list(spec.assets),
        reference=spec.reference,
        edges=spec.edges,
        merged=spec.merged,
        merge=spec.merge,
        options=spec.options.to_dict(),
        webhook=webhook,
    )
