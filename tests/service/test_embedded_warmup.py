"""Embedded mode (`gsa serve` without Redis) warms its worker up before it takes a job, as the RQ
worker does (service.worker.runners._warm_up): the first job with renders does not pay the
library's imports and numba kernels (87 s on an empty numba cache), and the API
answers while the worker warms up."""

from __future__ import annotations

import json
from datetime import datetime

import httpx
import pytest

from tests.service.conftest import ALICE, service_env, start_api, submit_pair, wait_job

pytestmark = pytest.mark.slow  # starts an API process that imports torch and numba


def _ts(iso: str) -> float:
    return datetime.fromisoformat(iso.replace("Z", "+00:00")).timestamp()


def test_embedded_worker_warms_up_before_its_first_job_while_the_api_answers(tmp_path, pair):
    env = service_env(tmp_path, GSA_LOG_FORMAT="json", GSA_EMBEDDED_WORKERS=1)
    api, url, _ = start_api(tmp_path, env, name="embedded", log_level="info")  # returns once /healthz answers
    try:
        healthy = datetime.now().timestamp()
        with httpx.Client(base_url=url, headers=ALICE, timeout=60) as http:
            r = submit_pair(http, pair)  # the default outputs: renders and preview too
            assert r.status_code == 202, r.text
            job = wait_job(http, r.json()["id"], timeout=300)
        assert job["state"] == "succeeded", job
        lines = [json.loads(x) for x in api.log.read_text(errors="replace").splitlines() if x.startswith("{")]
        messages = [x["message"] for x in lines]
        assert not [m for m in messages if m.startswith("worker warm-up failed")], api.tail()
        warmed = [x for x in lines if x["message"].startswith("worker warm-up took")]
        assert len(warmed) == 1, api.tail()
        done = _ts(warmed[0]["time"])
        # The API answered, and took the job, while the worker was warming up; the worker
        # claimed the job only once warm.
        assert healthy < done, "the warm-up held the API up"
        assert _ts(job["created_at"]) < done <= _ts(job["started_at"]), (job, warmed)
    finally:
        api.stop()
