"""Tenant-facing bounds (issue 28): `outputs` deduplicated and bounded (100,000 duplicate
entries were stored as given: a 923 KB job record), and `/metrics`, which counts every
tenant's jobs, only for operator keys (GSA_METRICS_OWNERS; the test stack names alice)."""

from __future__ import annotations

import httpx

from tests.service.conftest import ALICE, BOB, assert_problem, submit_pair


def _assets(c: httpx.Client, pair) -> list[str]:
    ids = []
    for k in ("source", "target"):
        with open(pair[k], "rb") as fh:
            ids.append(c.post("/v1/assets", files={"file": (f"{k}.ply", fh)}).json()["id"])
    return ids


def test_outputs_are_deduplicated_and_bounded(stack, pair):
    with httpx.Client(base_url=stack["url"], headers=ALICE, timeout=60) as c:
        src, tgt = _assets(c, pair)
        many = {"stages": ["coarse"], "outputs": ["result"] * 90_000}
        body = {"source": src, "target": tgt, "options": many}
        p = assert_problem(c.post("/v1/jobs", json=body), 422, "invalid-input")
        assert p["option"] == "outputs" and p["maximum"] == 64, p
        assert_problem(submit_pair(c, pair, many), 422, "invalid-input")

        dup = {"stages": ["coarse"], "outputs": ["result", "aligned", "result", "aligned", "result"]}
        r = c.post("/v1/jobs", json={"source": src, "target": tgt, "options": dup})
        assert r.status_code == 202, r.text
        job = c.get(f"/v1/jobs/{r.json()['id']}").json()
        assert job["options"]["outputs"] == ["result", "aligned"], job["options"]


def test_metrics_are_for_operators_only(stack):
    with httpx.Client(base_url=stack["url"], timeout=30) as c:
        assert_problem(c.get("/metrics", headers=BOB), 403, "forbidden")
        r = c.get("/metrics", headers=ALICE)  # an owner in GSA_METRICS_OWNERS
        assert r.status_code == 200 and "gsa_jobs" in r.text
        assert_problem(c.get("/metrics"), 401)
