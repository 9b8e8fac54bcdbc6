"""Property-based fuzzing of the HTTP API on a real deployment (redis-server,
`gsa serve`, a `gsa worker` for the baseline): generated JSON and multipart
bodies, headers, ids, Range/If-Range, job options, corrupted PLY/zip/image bytes.

For every answer: no 5xx (503 only while Redis is down), no request beyond the
time bound, problem+json for errors, an X-Request-Id; the server's memory stays
bounded; and the jobs, assets and artifacts stored before are byte-identical
after. benchmarks/service/fuzz_service.py runs the same with thousands of requests.

Derandomized: every run (with or without CI) sends the same sequence, so a test run
never fails on a case nobody has seen. The random search is benchmarks/service/fuzz_service.py
(before a release); what it finds joins tests/service/corpus/, which
test_fuzz_corpus.py replays."""

from __future__ import annotations

import pytest
from hypothesis import HealthCheck, given, settings

from tests.service.fuzz_requests import requests
from tests.service.fuzz_run import FuzzSession, dumps

pytestmark = pytest.mark.slow  # starts servers and worker processes

FUZZ = settings(
    max_examples=300,
    derandomize=True,  # a fixed sequence everywhere, not only under CI's profile
    deadline=None,
    database=None,
    suppress_health_check=list(HealthCheck),
)
RSS_GROWTH_LIMIT = 200 * 2**20


@pytest.fixture(scope="module")
def session(tmp_path_factory, pair):
    s = FuzzSession(tmp_path_factory.mktemp("fuzz"), pair["source"].read_bytes())
    s.targets = s.store_baseline(pair["source"], pair["target"])
    yield s
    s.close()


def test_generated_requests_keep_the_contract(session):
    @FUZZ
    @given(req=requests(session.corpus, session.targets, session.names))
    def one(req):
        problems = session.run(req)
        assert not problems, (req, problems)

    one()
    summary = session.summary()
    assert summary["requests"] >= 300, dumps(summary)
    # the generators reach every kind of request, and the server answered them all
    assert len(summary["by_kind"]) >= 10, dumps(summary)
    assert session.stats.rss_peak - session.stats.rss_start < RSS_GROWTH_LIMIT, dumps(summary)
    assert session.changed() == [], session.dep.logs()


def test_during_a_redis_outage_only_503_and_nothing_stored_changes(session):
    session.redis_down()
    try:

        @settings(FUZZ, max_examples=60)
        @given(req=requests(session.corpus, session.targets, session.names))
        def one(req):
            problems = session.run(req)
            assert not problems, (req, problems)

        one()
        assert session.stats.by_status.get(503, 0) > 0, dumps(session.summary())
    finally:
        session.redis_up()
    assert session.changed() == [], session.dep.logs()
