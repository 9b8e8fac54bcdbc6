"""The stored corpus: every request that once broke the service's contract
(tests/service/corpus/*.http, format in fuzz_requests.dump_http), replayed on every
run against a real deployment (uvicorn API, redis-server, a worker).

Each must get the answer its file names ("# expect: 4xx" by default: a problem+json
refusal, never a 5xx), with an X-Request-Id, in time. The long random runs
(benchmarks/service/fuzz_service.py --save DIR) write what they find in this format: copy it
here, fix the defect, and the case is replayed from then on."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.service.fuzz_requests import load_http, problems_with, send

pytestmark = pytest.mark.slow  # starts servers and a worker process

CORPUS = Path(__file__).with_name("corpus")
CASES = sorted(CORPUS.glob("*.http"))
BOUND_S = 10.0


def _status_ok(status: int, expect: str) -> bool:
    expect = expect.lower()
    if expect.endswith("xx"):
        return status // 100 == int(expect[0])
    return status == int(expect)


def test_the_corpus_is_there():
    assert CASES, f"no stored requests in {CORPUS}"


@pytest.mark.parametrize("case", CASES, ids=[p.stem for p in CASES])
def test_stored_request_keeps_the_contract(stack, case):
    req, notes = load_http(case.read_bytes(), kind=case.stem)
    host, port = stack["url"].removeprefix("http://").split(":")
    resp = send(host, int(port), req, timeout=BOUND_S + 20)
    problems = problems_with(req, resp, BOUND_S, outage=False)
    assert not problems, (case.name, problems, resp.body[:500])
    expect = notes.get("expect", "4xx")
    assert _status_ok(resp.status, expect), (case.name, resp.status, resp.body[:500])
    assert "x-request-id" in resp.headers
    if resp.status >= 400:
        assert resp.headers["content-type"].startswith("application/problem+json"), resp.headers
