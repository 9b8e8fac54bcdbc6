"""`gsa worker` takes its settings from its flags over the environment, at start-up: a worker
given --redis-url and --storage-root, with neither in its environment, runs jobs with them
(its work horses, forked, inherit the backend made from them)."""

from __future__ import annotations

import time

import httpx
import pytest

from tests.service.conftest import ALICE, PY, Proc, service_env, start_api, submit_pair, wait_job

pytestmark = pytest.mark.slow  # starts servers and a worker process


def test_worker_flags_reach_its_work_horses(tmp_path, pair, redis_url):
    url_db = redis_url + "/8"
    env = service_env(tmp_path, GSA_REDIS_URL=url_db, GSA_QUEUE_NAME="flags")
    api, url, _ = start_api(tmp_path, env)
    worker_env = {k: v for k, v in env.items() if k not in ("GSA_REDIS_URL", "GSA_STORAGE_ROOT")}
    worker_env["GSA_QUEUE_NAME"] = "flags"
    args = ["--redis-url", url_db, "--storage-root", env["GSA_STORAGE_ROOT"], "--name", f"flags-{time.time_ns()}"]
    worker = Proc([PY, "-m", "service.cli", "worker", *args], worker_env, tmp_path / "worker.log")
    try:
        with httpx.Client(base_url=url, headers=ALICE, timeout=60) as c:
            r = submit_pair(c, pair, {"stages": ["coarse"], "outputs": ["result"]})
            assert r.status_code == 202, r.text
            job = wait_job(c, r.json()["id"], timeout=180)
            assert job["state"] == "succeeded", (job.get("error"), worker.tail())
    finally:
        worker.stop()
        api.stop()
