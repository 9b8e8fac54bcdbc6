"""GET /v1/assets (listAssets): a tenant's assets, newest first, in pages with the cursor of
listJobs, in both modes (Redis; embedded SQLite) against real servers: every asset once, only
the caller's (another tenant sees none of them), a deleted one gone, bad paging 422; in Redis,
assets stored before the per-owner index existed are listed too. Before, no route listed them,
so an asset whose id was lost could not be found or freed."""

from __future__ import annotations

import httpx
import pytest
import redis

from tests.service.conftest import ALICE, BOB, assert_problem, service_env, start_api

pytestmark = pytest.mark.slow  # starts servers


@pytest.fixture(params=["redis", "embedded"])
def server(request, tmp_path, redis_url):
    extra = {}
    if request.param == "redis":
        extra["GSA_REDIS_URL"] = redis_url + "/12"
        redis.Redis.from_url(extra["GSA_REDIS_URL"]).flushdb()
    api, url, _ = start_api(tmp_path, service_env(tmp_path, **extra))
    yield request.param, url, extra.get("GSA_REDIS_URL")
    api.stop()


def _pages(c: httpx.Client, limit: int) -> list[list[str]]:
    pages, cursor = [], None
    while True:
        r = c.get("/v1/assets", params={"limit": limit, **({"cursor": cursor} if cursor else {})})
        assert r.status_code == 200, r.text
        body = r.json()
        pages.append([a["id"] for a in body["items"]])
        cursor = body["next_cursor"]
        if not cursor:
            return pages


def test_assets_are_listed_per_tenant_newest_first(server, pair):
    mode, url, rurl = server
    data = pair["source"].read_bytes()
    with (
        httpx.Client(base_url=url, headers=ALICE, timeout=60) as alice,
        httpx.Client(base_url=url, headers=BOB, timeout=60) as bob,
    ):
        ids = []
        for i in range(5):  # the same bytes make a new asset each time (one stored copy)
            r = alice.post("/v1/assets", files={"file": (f"m{i}.ply", data)})
            assert r.status_code == 201, r.text
            ids.append(r.json()["id"])
        bobs = bob.post("/v1/assets", files={"file": ("b.ply", data)}).json()["id"]
        pages = _pages(alice, 2)
        assert [len(p) for p in pages] == [2, 2, 1], pages
        assert sum(pages, []) == ids[::-1]  # newest first, each once
        first = alice.get("/v1/assets").json()
        assert first["next_cursor"] is None and first["items"][0]["filename"] == "m4.ply"
        assert first["items"][0]["n_gaussians"] == 3000 and first["items"][0]["kind"] == "ply"
        assert _pages(bob, 50) == [[bobs]]  # Bob sees his own, none of Alice's
        assert alice.delete(f"/v1/assets/{ids[2]}").status_code == 204
        assert sum(_pages(alice, 2), []) == [ids[4], ids[3], ids[1], ids[0]]
        assert_problem(alice.get("/v1/assets", params={"cursor": "not-a-cursor"}), 422)
        assert_problem(alice.get("/v1/assets", params={"limit": 0}), 422, "validation-error")
        assert_problem(httpx.get(url + "/v1/assets"), 401)
        if mode == "redis":
            # as if stored before the index: the index and its marker gone, the records kept
            r = redis.Redis.from_url(rurl)
            for key in r.scan_iter(match="*owner-assets*"):
                r.delete(key)
            assert sum(_pages(alice, 3), []) == [ids[4], ids[3], ids[1], ids[0]]
            assert _pages(bob, 3) == [[bobs]]
