"""Deleting jobs and assets (HTTP and gRPC), content-addressed upload dedup and the
retention sweep, against real servers (Redis stack, embedded SQLite) and storage."""

from __future__ import annotations

import hashlib

import grpc
import httpx
import pytest

from service.rpc.generated import alignment_pb2 as pb
from service.rpc.generated import alignment_pb2_grpc as pbg
from tests.service.conftest import (
    ALICE,
    BOB,
    assert_problem,
    service_env,
    start_api,
    submit_slow_job,
    wait_job,
    wait_until,
)

pytestmark = pytest.mark.slow  # starts servers and worker processes

OPTS = {"stages": ["coarse"], "outputs": ["result", "aligned"]}


@pytest.fixture(scope="module")
def unique_ply(tmp_path_factory):
    """A PLY no other test uploads, so blob counts in the shared stack are this test's."""
    from gsa.io.ply import write_ply
    from gsa.synth import make_object

    p = tmp_path_factory.mktemp("uniq") / "unique.ply"
    write_ply(make_object("chair", seed=1234, n_gaussians=1500), p)
    return p


def _blobs_with(root, data: bytes) -> list:
    """Files anywhere under the storage root holding exactly these bytes."""
    sha = hashlib.sha256(data).hexdigest()
    return [
        p
        for p in root.rglob("*")
        if p.is_file() and p.stat().st_size == len(data) and hashlib.sha256(p.read_bytes()).hexdigest() == sha
    ]


def _upload(http, name, data) -> dict:
    r = http.post("/v1/assets", files={"file": (name, data)})
    assert r.status_code == 201, r.text
    return r.json()


def test_identical_uploads_are_stored_once_and_outlive_one_delete(http, stack, pair, unique_ply):
    root = stack["tmp"] / "data" / "blobs"
    data = unique_ply.read_bytes()
    a, b = _upload(http, "one.ply", data), _upload(http, "two.ply", data)
    assert a["id"] != b["id"] and a["sha256"] == b["sha256"] == hashlib.sha256(data).hexdigest()
    assert b["filename"] == "two.ply" and b["n_gaussians"] == a["n_gaussians"] == 1500
    assert len(_blobs_with(root, data)) == 1
    # Another owner's identical upload is its own copy: dedup never crosses tenants.
    c = _upload(httpx.Client(base_url=stack["url"], headers=BOB, timeout=60), "bob.ply", data)
    assert len(_blobs_with(root, data)) == 2

    assert_problem(http.delete(f"/v1/assets/{a['id']}", headers=BOB), 404, "not-found")
    r = http.delete(f"/v1/assets/{a['id']}")
    assert r.status_code == 204 and r.content == b""
    assert_problem(http.get(f"/v1/assets/{a['id']}"), 404)
    assert_problem(http.delete(f"/v1/assets/{a['id']}"), 404)
    assert len(_blobs_with(root, data)) == 2  # b still needs the bytes

    # The remaining id still works as a job input.
    with open(pair["target"], "rb") as fh:
        tgt = _upload(http, "t.ply", fh.read())
    job = http.post("/v1/jobs", json={"source": b["id"], "target": tgt["id"], "options": OPTS}).json()
    assert wait_job(http, job["id"])["state"] == "succeeded"

    assert http.delete(f"/v1/assets/{b['id']}").status_code == 204
    assert len(_blobs_with(root, data)) == 1  # only bob's copy is left
    assert httpx.delete(f"{stack['url']}/v1/assets/{c['id']}", headers=BOB).status_code == 204
    assert _blobs_with(root, data) == []


def test_delete_finished_job_removes_artifacts_and_frees_its_idempotency_key(http, stack, pair):
    ids = [_upload(http, n, open(pair[n], "rb").read())["id"] for n in ("source", "target")]
    body = {"source": ids[0], "target": ids[1], "options": OPTS}
    key = {"Idempotency-Key": "delete-me-1"}
    job = http.post("/v1/jobs", json=body, headers=key).json()
    done = wait_job(http, job["id"])
    assert done["state"] == "succeeded"
    art_dir = stack["tmp"] / "data" / "blobs" / "jobs" / job["id"]
    assert any(p.is_file() for p in art_dir.rglob("*"))
    href = done["artifacts"][0]["href"]

    assert_problem(http.delete(f"/v1/jobs/{job['id']}", headers=BOB), 404, "not-found")
    r = http.delete(f"/v1/jobs/{job['id']}")
    assert r.status_code == 204 and r.content == b""
    assert_problem(http.get(f"/v1/jobs/{job['id']}"), 404)
    assert_problem(http.get(href), 404)
    assert not art_dir.exists()
    assert job["id"] not in [j["id"] for j in http.get("/v1/jobs", params={"limit": 200}).json()["items"]]
    assert_problem(http.delete(f"/v1/jobs/{job['id']}"), 404)
    # The inputs are assets of their own and stay.
    assert all(http.get(f"/v1/assets/{i}").status_code == 200 for i in ids)

    # The key now names no job: the same request makes a new one (not a replay, not 409).
    again = http.post("/v1/jobs", json=body, headers=key)
    assert again.status_code == 202 and again.json()["id"] != job["id"]
    assert "idempotent-replayed" not in again.headers
    wait_job(http, again.json()["id"])


def test_running_job_and_its_assets_cannot_be_deleted_until_cancelled(http, stack, pair):
    job, ids = submit_slow_job(http, pair, copies=6)
    wait_job(http, job["id"], states=("running",), timeout=60)
    b = assert_problem(http.delete(f"/v1/jobs/{job['id']}"), 409, "job-not-finished")
    assert ":cancel" in b["detail"]
    b = assert_problem(http.delete(f"/v1/assets/{ids[0]}"), 409, "asset-in-use")
    assert b["job_id"] == job["id"]
    assert http.get(f"/v1/assets/{ids[0]}").status_code == 200

    http.post(f"/v1/jobs/{job['id']}:cancel")
    assert wait_job(http, job["id"], timeout=60)["state"] == "cancelled"
    assert http.delete(f"/v1/assets/{ids[0]}").status_code == 204
    assert http.delete(f"/v1/jobs/{job['id']}").status_code == 204
    assert_problem(http.get(f"/v1/jobs/{job['id']}"), 404)


def test_grpc_delete_job(http, stack, pair):
    ids = [_upload(http, n, open(pair[n], "rb").read())["id"] for n in ("source", "target")]
    jid = http.post("/v1/jobs", json={"source": ids[0], "target": ids[1], "options": OPTS}).json()["id"]
    ch = grpc.insecure_channel(stack["grpc"])
    stub = pbg.AlignmentServiceStub(ch)
    alice = (("authorization", "Bearer key-alice"),)
    try:
        wait_job(http, jid)
        with pytest.raises(grpc.RpcError) as e:
            stub.DeleteJob(pb.JobRef(job_id=jid), metadata=(("authorization", "Bearer key-bob"),))
        assert e.value.code() == grpc.StatusCode.NOT_FOUND
        stub.DeleteJob(pb.JobRef(job_id=jid), metadata=alice)
        assert_problem(http.get(f"/v1/jobs/{jid}"), 404)
        with pytest.raises(grpc.RpcError) as e:
            stub.DeleteJob(pb.JobRef(job_id=jid), metadata=alice)
        assert e.value.code() == grpc.StatusCode.NOT_FOUND

        slow, _ = submit_slow_job(http, pair, copies=4)
        with pytest.raises(grpc.RpcError) as e:
            stub.DeleteJob(pb.JobRef(job_id=slow["id"]), metadata=alice)
        assert e.value.code() == grpc.StatusCode.FAILED_PRECONDITION
        http.post(f"/v1/jobs/{slow['id']}:cancel")
        wait_job(http, slow["id"], timeout=60)
    finally:
        ch.close()


def test_retention_sweep_deletes_old_jobs_and_unused_assets(tmp_path, pair):
    """Embedded mode (SQLite): a retention of 3 s swept every 0.3 s."""
    env = service_env(
        tmp_path, GSA_EMBEDDED_WORKERS=1, GSA_RETENTION_DAYS=3 / 86400, GSA_RETENTION_SWEEP_INTERVAL_S=0.3
    )
    api, url, _ = start_api(tmp_path, env, name="retention")
    blobs = tmp_path / "data" / "blobs"
    try:
        with httpx.Client(base_url=url, headers=ALICE, timeout=60) as http:
            ids = [_upload(http, n, open(pair[n], "rb").read())["id"] for n in ("source", "target")]
            spare = _upload(http, "spare.ply", open(pair["source2"], "rb").read())["id"]
            jid = http.post("/v1/jobs", json={"source": ids[0], "target": ids[1], "options": OPTS}).json()["id"]
            assert wait_job(http, jid)["state"] == "succeeded"
            assert (blobs / "jobs" / jid).exists()
            # Everything goes once its time is up: the job, its artifacts, then its inputs.
            wait_until(lambda: http.get(f"/v1/jobs/{jid}").status_code == 404, 20, 0.1, "the job to expire")
            assert not (blobs / "jobs" / jid).exists()
            for i in (*ids, spare):
                wait_until(lambda i=i: http.get(f"/v1/assets/{i}").status_code == 404, 20, 0.1, f"{i} to expire")
            assert not [p for p in (blobs / "cas").rglob("*") if p.is_file()]
            # A fresh upload is kept while it is within the retention.
            fresh = _upload(http, "fresh.ply", open(pair["source"], "rb").read())["id"]
            assert http.get(f"/v1/assets/{fresh}").status_code == 200
    finally:
        api.stop()


def test_retention_keeps_what_is_recent_or_still_in_use(tmp_path):
    """The sweep's decisions at a given time, on a real SQLite store and local storage."""
    from service.backend import make_backend
    from service.jobs.retention import sweep
    from service.models import Asset, InputRef, Job, JobState
    from service.settings import Settings

    b = make_backend(Settings(storage_root=tmp_path, retention_days=1))
    day, now = 86400.0, 10 * 86400.0

    def asset(name, age_days):
        key = f"cas/{'0' * 32}/{hashlib.sha256(name.encode()).hexdigest()}"
        b.storage.put(key, [name.encode()])
        a = Asset(id=f"ast_{name}", owner="o", kind="ply", key=key, size=len(name), content_type="x",
                  sha256="0", created_at=now - age_days * day)  # fmt: skip
        b.store.put_asset(a)
        b.store.add_blob_ref(key, a.id)
        return a

    def job(name, state, age_days, src, tgt):
        ref = lambda a: InputRef(asset_id=a.id, key=a.key, kind="ply")  # noqa: E731
        t = now - age_days * day
        b.store.create(Job(id=f"job_{name}", owner="o", state=state, created_at=t, updated_at=t,
                           finished_at=t if state != JobState.running else None, sources=[ref(src)], target=ref(tgt)))  # fmt: skip
        b.storage.put(f"jobs/job_{name}/tok/result.json", [b"{}"])

    old_in, old_in2, old_free, new_free = asset("a", 5), asset("b", 5), asset("c", 5), asset("d", 0.5)
    old_run_in = asset("e", 5)
    job("old", JobState.succeeded, 2, old_in, old_in)
    job("recent", JobState.failed, 0.5, old_in2, old_in2)
    job("running", JobState.running, 3, old_run_in, old_run_in)

    assert sweep(b, now=now) == {"jobs": 1, "assets": 2}  # job_old; then a (no job left) and c
    assert b.store.get("job_old") is None and not b.storage.exists("jobs/job_old/tok/result.json")
    assert b.store.get("job_recent") is not None and b.store.get("job_running") is not None
    assert b.storage.exists("jobs/job_recent/tok/result.json")
    gone = {a.id for a in (old_in, old_free)}
    for a in (old_in, old_in2, old_free, new_free, old_run_in):
        assert (b.store.get_asset(a.id) is None) == (a.id in gone), a.id
        assert b.storage.exists(a.key) == (a.id not in gone), a.id
    assert sweep(b, now=now) == {"jobs": 0, "assets": 0}
    assert sweep(make_backend(Settings(storage_root=tmp_path)), now=now + 100 * day) == {"jobs": 0, "assets": 0}


@pytest.mark.parametrize("kind", ["sqlite", "redis"])
def test_concurrent_identical_uploads_and_deletes_never_lose_live_bytes(kind, tmp_path, redis_url, unique_ply):
    """Threads upload the same bytes and delete their assets at once (the blob's reference
    count hits 0 and goes up again all the time): every live asset keeps its bytes, and the
    bytes go with the last asset. Real store (SQLite or a private Redis) and local storage."""
    import io
    import random
    import threading

    from service.backend import make_backend
    from service.jobs import core
    from service.jobs.retention import delete_asset
    from service.settings import Settings

    extra = {"redis_url": redis_url + "/5"} if kind == "redis" else {}
    b = make_backend(Settings(storage_root=tmp_path, **extra))
    data = unique_ply.read_bytes()
    key = core.blob_key("racer", hashlib.sha256(data).hexdigest())
    kept, errors = [], []

    def racer(seed):
        rng = random.Random(seed)
        try:
            for _ in range(15):
                a = core.ingest(b, "racer", io.BytesIO(data), "same.ply")
                if rng.random() < 0.8:
                    delete_asset(b, "racer", a.id)
                else:
                    kept.append(a)
        except Exception as exc:  # noqa: BLE001 -- reported below: a thread's exception must fail the test
            errors.append(exc)

    threads = [threading.Thread(target=racer, args=(i,)) for i in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(120)
    assert not errors, errors
    assert sorted(b.store.blob_ref_ids(key)) == sorted(a.id for a in kept)
    if kept:
        assert b.storage.local_path(key).read_bytes() == data
    for a in kept:
        delete_asset(b, "racer", a.id)
    assert not b.storage.exists(key) and b.store.blob_ref_ids(key) == []
