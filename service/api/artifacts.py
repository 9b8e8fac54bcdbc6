"""Artifacts: downloading a finished job's files, with single byte ranges."""

from __future__ import annotations

import re
from typing import Annotated

from fastapi import APIRouter, Header, Response
from fastapi.responses import StreamingResponse

from service import core
from service.api.deps import B, Owner
from service.api.openapi import problem_responses
from service.problems import Problem as ProblemError

router = APIRouter()


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
        **problem_responses(401, 404, 409, 416),
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
