"""Pieces on their own: settings, storage, SQLite store, input checks, webhooks, compose."""

from __future__ import annotations

import io
import re
import shutil
import subprocess
import time
import zipfile

import numpy as np
import pytest

from service.models import InputRef, Job, JobState
from service.problems import Problem
from service.settings import Settings
from service.storage import LocalStorage, new_key
from service.stores.sqlite_store import SQLiteJobStore
from tests.service.conftest import ROOT


def test_settings_from_env(monkeypatch):
    monkeypatch.setenv("GSA_API_KEYS", '{"k1": "alice"}')
    monkeypatch.setenv("GSA_MAX_UPLOAD_BYTES", "123")
    s = Settings()
    assert s.api_keys == {"k1": "alice"} and s.max_upload_bytes == 123 and s.embedded
    monkeypatch.setenv("GSA_API_KEYS", "k1:alice,k2:bob")
    monkeypatch.setenv("GSA_REDIS_URL", "redis://x:1/0")
    s = Settings()
    assert s.api_keys == {"k1": "alice", "k2": "bob"} and not s.embedded
    assert not Settings().auth_disabled  # auth is on unless explicitly disabled


def test_local_storage_keys_and_limits(tmp_path):
    st = LocalStorage(tmp_path)
    key = new_key("uploads", "../../etc/passwd")
    assert ".." not in key and key.startswith("uploads/")
    assert st.put(key, io.BytesIO(b"x" * 100)) == 100
    assert b"".join(st.open(key, 10, 19)) == b"x" * 10 and st.size(key) == 100
    for bad in (
        "../x",
        "/etc/passwd",
        "uploads/../../x",
        "uploads//x",
        "uploads/a/.hidden",
    ):
        with pytest.raises(ValueError):
            st.put(bad, io.BytesIO(b"x"))
    k2 = new_key("uploads", "big.ply")
    with pytest.raises(Problem) as e:
        st.put(k2, iter([b"x" * 60, b"x" * 60]), max_bytes=100)
    assert e.value.status == 413
    assert not st.exists(k2)
    assert [p for p in tmp_path.rglob("*") if p.is_file() and ".part" in p.name] == []
    st.delete(key)
    assert not any(tmp_path.rglob("*.ply"))


def _job(jid, owner="o", t=None):
    ref = InputRef(asset_id="a", key="uploads/x/y", kind="ply")
    t = t or time.time()
    return Job(id=jid, owner=owner, created_at=t, updated_at=t, sources=[ref], target=ref)


def test_both_stores_implement_the_store_protocol():
    """Each store defines every JobStore method itself (the protocol's bodies are `...`)."""
    from service.stores.base import JobStore
    from service.stores.redis_store import RedisJobStore

    wanted = {n for n, v in vars(JobStore).items() if callable(v) and not n.startswith("_")}
    assert {"create", "get", "update", "list", "ping"} <= wanted
    for store in (RedisJobStore, SQLiteJobStore):
        assert JobStore not in store.__mro__
        assert wanted <= set(vars(store)), (store.__name__, sorted(wanted - set(vars(store))))


def test_sqlite_store_cas_persistence_and_pages(tmp_path):
    db = tmp_path / "jobs.sqlite3"
    st = SQLiteJobStore(db)
    for i in range(5):
        st.create(_job(f"j{i}", t=1000.0 + (i // 2)))  # ties in created_at
    assert st.update("j0", states={JobState.queued}, state=JobState.running, run_token="t1")
    assert not st.update("j0", states={JobState.queued}, state=JobState.running, run_token="t2")
    assert not st.update("j0", token="other", progress=0.5)
    assert st.update("j0", token="t1", progress=0.5)
    assert st.claim_idempotency("o", "k", "h1", "j0") is None
    assert st.claim_idempotency("o", "k", "h2", "j9") == ("j0", "h1")
    st.db.close()
    st = SQLiteJobStore(db)  # reopened: everything is still there
    j0 = st.get("j0")
    assert j0.state == JobState.running and j0.progress == 0.5 and j0.version == 2
    assert st.counts()["queued"] == 4 and st.counts()["running"] == 1
    pages, cursor = [], None
    while True:
        page = st.list("o", None, 2, cursor)
        if not page:
            break
        pages += [j.id for j in page]
        cursor = (page[-1].created_at, page[-1].id)
    assert sorted(pages) == [f"j{i}" for i in range(5)] and len(pages) == 5
    assert [j.id for j in st.list("o", JobState.running, 10, None)] == ["j0"]
    assert st.list("someone-else", None, 10, None) == []


def test_redis_store_matches_sqlite_semantics(redis_url):
    import redis as redislib

    from service.stores.redis_store import RedisJobStore

    r = redislib.Redis.from_url(redis_url + "/2")
    r.flushdb()  # our private test server's db 2 only
    st = RedisJobStore(r)
    for i in range(5):
        st.create(_job(f"j{i}", t=1000.0 + (i // 2)))
    assert st.update("j0", states={JobState.queued}, state=JobState.running, run_token="t1")
    assert not st.update("j0", states={JobState.queued}, state=JobState.running)
    assert not st.update("j0", token="nope", progress=0.3)
    assert st.counts()["running"] == 1 and st.counts()["queued"] == 4
    assert [j.id for j in st.running()] == ["j0"]
    pages, cursor = [], None
    while page := st.list("o", None, 2, cursor):
        pages += [j.id for j in page]
        cursor = (page[-1].created_at, page[-1].id)
    assert sorted(pages) == [f"j{i}" for i in range(5)] and len(pages) == 5


def _ply_header(n, extra=""):
    props = "".join(
        f"property float {p}\n"
        for p in [
            "x",
            "y",
            "z",
            "f_dc_0",
            "f_dc_1",
            "f_dc_2",
            "opacity",
            "scale_0",
            "scale_1",
            "scale_2",
            "rot_0",
            "rot_1",
            "rot_2",
            "rot_3",
        ]
    )
    return f"ply\nformat binary_little_endian 1.0\nelement vertex {n}\n{props}{extra}end_header\n".encode()


def test_validate_ply_limits(tmp_path):
    from service.jobs.inputs import validate_ply

    p = tmp_path / "a.ply"
    body = np.zeros((10, 14), "<f4")
    body[:, 10] = 1.0  # rot_0: a unit quaternion (a zero one is refused at upload)
    p.write_bytes(_ply_header(10) + body.tobytes())
    assert validate_ply(p, 100, "a.ply") == 10
    with pytest.raises(Problem) as e:
        validate_ply(p, 5, "a.ply")
    assert e.value.status == 413
    p.write_bytes(_ply_header(1_000_000_000))  # a huge claim costs nothing to refuse
    with pytest.raises(Problem) as e:
        validate_ply(p, 2_000_000_000, "a.ply")
    assert e.value.status == 422 and "truncated" in e.value.detail


def test_zip_limits(tmp_path):
    from service.jobs.inputs import validate_zip
    from tests.service.test_http import _png

    def make(entries):
        p = tmp_path / "x.zip"
        with zipfile.ZipFile(p, "w") as zf:
            for name, data in entries:
                zf.writestr(name, data)
        return p

    s = Settings(max_zip_entries=3, max_images=2, max_image_pixels=100)
    assert validate_zip(make([("a.png", _png(8, 8)), ("b.png", _png(8, 8))]), s, "z") == 2
    for entries, status in (
        ([(f"{i}.png", _png(2, 2)) for i in range(4)], 413),  # entries
        ([(f"{i}.png", _png(2, 2)) for i in range(3)], 413),  # images
        ([("big.png", _png(20, 20))], 413),  # pixels
        ([("notes.txt", b"hi")], 422),  # no images
        ([("../a.png", _png())], 422),
    ):
        with pytest.raises(Problem) as e:
            validate_zip(make(entries), s, "z")
        assert e.value.status == status, entries[0][0]


def test_webhook_signature_and_ssrf():
    from service.webhooks.delivery import check_url, sign, verify

    sig = sign("k", "123", b"{}")
    assert verify("k", "123", b"{}", sig) and not verify("k", "124", b"{}", sig)
    for bad in (
        "ftp://x/y",
        "http://127.0.0.1:9/",
        "http://10.0.0.1/",
        "http://[::1]/",
    ):
        with pytest.raises(ValueError):
            check_url(bad, allow_private=False)
    check_url("http://127.0.0.1:9/", allow_private=True)


@pytest.mark.skipif(shutil.which("docker-compose") is None, reason="docker-compose not installed")
def test_compose_file_valid():
    for args in ([], ["--profile", "gpu"]):
        r = subprocess.run(
            [
                "docker-compose",
                *args,
                "-f",
                str(ROOT / "docker-compose.yml"),
                "config",
                "-q",
            ],
            capture_output=True,
            text=True,
            cwd=ROOT,
        )
        assert r.returncode == 0, r.stderr


def test_compose_publishes_on_loopback_by_default():
    """docker-compose.yml's published ports bind 127.0.0.1 unless GSA_PUBLISH_HOST says
    otherwise: the API and gRPC are plaintext, so `docker-compose up` must not put them on
    every interface (it published 8000 and 50051 as "8000:8000")."""
    lines = (ROOT / "docker-compose.yml").read_text().splitlines()
    published = []
    for i, line in enumerate(lines):
        if line.strip() != "ports:":
            continue
        indent = len(line) - len(line.lstrip())
        for item in lines[i + 1 :]:
            if not item.strip() or item.lstrip().startswith("#"):
                continue
            if len(item) - len(item.lstrip()) <= indent or not item.lstrip().startswith("- "):
                break
            published.append(item.strip()[2:].strip("\"'"))
    assert {p.rsplit(":", 1)[-1] for p in published} == {"8000", "50051"}, published
    for p in published:
        host = re.sub(r"\$\{[A-Z_]+:-([^}]*)\}", r"\1", p).rsplit(":", 2)[0]
        assert host == "127.0.0.1", p


def test_gsa_does_not_import_service():
    import sys

    r = subprocess.run(
        [
            sys.executable,
            "-c",
            "import sys, gsa, gsa.client, gsa.align.pipeline; "
            "assert not any(m == 'service' or m.startswith('service.') for m in sys.modules)",
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        env={"PYTHONPATH": str(ROOT)},
    )
    assert r.returncode == 0, r.stderr


def test_openapi_paths_and_methods_are_the_public_contract(tmp_path):
    """The routers are split per resource; the document's paths, their order and
    methods are what clients were given, and must not move."""
    from service.api.app import create_app

    app = create_app(Settings(storage_root=tmp_path, auth_disabled=True), run_workers=False)
    assert [(p, list(ops)) for p, ops in app.openapi()["paths"].items()] == [
        ("/healthz", ["get"]),
        ("/readyz", ["get"]),
        ("/metrics", ["get"]),
        ("/v1/assets", ["post", "get"]),  # listAssets: a method added, no path moved
        ("/v1/assets/{asset_id}", ["get", "delete"]),
        ("/v1/jobs", ["post", "get"]),
        ("/v1/jobs/{job_id}", ["get", "delete"]),
        ("/v1/jobs/{job_id}:cancel", ["post"]),
        ("/v1/jobs/{job_id}:refine", ["post"]),
        ("/v1/jobs/{job_id}/refine", ["post"]),
        ("/v1/jobs/{job_id}/artifacts/{name}", ["get", "head"]),
        ("/v1/jobs/{job_id}/view-link", ["post"]),
        ("/v1/view-link", ["post"]),
        ("/v1/many-jobs", ["post"]),  # N-way registration: added last, so no path moved
    ]


def test_readyz_reports_unreachable_redis(tmp_path):
    from fastapi.testclient import TestClient

    from service.api.app import create_app
    from tests.service.conftest import free_port

    s = Settings(
        redis_url=f"redis://127.0.0.1:{free_port()}/0",
        storage_root=tmp_path,
        auth_disabled=True,
    )
    with TestClient(create_app(s)) as c:
        r = c.get("/readyz")
        assert r.status_code == 503 and r.headers["content-type"].startswith("application/problem+json")
        assert r.json()["checks"] == {"store": False, "storage": True, "disk_space": True}
        assert c.get("/healthz").status_code == 200


def test_cancel_queued_and_job_timeout_in_process(tmp_path, pair):
    """Embedded app in-process: a queued job is cancelled at once (no worker
    running); a job over its time limit fails with a job-timeout problem."""
    import json as _json

    from fastapi.testclient import TestClient

    from service.api.app import create_app
    from service.backend import make_backend
    from service.worker.execution import execute

    s = Settings(storage_root=tmp_path, api_keys={"k": "me"}, job_timeout_s=0.0)
    H = {"Authorization": "Bearer k"}
    backend = make_backend(s)
    with TestClient(create_app(s, backend, run_workers=False)) as c:

        def submit():
            with open(pair["source"], "rb") as a, open(pair["target"], "rb") as b:
                r = c.post(
                    "/v1/jobs",
                    headers=H,
                    files=[("source", ("s.ply", a)), ("target", ("t.ply", b))],
                    data={"options": _json.dumps({"outputs": ["result"]})},
                )
            assert r.status_code == 202, r.text
            return r.json()["id"]

        jid = submit()
        r = c.post(f"/v1/jobs/{jid}:cancel", headers=H)
        assert r.status_code == 202 and r.json()["state"] == "cancelled"
        assert execute(jid, backend) is None  # a worker that dequeues it later leaves it alone
        assert c.get(f"/v1/jobs/{jid}", headers=H).json()["state"] == "cancelled"

        jid = submit()
        assert execute(jid, backend) == JobState.failed
        job = c.get(f"/v1/jobs/{jid}", headers=H).json()
        assert job["error"]["type"].endswith("/job-timeout") and job["error"]["status"] == 504
        assert job["artifacts"] == [] and job["attempts"] == 1


def test_serve_flags_reach_the_settings_not_the_environment(monkeypatch):
    """`gsa serve` makes its settings from the environment with its flags over it, and
    leaves the environment as it was."""
    import os

    from gsa.cli import build_parser
    from service.cli import _settings

    monkeypatch.setenv("GSA_GRPC_HOST", "127.0.0.2")
    monkeypatch.setenv("GSA_MAX_SOURCES", "3")
    for name in ("GSA_GRPC_PORT", "GSA_AUTH_DISABLED", "GSA_EMBEDDED_WORKERS"):
        monkeypatch.delenv(name, raising=False)
    args = build_parser().parse_args(
        ["serve", "--grpc-port", "50099", "--grpc-host", "127.0.0.3", "--no-auth", "--workers", "2"]
    )
    s = _settings(args)
    assert (s.grpc_host, s.grpc_port, s.auth_disabled, s.embedded_workers) == ("127.0.0.3", 50099, True, 2)
    assert s.max_sources == 3  # the environment's, where no flag is given
    assert os.environ["GSA_GRPC_HOST"] == "127.0.0.2" and "GSA_GRPC_PORT" not in os.environ
    assert _settings(build_parser().parse_args(["serve"])).grpc_host == "127.0.0.2"


def test_fingerprint_counts_uploads_by_their_bytes():
    """An Upload in a request's identity stands for its bytes' sha256, under the separators
    the front end gives (a changed fingerprint would turn an idempotent replay into a 422)."""
    import hashlib
    import json

    from service.jobs.core import Upload, fingerprint, sha256_file

    data = io.BytesIO(b"ply\n" * 1000)
    sha = hashlib.sha256(data.getvalue()).hexdigest()
    assert sha256_file(data) == sha and data.tell() == 0
    with pytest.raises(Problem) as exc:
        sha256_file(data, max_bytes=10)
    assert exc.value.status == 413
    identity = {"files": {"source": [Upload(data, "a.ply")]}, "options": {"seed": 1}}
    plain = {"files": {"source": [sha]}, "options": {"seed": 1}}
    for seps in ((",", ":"), (", ", ": ")):
        want = hashlib.sha256(json.dumps(plain, sort_keys=True, separators=seps).encode()).hexdigest()
        assert fingerprint(identity, seps) == want


def test_grpc_front_end_does_not_import_the_http_one():
    from tests.test_import_graph import ROOT, import_graph

    graph = import_graph(ROOT, ("service",))
    assert not sorted(m for m in graph["service.rpc.server"] if m.startswith("service.api"))


def test_rigid_option_is_checked_as_a_bool():
    from service.jobs.options import check_option_values

    check_option_values({"rigid": True})
    with pytest.raises(Exception, match="rigid"):
        check_option_values({"rigid": "yes"})


def test_the_deployment_can_turn_the_semantic_tie_break_off():
    from service.jobs.options import align_options

    on = Settings(semantic="auto")  # (the tests' environment says off: tests/conftest.py)
    assert align_options(on, {}).semantic == "auto"
    assert align_options(on, {"semantic": "off"}).semantic == "off"
    assert align_options(Settings(semantic="off"), {"semantic": "auto"}).semantic == "off"  # the deployment wins


def test_a_job_can_keep_its_poses_as_refined():
    from service.jobs.options import align_options, check_option_values

    assert align_options(Settings(), {}).frame_snap == "auto"
    assert align_options(Settings(), {"frame_snap": "off"}).frame_snap == "off"
    with pytest.raises(Exception, match="frame_snap"):
        check_option_values({"frame_snap": "sometimes"})
