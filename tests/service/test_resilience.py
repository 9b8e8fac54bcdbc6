"""Infrastructure failures: a Redis that goes away and comes back (worker
supervisor, 503 answers, readiness), storage errors, temp-dir cleanup.

Each test runs its own redis-server on a free port (never 6379), with an
append-only file in its own folder so the queue survives a restart."""

from __future__ import annotations

import shutil
import subprocess
import time
from pathlib import Path

import httpx
import pytest

from tests.service.conftest import (
    ALICE,
    free_port,
    service_env,
    start_api,
    start_worker,
    submit_pair,
    submit_slow_job,
    wait_job,
    wait_until,
)

pytestmark = pytest.mark.slow  # starts servers and worker processes


class RedisServer:
    """A private redis-server that can be stopped and started again on the same
    port and data folder (appendonly: what was queued survives the restart)."""

    def __init__(self, d: Path):
        self.exe = shutil.which("redis-server")
        if self.exe is None:
            pytest.fail("redis-server not installed (./dev.sh test installs it)")
        self.dir, self.port, self.p = d, free_port(), None
        d.mkdir(parents=True, exist_ok=True)

    @property
    def url(self) -> str:
        return f"redis://127.0.0.1:{self.port}/0"

    def start(self) -> None:
        args = [self.exe, "--port", str(self.port), "--bind", "127.0.0.1", "--dir", str(self.dir)]
        args += ["--appendonly", "yes", "--appendfsync", "always", "--save", ""]
        self.p = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        import redis

        r = redis.Redis(port=self.port)

        def up():
            try:
                return r.ping()
            except Exception:
                return False

        wait_until(up, 20, 0.05, "redis-server")
        r.close()

    def stop(self) -> None:
        if self.p is not None and self.p.poll() is None:
            self.p.terminate()
            self.p.wait(20)
        self.p = None


@pytest.fixture
def redis_server(tmp_path):
    srv = RedisServer(tmp_path / "redis")
    srv.start()
    yield srv
    srv.stop()


def _alive_for(proc, seconds: float) -> None:
    t = time.monotonic() + seconds
    while time.monotonic() < t:
        assert proc.p.poll() is None, proc.tail()
        time.sleep(0.2)


def test_worker_survives_redis_restart(tmp_path, redis_server, pair):
    """Redis restarts while a job runs: the worker stays up, the interrupted job is
    requeued and finishes, and a job submitted after the restart runs too."""
    env = service_env(
        tmp_path,
        GSA_REDIS_URL=redis_server.url,
        GSA_WORKER_RECONNECT_MIN_S="0.2",
        GSA_WORKER_RECONNECT_MAX_S="1",
    )
    api, url, _ = start_api(tmp_path, env, name="api-restart")
    worker = start_worker(tmp_path, env, name="worker-restart")
    try:
        with httpx.Client(base_url=url, headers=ALICE, timeout=60) as http:
            job, _ = submit_slow_job(http, pair, copies=3)
            wait_job(http, job["id"], states=("running",), timeout=120)
            redis_server.stop()
            _alive_for(worker, 4)
            redis_server.start()
            done = wait_job(http, job["id"], timeout=180)
            assert done["state"] == "succeeded", (done, worker.tail())
            second = submit_pair(http, pair, {"stages": ["coarse"], "outputs": ["result"]})
            assert second.status_code == 202, second.text
            done = wait_job(http, second.json()["id"], timeout=120)
            assert done["state"] == "succeeded", (done, worker.tail())
            assert worker.p.poll() is None
    finally:
        worker.stop()
        api.stop()


def test_worker_started_while_redis_is_down_waits_for_it(tmp_path, redis_server, pair):
    env = service_env(
        tmp_path,
        GSA_REDIS_URL=redis_server.url,
        GSA_WORKER_RECONNECT_MIN_S="0.2",
        GSA_WORKER_RECONNECT_MAX_S="1",
    )
    redis_server.stop()
    worker = start_worker(tmp_path, env, name="worker-early")
    api = None
    try:

        def retrying():
            assert worker.p.poll() is None, worker.tail()
            return "reconnect attempt 2" in worker.tail(50000)

        wait_until(retrying, 90, 0.2, "the worker to retry")
        assert worker.p.poll() is None, worker.tail()
        redis_server.start()
        wait_until(lambda: "Redis is back" in worker.tail(50000), 30, 0.2, "the worker to reconnect")
        api, url, _ = start_api(tmp_path, env, name="api-early")
        with httpx.Client(base_url=url, headers=ALICE, timeout=60) as http:
            r = submit_pair(http, pair, {"stages": ["coarse"], "outputs": ["result"]})
            assert r.status_code == 202, r.text
            done = wait_job(http, r.json()["id"], timeout=120)
            assert done["state"] == "succeeded", (done, worker.tail())
    finally:
        worker.stop()
        if api is not None:
            api.stop()
