"""Jobs: creating (from asset ids or uploads, with idempotency), reading,
listing and cancelling alignment jobs."""

from __future__ import annotations

import base64
import hashlib
import json
from typing import Annotated

from fastapi import APIRouter, Header, Query, Request, Response
from fastapi.concurrency import run_in_threadpool
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse

from service.api.deps import AppBackend, Owner
from service.api.openapi import JOB_BODY, problem_responses
from service.api.schemas import JobCreate, JobList, JobOut, RefineIn, WebhookIn
from service.api.upload import Form, parse_multipart
from service.backend import Backend
from service.jobs import core, retention
from service.jobs.options import parse_options
from service.models import JobState
from service.problems import Problem, invalid_input

router = APIRouter()


def _job_response(job, created: bool) -> JSONResponse:
    out = JobOut.from_job(job)
    headers = {"Location": f"/v1/jobs/{job.id}"}
    if not created:
        headers["Idempotent-Replayed"] = "true"
    return JSONResponse(out.model_dump(mode="json"), status_code=202, headers=headers)


@router.post(
    "/v1/jobs",
    operation_id="createJob",
    status_code=202,
    response_model=JobOut,
    tags=["jobs"],
    summary="Create an alignment job (uploads or asset ids)",
    description="Answers 202 with Location. `Idempotency-Key`: the same key and body return the same job "
    "(header Idempotent-Replayed: true); the same key with a different body is 422.",
    openapi_extra=JOB_BODY,
    responses=problem_responses(401, 404, 409, 413, 422),
)
async def create_job(
    request: Request,
    owner: Owner,
    b: AppBackend,
    idempotency_key: Annotated[str | None, Header(alias="Idempotency-Key")] = None,
):
    ctype = request.headers.get("content-type", "")
    if ctype.startswith("application/json"):
        try:
            spec = JobCreate.model_validate_json(await request.body())
        except ValueError as exc:
            errs = exc.errors() if hasattr(exc, "errors") else [{"loc": ("body",), "msg": str(exc), "type": "json"}]
            raise RequestValidationError(errs) from None
        ids = spec.sources or ([spec.source] if spec.source else [])
        if spec.source and spec.sources:
            raise invalid_input("give either 'source' or 'sources', not both")
        options = spec.options.to_dict()
        webhook = spec.webhook.model_dump(exclude_none=True) if spec.webhook else None
        identity = {"sources": ids, "target": spec.target, "options": options, "webhook": webhook}
        req = core.JobRequest(list(ids), spec.target, options, webhook, identity)
        return await _submit(request, b, owner, req, idempotency_key)
    if not ctype.startswith("multipart/form-data"):
        raise Problem(
            415,
            "unsupported-media-type",
            "Unsupported Media Type",
            "send application/json (asset ids) or multipart/form-data (uploads)",
        )
    s = b.settings
    form = await parse_multipart(request, s.max_upload_bytes, max_files=2 * s.max_images + s.max_sources + 1)
    try:
        return await _submit(request, b, owner, _form_request(form), idempotency_key)
    finally:
        form.close()


def _form_request(form: Form) -> core.JobRequest:
    """A multipart job submission: model files and image sets, options as a JSON field."""
    unknown = set(form.files) - {"source", "target", "source_images", "target_images"}
    unknown |= set(form.fields) - {"options", "webhook_url", "webhook_secret"}
    if unknown:
        raise invalid_input(f"unknown form field(s): {', '.join(sorted(unknown))}")
    files = {k: [core.Upload(p.file, p.filename) for p in parts] for k, parts in form.files.items()}
    src_files, tgt_files = files.get("source", []), files.get("target", [])
    src_imgs, tgt_imgs = files.get("source_images", []), files.get("target_images", [])
    if len(tgt_files) + bool(tgt_imgs) != 1:
        raise invalid_input("exactly one target is required: a 'target' file or 'target_images'")
    options = parse_options(form.field("options") or "{}", "'options' is not a valid options JSON object")
    webhook = None
    if form.field("webhook_url"):
        webhook = WebhookIn(url=form.field("webhook_url"), secret=form.field("webhook_secret")).model_dump(
            exclude_none=True
        )
    sources: list[core.Input] = list(src_files)
    if src_imgs:
        sources.append(core.ImageSet(src_imgs, "source_images"))
    target = tgt_files[0] if tgt_files else core.ImageSet(tgt_imgs, "target_images")
    identity = {"files": files, "options": options, "webhook": webhook}
    return core.JobRequest(sources, target, options, webhook, identity)


async def _submit(request: Request, b: Backend, owner: str, req: core.JobRequest, idem: str | None):
    job, created = await run_in_threadpool(core.submit_job, b, owner, req, idem)
    if created:
        request.app.state.metrics.job_created("http", owner)
    return _job_response(job, created)


def _etag(payload: bytes) -> str:
    return '"' + hashlib.sha256(payload).hexdigest()[:32] + '"'


def _etag_matches(header: str | None, etag: str) -> bool:
    if not header:
        return False
    if header.strip() == "*":
        return True
    tags = [t.strip().removeprefix("W/") for t in header.split(",")]
    return etag in tags


@router.get(
    "/v1/jobs/{job_id}",
    operation_id="getJob",
    response_model=JobOut,
    tags=["jobs"],
    summary="Job state, progress and result",
    description="Carries an ETag; send it back in If-None-Match to get 304 while nothing changed.",
    responses={304: {"description": "not modified"}, **problem_responses(401, 404)},
)
async def get_job(
    job_id: str,
    owner: Owner,
    b: AppBackend,
    if_none_match: Annotated[str | None, Header(alias="If-None-Match")] = None,
):
    job = core.get_job(b, owner, job_id)
    body = JobOut.from_job(job).model_dump_json().encode()
    etag = _etag(body)
    headers = {"ETag": etag, "Cache-Control": "no-cache"}
    if _etag_matches(if_none_match, etag):
        return Response(status_code=304, headers=headers)
    return Response(body, media_type="application/json", headers=headers)


def _encode_cursor(job) -> str:
    return base64.urlsafe_b64encode(json.dumps([job.created_at, job.id]).encode()).decode().rstrip("=")


def _decode_cursor(c: str) -> tuple[float, str]:
    try:
        t, i = json.loads(base64.urlsafe_b64decode(c + "=" * (-len(c) % 4)))
        return float(t), str(i)
    except (TypeError, ValueError):  # not base64, not JSON (ValueError subclasses), not [time, id]
        raise invalid_input("invalid cursor") from None


@router.get(
    "/v1/jobs",
    operation_id="listJobs",
    response_model=JobList,
    tags=["jobs"],
    summary="List your jobs, newest first",
    responses=problem_responses(401, 422),
)
async def list_jobs(
    owner: Owner,
    b: AppBackend,
    state: JobState | None = None,
    limit: Annotated[int, Query(ge=1, le=200)] = 50,
    cursor: str | None = None,
):
    jobs = b.store.list(owner, state, limit + 1, _decode_cursor(cursor) if cursor else None)
    more = len(jobs) > limit
    jobs = jobs[:limit]
    return JobList(
        items=[JobOut.from_job(j) for j in jobs],
        next_cursor=_encode_cursor(jobs[-1]) if more and jobs else None,
    )


@router.post(
    "/v1/jobs/{job_id}:cancel",
    operation_id="cancelJob",
    status_code=202,
    response_model=JobOut,
    tags=["jobs"],
    summary="Cancel a job",
    description="A queued job is cancelled at once; a running job stops at its next progress report "
    "(cancel_requested is true until then). 409 if the job already succeeded or failed.",
    responses=problem_responses(401, 404, 409),
)
async def cancel_job(job_id: str, owner: Owner, b: AppBackend):
    return JobOut.from_job(core.cancel_job(b, owner, job_id))


@router.delete(
    "/v1/jobs/{job_id}",
    operation_id="deleteJob",
    status_code=204,
    response_class=Response,
    tags=["jobs"],
    summary="Delete a finished job and its artifacts",
    description="Only a final job (succeeded, failed, cancelled) can be deleted; a queued or running job "
    "answers 409 job-not-finished: cancel it first. The job's input assets stay (DELETE /v1/assets/{id}).",
    responses=problem_responses(401, 404, 409),
)
async def delete_job(job_id: str, owner: Owner, b: AppBackend):
    await run_in_threadpool(retention.delete_job, b, owner, job_id)
    return Response(status_code=204)


@router.post(
    "/v1/jobs/{job_id}:refine",
    operation_id="refineJob",
    status_code=202,
    response_model=JobOut,
    tags=["jobs"],
    summary="Refine a finished job from a chosen pose or picked point pairs",
    description="Creates a follow-up job on the parent's own inputs and options, starting from one of "
    "the parent result's `metrics.alternatives` (`alternative`: its index), a pose (`init_transform`) or "
    "picked point pairs (`point_pairs`); `up_axes`, `front_axes` and `fixed_scale` replace the parent's "
    "(null drops one; new `up_axes` without `front_axes` drop the parent's fronts). The new job has "
    "`parent_job`; the parent lists it in `children`. 409 while the parent is queued or running (and "
    "for `alternative` when it has no result); 422 for a bad hint or an alternative index the result "
    "does not have. `/v1/jobs/{job_id}/refine` is the same operation. `Idempotency-Key` as for createJob.",
    responses=problem_responses(401, 404, 409, 422),
)
async def refine_job(
    job_id: str,
    body: RefineIn,
    request: Request,
    owner: Owner,
    b: AppBackend,
    idempotency_key: Annotated[str | None, Header(alias="Idempotency-Key")] = None,
):
    hints = body.model_dump(exclude_unset=True)
    job, created = await run_in_threadpool(core.refine_job, b, owner, job_id, hints, idempotency_key)
    if created:
        request.app.state.metrics.job_created("http", owner)
    return _job_response(job, created)


# The same operation for clients and proxies that cannot put a colon in a path.
router.add_api_route(
    "/v1/jobs/{job_id}/refine",
    refine_job,
    methods=["POST"],
    operation_id="refineJobSlash",
    status_code=202,
    response_model=JobOut,
    tags=["jobs"],
    summary="Refine a finished job (same as POST /v1/jobs/{job_id}:refine)",
    responses=problem_responses(401, 404, 409, 422),
)
