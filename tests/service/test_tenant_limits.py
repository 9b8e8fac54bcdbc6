"""Tenant-facing bounds: `outputs` deduplicated and bounded (100,000 duplicate
entries were stored as given: a 923 KB job record), and `/metrics`, which counts every
tenant's jobs, only for operator keys (GSA_METRICS_OWNERS; the test stack names alice)."""

from __future__ import annotations

import json
import time
from concurrent.futures import ThreadPoolExecutor

import httpx
import pytest

from tests.service.conftest import (
    ALICE,
    BOB,
    assert_problem,
    service_env,
    start_api,
    start_worker,
    submit_pair,
    wait_job,
)


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


# ------------------------------------------------------------------ per-tenant quotas (service.jobs.quotas)
# Each test starts its own deployment, in both modes: embedded (SQLite, in-process worker) and
# Redis (a database of the session's redis-server of its own, a `gsa worker` where jobs must run).

_DB = iter(range(5, 15))  # Redis databases no other test uses


def _deploy(tmp_path, mode: str, redis_url: str, *, worker: bool, apis: int = 1, grpc: bool = False, **env):
    """Start `apis` API processes (+ a worker in Redis mode); returns (urls, grpc address, procs)."""
    if mode == "redis":
        env["GSA_REDIS_URL"] = f"{redis_url}/{next(_DB)}"
    env.setdefault("GSA_TENANT_RATE_PER_S", 0)  # each test turns on the limit it tests
    e = service_env(tmp_path, **env)
    procs, urls, gport = [], [], None
    for i in range(apis):
        api, url, gp = start_api(tmp_path, e, grpc=grpc and i == 0, name=f"api{i}")
        procs.append(api)
        urls.append(url)
        gport = gport or gp
    if worker and mode == "redis":
        procs.append(start_worker(tmp_path, e))
    return urls, f"127.0.0.1:{gport}" if gport else None, procs


def _upload(c: httpx.Client, path) -> httpx.Response:
    with open(path, "rb") as fh:
        return c.post("/v1/assets", files={"file": (path.name, fh)})


@pytest.mark.parametrize("mode", ["embedded", "redis"])
def test_a_tenant_over_its_storage_quota_gets_507_while_another_still_stores(tmp_path, pair, redis_url, mode):
    size = pair["source"].stat().st_size  # the target has the same layout and count
    quota = int(size * 2.5)  # both inputs fit; their job's aligned model does not
    urls, _, procs = _deploy(tmp_path, mode, redis_url, worker=True, GSA_TENANT_STORAGE_QUOTA_BYTES=quota)
    try:
        with (
            httpx.Client(base_url=urls[0], headers=ALICE, timeout=60) as a,
            httpx.Client(base_url=urls[0], headers=BOB, timeout=60) as b,
        ):
            src, tgt = (_upload(a, pair[k]).json()["id"] for k in ("source", "target"))
            opts = {"stages": ["coarse"], "coarse_iterations": 50, "outputs": ["result", "aligned"]}
            r = a.post("/v1/jobs", json={"source": src, "target": tgt, "options": opts})
            assert r.status_code == 202, r.text
            job = wait_job(a, r.json()["id"], timeout=120)
            assert job["state"] == "succeeded", job
            # Alice's inputs and artifacts now pass her quota: no more uploads, no more jobs.
            p = assert_problem(_upload(a, pair["source2"]), 507, "storage-quota-exceeded")
            assert p["quota"] == quota and p["used"] > quota, p
            assert "Retry-After" not in _upload(a, pair["source2"]).headers  # waiting frees nothing
            assert_problem(a.post("/v1/jobs", json={"source": src, "target": tgt}), 507, "storage-quota-exceeded")
            assert_problem(submit_pair(a, pair, {"stages": ["coarse"]}), 507, "storage-quota-exceeded")
            # Bytes she already stores are shared, not stored again: still accepted.
            assert _upload(a, pair["source"]).status_code == 201
            # Bob is not held by Alice's usage: he uploads and runs jobs.
            r = submit_pair(b, pair, {"stages": ["coarse"], "coarse_iterations": 50, "outputs": ["result"]})
            assert r.status_code == 202, r.text
            assert wait_job(b, r.json()["id"], timeout=120)["state"] == "succeeded"
            # Deleting her job frees its artifacts' share: she may run jobs again.
            assert a.delete(f"/v1/jobs/{job['id']}").status_code == 204
            r = a.post("/v1/jobs", json={"source": src, "target": tgt, "options": opts})
            assert r.status_code == 202, r.text
            wait_job(a, r.json()["id"], timeout=120)
    finally:
        for p in procs:
            p.stop()


def _long_job(c: httpx.Client, ids: list[str]) -> httpx.Response:
    # Eight copies of the 50k-Gaussian source: seconds of work, so an embedded worker is busy.
    return c.post("/v1/jobs", json={"sources": [ids[0]] * 8, "target": ids[1], "options": {"outputs": ["result"]}})


@pytest.mark.parametrize("mode", ["embedded", "redis"])
def test_concurrent_job_limit_is_429_with_retry_after(tmp_path, pair, redis_url, mode):
    import grpc

    from service.rpc.generated import alignment_pb2 as pb
    from service.rpc.generated import alignment_pb2_grpc as pbg

    # Redis mode runs no worker, so accepted jobs stay queued; the embedded worker runs one at a time.
    urls, gaddr, procs = _deploy(
        tmp_path,
        mode,
        redis_url,
        worker=False,
        grpc=True,
        GSA_TENANT_MAX_ACTIVE_JOBS=2,
        GSA_TENANT_JOBS_RETRY_AFTER_S=7,
    )
    try:
        with (
            httpx.Client(base_url=urls[0], headers=ALICE, timeout=60) as a,
            httpx.Client(base_url=urls[0], headers=BOB, timeout=60) as b,
        ):
            ids = [_upload(a, pair[k]).json()["id"] for k in ("big_source", "big_target")]
            first = [_long_job(a, ids) for _ in range(2)]
            assert [r.status_code for r in first] == [202, 202], [r.text for r in first]
            r = _long_job(a, ids)
            p = assert_problem(r, 429, "too-many-jobs")
            assert r.headers["Retry-After"] == "7" and p["retry_after"] == 7, (r.headers, p)
            assert p["limit"] == 2 and p["active"] == 2, p
            assert_problem(submit_pair(a, pair, {"stages": ["coarse"]}), 429, "too-many-jobs")
            # gRPC: the same limit, RESOURCE_EXHAUSTED with the problem and Retry-After in its trailers.
            with grpc.insecure_channel(gaddr) as ch:
                head = pb.SubmitHeader(source_asset_ids=[ids[0]], target_asset_id=ids[1], options_json="{}")
                with pytest.raises(grpc.RpcError) as err:
                    pbg.AlignmentServiceStub(ch).SubmitAlignment(
                        iter([pb.SubmitRequest(header=head)]), metadata=(("authorization", "Bearer key-alice"),)
                    )
                assert err.value.code() == grpc.StatusCode.RESOURCE_EXHAUSTED
                trailers = dict(err.value.trailing_metadata())
                assert json.loads(trailers["gsa-problem"])["type"].endswith("/too-many-jobs")
                assert trailers["retry-after"] == "7"
            # Bob has his own limit.
            bids = [_upload(b, pair[k]).json()["id"] for k in ("source", "target")]
            assert b.post("/v1/jobs", json={"source": bids[0], "target": bids[1]}).status_code == 202
            # A cancelled job frees its slot; concurrent submissions then get exactly that one slot.
            for r in first:
                assert a.post(f"/v1/jobs/{r.json()['id']}:cancel").status_code == 202
                wait_job(a, r.json()["id"], timeout=60)  # a running one stops at its next progress report
            one = _long_job(a, ids)
            assert one.status_code == 202, one.text
            with ThreadPoolExecutor(6) as pool:
                codes = sorted(r.status_code for r in pool.map(lambda _: _long_job(a, ids), range(6)))
            assert codes == [202] + [429] * 5, codes
            listed = a.get("/v1/jobs", params={"limit": 50}).json()["items"]
            assert sum(j["state"] in ("queued", "running") for j in listed) == 2
            for j in listed:
                a.post(f"/v1/jobs/{j['id']}:cancel")
    finally:
        for p in procs:
            p.stop()


@pytest.mark.parametrize("mode", ["embedded", "redis"])
def test_request_rate_is_429_with_retry_after(tmp_path, pair, redis_url, mode):
    import grpc

    from service.rpc.generated import alignment_pb2 as pb
    from service.rpc.generated import alignment_pb2_grpc as pbg

    # Redis mode: two API processes draw from one bucket per tenant, kept in Redis.
    urls, gaddr, procs = _deploy(
        tmp_path,
        mode,
        redis_url,
        worker=False,
        apis=2 if mode == "redis" else 1,
        grpc=True,
        GSA_TENANT_RATE_PER_S=0.5,
        GSA_TENANT_RATE_BURST=6,
    )
    try:
        clients = [httpx.Client(base_url=u, headers=ALICE, timeout=30) for u in urls]
        codes = [clients[i % len(clients)].get("/v1/jobs").status_code for i in range(6)]
        assert codes == [200] * 6, codes
        r = clients[-1].get("/v1/jobs")
        p = assert_problem(r, 429, "rate-limited")
        wait = int(r.headers["Retry-After"])
        assert 1 <= wait <= 2 and p["retry_after"] == wait, (r.headers, p)
        assert clients[0].get("/v1/jobs").status_code == 429
        with grpc.insecure_channel(gaddr) as ch:
            with pytest.raises(grpc.RpcError) as err:
                pbg.AlignmentServiceStub(ch).GetJob(
                    pb.JobRef(job_id="job_x"), metadata=(("authorization", "Bearer key-alice"),)
                )
            assert err.value.code() == grpc.StatusCode.RESOURCE_EXHAUSTED
            assert json.loads(dict(err.value.trailing_metadata())["gsa-problem"])["type"].endswith("/rate-limited")
        # Other tenants and unauthenticated probes are not held by Alice's rate.
        assert clients[-1].get("/v1/jobs", headers=BOB).status_code == 200
        assert clients[-1].get("/healthz").status_code == 200
        time.sleep(wait + 0.2)  # Retry-After is honest: a token is back by then
        assert clients[-1].get("/v1/jobs").status_code == 200
        for c in clients:
            c.close()
    finally:
        for p in procs:
            p.stop()
