"""Artifacts: downloading a finished job's files, with single byte ranges."""

from __future__ import annotations

import re
from email.utils import formatdate, parsedate_to_datetime
from typing import Annotated

from fastapi import APIRouter, Header, Query, Response
from fastapi.responses import StreamingResponse
from starlette.concurrency import run_in_threadpool

from service.api.deps import AppBackend, Owner
from service.api.jobs import _etag_matches
from service.api.openapi import problem_responses
from service.jobs import core
from service.problems import Problem
from service.worker.convert import conversions

router = APIRouter()


_RANGE = re.compile(r"^bytes=(\d*)-(\d*)$")


@router.get(
    "/v1/jobs/{job_id}/artifacts/{name:path}",
    operation_id="getArtifact",
    tags=["jobs"],
    summary="Download an artifact",
    description="Supports single byte ranges (Range: bytes=a-b) with 206 Partial Content. With If-Range "
    "(the ETag or Last-Modified of a copy you hold), a range is served only if the artifact is still that "
    "version; otherwise the whole artifact comes with 200 (RFC 9110). With If-None-Match naming its ETag, "
    "304 Not Modified without a body.",
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
        304: {"description": "not modified (If-None-Match names the artifact's ETag)"},
        **problem_responses(401, 404, 409, 416, 422, 503, 504),
    },
)
async def get_artifact(
    job_id: str,
    name: str,
    owner: Owner,
    b: AppBackend,
    range_header: Annotated[str | None, Header(alias="Range")] = None,
    if_range: Annotated[str | None, Header(alias="If-Range")] = None,
    if_none_match: Annotated[str | None, Header(alias="If-None-Match")] = None,
    model_format: Annotated[
        str | None,
        Query(
            alias="format",
            description="a model artifact converted to ply, compressed-ply, splat, ksplat, spz, sog or glb "
            "(docs/formats.md), in a child process, then kept: served like any artifact (Range, ETag). "
            "503 conversions-busy with Retry-After when every conversion slot stays taken",
        ),
    ] = None,
):
    # async, and the store read in the threadpool: a request waiting for a conversion then
    # holds no thread (the threadpool serves every other sync route).
    job, art = await run_in_threadpool(core.get_artifact, b, owner, job_id, name)
    if model_format is not None:
        art = await conversions(b).converted(b, art, model_format)
    status, headers, start, end = _plan(job, art, range_header, if_range, if_none_match)
    if status == 304:
        return Response(status_code=304, headers=headers)
    if art.size == 0:
        return Response(b"", media_type=art.content_type, headers=headers)
    return StreamingResponse(
        b.storage.open(art.key, start, end),
        status_code=status,
        media_type=art.content_type,
        headers=headers,
    )


@router.head(
    "/v1/jobs/{job_id}/artifacts/{name:path}",
    operation_id="headArtifact",
    tags=["jobs"],
    summary="An artifact's headers (size, ETag) without its body",
    response_class=Response,
    responses={
        206: {"description": "partial content"},
        304: {"description": "not modified (If-None-Match names the artifact's ETag)"},
        **problem_responses(401, 404, 409, 416, 422, 503, 504),
    },
)
async def head_artifact(
    job_id: str,
    name: str,
    owner: Owner,
    b: AppBackend,
    range_header: Annotated[str | None, Header(alias="Range")] = None,
    if_range: Annotated[str | None, Header(alias="If-Range")] = None,
    if_none_match: Annotated[str | None, Header(alias="If-None-Match")] = None,
    model_format: Annotated[
        str | None, Query(alias="format", description="the headers of the artifact in this format (as GET)")
    ] = None,
):
    job, art = await run_in_threadpool(core.get_artifact, b, owner, job_id, name)
    if model_format is not None:  # the same headers as GET ?format= (it converts if it must)
        art = await conversions(b).converted(b, art, model_format)
    status, headers, _, _ = _plan(job, art, range_header, if_range, if_none_match)
    if status != 304:
        headers["Content-Type"] = art.content_type
    return Response(status_code=status, headers=headers)


def _plan(
    job, art, range_header: str | None, if_range: str | None, if_none_match: str | None = None
) -> tuple[int, dict[str, str], int, int]:
    """(status, headers, first byte, last byte) of a download: 304 when If-None-Match names
    this version (RFC 9110 §13.2.2: before any Range), 206 for one satisfiable range, unless
    an If-Range names another version (then the whole artifact, 200)."""
    size = art.size
    etag = f'"{art.key.rsplit("/", 2)[-2][:16]}-{size}"'
    modified = formatdate(job.finished_at or job.updated_at, usegmt=True)
    headers = {
        "Accept-Ranges": "bytes",
        "ETag": etag,
        "Last-Modified": modified,
        "Content-Disposition": f'attachment; filename="{art.name}"',
    }
    if _etag_matches(if_none_match, etag):
        return 304, {"ETag": etag, "Last-Modified": modified}, 0, -1
    start, end, status = 0, size - 1, 200
    m = _RANGE.match(range_header.strip()) if range_header else None
    if m and (m.group(1) or m.group(2)) and _if_range_holds(if_range, etag, modified):
        a, z = m.group(1), m.group(2)
        if a:
            start, end = int(a), min(int(z), size - 1) if z else size - 1
        else:
            start, end = max(size - int(z), 0), size - 1
        if start >= size or start > end:
            p = Problem(
                416,
                "range-not-satisfiable",
                "Range Not Satisfiable",
                f"the artifact is {size} bytes",
            )
            p.headers["Content-Range"] = f"bytes */{size}"
            raise p
        status = 206
        headers["Content-Range"] = f"bytes {start}-{end}/{size}"
    headers["Content-Length"] = str(max(end - start + 1, 0))
    return status, headers, start, end


def _if_range_holds(if_range: str | None, etag: str, modified: str) -> bool:
    """RFC 9110 §13.1.5: no If-Range, or one naming this version (the same strong ETag,
    or exactly this Last-Modified date); anything else (weak or stale) sends the whole artifact."""
    if if_range is None:
        return True
    v = if_range.strip()
    if v.startswith(('"', "W/")):
        return v == etag
    try:
        return parsedate_to_datetime(v) == parsedate_to_datetime(modified)
    except (TypeError, ValueError):
        return False
