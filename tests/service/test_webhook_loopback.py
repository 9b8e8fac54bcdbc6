"""Test and fuzz deployments never send a webhook off this machine.

The test stack allows private webhook hosts (its receivers listen on loopback), which used
to mean any http(s) URL was accepted: the fuzzer's multipart `webhook_url` values included
`https://example.invalid/x`, so a fuzzed job that ran would resolve that name (a DNS query
off the machine) and POST to whatever it named. Now:

- `GSA_WEBHOOK_LOOPBACK_ONLY=true` (set by `service_env`, which every test and fuzz deployment
  uses) makes the server refuse, at submission (422) and again at delivery, any webhook whose
  host is not a loopback literal (127.0.0.0/8, ::1) or `localhost`; other names are refused
  without a DNS lookup;
- the fuzzer generates webhook URLs that name only loopback hosts, or strings that are no
  http(s) URL at all.
"""

from __future__ import annotations

import json
import socket
from urllib.parse import urlparse

import httpx
import pytest
from hypothesis import HealthCheck, given, settings

from service.webhooks.delivery import check_url
from tests.service.conftest import ALICE, assert_problem, service_env, start_api, submit_pair

LOOPBACK_HOSTS = {"127.0.0.1", "localhost", "::1"}

OFF_MACHINE = [
    "https://example.invalid/x",
    "http://example.com/hook",
    "http://8.8.8.8/",
    "http://10.0.0.1/",
    "http://100.100.100.200/latest/meta-data/",
    "http://[2606:4700::1111]/",
    "http://2130706433.example/",
    "http://localhost.example/",
    "http://[::ffff:127.0.0.1]/",
]


def _no_dns(monkeypatch):
    def no_dns(host, *a, **k):
        raise AssertionError(f"looked up {host!r}: a loopback-only check must not use DNS")

    monkeypatch.setattr(socket, "getaddrinfo", no_dns)


@pytest.mark.parametrize("url", OFF_MACHINE)
def test_loopback_only_refuses_every_other_host_without_dns(monkeypatch, url):
    _no_dns(monkeypatch)
    for allow_private in (True, False):
        with pytest.raises(ValueError):
            check_url(url, allow_private, loopback_only=True)
        with pytest.raises(ValueError):
            check_url(url, allow_private, loopback_only=True, resolve=True)  # delivery


def test_loopback_only_accepts_loopback_and_pins_localhost(monkeypatch):
    _no_dns(monkeypatch)
    assert check_url("http://127.0.0.1:9/h", True, loopback_only=True, resolve=True) == ["127.0.0.1"]
    assert check_url("http://127.8.9.10/h", True, loopback_only=True, resolve=True) == ["127.8.9.10"]
    assert check_url("http://[::1]:9/h", True, loopback_only=True, resolve=True) == ["::1"]
    assert check_url("http://LOCALHOST.:9/h", True, loopback_only=True, resolve=True) == ["127.0.0.1", "::1"]
    # the same without GSA_WEBHOOK_ALLOW_PRIVATE: loopback is what the mode is for (literals were refused)
    for url, addrs in (
        ("http://127.0.0.1:9/h", ["127.0.0.1"]),
        ("http://[::1]/", ["::1"]),
        ("http://localhost/", ["127.0.0.1", "::1"]),
    ):
        assert check_url(url, False, loopback_only=True) == addrs
        assert check_url(url, False, loopback_only=True, resolve=True) == addrs


@pytest.fixture(scope="module")
def test_api(tmp_path_factory, redis_url):
    """An API configured exactly as the test and fuzz deployments are."""
    tmp = tmp_path_factory.mktemp("loopback")
    proc, url, _ = start_api(tmp, service_env(tmp, GSA_REDIS_URL=redis_url + "/4"))
    yield url
    proc.stop()


@pytest.mark.parametrize("hook", ["https://example.invalid/x", "http://8.8.8.8/", "http://10.0.0.1:8080/"])
def test_a_test_deployment_refuses_off_machine_webhooks(test_api, pair, hook):
    with httpx.Client(base_url=test_api, headers=ALICE, timeout=60) as c:
        before = len(c.get("/v1/jobs").json()["items"])
        r = submit_pair(c, pair, {"stages": ["coarse"], "outputs": ["result"]}, webhook_url=hook)
        assert "loopback" in assert_problem(r, 422, "invalid-input")["detail"]
        assert len(c.get("/v1/jobs").json()["items"]) == before  # nothing was created
        ok = submit_pair(c, pair, {"stages": ["coarse"], "outputs": ["result"]}, webhook_url="http://127.0.0.1:9/h")
        assert ok.status_code == 202, ok.text
        c.post(f"/v1/jobs/{ok.json()['id']}:cancel")


# ------------------------------------------------------------------ the fuzzer's own URLs
def _webhook_urls(req) -> list[str]:
    """Every webhook URL a generated request carries: JSON `webhook.url`, multipart `webhook_url`."""
    urls = []
    if req.kind == "json_job":
        try:
            spec = json.loads(req.body)
        except ValueError:
            spec = None
        if isinstance(spec, dict) and isinstance(spec.get("webhook"), dict):
            u = spec["webhook"].get("url")
            if isinstance(u, str):
                urls.append(u)
    if req.kind == "multipart_job":
        for part in req.body.split(b'name="webhook_url"')[1:]:
            value = part.split(b"\r\n\r\n", 1)[-1].split(b"\r\n--", 1)[0]
            urls.append(value.decode("utf-8", "replace"))
    return urls


def _names_an_outside_host(url: str) -> bool:
    try:
        u = urlparse(url)
        return u.scheme in ("http", "https") and bool(u.hostname) and u.hostname not in LOOPBACK_HOSTS
    except ValueError:
        return False


def _refused_by_a_test_deployment(url: str) -> bool:
    try:
        check_url(url, True, loopback_only=True)
    except ValueError:
        return True
    return False


def test_the_fuzzer_only_generates_loopback_webhooks_or_refused_ones(monkeypatch, tmp_path):
    """Every webhook URL the fuzzer sends names a loopback host or is refused at validation
    by a deployment configured as the fuzz session's is (it was: `https://example.invalid/x`
    passed, and was resolved and POSTed to once its job ran)."""
    from tests.service.fuzz_requests import Targets, build_corpus, option_names, requests

    _no_dns(monkeypatch)
    ply = b"ply\nformat binary_little_endian 1.0\nelement vertex 0\nend_header\n"
    targets = Targets(
        own_job="job_a", own_asset="ast_a", other_job="job_b", other_asset="ast_b", artifacts=["result.json"]
    )
    seen, outside = [], []

    @settings(max_examples=3000, derandomize=True, database=None, suppress_health_check=list(HealthCheck))
    @given(requests(build_corpus(ply), targets, option_names()))
    def draw(req):
        for url in _webhook_urls(req):
            seen.append(url)
            if _names_an_outside_host(url) and not _refused_by_a_test_deployment(url):
                outside.append(url)

    draw()
    assert seen, "no webhook URL was generated"
    assert not outside, sorted(set(outside))[:10]
    assert service_env(tmp_path)["GSA_WEBHOOK_LOOPBACK_ONLY"] == "true"  # what FuzzSession runs with
