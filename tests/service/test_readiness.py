"""/readyz takes an instance out of rotation when its disk is nearly full."""

from __future__ import annotations

import httpx
import pytest

from tests.service.conftest import service_env, start_api

pytestmark = pytest.mark.slow  # starts an API process


def test_readyz_fails_below_the_free_space_floor(tmp_path):
    env = service_env(tmp_path, GSA_MIN_FREE_BYTES=str(10**18))  # more than any disk has
    proc, url, _ = start_api(tmp_path, env)
    try:
        r = httpx.get(url + "/readyz")
        assert r.status_code == 503 and r.headers["content-type"].startswith("application/problem+json")
        body = r.json()
        assert body["checks"]["disk_space"] is False and body["checks"]["store"] is True
        assert "disk_space" in body["detail"] and r.headers["retry-after"]
        assert httpx.get(url + "/healthz").status_code == 200  # alive, just not ready
    finally:
        proc.stop()


def test_readyz_reports_disk_space_when_there_is_room(stack):
    r = httpx.get(stack["url"] + "/readyz")
    assert r.status_code == 200 and r.json()["checks"]["disk_space"] is True
