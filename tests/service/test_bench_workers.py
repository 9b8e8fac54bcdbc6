"""benchmarks/service/bench_workers.py polls within the tenant's rate limit: it waited for jobs with 50
requests a second per job and stopped with KeyError 'state' on the first 429. Real API
(embedded mode: its own worker thread runs the jobs) with a rate limit the old polling passed
at once."""

from __future__ import annotations

import time

import httpx
import pytest

from tests.service.conftest import ALICE, service_env, start_api, submit_pair

pytestmark = pytest.mark.slow  # starts an API process


def _bench():
    from benchmarks.service import bench_workers

    return bench_workers


def test_the_workers_benchmark_waits_for_jobs_within_the_rate_limit(tmp_path, pair):
    bench = _bench()
    env = service_env(tmp_path, GSA_TENANT_RATE_PER_S=5, GSA_TENANT_RATE_BURST=5)
    api, url, _ = start_api(tmp_path, env, name="bench-api")
    try:
        with httpx.Client(base_url=url, headers=ALICE, timeout=60) as c:
            ids = []
            for _ in range(3):
                ids.append(submit_pair(c, pair, {"stages": ["coarse"], "outputs": ["result"]}).json()["id"])
                time.sleep(0.4)  # the submissions within the rate themselves
            done = bench.wait_final(c, ids, timeout=240)
            limited = c.get(f"/v1/jobs/{ids[0]}")
            for _ in range(10):  # the bucket is empty after this: the benchmark's calls wait it out
                limited = c.get(f"/v1/jobs/{ids[0]}")
            assert limited.status_code == 429, limited.text
            again = bench.request(c, "GET", f"/v1/jobs/{ids[0]}").json()
        assert sorted(done) == sorted(ids)
        assert {j["state"] for j in done.values()} == {"succeeded"}, done
        assert again["state"] == "succeeded"
    finally:
        api.stop()
