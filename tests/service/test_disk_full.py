"""A really full disk in embedded mode (issue 28): `gsa serve` runs with its storage and SQLite
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
from pathlib import Path

import httpx
import pytest

from tests.service.conftest import ALICE, PY, Proc, assert_problem, free_port, service_env, wait_job, wait_until

COARSE = {"stages": ["coarse"], "outputs": ["result"]}


def _namespaces_work() -> bool:
    if not shutil.which("unshare"):
        return False
    return subprocess.run(["unshare", "-Urm", "true"], capture_output=True).returncode == 0


pytestmark = pytest.mark.skipif(not _namespaces_work(), reason="needs unprivileged user namespaces (unshare -Urm)")


@pytest.fixture
def small_disk(tmp_path):
    disk, ctl = tmp_path / "disk", tmp_path / "ctl"
    ctl.mkdir()
    env = service_env(disk, GSA_MIN_FREE_BYTES=0)
    env.pop("GSA_REDIS_URL", None)  # embedded mode
    port = free_port()
    cmd = ["unshare", "-Urm", PY, "tests/service/fulldisk.py", str(disk), "16m", str(ctl), "--"]
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
    from service.stores.sqlite_store import SQLiteJobStore

    store = SQLiteJobStore(tmp_path / "jobs.sqlite3", reserve_bytes=1 << 20)
    reserve = Path(str(tmp_path / "jobs.sqlite3") + ".reserve")
    assert reserve.stat().st_size == 1 << 20
    seen = []

    def delete():  # full the first time, as a DELETE on a full disk is
        seen.append(reserve.exists())
        if len(seen) == 1:
            raise sqlite3.OperationalError("database or disk is full")
        return "deleted"

    assert store._freeing(delete) == "deleted"
    assert seen == [True, False]  # retried once the reserve was given up
    assert reserve.stat().st_size == 1 << 20  # and taken back
