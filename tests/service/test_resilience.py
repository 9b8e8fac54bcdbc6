"""Infrastructure failures: a Redis that goes away and comes back (worker
supervisor, 503 answers, readiness), storage errors, temp-dir cleanup.

Each test runs its own redis-server on a free port (never 6379), with an
append-only file in its own folder so the queue survives a restart."""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import httpx
import pytest

from tests.service.conftest import (
    ALICE,
    assert_problem,
    service_env,
    start_api,
    start_worker,
    submit_pair,
    submit_slow_job,
    wait_job,
    wait_until,
)
from tests.service.harness import RedisServer

pytestmark = pytest.mark.slow  # starts servers and worker processes


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


def test_api_answers_503_while_redis_is_down_and_recovers_on_the_same_connection(tmp_path, redis_server, pair):
    import http.client

    env = service_env(tmp_path, GSA_REDIS_URL=redis_server.url, GSA_UNAVAILABLE_RETRY_AFTER_S="7")
    api, url, _ = start_api(tmp_path, env, name="api-503")
    try:
        with httpx.Client(base_url=url, headers=ALICE, timeout=60) as http_:
            r = submit_pair(http_, pair, {"stages": ["coarse"], "outputs": ["result"]})
            assert r.status_code == 202, r.text
            job_id = r.json()["id"]
        host, port = url.removeprefix("http://").split(":")
        conn = http.client.HTTPConnection(host, int(port), timeout=30)

        def call(method, path, body=None):
            headers = {**ALICE, "Content-Type": "application/json"} if body else dict(ALICE)
            conn.request(method, path, body=body, headers=headers)
            resp = conn.getresponse()
            return resp, resp.read()

        resp, _ = call("GET", f"/v1/jobs/{job_id}")
        assert resp.status == 200
        sock = conn.sock

        redis_server.stop()
        for method, path, body in (
            ("GET", f"/v1/jobs/{job_id}", None),
            ("GET", "/v1/jobs", None),
            ("POST", "/v1/jobs", b'{"sources": ["ast_x"], "target": "ast_y"}'),
            ("POST", f"/v1/jobs/{job_id}:cancel", None),
        ):
            resp, raw = call(method, path, body)
            assert resp.status == 503, (method, path, resp.status, raw)
            assert resp.getheader("Content-Type").startswith("application/problem+json")
            assert resp.getheader("Retry-After") == "7"
            problem = json.loads(raw)
            assert problem["status"] == 503 and problem["type"].endswith("/store-unavailable"), problem
            assert not resp.will_close and conn.sock is sock, "the keep-alive connection must survive"
        resp, raw = call("GET", "/readyz")
        assert resp.status == 503 and resp.getheader("Retry-After"), raw
        assert json.loads(raw)["checks"]["store"] is False

        redis_server.start()
        resp, raw = call("GET", f"/v1/jobs/{job_id}")
        assert resp.status == 200, raw
        assert conn.sock is sock  # the same connection, still serving
        resp, raw = call("GET", "/readyz")
        assert resp.status == 200, raw
        conn.close()
    finally:
        api.stop()


def test_storage_errors_are_507_or_503_and_jobs_retry_them(tmp_path, pair, monkeypatch):
    """Disk full on an upload is 507, another storage I/O error 503 (problem+json,
    not 500); a job attempt that hits a full disk is requeued, and fails with
    insufficient-storage (not alignment-failed) once its attempts are spent."""
    import errno

    from fastapi.testclient import TestClient

    from service.api.app import create_app
    from service.backend import make_backend
    from service.models import JobState
    from service.settings import Settings
    from service.worker.execution import execute

    # No back-off here, so the retry can run at once (back-off: test_retry_backoff.py).
    s = Settings(storage_root=tmp_path / "data", api_keys={"k": "me"}, max_attempts=2, retry_backoff_base_s=0)
    H = {"Authorization": "Bearer k"}
    backend = make_backend(s)
    real_put = backend.storage.put
    with TestClient(create_app(s, backend, run_workers=False)) as c:

        def upload():
            with open(pair["source"], "rb") as fh:
                return c.post("/v1/assets", headers=H, files={"file": ("s.ply", fh)})

        def failing_put(code):
            def put(key, data, **kw):
                raise OSError(code, os.strerror(code))

            return put

        monkeypatch.setattr(backend.storage, "put", failing_put(errno.ENOSPC))
        assert_problem(upload(), 507, "insufficient-storage")
        monkeypatch.setattr(backend.storage, "put", failing_put(errno.EIO))
        r = upload()
        assert_problem(r, 503, "storage-unavailable")
        assert r.headers["Retry-After"]

        monkeypatch.setattr(backend.storage, "put", real_put)
        with open(pair["source"], "rb") as a, open(pair["target"], "rb") as b:
            r = c.post(
                "/v1/jobs",
                headers=H,
                files=[("source", ("s.ply", a)), ("target", ("t.ply", b))],
                data={"options": '{"stages": ["coarse"], "outputs": ["result"]}'},
            )
        assert r.status_code == 202, r.text
        jid = r.json()["id"]
        monkeypatch.setattr(backend.storage, "put", failing_put(errno.ENOSPC))
        assert execute(jid, backend) == JobState.queued  # storing the artifacts failed: try again
        job = c.get(f"/v1/jobs/{jid}", headers=H).json()
        assert job["state"] == "queued" and job["attempts"] == 1 and job["error"] is None, job
        assert execute(jid, backend) == JobState.failed  # attempts spent
        job = c.get(f"/v1/jobs/{jid}", headers=H).json()
        assert job["error"]["type"].endswith("/insufficient-storage") and job["error"]["status"] == 507, job


# ------------------------------------------------------------ job temp folders
def _workspaces(root: Path) -> list[Path]:
    return sorted(root.glob("gsa-job-*"))


def test_every_exit_path_removes_the_job_temp_folder(tmp_path, pair, monkeypatch):
    import tempfile

    import gsa.align.pipeline as pipeline
    from service.backend import make_backend
    from service.models import JobState
    from service.settings import Settings
    from service.worker.execution import execute

    tmp = tmp_path / "tmp"
    tmp.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(tmp))
    s = Settings(storage_root=tmp_path / "data", api_keys={"k": "me"}, max_attempts=1)
    backend = make_backend(s)
    real_align = pipeline.align
    seen = []

    def submit() -> str:
        from fastapi.testclient import TestClient

        from service.api.app import create_app

        with TestClient(create_app(s, backend, run_workers=False)) as c:
            with open(pair["source"], "rb") as a, open(pair["target"], "rb") as b:
                r = c.post(
                    "/v1/jobs",
                    headers={"Authorization": "Bearer k"},
                    files=[("source", ("s.ply", a)), ("target", ("t.ply", b))],
                    data={"options": '{"stages": ["coarse"], "outputs": ["result"]}'},
                )
        assert r.status_code == 202, r.text
        return r.json()["id"]

    def run_with(fake) -> tuple[JobState | None, str]:
        jid = submit()

        def align(source, target, opts, progress=None):
            seen.append(_workspaces(tmp))
            return fake(jid, source, target, opts, progress)

        monkeypatch.setattr(pipeline, "align", align)
        try:
            state = execute(jid, backend)
        finally:
            monkeypatch.setattr(pipeline, "align", real_align)
        assert seen[-1], "the attempt should have had a workspace"
        assert _workspaces(tmp) == [], f"workspace left behind after {state}"
        return state, jid

    def ok(jid, *a):
        return real_align(*a)

    def boom(jid, *a):
        raise RuntimeError("library bug")

    def cancelled(jid, *a):
        backend.store.update(jid, cancel_requested=True)
        a[-1]("coarse", 0.5)

    def lease_lost(jid, *a):
        backend.store.update(jid, run_token="someone-else")
        a[-1]("coarse", 0.5)

    def timed_out(jid, *a):
        backend.settings.job_timeout_s = 0.0
        try:
            a[-1]("coarse", 0.5)
        finally:
            backend.settings.job_timeout_s = 3600.0

    def interrupted(jid, *a):
        raise SystemExit(143)  # what run_job turns the work horse's SIGTERM into

    assert run_with(ok)[0] == JobState.succeeded
    assert run_with(boom)[0] == JobState.failed
    assert run_with(cancelled)[0] == JobState.cancelled
    assert run_with(lease_lost)[0] is None
    assert run_with(timed_out)[0] == JobState.failed
    with pytest.raises(SystemExit):
        run_with(interrupted)
    assert _workspaces(tmp) == []


def test_sweep_removes_only_workspaces_no_live_attempt_owns(tmp_path):
    import time as _time

    from service.backend import make_backend
    from service.models import InputRef, Job, JobState
    from service.settings import Settings
    from service.worker.leases import sweep_workspaces

    b = make_backend(Settings(storage_root=tmp_path / "data", lease_s=30, job_timeout_s=600))
    ref = InputRef(asset_id="a", key="uploads/x/y", kind="ply")
    now = _time.time()

    def job(jid, state, token=None, lease=None):
        b.store.create(Job(id=jid, owner="o", created_at=now, updated_at=now, sources=[ref], target=ref))
        if state != JobState.queued:
            b.store.update(jid, state=state, run_token=token, lease_until=lease)

    tok = "a" * 32
    job("job_" + "1" * 32, JobState.running, tok, now + 60)  # live attempt
    job("job_" + "2" * 32, JobState.queued)  # its worker died: the reaper requeued it
    job("job_" + "3" * 32, JobState.failed)  # finished
    job("job_" + "4" * 32, JobState.running, "b" * 32, now + 60)  # a newer attempt owns it
    root = tmp_path / "tmp"
    dirs = {}
    for name, age in (
        ("live", 120),
        ("expired", 120),
        ("finished", 120),
        ("superseded", 120),
        ("young", 5),
        ("legacy-old", 1000),
        ("legacy-recent", 120),
        ("other-store", 120),  # a job this store does not know: another deployment's
        ("other-store-old", 1000),
    ):
        n = {"live": 1, "expired": 2, "finished": 3, "superseded": 4, "young": 3, "other-store": 7}.get(name)
        n = {"other-store-old": 8}.get(name, n)
        d = root / (f"gsa-job-job_{str(n) * 32}-{tok[:12]}-x{name}" if n else f"gsa-job-{name}")
        (d / "out0").mkdir(parents=True)
        (d / "source0.ply").write_bytes(b"ply")
        os.utime(d, (now - age, now - age))
        dirs[name] = d
    removed = {p.name for p in sweep_workspaces(b, root)}
    assert removed == {dirs[k].name for k in ("expired", "finished", "superseded", "legacy-old", "other-store-old")}
    kept = ("live", "young", "legacy-recent", "other-store")
    assert {p.name for p in _workspaces(root)} == {dirs[k].name for k in kept}


def test_sigterm_of_the_work_horse_removes_its_temp_folder(tmp_path, redis_url, pair):
    tmp = tmp_path / "tmp"
    tmp.mkdir()
    env = service_env(
        tmp_path,
        GSA_REDIS_URL=redis_url + "/2",
        GSA_QUEUE_NAME="sigterm",
        TMPDIR=str(tmp),
        # no reaper pass during the test: the folder must go because the horse cleaned up
        GSA_REAPER_INTERVAL_S="3600",
        GSA_LEASE_S="60",
    )
    api, url, _ = start_api(tmp_path, env, name="api-sigterm")
    worker = start_worker(tmp_path, env, name="worker-sigterm")
    try:
        with httpx.Client(base_url=url, headers=ALICE, timeout=60) as http_:
            job, _ = submit_slow_job(http_, pair, copies=4)
            wait_job(http_, job["id"], states=("running",), timeout=120)
            wait_until(lambda: _workspaces(tmp), 60, 0.1, "the job's temp folder")
            assert job["id"] in _workspaces(tmp)[0].name

            def horse():
                for pid in worker.descendants():
                    try:
                        pgrp = int(Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[2])
                    except (OSError, ValueError, IndexError):
                        continue
                    if pgrp == pid:  # RQ's work horse leads its own process group
                        return pid
                return None

            pid = wait_until(horse, 30, 0.1, "the work horse")
            os.kill(pid, 15)
            wait_until(lambda: not _workspaces(tmp), 60, 0.1, "the horse to remove its temp folder")
    finally:
        worker.stop()
        api.stop()


def test_embedded_store_errors_are_problems(tmp_path, monkeypatch):
    """SQLite's equivalents: a locked database is 503 + Retry-After, a full one 507,
    and a genuine bug (no such table) stays a 500."""
    import sqlite3

    from fastapi.testclient import TestClient

    from service.api.app import create_app
    from service.backend import make_backend
    from service.settings import Settings

    s = Settings(storage_root=tmp_path / "data", api_keys={"k": "me"}, unavailable_retry_after_s=11)
    backend = make_backend(s)
    with TestClient(create_app(s, backend, run_workers=False), raise_server_exceptions=False) as c:
        for message, status, kind in (
            ("database is locked", 503, "store-unavailable"),
            ("database or disk is full", 507, "insufficient-storage"),
            ("no such table: jobs", 500, "internal-error"),
        ):

            def get(job_id, message=message):
                raise sqlite3.OperationalError(message)

            monkeypatch.setattr(backend.store, "get", get)
            r = c.get("/v1/jobs/job_x", headers={"Authorization": "Bearer k"})
            assert_problem(r, status, kind)
            assert (r.headers.get("Retry-After") == "11") == (status == 503), r.headers
