"""X-Request-Id on every response (echoed or made up) and in the access log; CORS only
for the configured origins. Against real servers."""

from __future__ import annotations

import re

import httpx
import pytest

from tests.service.conftest import ALICE, service_env, start_api, wait_until

pytestmark = pytest.mark.slow  # starts API processes


@pytest.fixture(scope="module")
def api(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("rid")
    env = service_env(tmp, GSA_CORS_ORIGINS='["https://assets.example"]')
    proc, url, _ = start_api(tmp, env, log_level="info")
    yield proc, url
    proc.stop()


def test_request_id_is_echoed_or_made_up_and_logged(api):
    proc, url = api
    r = httpx.get(url + "/v1/jobs", headers={**ALICE, "X-Request-Id": "client-42.a"})
    assert r.status_code == 200 and r.headers["x-request-id"] == "client-42.a"
    made_up = httpx.get(url + "/v1/jobs/nope", headers=ALICE)
    assert made_up.status_code == 404
    assert re.fullmatch(r"[0-9a-f]{32}", made_up.headers["x-request-id"])
    # an id that could forge log fields is replaced, not echoed
    forged = httpx.get(url + "/healthz", headers={"X-Request-Id": "a b\tc"})
    assert forged.headers["x-request-id"] != "a b\tc"
    # refused before routing (413 by the body limit) still carries an id
    big = httpx.post(url + "/v1/jobs", headers={**ALICE, "Content-Type": "application/json"}, content=b"{" * (2 << 20))
    assert big.status_code == 413 and big.headers.get("x-request-id")
    wait_until(lambda: "[client-42.a]: GET /v1/jobs 200" in proc.tail(20000), 10, 0.1, "the access log line")


def test_cors_allows_only_the_configured_origin(api):
    _, url = api
    pre = {"Origin": "https://assets.example", "Access-Control-Request-Method": "POST"}
    ok = httpx.options(url + "/v1/jobs", headers={**pre, "Access-Control-Request-Headers": "authorization"})
    assert ok.status_code == 200
    assert ok.headers["access-control-allow-origin"] == "https://assets.example"
    other = httpx.options(url + "/v1/jobs", headers={**pre, "Origin": "https://evil.example"})
    assert "access-control-allow-origin" not in other.headers
    simple = httpx.get(url + "/healthz", headers={"Origin": "https://assets.example"})
    assert simple.headers["access-control-allow-origin"] == "https://assets.example"
    assert "x-request-id" in simple.headers["access-control-expose-headers"].lower()


def test_no_cors_headers_without_configured_origins(stack):
    r = httpx.get(stack["url"] + "/healthz", headers={"Origin": "https://assets.example"})
    assert r.status_code == 200 and "access-control-allow-origin" not in r.headers
    assert r.headers.get("x-request-id")


def test_an_unhandled_error_is_a_500_problem_with_the_request_id(tmp_path, caplog):
    # Starlette's catch-all answers outside every middleware, so its 500 had no id
    # (a zip error escaped as exactly that). RequestIds answers it now.
    from fastapi.testclient import TestClient

    from service.api.app import create_app
    from service.settings import Settings

    app = create_app(Settings(storage_root=tmp_path, auth_disabled=True), run_workers=False)

    def boom():
        raise RuntimeError("a defect")

    app.add_api_route("/boom", boom)
    with TestClient(app, raise_server_exceptions=False) as c:
        r = c.get("/boom", headers={"X-Request-Id": "client-500"})
    assert r.status_code == 500 and r.headers["x-request-id"] == "client-500"
    assert r.headers["content-type"].startswith("application/problem+json")
    assert r.json()["type"].endswith("/internal-error") and "defect" not in r.text
    assert any("unhandled error on GET /boom" in m for m in caplog.messages)


def test_cors_preflight_allows_the_conditional_range_headers(api):
    """A browser resuming a download sends Range with If-Range: the preflight must allow both
    (If-Range was missing from the allowed headers)."""
    _, url = api
    pre = {
        "Origin": "https://assets.example",
        "Access-Control-Request-Method": "GET",
        "Access-Control-Request-Headers": "authorization, range, if-range, if-none-match",
    }
    r = httpx.options(url + "/v1/jobs/j/artifacts/aligned.ply", headers=pre)
    assert r.status_code == 200, r.text
    allowed = {h.strip().lower() for h in r.headers["access-control-allow-headers"].split(",")}
    assert {"range", "if-range", "if-none-match"} <= allowed, allowed
