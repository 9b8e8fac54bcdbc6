"""The hand-written parts of the OpenAPI document.

Request bodies that the handlers parse themselves (JSON or streamed multipart)
are not visible to FastAPI, so they are declared here and attached with
`openapi_extra`; `custom_openapi` makes sure the models they reference exist.
"""

from __future__ import annotations

import json
from http import HTTPStatus

from fastapi import FastAPI
from fastapi.openapi.utils import get_openapi

from service.api.middleware import PROBLEM_JSON
from service.api.schemas import JobCreate, Problem


def problem_content() -> dict:
    """The one body every 4xx/5xx answer has: an RFC 9457 Problem as application/problem+json."""
    return {PROBLEM_JSON: {"schema": {"$ref": "#/components/schemas/Problem"}}}


def problem_responses(*codes: int) -> dict:
    """`responses=` entries for these status codes: RFC 9457 bodies as application/problem+json.
    No `model`: FastAPI would declare it a second time under application/json, and generated
    clients then take the first media type, one without a schema, and parse nothing."""
    return {c: {"description": _phrase(c), "content": problem_content()} for c in codes}


def _phrase(code: int) -> str:
    try:
        return HTTPStatus(code).phrase
    except ValueError:
        return "Error"


# POST /v1/assets: one or more files in the multipart field "file".
UPLOAD_BODY = {
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

# POST /v1/jobs: asset ids as JSON, or the files themselves as multipart.
JOB_BODY = {
    "requestBody": {
        "required": True,
        "content": {
            "application/json": {"schema": {"$ref": "#/components/schemas/JobCreate"}},
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


def custom_openapi(app: FastAPI) -> dict:
    """app.openapi: the generated document plus the models the hand-written bodies reference."""
    if app.openapi_schema:
        return app.openapi_schema
    schema = get_openapi(
        title=app.title,
        version=app.version,
        summary=app.summary,
        description=app.description,
        routes=app.routes,
    )
    comps = schema.setdefault("components", {}).setdefault("schemas", {})
    for model in (JobCreate, Problem):
        js = model.model_json_schema(ref_template="#/components/schemas/{model}")
        for name, d in js.pop("$defs", {}).items():
            comps.setdefault(name, d)
        comps.setdefault(model.__name__, js)
    _tenant_limits(schema)
    _problems_only(schema)
    app.openapi_schema = schema
    return schema


# Operations that store bytes for the caller: 507 past the tenant's storage quota (service.jobs.quotas).
_STORING = {"uploadAsset", "createJob", "refineJob", "refineJobSlash"}


def _tenant_limits(schema: dict) -> None:
    """Every operation that takes an API key may answer 429 (the tenant's request rate; createJob
    and refine also its job limit), the storing ones 507, and all 503 (job store or storage
    unavailable): documented once here, not per route."""
    problem = problem_content()
    for item in schema.get("paths", {}).values():
        for op in item.values():
            responses = op.get("responses") if isinstance(op, dict) else None
            if not responses or "401" not in responses:
                continue
            responses.setdefault(
                "429",
                {"description": "the tenant's request rate or job limit; see Retry-After", "content": problem},
            )
            if op.get("operationId") in _STORING:
                responses.setdefault(
                    "507", {"description": "the tenant's storage quota, or storage full", "content": problem}
                )
            # Every operation with a key reads the job store: unreachable, it answers 503 store-unavailable.
            responses.setdefault(
                "503", {"description": "the job store or storage is unavailable; see Retry-After", "content": problem}
            )


def _problems_only(schema: dict) -> None:
    """Every 4xx/5xx response, also those FastAPI adds itself (the 422 of operations with
    parameters, declared as its HTTPValidationError), as the server sends it: one Problem
    under application/problem+json and nothing else. Then FastAPI's validation models, which
    nothing sends, leave the document."""
    for item in schema.get("paths", {}).values():
        for op in item.values():
            responses = op.get("responses") if isinstance(op, dict) else None
            for code, response in (responses or {}).items():
                if code[:1] in "45":
                    response["content"] = problem_content()
                    if response.get("description") == "Validation Error":
                        response["description"] = "the request is not valid: a validation-error problem"
    comps = schema.get("components", {}).get("schemas", {})
    for name in ("HTTPValidationError", "ValidationError"):
        rest = {k: v for k, v in schema.items() if k != "components"}, {k: v for k, v in comps.items() if k != name}
        if f'"#/components/schemas/{name}"' not in json.dumps(rest):
            comps.pop(name, None)
