"""`gsa wait` outlives a dropped connection: the API SIGKILLed while the client polls (its
keep-alive connection drops, the next polls are refused) and started again on the same port;
the client retries with back-off and reports the job's end (it exited 3, "cannot reach", on
the first failed poll). A server never reached still fails at once
(tests/service/test_client_cli.py)."""

from __future__ import annotations

import json
import subprocess
import time

import pytest

from tests.service.conftest import ALICE, PY, ROOT, service_env, submit_pair
from tests.service.harness import Deployment, RedisServer

pytestmark = pytest.mark.slow  # starts servers and worker processes


def test_gsa_wait_retries_a_dropped_connection(tmp_path, pair):
    redis = RedisServer(tmp_path / "redis")
    redis.start()
    d = Deployment(tmp_path, service_env(tmp_path, GSA_REDIS_URL=redis.url), redis)
    try:
        url = d.start_api()
        with d.client(ALICE) as c:  # no worker yet: the job waits queued
            r = submit_pair(c, pair, {"stages": ["coarse"], "outputs": ["result"]})
        assert r.status_code == 202, r.text
        job_id = r.json()["id"]
        args = [PY, "-m", "gsa.cli", "wait", job_id, "--server", url, "--api-key", "key-alice"]
        waiter = subprocess.Popen(args, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            time.sleep(3)  # it has polled and been answered
            assert waiter.poll() is None, waiter.communicate()
            d.stop_api(kill=True)
            time.sleep(1)  # polls meanwhile are refused
            assert waiter.poll() is None, waiter.communicate()
            d.start_api()
            d.add_worker()
            out, err = waiter.communicate(timeout=180)
        finally:
            if waiter.poll() is None:
                waiter.kill()
        assert waiter.returncode == 0, err
        assert json.loads(out)["state"] == "succeeded", out
        assert "Traceback" not in err and "cannot reach" not in err, err
    finally:
        d.close()
