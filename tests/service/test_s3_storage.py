"""S3Storage against a real S3-speaking server: moto's standalone server (`python -m moto.server`,
the `dev` extra's moto[s3] + flask), started here as its own process on a free loopback port and
reached over HTTP by boto3, as a deployment reaches AWS or MinIO. No in-process mock.

The storage contract runs against LocalStorage too, so both backends answer the same way; then one
job goes through the real HTTP API and a worker with GSA_STORAGE_BACKEND=s3."""

from __future__ import annotations

import io
import os
import uuid

import httpx
import pytest

from service.storage import LocalStorage, S3Storage
from tests.service.conftest import (
    ALICE,
    PY,
    Proc,
    free_port,
    service_env,
    start_api,
    start_worker,
    wait_job,
    wait_until,
)

BUCKET = "gsa-test"

# Credentials the server accepts (any), a region, and nothing read from this machine's AWS
# config or its instance metadata service: boto3 talks to the loopback server only.
AWS_ENV = {
    "AWS_ACCESS_KEY_ID": "testing",
    "AWS_SECRET_ACCESS_KEY": "testing",
    "AWS_DEFAULT_REGION": "us-east-1",
    "AWS_EC2_METADATA_DISABLED": "true",
    "AWS_CONFIG_FILE": os.devnull,
    "AWS_SHARED_CREDENTIALS_FILE": os.devnull,
    "NO_PROXY": "127.0.0.1",
}


@pytest.fixture(scope="module")
def s3_server(tmp_path_factory):
    try:
        import boto3  # noqa: F401
        import moto.server  # noqa: F401
    except ImportError as exc:  # a failure, not a skip: a missing install must not pass as green
        pytest.fail(f"{exc}: the dev extra installs boto3 and moto[s3] (./dev.sh test)")
    tmp = tmp_path_factory.mktemp("s3")
    port = free_port()
    env = {**os.environ, **AWS_ENV}
    proc = Proc([PY, "-m", "moto.server", "-H", "127.0.0.1", "-p", str(port)], env, tmp / "moto.log")
    url = f"http://127.0.0.1:{port}"

    def up():
        if proc.p.poll() is not None:
            raise RuntimeError(f"moto server exited: {proc.tail()}")
        try:
            httpx.get(url, timeout=1)
            return True
        except httpx.HTTPError:
            return False

    wait_until(up, 60, 0.1, "moto server")
    saved = {k: os.environ.get(k) for k in AWS_ENV}
    os.environ.update(AWS_ENV)  # S3Storage's boto3 client in this process reads them
    import boto3

    client = boto3.client("s3", endpoint_url=url)
    client.create_bucket(Bucket=BUCKET)
    yield {"url": url, "client": client, "proc": proc}
    for k, v in saved.items():
        if v is None:
            os.environ.pop(k, None)
        else:
            os.environ[k] = v
    proc.stop()


def _keys(client, prefix: str = "") -> list[str]:
    pages = client.get_paginator("list_objects_v2").paginate(Bucket=BUCKET, Prefix=prefix)
    return sorted(o["Key"] for page in pages for o in page.get("Contents", []))


@pytest.fixture(params=["local", "s3"])
def storage(request, tmp_path):
    if request.param == "local":
        yield LocalStorage(tmp_path / "blobs")
        return
    srv = request.getfixturevalue("s3_server")
    prefix = f"t{uuid.uuid4().hex[:8]}/"  # each test its own folder of the bucket
    yield S3Storage(BUCKET, prefix, srv["url"])
    for k in _keys(srv["client"], prefix):
        srv["client"].delete_object(Bucket=BUCKET, Key=k)


def _read(st, key, start=0, end=None) -> bytes:
    return b"".join(st.open(key, start, end))


def test_put_get_ranges_size_exists(storage):
    data = os.urandom(3 * (1 << 20) + 12345)  # several of the service's 1 MiB chunks, not a multiple
    assert storage.put("uploads/a1/model.ply", io.BytesIO(data)) == len(data)
    assert storage.size("uploads/a1/model.ply") == len(data)
    assert storage.exists("uploads/a1/model.ply") and not storage.exists("uploads/a1/other.ply")
    assert _read(storage, "uploads/a1/model.ply") == data
    assert _read(storage, "uploads/a1/model.ply", 5, 9) == data[5:10]  # inclusive end, as HTTP Range
    assert _read(storage, "uploads/a1/model.ply", len(data) - 7) == data[-7:]  # open-ended
    assert _read(storage, "uploads/a1/model.ply", (1 << 20) - 3, (1 << 20) + 2) == data[(1 << 20) - 3 : (1 << 20) + 3]
    # An iterable of chunks is a stream too (artifacts, image sets).
    assert storage.put("jobs/j1/t1/result.json", iter([b"{", b'"a": 1', b"}"])) == 8
    assert _read(storage, "jobs/j1/t1/result.json") == b'{"a": 1}'
    # Overwriting replaces.
    storage.put("jobs/j1/t1/result.json", io.BytesIO(b"{}"))
    assert _read(storage, "jobs/j1/t1/result.json") == b"{}" and storage.size("jobs/j1/t1/result.json") == 2


def test_empty_blob_reads_as_nothing(storage):
    # An empty artifact is served as 0 bytes; S3 refuses "Range: bytes=0-" on an empty object (416).
    assert storage.put("jobs/j2/t/notes.txt", io.BytesIO(b"")) == 0
    assert storage.size("jobs/j2/t/notes.txt") == 0
    assert _read(storage, "jobs/j2/t/notes.txt") == b""


def test_size_limit_leaves_nothing(storage):
    from service.problems import Problem

    with pytest.raises(Problem) as err:
        storage.put("uploads/a2/big.ply", io.BytesIO(b"x" * 5000), max_bytes=4096)
    assert err.value.status == 413
    assert not storage.exists("uploads/a2/big.ply")


def test_delete_and_delete_prefix(storage, tmp_path):
    for k in ("jobs/ab/t1/a.ply", "jobs/ab/t1/renders/v0.png", "jobs/ab/t2/a.ply", "jobs/abc/t1/a.ply"):
        storage.put(k, io.BytesIO(k.encode()))
    storage.delete("jobs/ab/t2/a.ply")
    assert not storage.exists("jobs/ab/t2/a.ply")
    storage.delete("jobs/ab/t2/a.ply")  # deleting what is gone is no error
    storage.delete_prefix("jobs/ab")  # a job's folder, not every key that starts with its id
    assert not storage.exists("jobs/ab/t1/a.ply") and not storage.exists("jobs/ab/t1/renders/v0.png")
    assert _read(storage, "jobs/abc/t1/a.ply") == b"jobs/abc/t1/a.ply"


def test_download_and_ping(storage, tmp_path):
    data = os.urandom(200_000)
    storage.put("uploads/a3/m.ply", io.BytesIO(data))
    dest = storage.download("uploads/a3/m.ply", tmp_path / "m.ply")
    assert dest.read_bytes() == data
    assert storage.ping()


def test_keys_are_checked(storage):
    for bad in ("../etc/passwd", "uploads/../x", "/abs/key", "uploads"):
        with pytest.raises(ValueError):
            storage.put(bad, io.BytesIO(b"x"))


def test_ping_is_false_for_a_missing_bucket(s3_server):
    assert not S3Storage("gsa-no-such-bucket", "", s3_server["url"]).ping()


@pytest.mark.slow
def test_job_end_to_end_through_the_http_api_on_s3(tmp_path, s3_server, redis_url, pair):
    """API + worker (Redis mode) with every blob in the S3 server: uploads, a job's artifacts, a
    ranged download, deletion; nothing written to local blob storage."""
    prefix = "e2e/"
    env = service_env(
        tmp_path,
        GSA_REDIS_URL=f"{redis_url}/4",
        GSA_STORAGE_BACKEND="s3",
        GSA_S3_BUCKET=BUCKET,
        GSA_S3_PREFIX=prefix,
        GSA_S3_ENDPOINT_URL=s3_server["url"],
        **AWS_ENV,
    )
    api, url, _ = start_api(tmp_path, env)
    worker = start_worker(tmp_path, env)
    client = s3_server["client"]
    try:
        with httpx.Client(base_url=url, headers=ALICE, timeout=60) as c:
            assert c.get("/readyz").status_code == 200  # storage ping: the bucket
            with open(pair["source"], "rb") as s, open(pair["target"], "rb") as t:
                r = c.post(
                    "/v1/jobs",
                    files=[("source", ("source.ply", s)), ("target", ("target.ply", t))],
                    data={"options": '{"stages": ["coarse"], "outputs": ["result", "aligned"]}'},
                )
            assert r.status_code == 202, r.text
            job = wait_job(c, r.json()["id"], timeout=120)
            assert job["state"] == "succeeded", (job, worker.tail())
            stored = _keys(client, prefix)
            # Both uploads (content-addressed) and the job's artifacts are objects in the bucket.
            assert sum(k.startswith(prefix + "cas/") for k in stored) == 2, stored
            arts = {a["name"]: a for a in job["artifacts"]}
            assert {"result.json", "aligned.ply"} <= set(arts)
            job_keys = [k for k in stored if k.startswith(f"{prefix}jobs/{job['id']}/")]
            assert len(job_keys) == len(arts), stored
            # Served from S3: whole, ranged, and byte-identical to the object.
            body = c.get(f"/v1/jobs/{job['id']}/artifacts/aligned.ply")
            assert body.status_code == 200 and len(body.content) == arts["aligned.ply"]["size"]
            obj = next(k for k in job_keys if k.endswith("/aligned.ply"))
            assert client.get_object(Bucket=BUCKET, Key=obj)["Body"].read() == body.content
            part = c.get(f"/v1/jobs/{job['id']}/artifacts/aligned.ply", headers={"Range": "bytes=100-199"})
            assert part.status_code == 206 and part.content == body.content[100:200]
            assert not list((tmp_path / "data" / "blobs").rglob("*.ply"))  # nothing local
            # Deleting the job removes its objects; the inputs stay until their assets go.
            assert c.delete(f"/v1/jobs/{job['id']}").status_code == 204
            left = _keys(client, prefix)
            assert not [k for k in left if k.startswith(f"{prefix}jobs/{job['id']}/")], left
            for ref in job["sources"] + [job["target"]]:
                assert c.delete(f"/v1/assets/{ref}").status_code == 204
            assert _keys(client, prefix) == []
    finally:
        worker.stop()
        api.stop()
