"""GSA_LOG_FORMAT=json: `gsa serve` and `gsa worker` write one JSON object per line,
and lines written while a request is handled carry its request id. Real processes."""

from __future__ import annotations

import json

import httpx
import pytest

from tests.service.conftest import ALICE, service_env, start_api, start_worker, wait_until

pytestmark = pytest.mark.slow  # starts API and worker processes


def _records(proc) -> list[dict]:
    lines = [line for line in proc.tail(200_000).splitlines() if line.strip()]
    return [json.loads(line) for line in lines]  # every line is a JSON object, or this raises


def test_json_log_lines_carry_the_request_id(tmp_path, redis_url):
    env = service_env(tmp_path, GSA_LOG_FORMAT="json", GSA_REDIS_URL=redis_url + "/4")
    api, url, _ = start_api(tmp_path, env, log_level="info", name="json-api")
    worker = start_worker(tmp_path, env, name="json-worker")
    try:
        r = httpx.get(url + "/v1/jobs", headers={**ALICE, "X-Request-Id": "json-req-7"})
        assert r.status_code == 200
        httpx.get(url + "/v1/jobs/job_nope", headers={**ALICE, "X-Request-Id": "json-req-8"})

        def access(rid):
            return [x for x in _records(api) if x.get("request_id") == rid and x["logger"] == "gsa.api.access"]

        wait_until(lambda: access("json-req-7") and access("json-req-8"), 10, 0.1, "the access log lines")
        line = access("json-req-7")[0]
        assert line["message"].startswith("GET /v1/jobs 200") and line["level"] == "INFO"
        assert line["time"].endswith("Z")
        assert access("json-req-8")[0]["message"].startswith("GET /v1/jobs/job_nope 404")
        assert any(x["logger"] == "gsa.serve" and "gsa serve:" in x["message"] for x in _records(api))
        # Lines outside a request have no request id; the worker's lines are JSON too.
        wait_until(lambda: any("warm-up" in x["message"] for x in _records(worker)), 120, 0.2, "worker warm-up")
        assert all("request_id" not in x for x in _records(worker))
    finally:
        worker.stop()
        api.stop()
