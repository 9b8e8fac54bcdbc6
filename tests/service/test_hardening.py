"""Service hardening: option bounds and the work budget, stage names, the gRPC
bind host, request-body limits for non-multipart bodies, Unicode file names and
job errors free of worker paths."""

from __future__ import annotations

import json

import grpc
import pytest

from service.rpc.generated import alignment_pb2 as pb
from service.rpc.generated import alignment_pb2_grpc as pbg
from tests.service.conftest import assert_problem, submit_pair

AUTH = (("authorization", "Bearer key-alice"),)


@pytest.fixture
def stub(stack):
    ch = grpc.insecure_channel(stack["grpc"])
    yield pbg.AlignmentServiceStub(ch)
    ch.close()


def _json_job(http, options: dict):
    # Options are checked before the asset ids are looked up: a valid request
    # with made-up ids answers 404, an invalid one 422.
    return http.post("/v1/jobs", json={"source": "ast_nope", "target": "ast_nope", "options": options})


def _grpc_submit(stub, options: dict):
    header = pb.SubmitHeader(
        options_json=json.dumps(options), source_asset_ids=["ast_nope"], target_asset_id="ast_nope"
    )
    with pytest.raises(grpc.RpcError) as e:
        stub.SubmitAlignment(iter([pb.SubmitRequest(header=header)]), metadata=AUTH)
    return e.value.code(), json.loads(dict(e.value.trailing_metadata())["gsa-problem"])


# ------------------------------------------------------------------ 1. bounds
@pytest.mark.parametrize(
    "option,value,bound",
    [("fine_views", 65, 64), ("fine_image_size", 1025, 1024), ("fine_iterations", 5001, 5000)],
)
def test_option_upper_bounds_http_json_multipart_and_grpc(http, stub, pair, option, value, bound):
    body = assert_problem(_json_job(http, {option: value}), 422, "invalid-input")
    assert body["option"] == option and body["maximum"] == bound, body
    assert option in body["detail"] and str(bound) in body["detail"]

    body = assert_problem(submit_pair(http, pair, {option: value}), 422, "invalid-input")
    assert body["option"] == option and body["maximum"] == bound

    code, problem = _grpc_submit(stub, {option: value})
    assert code == grpc.StatusCode.INVALID_ARGUMENT
    assert problem["option"] == option and problem["maximum"] == bound

    # The bound itself is allowed: validation passes and the made-up asset is the 404.
    assert_problem(_json_job(http, {option: bound}), 404, "not-found")
    code, _ = _grpc_submit(stub, {option: bound})
    assert code == grpc.StatusCode.NOT_FOUND


def test_other_numeric_options_are_bounded(http):
    for option, value in [
        ("seed", -1),
        ("max_points", 10**9),
        ("refine_iterations", 10**6),
        ("hypothesis_points", 10**9),
        ("fine_lr", 0),
        ("coarse_iterations", 1001),
        ("recon_iterations", 10**9),
        ("fine_views", "many"),
    ]:
        body = assert_problem(_json_job(http, {option: value}), 422)
        assert option in json.dumps(body), (option, body)


def test_fine_work_budget(http, stub):
    from service.settings import Settings

    budget = Settings.model_fields["max_fine_work"].default  # the server runs with the default
    over = {"fine_views": 64, "fine_image_size": 1024, "fine_iterations": 100}  # each within its bound
    assert 64 * 1024**2 * 100 > budget
    body = assert_problem(_json_job(http, over), 422, "invalid-input")
    assert body["maximum"] == budget and body["value"] == 64 * 1024**2 * 100
    assert "fine_views" in body["option"] and "fine_iterations" in body["option"]
    code, problem = _grpc_submit(stub, over)
    assert code == grpc.StatusCode.INVALID_ARGUMENT and problem["maximum"] == budget
    # within the budget: accepted as before
    assert_problem(_json_job(http, {"fine_views": 64, "fine_image_size": 256, "fine_iterations": 100}), 404)


def test_openapi_documents_the_bounds(http):
    props = http.get("/openapi.json").json()["components"]["schemas"]["AlignOptionsIn"]["properties"]
    assert props["fine_views"]["maximum"] == 64
    assert props["fine_image_size"]["maximum"] == 1024
    assert props["fine_iterations"]["maximum"] == 5000


# ------------------------------------------------------------------ 2. stages
def test_unknown_stage_is_rejected_at_submission(http, stub, pair):
    body = assert_problem(_json_job(http, {"stages": ["warp"]}), 422, "invalid-input")
    assert body["option"] == "stages" and "warp" in body["detail"]
    assert_problem(submit_pair(http, pair, {"stages": ["warp"]}), 422, "invalid-input")
    assert_problem(_json_job(http, {"stages": ["fine"]}), 422, "invalid-input")  # not a pipeline
    code, problem = _grpc_submit(stub, {"stages": ["warp"]})
    assert code == grpc.StatusCode.INVALID_ARGUMENT and problem["option"] == "stages"
    # other library checks too, and choices only the fine stage would have checked
    assert_problem(_json_job(http, {"features": "magic"}), 422, "invalid-input")
    assert_problem(_json_job(http, {"fine_loss": "l7"}), 422, "invalid-input")
    body = assert_problem(_json_job(http, {"semantic": "sometimes"}), 422, "invalid-input")
    assert body["option"] == "semantic"
    code, problem = _grpc_submit(stub, {"semantic": "sometimes"})
    assert code == grpc.StatusCode.INVALID_ARGUMENT and problem["option"] == "semantic"
    for value in ("auto", "off"):  # valid: past the options to the missing assets
        assert_problem(_json_job(http, {"semantic": value}), 404)
        assert_problem(_json_job(http, {"frame_snap": value}), 404)
    body = assert_problem(_json_job(http, {"frame_snap": "never"}), 422, "invalid-input")
    assert body["option"] == "frame_snap"
    # valid stage lists still pass
    for stages in (["auto"], ["coarse"], ["coarse", "fine"]):
        assert_problem(_json_job(http, {"stages": stages}), 404)


# ------------------------------------------------------------------ 3. gRPC bind host
def _listening(port: int) -> set[str]:
    """The local addresses with a TCP socket listening on `port` (from /proc/net)."""
    import ipaddress
    from pathlib import Path

    out = set()
    for table in ("tcp", "tcp6"):
        for line in Path(f"/proc/net/{table}").read_text().splitlines()[1:]:
            local, state = line.split()[1], line.split()[3]
            addr, p = local.split(":")
            if state != "0A" or int(p, 16) != port:
                continue
            raw = bytes.fromhex(addr)
            # /proc/net stores each 32-bit word in host (little-endian) order
            raw = b"".join(raw[i : i + 4][::-1] for i in range(0, len(raw), 4))
            ip = ipaddress.ip_address(raw)
            out.add(str(getattr(ip, "ipv4_mapped", None) or ip))  # gRPC may bind 127.0.0.1 as ::ffff:127.0.0.1
    return out


def _health(target: str) -> bool:
    from grpc_health.v1 import health_pb2, health_pb2_grpc

    with grpc.insecure_channel(target) as ch:
        try:
            health_pb2_grpc.HealthStub(ch).Check(health_pb2.HealthCheckRequest(), timeout=3)
            return True
        except grpc.RpcError:
            return False


def test_grpc_binds_loopback_by_default(stack):
    # The real server started by `gsa serve --grpc-port` with no host configured.
    port = int(stack["grpc"].rsplit(":", 1)[1])
    assert _listening(port) == {"127.0.0.1"}


def test_grpc_listens_on_the_configured_host_only(tmp_path):
    from service.backend import make_backend
    from service.rpc.server import serve_grpc
    from service.settings import Settings
    from tests.service.conftest import free_port

    port = free_port()
    b = make_backend(Settings(storage_root=tmp_path, auth_disabled=True, grpc_host="127.0.0.2"))
    server = serve_grpc(b, port)
    try:
        assert _listening(port) == {"127.0.0.2"}
        assert _health(f"127.0.0.2:{port}")
        assert not _health(f"127.0.0.1:{port}")
    finally:
        server.stop(grace=0)


# ------------------------------------------------------------------ 4. body limits
def _raw(url: str, head: bytes, parts=(), timeout=30.0) -> tuple[int, dict, bytes]:
    """Send a request head and some body bytes over a plain socket, then read the
    answer without finishing the body: only a server that enforces the limit
    up front (or while streaming) answers at all."""
    import socket
    import time
    from urllib.parse import urlsplit

    u = urlsplit(url)
    with socket.create_connection((u.hostname, u.port), timeout=timeout) as sock:
        sock.sendall(head)
        try:
            for p in parts:
                sock.sendall(p)
        except (BrokenPipeError, ConnectionResetError):
            pass  # the server answered and closed early: read what it said
        buf = b""
        deadline = time.monotonic() + timeout
        while b"\r\n\r\n" not in buf and time.monotonic() < deadline:
            chunk = sock.recv(65536)
            if not chunk:
                break
            buf += chunk
        head_raw, _, body = buf.partition(b"\r\n\r\n")
        lines = head_raw.decode("latin-1").split("\r\n")
        status = int(lines[0].split()[1])
        headers = {k.strip().lower(): v.strip() for k, _, v in (line.partition(":") for line in lines[1:])}
        n = int(headers.get("content-length", "0"))
        while len(body) < n and time.monotonic() < deadline:
            chunk = sock.recv(65536)
            if not chunk:
                break
            body += chunk
        return status, headers, body


def _head(url: str, extra: str) -> bytes:
    from urllib.parse import urlsplit

    u = urlsplit(url)
    return (
        f"POST /v1/jobs HTTP/1.1\r\nHost: {u.hostname}:{u.port}\r\nAuthorization: Bearer key-alice\r\n"
        f"Content-Type: application/json\r\n{extra}\r\n"
    ).encode()


def _is_413(status, headers, body):
    assert status == 413, (status, body)
    assert headers["content-type"].startswith("application/problem+json")
    p = json.loads(body)
    assert p["status"] == 413 and p["type"].endswith("/payload-too-large") and str(1 << 20) in p["detail"]


def test_json_body_over_the_limit_by_content_length(stack):
    # A 600 MB JSON body is refused from its Content-Length alone: not one byte of it is sent.
    _is_413(*_raw(stack["url"], _head(stack["url"], "Content-Length: 600000000\r\n")))


def test_chunked_json_body_over_the_limit_while_streaming(stack):
    # No Content-Length: the server counts bytes as they arrive and answers once 1 MiB is
    # passed, without waiting for (or buffering) the rest, which is never sent.
    piece = b"[" + b" " * (64 * 1024 - 1)
    frame = b"%x\r\n%s\r\n" % (len(piece), piece)
    _is_413(*_raw(stack["url"], _head(stack["url"], "Transfer-Encoding: chunked\r\n"), [frame] * 20))


def test_bodies_under_the_limit_and_uploads_are_unchanged(http):
    # ~0.9 MiB of JSON is read and handled as before (the made-up asset is the 404)
    r = http.post("/v1/jobs", json={"source": "ast_" + "x" * 900_000, "target": "ast_nope"})
    assert_problem(r, 404, "not-found")
    # multipart uploads keep their own (per-file) limits: 2 MiB is not a 413
    r = http.post("/v1/assets", files={"file": ("junk.bin", b"\1" * (2 << 20))})
    assert_problem(r, 422, "invalid-input")


# ------------------------------------------------------------------ 5. names and paths
UNICODE_NAME = "пример-模型.ply"


def test_unicode_file_names_are_stored_and_returned(http, pair):
    data = pair["source"].read_bytes()
    r = http.post("/v1/assets", files={"file": (UNICODE_NAME, data)})  # raw UTF-8 in filename="..."
    assert r.status_code == 201, r.text
    assert r.json()["filename"] == UNICODE_NAME
    assert http.get(f"/v1/assets/{r.json()['id']}").json()["filename"] == UNICODE_NAME

    # RFC 5987 filename* wins over the ASCII fallback
    from urllib.parse import quote

    body = (
        b'--bnd\r\nContent-Disposition: form-data; name="file"; filename="fallback.ply"; filename*=UTF-8\'\''
        + quote(UNICODE_NAME).encode()
        + b"\r\nContent-Type: application/octet-stream\r\n\r\n"
        + data
        + b"\r\n--bnd--\r\n"
    )
    r = http.post("/v1/assets", content=body, headers={"Content-Type": "multipart/form-data; boundary=bnd"})
    assert r.status_code == 201, r.text
    assert r.json()["filename"] == UNICODE_NAME


def test_bad_model_errors_name_the_asset_not_server_paths(http, pair, tmp_path):
    from gsa.io.ply import read_ply, write_ply

    m = read_ply(pair["source"])
    m.means[0, 0] = float("nan")  # the header is fine; the values are checked at upload
    write_ply(m, tmp_path / "nan.ply")
    src = http.post("/v1/assets", files={"file": (UNICODE_NAME, (tmp_path / "nan.ply").read_bytes())})
    err = src.json()
    assert src.status_code == 422 and err["type"].endswith("/invalid-input"), err
    assert UNICODE_NAME in err["detail"] and "NaN" in err["detail"], err
    assert "gsa-" not in json.dumps(err, ensure_ascii=False) and "/tmp" not in err["detail"], err


def test_redact_work_paths_maps_every_workspace_file():
    from service.jobs.inputs import redact_work_paths
    from service.models import InputRef, Job

    def ref(i, name, kind="ply"):
        return InputRef(asset_id=i, key="k", kind=kind, filename=name)

    job = Job(
        id="job_x",
        owner="o",
        created_at=0,
        updated_at=0,
        max_attempts=1,
        sources=[ref("ast_a", UNICODE_NAME), ref("ast_b", None, "images")],
        target=ref("ast_t", "t.ply"),
        options={},
    )
    cases = {
        "/tmp/gsa-job-ab_1/source0.ply: bad": f"{UNICODE_NAME}: bad",
        "open '/var/tmp/gsa-job-q/target.ply' failed": "open 't.ply' failed",
        "/tmp/gsa-job-q/source1-images/00003.png is broken": "ast_b/00003.png is broken",
        "/tmp/gsa-job-q/target-recon/sparse/0: no model": "t.ply: no model",
        "/tmp/gsa-job-q/out0/aligned.ply": "aligned.ply",
        "in /tmp/gsa-job-q": "in job workspace",
    }
    for text, want in cases.items():
        assert redact_work_paths(text, job) == want
