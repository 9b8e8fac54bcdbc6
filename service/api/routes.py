"""HTTP routes (v1). Handlers stay thin: parsing/limits here, logic in service.core."""

from __future__ import annotations

import base64
import hashlib
import json
import re
from typing import Annotated

from fastapi import APIRouter, Depends, Header, Query, Request, Response
from fastapi.concurrency import run_in_threadpool
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, StreamingResponse
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest

from service import core
from service.api.deps import get_backend, require_owner
from service.api.middleware import PROBLEM_JSON
from service.api.schemas import (
    AlignOptionsIn,
    AssetOut,
    Health,
    JobCreate,
    JobList,
    JobOut,
    Problem,
    WebhookIn,
)
from service.api.upload import Form, parse_multipart
from service.backend import Backend
from service.models import JobState
from service.problems import Problem as ProblemError
from service.problems import invalid_input

Owner = Annotated[str, Depends(require_owner)]
B = Annotated[Backend, Depends(get_backend)]


def _problems(*codes: int) -> dict:
    return {c: {"model": Problem, "content": {PROBLEM_JSON: {}}} for c in codes}


router = APIRouter()


# ------------------------------------------------------------------ health
@router.get("/healthz", response_model=Health, tags=["ops"], summary="Liveness")
async def healthz() -> Health:
    return Health(status="ok")


@router.get(
    "/readyz",
    response_model=Health,
    tags=["ops"],
    summary="Readiness: job store and storage reachable",
    responses=_problems(503),
)
def readyz(b: B):
    checks = b.ready()
    if not all(checks.values()):
        bad = ", ".join(k for k, v in checks.items() if not v)
        p = ProblemError(
            503, "not-ready", "Service not ready", f"unreachable: {bad}", checks=checks
        )
        raise p
    return Health(status="ready", checks=checks)


@router.get(
    "/metrics",
    tags=["ops"],
    summary="Prometheus metrics (any valid API key)",
    responses={200: {"content": {CONTENT_TYPE_LATEST: {}}}},
    response_class=Response,
)
def metrics(request: Request, owner: Owner):
    return Response(
        generate_latest(request.app.state.metrics.registry),
        media_type=CONTENT_TYPE_LATEST,
    )


# ------------------------------------------------------------------ assets
_UPLOAD_BODY = {
    "requestBody": {
        "required": True,
        "content": {
            "multipart/form-data": {
                "schema": {
                    "type": "object",
                    "required": ["file"],
                    "properties": {
                        "file": {
                            "type": "array",
                            "items": {"type": "string", "format": "binary"},
                            "description": "one 3DGS .ply, one .zip of images, or several PNG/JPEG images",
                        }
                    },
                }
            }
        },
    }
}


@router.post(
    "/v1/assets",
    status_code=201,
    response_model=AssetOut,
    tags=["assets"],
    summary="Upload a model (PLY) or an image set (zip or several images)",
    openapi_extra=_UPLOAD_BODY,
    responses=_problems(401, 413, 422),
)
async def upload_asset(request: Request, response: Response, owner: Owner, b: B):
    s = b.settings
    form = await parse_multipart(request, s.max_upload_bytes, max_files=s.max_images)
    try:
        files = form.files.get("file", [])
        if not files:
            raise invalid_input("multipart field 'file' is required")
        if len(files) == 1:
            asset = await run_in_threadpool(
                core.ingest, b, owner, files[0].file, files[0].filename
            )
        else:
            asset = await run_in_threadpool(
                core.ingest_images,
                b,
                owner,
                [(f.filename, f.file) for f in files],
                "images",
            )
    finally:
        form.close()
    response.headers["Location"] = f"/v1/assets/{asset.id}"
    return AssetOut.from_asset(asset)


@router.get(
    "/v1/assets/{asset_id}",
    response_model=AssetOut,
    tags=["assets"],
    summary="Asset metadata",
    responses=_problems(401, 404),
)
async def get_asset(asset_id: str, owner: Owner, b: B):
    return AssetOut.from_asset(core.get_asset(b, owner, asset_id))


# -------------------------------------------------------------------- jobs
def _job_body_openapi() -> dict:
    return {
        "requestBody": {
            "required": True,
            "content": {
                "application/json": {
                    "schema": {"$ref": "#/components/schemas/JobCreate"}
                },
                "multipart/form-data": {
                    "schema": {
                        "type": "object",
                        "properties": {
                            "source": {
                                "type": "array",
                                "items": {"type": "string", "format": "binary"},
                                "description": "source model(s): 3DGS .ply or .zip of images; several = multi-model job",
                            },
                            "target": {
                                "type": "string",
                                "format": "binary",
                                "description": "target (reference) .ply or .zip",
                            },
                            "source_images": {
                                "type": "array",
                                "items": {"type": "string", "format": "binary"},
                                "description": "source image set as individual PNG/JPEG files",
                            },
                            "target_images": {
                                "type": "array",
                                "items": {"type": "string", "format": "binary"},
                                "description": "target image set as individual PNG/JPEG files",
                            },
                            "options": {
                                "type": "string",
                                "description": "JSON object, see AlignOptionsIn",
                            },
                            "webhook_url": {"type": "string"},
                            "webhook_secret": {"type": "string"},
                        },
                    }
                },
            },
        }
    }


def _sha_file(fh) -> str:
    h = hashlib.sha256()
    fh.seek(0)
    while chunk := fh.read(1 << 20):
        h.update(chunk)
    fh.seek(0)
    return h.hexdigest()


def _fingerprint(obj) -> str:
    return hashlib.sha256(
        json.dumps(obj, sort_keys=True, separators=(",", ":")).encode()
    ).hexdigest()


def _job_response(job, created: bool) -> JSONResponse:
    out = JobOut.from_job(job)
    headers = {"Location": f"/v1/jobs/{job.id}"}
    if not created:
        headers["Idempotent-Replayed"] = "true"
    return JSONResponse(out.model_dump(mode="json"), status_code=202, headers=headers)


@router.post(
    "/v1/jobs",
    status_code=202,
    response_model=JobOut,
    tags=["jobs"],
    summary="Create an alignment job (uploads or asset ids)",
    description="Answers 202 with Location. `Idempotency-Key`: the same key and body return the same job "
    "(header Idempotent-Replayed: true); the same key with a different body is 422.",
    openapi_extra=_job_body_openapi(),
    responses=_problems(401, 404, 409, 413, 422),
)
async def create_job(
    request: Request,
    owner: Owner,
    b: B,
    idempotency_key: Annotated[str | None, Header(alias="Idempotency-Key")] = None,
):
    ctype = request.headers.get("content-type", "")
    if ctype.startswith("application/json"):
        try:
            spec = JobCreate.model_validate_json(await request.body())
        except ValueError as exc:
            errs = (
                exc.errors()
                if hasattr(exc, "errors")
                else [{"loc": ("body",), "msg": str(exc), "type": "json"}]
            )
            raise RequestValidationError(errs) from None
        ids = spec.sources or ([spec.source] if spec.source else [])
        if spec.source and spec.sources:
            raise invalid_input("give either 'source' or 'sources', not both")
        options = spec.options.to_dict()
        webhook = spec.webhook.model_dump(exclude_none=True) if spec.webhook else None
        core.check_request(b, len(ids), options, webhook)
        sources = [core.get_asset(b, owner, i) for i in ids]
        target = core.get_asset(b, owner, spec.target)
        fp = _fingerprint(
            {
                "sources": ids,
                "target": spec.target,
                "options": options,
                "webhook": webhook,
            }
        )
        job_id, existing = core.claim(b, owner, idempotency_key, fp)
        if existing is not None:
            return _job_response(existing, False)
        job = core.create_job(
            b, owner, job_id, sources, target, options, webhook, idempotency_key
        )
        request.app.state.metrics.jobs_created.labels("http").inc()
        return _job_response(job, True)
    if not ctype.startswith("multipart/form-data"):
        raise ProblemError(
            415,
            "unsupported-media-type",
            "Unsupported Media Type",
            "send application/json (asset ids) or multipart/form-data (uploads)",
        )
    s = b.settings
    form = await parse_multipart(
        request, s.max_upload_bytes, max_files=2 * s.max_images + s.max_sources + 1
    )
    try:
        return await _create_from_form(request, form, owner, b, idempotency_key)
    finally:
        form.close()


async def _create_from_form(
    request: Request, form: Form, owner: str, b: Backend, idem: str | None
):
    unknown = set(form.files) - {"source", "target", "source_images", "target_images"}
    unknown |= set(form.fields) - {"options", "webhook_url", "webhook_secret"}
    if unknown:
        raise invalid_input(f"unknown form field(s): {', '.join(sorted(unknown))}")
    src_files, tgt_files = form.files.get("source", []), form.files.get("target", [])
    src_imgs, tgt_imgs = (
        form.files.get("source_images", []),
        form.files.get("target_images", []),
    )
    if len(tgt_files) + bool(tgt_imgs) != 1:
        raise invalid_input(
            "exactly one target is required: a 'target' file or 'target_images'"
        )
    try:
        options = AlignOptionsIn.model_validate_json(
            form.field("options") or "{}"
        ).to_dict()
    except ValueError as exc:
        raise invalid_input(
            f"'options' is not a valid options JSON object: {exc}"
        ) from None
    webhook = None
    if form.field("webhook_url"):
        webhook = WebhookIn(
            url=form.field("webhook_url"), secret=form.field("webhook_secret")
        ).model_dump(exclude_none=True)
    n_sources = len(src_files) + bool(src_imgs)
    core.check_request(b, n_sources, options, webhook)
    digests = {k: [_sha_file(p.file) for p in v] for k, v in form.files.items()}
    fp = _fingerprint({"files": digests, "options": options, "webhook": webhook})
    job_id, existing = core.claim(b, owner, idem, fp)
    if existing is not None:
        return _job_response(existing, False)
    made = []
    try:
        for p in src_files:
            made.append(
                await run_in_threadpool(core.ingest, b, owner, p.file, p.filename)
            )
        if src_imgs:
            made.append(
                await run_in_threadpool(
                    core.ingest_images,
                    b,
                    owner,
                    [(p.filename, p.file) for p in src_imgs],
                    "source_images",
                )
            )
        sources = list(made)
        if tgt_files:
            target = await run_in_threadpool(
                core.ingest, b, owner, tgt_files[0].file, tgt_files[0].filename
            )
        else:
            target = await run_in_threadpool(
                core.ingest_images,
                b,
                owner,
                [(p.filename, p.file) for p in tgt_imgs],
                "target_images",
            )
        made.append(target)
        job = core.create_job(b, owner, job_id, sources, target, options, webhook, idem)
    except BaseException:
        # Leave nothing behind: uploaded blobs, asset records, the idempotency claim.
        for a in made:
            core.discard_asset(b, a)
        core.release(b, owner, idem)
        raise
    request.app.state.metrics.jobs_created.labels("http").inc()
    return _job_response(job, True)


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
    response_model=JobOut,
    tags=["jobs"],
    summary="Job state, progress and result",
    description="Carries an ETag; send it back in If-None-Match to get 304 while nothing changed.",
    responses={304: {"description": "not modified"}, **_problems(401, 404)},
)
async def get_job(
    job_id: str,
    owner: Owner,
    b: B,
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
    return (
        base64.urlsafe_b64encode(json.dumps([job.created_at, job.id]).encode())
        .decode()
        .rstrip("=")
    )


def _decode_cursor(c: str) -> tuple[float, str]:
    try:
        t, i = json.loads(base64.urlsafe_b64decode(c + "=" * (-len(c) % 4)))
        return float(t), str(i)
    except Exception:
        raise invalid_input("invalid cursor") from None


@router.get(
    "/v1/jobs",
    response_model=JobList,
    tags=["jobs"],
    summary="List your jobs, newest first",
    responses=_problems(401, 422),
)
async def list_jobs(
    owner: Owner,
    b: B,
    state: JobState | None = None,
    limit: Annotated[int, Query(ge=1, le=200)] = 50,
    cursor: str | None = None,
):
    jobs = b.store.list(
        owner, state, limit + 1, _decode_cursor(cursor) if cursor else None
    )
    more = len(jobs) > limit
    jobs = jobs[:limit]
    return JobList(
        items=[JobOut.from_job(j) for j in jobs],
        next_cursor=_encode_cursor(jobs[-1]) if more and jobs else None,
    )


@router.post(
    "/v1/jobs/{job_id}:cancel",
    status_code=202,
    response_model=JobOut,
    tags=["jobs"],
    summary="Cancel a job",
    description="A queued job is cancelled at once; a running job stops at its next progress report "
    "(cancel_requested is true until then). 409 if the job already succeeded or failed.",
    responses=_problems(401, 404, 409),
)
async def cancel_job(job_id: str, owner: Owner, b: B):
    return JobOut.from_job(core.cancel_job(b, owner, job_id))


_RANGE = re.compile(r"^bytes=(\d*)-(\d*)$")


@router.get(
    "/v1/jobs/{job_id}/artifacts/{name:path}",
    tags=["jobs"],
    summary="Download an artifact",
    description="Supports single byte ranges (Range: bytes=a-b) with 206 Partial Content.",
    response_class=StreamingResponse,
    responses={
        200: {
            "content": {
                "application/octet-stream": {},
                "application/x-ply": {},
                "image/png": {},
                "application/json": {},
            }
        },
        206: {"description": "partial content"},
        **_problems(401, 404, 409, 416),
    },
)
def get_artifact(
    job_id: str,
    name: str,
    owner: Owner,
    b: B,
    range_header: Annotated[str | None, Header(alias="Range")] = None,
):
    _, art = core.get_artifact(b, owner, job_id, name)
    size = art.size
    headers = {
        "Accept-Ranges": "bytes",
        "ETag": f'"{art.key.rsplit("/", 2)[-2][:16]}-{size}"',
        "Content-Disposition": f'attachment; filename="{art.name}"',
    }
    start, end, status = 0, size - 1, 200
    m = _RANGE.match(range_header.strip()) if range_header else None
    if m and (m.group(1) or m.group(2)):
        a, z = m.group(1), m.group(2)
        if a:
            start, end = int(a), min(int(z), size - 1) if z else size - 1
        else:
            start, end = max(size - int(z), 0), size - 1
        if start >= size or start > end:
            p = ProblemError(
                416,
                "range-not-satisfiable",
                "Range Not Satisfiable",
                f"the artifact is {size} bytes",
            )
            p.headers["Content-Range"] = f"bytes */{size}"
            raise p
        status = 206
        headers["Content-Range"] = f"bytes {start}-{end}/{size}"
    headers["Content-Length"] = str(end - start + 1)
    if size == 0:
        return Response(b"", media_type=art.content_type, headers=headers)
    return StreamingResponse(
        b.storage.open(art.key, start, end),
        status_code=status,
        media_type=art.content_type,
        headers=headers,
    )
