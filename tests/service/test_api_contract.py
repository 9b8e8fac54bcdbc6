"""The HTTP contract against the live server: stable operationIds, a typed job
`result` in OpenAPI that covers what the worker stores, HEAD on artifacts and
If-Range (RFC 9110 §13.1.5)."""

from __future__ import annotations

import re
from email.utils import formatdate

import pytest

from service.api.results import JobResult, Metrics, SourceResult
from tests.service.conftest import assert_problem, submit_pair, wait_job

pytestmark = pytest.mark.slow  # starts servers and worker processes

OPERATIONS = {
    ("get", "/healthz"): "healthz",
    ("get", "/readyz"): "readyz",
    ("get", "/metrics"): "getMetrics",
    ("post", "/v1/assets"): "uploadAsset",
    ("get", "/v1/assets"): "listAssets",
    ("get", "/v1/assets/{asset_id}"): "getAsset",
    ("delete", "/v1/assets/{asset_id}"): "deleteAsset",
    ("post", "/v1/jobs"): "createJob",
    ("get", "/v1/jobs"): "listJobs",
    ("get", "/v1/jobs/{job_id}"): "getJob",
    ("delete", "/v1/jobs/{job_id}"): "deleteJob",
    ("post", "/v1/jobs/{job_id}:cancel"): "cancelJob",
    ("post", "/v1/jobs/{job_id}:refine"): "refineJob",
    ("post", "/v1/jobs/{job_id}/refine"): "refineJobSlash",
    ("get", "/v1/jobs/{job_id}/artifacts/{name}"): "getArtifact",
    ("head", "/v1/jobs/{job_id}/artifacts/{name}"): "headArtifact",
}


@pytest.fixture(scope="module")
def done_job(stack, pair):
    import httpx

    from tests.service.conftest import ALICE

    with httpx.Client(base_url=stack["url"], headers=ALICE, timeout=60) as c:
        job = submit_pair(c, pair, {"stages": ["coarse", "fine"], "fine_iterations": 2, "outputs": ["result"]})
        done = wait_job(c, job.json()["id"], timeout=120)
    assert done["state"] == "succeeded", done
    return done


def test_operation_ids_are_explicit_stable_and_unique(http):
    doc = http.get("/openapi.json").json()
    found = {(m, p): op["operationId"] for p, ops in doc["paths"].items() for m, op in ops.items()}
    for where, op_id in OPERATIONS.items():
        assert found.get(where) == op_id, (where, found.get(where))
    ids = list(found.values())
    assert len(ids) == len(set(ids)), ids
    # Every route, also ones added later without an explicit id: camelCase, never FastAPI's path-derived id.
    assert all(re.fullmatch(r"[a-z][A-Za-z0-9]*", i) for i in ids), ids


def _resolve(doc, schema):
    if "$ref" in schema:
        return doc["components"]["schemas"][schema["$ref"].rsplit("/", 1)[1]]
    options = [s for s in schema.get("anyOf", []) if s.get("type") != "null"]
    return _resolve(doc, options[0]) if options else schema


def test_job_result_schema_is_typed(http):
    doc = http.get("/openapi.json").json()
    result = _resolve(doc, doc["components"]["schemas"]["JobOut"]["properties"]["result"])
    props = result["properties"]
    assert {"transform", "scale", "rotation", "quaternion", "translation", "metrics", "results"} <= set(props)
    assert props["transform"]["anyOf"][0]["type"] == "array"
    metrics = _resolve(doc, props["metrics"])
    assert metrics["properties"]["confidence"]["anyOf"][0]["type"] == "number"
    assert metrics["properties"]["doubtful"]["anyOf"][0]["type"] == "boolean"
    item = _resolve(doc, props["results"]["anyOf"][0]["items"])
    assert {"source_asset_id", "metrics", "stages", "timings"} <= set(item["properties"])
    stages = _resolve(doc, item["properties"]["stages"])
    fine = _resolve(doc, stages["properties"]["fine"])
    assert "loss_history" in fine["properties"]


def test_every_error_is_one_problem_schema(http):
    """What a generator reads: each 4xx/5xx response has exactly one media type,
    application/problem+json, with the Problem schema (no application/json twin, no FastAPI
    HTTPValidationError, which the server never sends); the Problem declares RFC 9457's members
    and the extensions the service sends; and what the server sends fits it."""
    doc = http.get("/openapi.json").json()
    ref = {"$ref": "#/components/schemas/Problem"}
    errors = 0
    for path, ops in doc["paths"].items():
        for method, op in ops.items():
            for code, response in op["responses"].items():
                if code[0] in "45":
                    errors += 1
                    assert response["content"] == {"application/problem+json": {"schema": ref}}, (method, path, code)
    assert errors > 50
    schemas = doc["components"]["schemas"]
    assert "HTTPValidationError" not in schemas and "ValidationError" not in schemas
    problem = schemas["Problem"]
    props = problem["properties"]
    assert {"type", "title", "status", "detail", "instance"} <= set(props)
    assert {"errors", "option", "minimum", "maximum", "allowed", "job_id", "limit", "quota", "retry_after"} <= set(
        props
    )
    assert set(problem["required"]) == {"type", "title", "status"}
    assert problem.get("additionalProperties", True) is not False  # members added later still reach clients
    kinds = {"integer": int, "number": (int, float), "string": str, "array": list, "object": dict}
    sent = [
        http.get("/v1/jobs/job_nope").json(),
        http.get("/v1/jobs", params={"limit": 0}).json(),
        http.post("/v1/jobs", json={"source": "a", "target": "b", "options": {"coarse_iterations": 0}}).json(),
    ]
    for body in sent:
        for member, value in body.items():
            declared = props.get(member, {})
            options = [d.get("type") for d in declared.get("anyOf", [declared])]
            if value is not None and any(options):
                assert any(isinstance(value, kinds[t]) for t in options if t in kinds), (member, value, declared)


def test_every_member_of_a_stored_result_is_typed(done_job):
    """What the worker stores has no member the schema leaves untyped."""
    result = done_job["result"]
    untyped = set(result) - set(JobResult.model_fields)
    assert not untyped, untyped
    assert not set(result["metrics"]) - set(Metrics.model_fields)
    for entry in result["results"]:
        assert not set(entry) - set(SourceResult.model_fields)
    parsed = JobResult.model_validate(result)
    assert parsed.stages.fine is not None and len(parsed.stages.fine.loss_history) == 3
    assert parsed.model_dump(mode="json") == result  # served as stored: no nulls added


def test_head_artifact(http, done_job):
    href = next(a["href"] for a in done_job["artifacts"] if a["name"] == "result.json")
    full = http.get(href)
    r = http.head(href)
    assert r.status_code == 200 and r.content == b""
    assert int(r.headers["content-length"]) == len(full.content)
    assert r.headers["etag"] == full.headers["etag"] and r.headers["etag"].startswith('"')
    assert r.headers["content-type"].startswith("application/json")
    assert r.headers["last-modified"] == full.headers["last-modified"]
    assert_problem(http.get(href.rsplit("/", 1)[0] + "/nope.json"), 404)
    r = http.head(href.rsplit("/", 1)[0] + "/nope.json")
    assert r.status_code == 404 and r.content == b""


def test_if_range(http, done_job):
    href = next(a["href"] for a in done_job["artifacts"] if a["name"] == "result.json")
    full = http.get(href)
    etag, modified = full.headers["etag"], full.headers["last-modified"]
    rng = {"Range": "bytes=0-9"}
    # Still the same version: the range is served.
    for validator in (etag, modified):
        r = http.get(href, headers={**rng, "If-Range": validator})
        assert r.status_code == 206 and r.content == full.content[:10], validator
    # Stale or weak validators: the whole artifact, 200.
    stale_date = formatdate(1_000_000_000, usegmt=True)
    for validator in ('"0000000000000000-1"', f"W/{etag}", stale_date, "not a date"):
        r = http.get(href, headers={**rng, "If-Range": validator})
        assert r.status_code == 200 and r.content == full.content, validator
        assert "content-range" not in r.headers
    assert http.get(href, headers=rng).status_code == 206
