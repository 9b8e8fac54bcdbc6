"""Webhook SSRF (server-side request forgery): every non-global address is refused at submission — REST
JSON, multipart and gRPC — including 100.64.0.0/10 (100.100.100.200 is a cloud metadata
address), which the old `is_private` test let through; and delivery connects to the
address that was checked, with no second DNS resolution.

No request leaves this machine: refused URLs are refused before anything is sent, names
are resolved by a stand-in resolver, and the one delivery goes to a receiver on loopback."""

from __future__ import annotations

import json
import socket
import threading
from http.server import BaseHTTPRequestHandler, HTTPServer
from types import SimpleNamespace

import grpc
import httpx
import pytest

from service.rpc.generated import alignment_pb2 as pb
from service.rpc.generated import alignment_pb2_grpc as pbg
from service.webhooks.delivery import check_url, non_global, pinned_request, post_job_event
from tests.service.conftest import ALICE, assert_problem, service_env, start_api

NON_GLOBAL = [
    "http://100.100.100.200/latest/meta-data/",  # shared address space: a metadata address
    "http://100.64.0.1/",
    "http://100.127.255.254:8080/x",
    "http://169.254.169.254/",
    "http://127.0.0.1:9/",
    "http://10.0.0.1/",
    "http://172.16.5.4/",
    "http://192.168.1.1/",
    "http://0.0.0.0/",
    "http://192.0.0.8/",
    "http://198.18.0.1/",  # benchmarking
    "http://192.0.2.1/",  # documentation
    "http://240.0.0.1/",  # reserved
    "http://255.255.255.255/",
    "http://224.0.1.1/",  # multicast (is_global says True)
    "http://[::1]/",
    "http://[::]/",
    "http://[fe80::1]/",
    "http://[fc00::1]/",
    "http://[2001:db8::1]/",
    "http://[::ffff:10.0.0.1]/",  # IPv4-mapped
    "http://[::ffff:100.100.100.200]/",
    "http://[2002:a00:1::1]/",  # 6to4 around 10.0.0.1
    "http://[64:ff9b::6464:64c8]/",  # NAT64 around 100.100.100.200
    "http://[::a9fe:a9fe]/",  # IPv4-compatible around 169.254.169.254
    "http://[::ffff:0:a9fe:a9fe]/",  # SIIT around 169.254.169.254
    "http://2130706433/",  # 127.0.0.1 as one number (numeric: no DNS)
    "http://0x7f.1/",
]


@pytest.mark.parametrize("url", NON_GLOBAL)
def test_non_global_addresses_are_refused(url):
    with pytest.raises(ValueError, match="non-public address"):
        check_url(url, allow_private=False)


def test_global_literals_pass_without_a_lookup(monkeypatch):
    def no_dns(*a, **k):
        raise AssertionError("a literal address must not be resolved")

    monkeypatch.setattr(socket, "getaddrinfo", no_dns)
    assert check_url("https://8.8.8.8/hook", allow_private=False) == ["8.8.8.8"]
    assert check_url("http://[2606:4700::1111]:8443/", allow_private=False) == ["2606:4700::1111"]
    assert not non_global(__import__("ipaddress").ip_address("1.1.1.1"))


def _resolver(monkeypatch, answers: dict[str, list[list[str]]]):
    """A stand-in for DNS: name -> one answer per call (the last repeats); other names
    (the loopback receiver's numeric address) go to the real resolver."""
    real = socket.getaddrinfo
    calls: dict[str, int] = {}

    def fake(host, port, *a, **k):
        if host not in answers:
            return real(host, port, *a, **k)
        n = calls[host] = calls.get(host, 0) + 1
        seq = answers[host]
        addrs = seq[min(n, len(seq)) - 1]
        if not addrs:
            raise socket.gaierror(socket.EAI_NONAME, "Name or service not known")
        return [(socket.AF_INET6 if ":" in a else socket.AF_INET, socket.SOCK_STREAM, 6, "", (a, port)) for a in addrs]

    monkeypatch.setattr(socket, "getaddrinfo", fake)
    return calls


def test_names_are_refused_when_any_address_is_not_global(monkeypatch):
    _resolver(
        monkeypatch,
        {
            "metadata.test": [["100.100.100.200"]],
            "mixed.test": [["93.184.216.34", "100.64.0.7"]],
            "v6.test": [["fd00::5"]],
            "gone.test": [[]],
        },
    )
    for host in ("metadata.test", "mixed.test", "v6.test"):
        with pytest.raises(ValueError, match="non-public address"):
            check_url(f"https://{host}/hook", allow_private=False)
    with pytest.raises(ValueError, match="does not resolve"):
        check_url("https://gone.test/hook", allow_private=False)


def test_the_request_is_pinned_to_the_checked_address():
    url, headers, ext = pinned_request("https://user:p%40ss@hooks.example:8443/a/b?c=1", "93.184.216.34")
    assert url == "https://93.184.216.34:8443/a/b?c=1"
    assert headers["Host"] == "hooks.example:8443" and headers["Authorization"] == "Basic dXNlcjpwQHNz"
    assert ext == {"sni_hostname": "hooks.example"}  # TLS: SNI and certificate check for the name
    url, headers, ext = pinned_request("http://hooks.example/x", "2606:4700::1111")
    assert url == "http://[2606:4700::1111]/x" and headers == {"Host": "hooks.example"} and ext == {}


class _Receiver(BaseHTTPRequestHandler):
    got: list[tuple[str, dict, bytes]] = []

    def do_POST(self):
        body = self.rfile.read(int(self.headers["Content-Length"]))
        _Receiver.got.append((self.path, dict(self.headers), body))
        self.send_response(204)
        self.end_headers()

    def log_message(self, *a):
        pass


def test_delivery_connects_to_the_address_checked_not_a_second_lookup(monkeypatch):
    # DNS rebinding: the name answers loopback once, then (for anyone asking again) nothing.
    # Delivery must reach the receiver through the first answer, with the name in Host.
    srv = HTTPServer(("127.0.0.1", 0), _Receiver)
    port = srv.server_address[1]
    threading.Thread(target=srv.serve_forever, daemon=True).start()
    try:
        calls = _resolver(monkeypatch, {"rebind.test": [["127.0.0.1"], []]})
        monkeypatch.setenv("HTTP_PROXY", "http://127.0.0.1:9")  # ignored: it would connect elsewhere
        job = SimpleNamespace(
            id="job_1",
            webhook={"url": f"http://rebind.test:{port}/hook"},
            state=SimpleNamespace(value="succeeded"),
            finished_at=0.0,
            attempts=1,
        )
        store = SimpleNamespace(get=lambda _id: job)
        settings = SimpleNamespace(webhook_allow_private=True, webhook_secret=None, webhook_timeout_s=5)
        _Receiver.got.clear()
        post_job_event(store, "job_1", settings)
        assert calls == {"rebind.test": 1}
        ((path, headers, body),) = _Receiver.got
        assert path == "/hook" and headers["Host"] == f"rebind.test:{port}"
        assert json.loads(body)["job_id"] == "job_1"
    finally:
        srv.shutdown()
        srv.server_close()


# ------------------------------------------------------------------ against a real server
@pytest.fixture(scope="module")
def strict_api(tmp_path_factory, redis_url):
    """An API that refuses non-public webhooks (the test stack allows loopback ones)."""
    tmp = tmp_path_factory.mktemp("ssrf")
    env = service_env(tmp, GSA_REDIS_URL=redis_url + "/3", GSA_WEBHOOK_ALLOW_PRIVATE="false")
    proc, url, gport = start_api(tmp, env, grpc=True)
    yield url, f"127.0.0.1:{gport}"
    proc.stop()


@pytest.mark.slow
@pytest.mark.parametrize("hook", ["http://100.100.100.200/latest/meta-data/", "http://100.64.0.1:8080/x"])
def test_submission_refuses_shared_address_space_over_rest_and_grpc(strict_api, pair, hook):
    url, grpc_target = strict_api
    with httpx.Client(base_url=url, headers=ALICE, timeout=60) as c:
        before = c.get("/v1/jobs").json()["items"]  # other tests on this server may have made jobs
        body = {"source": "ast_nope", "target": "ast_nope", "webhook": {"url": hook}}
        p = assert_problem(c.post("/v1/jobs", json=body), 422, "invalid-input")
        assert "non-public address" in p["detail"], p
        with open(pair["source"], "rb") as s, open(pair["target"], "rb") as t:
            r = c.post(
                "/v1/jobs",
                files=[("source", ("s.ply", s)), ("target", ("t.ply", t))],
                data={"options": "{}", "webhook_url": hook},
            )
        assert "non-public address" in assert_problem(r, 422, "invalid-input")["detail"]
        assert c.get("/v1/jobs").json()["items"] == before  # nothing was created
    ch = grpc.insecure_channel(grpc_target)
    try:
        header = pb.SubmitHeader(
            options_json="{}", source_asset_ids=["ast_nope"], target_asset_id="ast_nope", webhook=pb.Webhook(url=hook)
        )
        with pytest.raises(grpc.RpcError) as e:
            pbg.AlignmentServiceStub(ch).SubmitAlignment(
                iter([pb.SubmitRequest(header=header)]), metadata=(("authorization", "Bearer key-alice"),)
            )
        assert e.value.code() == grpc.StatusCode.INVALID_ARGUMENT
        assert "non-public address" in json.loads(dict(e.value.trailing_metadata())["gsa-problem"])["detail"]
    finally:
        ch.close()


def test_a_deployment_that_allows_private_hosts_does_not_resolve_at_submission(monkeypatch):
    def no_dns(*a, **k):
        raise AssertionError("no lookup at submission when private hosts are allowed")

    monkeypatch.setattr(socket, "getaddrinfo", no_dns)
    assert check_url("http://hooks.test:8080/x", allow_private=True) == []
    with pytest.raises(ValueError, match="absolute http"):
        check_url("ftp://hooks.test/x", allow_private=True)
