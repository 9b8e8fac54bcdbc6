"""A really full disk in embedded mode: `gsa serve` runs with its storage and SQLite
database on a small tmpfs (a user + mount namespace of its own: tests/service/fulldisk.py),
which the test fills to its last byte. Before: DELETE of a job answered 507 (SQLite could not
append the DELETE to its log), so the API could not free the space it needed; a COMMIT that
failed was hidden by its ROLLBACK ("no transaction is active": a 500) and could leave a job
created behind a failed answer. Now: POST /v1/jobs answers 507 with nothing created and its
`Idempotency-Key` free for the retry; DELETE of jobs and assets answer 204 (the database keeps a
reserve file it gives up for a delete on a full disk); once space is back, jobs are accepted.
"""

from __future__ import annotations

import shutil
import sqlite3
import subprocess
import time
from pathlib import Path

import httpx
import pytest

from tests.service.conftest import (
    ALICE,
    PY,
    Proc,
    assert_problem,
    free_port,
    service_env,
    submit_pair,
    wait_job,
    wait_until,
)

COARSE = {"stages": ["coarse"], "outputs": ["result"]}


def _namespaces_work() -> bool:
    if not shutil.which("unshare"):
        return False
    return subprocess.run(["unshare", "-Urm", "true"], capture_output=True).returncode == 0


pytestmark = pytest.mark.skipif(not _namespaces_work(), reason="needs unprivileged user namespaces (unshare -Urm)")


def _serve_on_small_disk(tmp_path, size: str, **env_extra):
    """`gsa serve` (embedded) with its storage and SQLite database on a tmpfs of `size`;
    returns (url, control, proc): control("fill") fills the disk to its last byte,
    control("free") removes that filler."""
    disk, ctl = tmp_path / "disk", tmp_path / "ctl"
    ctl.mkdir()
    env = service_env(disk, GSA_MIN_FREE_BYTES=0, **env_extra)
    env.pop("GSA_REDIS_URL", None)  # embedded mode
    port = free_port()
    cmd = ["unshare", "-Urm", PY, "tests/service/fulldisk.py", str(disk), size, str(ctl), "--"]
    cmd += [PY, "-m", "service.cli", "serve", "--port", str(port), "--log-level", "warning"]
    proc = Proc(cmd, env, tmp_path / "api.log")
    url = f"http://127.0.0.1:{port}"

    def up():
        if proc.p.poll() is not None:
            raise RuntimeError(proc.tail())
        try:
            return httpx.get(url + "/healthz", timeout=1).status_code == 200
        except httpx.HTTPError:
            return False

    wait_until(up, 60, 0.1, "API on the small disk")

    def control(what: str) -> None:
        (ctl / what).touch()
        done = {"fill": "filled", "free": "freed"}[what]
        wait_until(lambda: (ctl / done).exists(), 60, 0.05, what)
        (ctl / done).unlink()

    return url, control, proc


@pytest.fixture
def small_disk(tmp_path):
    url, control, proc = _serve_on_small_disk(tmp_path, "16m")
    yield url, control, proc
    proc.stop()


def test_full_disk_create_is_507_with_nothing_behind_and_deletes_free_space(small_disk, pair):
    url, control, proc = small_disk
    with httpx.Client(base_url=url, headers=ALICE, timeout=60) as c:
        ids = []
        for k in ("source", "target", "source2"):
            with open(pair[k], "rb") as fh:
                r = c.post("/v1/assets", files={"file": (f"{k}.ply", fh)})
            assert r.status_code == 201, r.text
            ids.append(r.json()["id"])
        done = c.post("/v1/jobs", json={"source": ids[0], "target": ids[1], "options": COARSE}).json()
        assert wait_job(c, done["id"])["state"] == "succeeded"

        control("fill")
        before = [j["id"] for j in c.get("/v1/jobs").json()["items"]]
        for i in range(5):
            r = c.post(
                "/v1/jobs",
                json={"source": ids[0], "target": ids[1], "options": COARSE},
                headers={"Idempotency-Key": f"full-{i % 2}"},
            )
            assert_problem(r, 507, "insufficient-storage")
        assert [j["id"] for j in c.get("/v1/jobs").json()["items"]] == before  # nothing half-created

        # Deletes work on the full disk, and free space.
        assert c.delete(f"/v1/jobs/{done['id']}").status_code == 204
        assert c.delete(f"/v1/assets/{ids[2]}").status_code == 204
        assert c.get(f"/v1/jobs/{done['id']}").status_code == 404
        assert c.get(f"/v1/assets/{ids[2]}").status_code == 404

        control("free")
        r = c.post(
            "/v1/jobs",
            json={"source": ids[0], "target": ids[1], "options": COARSE},
            headers={"Idempotency-Key": "full-0"},  # refused on the full disk: not left claimed
        )
        assert r.status_code == 202, r.text
        assert wait_job(c, r.json()["id"])["state"] == "succeeded"
    assert "no transaction is active" not in proc.tail(20000)


def test_a_failed_update_surfaces_its_own_error_not_the_rollbacks(tmp_path):
    """A write that fails inside update()'s transaction raises that error ("database or disk
    is full", a 507), never the ROLLBACK's "no transaction is active" (a 500)."""
    from service.models import InputRef, Job
    from service.problems import infrastructure_problem
    from service.stores.sqlite_store import SQLiteJobStore

    store = SQLiteJobStore(tmp_path / "jobs.sqlite3", reserve_bytes=0)
    ref = InputRef(asset_id="a", key="k", kind="ply")
    store.create(Job(id="job_1", owner="a", created_at=0, updated_at=0, max_attempts=1, sources=[ref], target=ref))
    pages = store.db.execute("PRAGMA page_count").fetchone()[0]
    store.db.execute(f"PRAGMA max_page_count={pages}")
    with pytest.raises(sqlite3.OperationalError) as err:
        store.update("job_1", error={"detail": "x" * 200_000})
    assert "full" in str(err.value) and infrastructure_problem(err.value).status == 507
    assert not store.db.in_transaction
    assert store.get("job_1").error is None


def test_the_reserve_is_given_up_for_a_delete_and_taken_back(tmp_path):
    from service.stores.sqlite_store import RESERVE_SLICE, SQLiteJobStore

    store = SQLiteJobStore(tmp_path / "jobs.sqlite3", reserve_bytes=1 << 20)
    reserve = Path(str(tmp_path / "jobs.sqlite3") + ".reserve")
    assert reserve.stat().st_size == 1 << 20
    seen = []

    def delete():  # full the first two times, as a DELETE on a full disk is
        seen.append(reserve.stat().st_size if reserve.exists() else 0)
        if len(seen) < 3:
            raise sqlite3.OperationalError("database or disk is full")
        return "deleted"

    assert store._freeing(delete) == "deleted"
    # retried with a slice of the reserve given up each time, not all of it at once
    assert seen == [1 << 20, (1 << 20) - RESERVE_SLICE, (1 << 20) - 2 * RESERVE_SLICE]
    assert reserve.stat().st_size == 1 << 20  # and taken back


@pytest.fixture(scope="module")
def distinct_plys(tmp_path_factory):
    """30 different 340 KB PLYs (5,000 Gaussians each) and a target."""
    from gsa.io.ply import write_ply
    from gsa.synth import make_object

    d = tmp_path_factory.mktemp("distinct")
    paths = []
    for i in range(31):
        paths.append(d / f"m{i}.ply")
        write_ply(make_object("car", seed=100 + i, n_gaussians=5000), paths[-1])
    return paths[0], paths[1:]


def _log_lines(proc: Proc) -> int:
    return len(proc.log.read_text(errors="replace").splitlines())


@pytest.mark.slow
def test_full_disk_with_queued_jobs_every_job_cancels_and_deletes_without_a_log_flood(tmp_path, distinct_plys, pair):
    """Embedded mode, a 12 MB disk filled by uploads while their jobs queue (every job with
    the default outputs). Before: `:cancel` answered 507 (its state change could not be
    written to the full database), DELETE of jobs and assets 409, two jobs stayed "running"
    and the worker logged ~12-18 tracebacks a second, trying one queued job after another."""
    url, control, proc = _serve_on_small_disk(
        tmp_path, "12m", GSA_RETRY_BACKOFF_BASE_S="2", GSA_RETRY_BACKOFF_MAX_S="8"
    )
    target_ply, sources = distinct_plys
    try:
        with httpx.Client(base_url=url, headers=ALICE, timeout=60) as c:
            r = c.post("/v1/assets", files={"file": ("target.ply", target_ply.read_bytes())})
            assert r.status_code == 201, r.text
            assets, jobs = [r.json()["id"]], []
            for p in sources:
                r = c.post("/v1/assets", files={"file": (p.name, p.read_bytes())})
                if r.status_code == 507:
                    continue
                assert r.status_code == 201, r.text
                assets.append(r.json()["id"])
                r = c.post("/v1/jobs", json={"source": assets[-1], "target": assets[0]})
                if r.status_code != 507:
                    assert r.status_code == 202, r.text
                    jobs.append(r.json()["id"])
            control("fill")  # to its last byte, whatever the jobs have stored so far
            states = [c.get(f"/v1/jobs/{j}").json()["state"] for j in jobs]
            assert states.count("queued") >= 5, states

            # No flood: on the full disk the worker backs off, one line per failed attempt.
            time.sleep(3)
            lines, t = _log_lines(proc), time.monotonic()
            time.sleep(10)
            rate = (_log_lines(proc) - lines) / (time.monotonic() - t)
            assert rate < 3, proc.tail(4000)

            # Every queued and running job cancels, on the disk full to its last byte again
            # (what the store gave up of its reserve meanwhile included).
            control("fill")
            for j in jobs:
                r = c.post(f"/v1/jobs/{j}:cancel")
                assert r.status_code == 202 or r.json().get("type", "").endswith("/job-finished"), r.text

            def settled():
                return all(c.get(f"/v1/jobs/{j}").json()["state"] not in ("queued", "running") for j in jobs)

            wait_until(settled, 60, 0.5, "every job final")
            # Then every job and every asset deletes.
            for j in jobs:
                r = c.delete(f"/v1/jobs/{j}")
                assert r.status_code == 204, r.text
            for a in assets:
                r = c.delete(f"/v1/assets/{a}")
                assert r.status_code == 204, r.text
            assert c.get("/v1/jobs").json()["items"] == []

            # Space back: the worker takes jobs again.
            control("free")
            job = submit_pair(c, pair, COARSE)
            assert job.status_code == 202, job.text
            assert wait_job(c, job.json()["id"], timeout=120)["state"] == "succeeded", proc.tail(4000)
        log = proc.log.read_text(errors="replace")
        assert log.count("Traceback") <= 2, proc.tail(8000)
    finally:
        proc.stop()
