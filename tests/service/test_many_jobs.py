"""Many jobs (N-way registration) against the real stack (uvicorn + RQ worker +
redis-server): POST /v1/many-jobs and gRPC SubmitManyAlignment over three partial captures of
one generated car, each under its own Sim(3); bad requests; cancel mid-edge."""

from __future__ import annotations

import json

import grpc
import httpx
import numpy as np
import pytest

from service.rpc.generated import alignment_pb2 as pb
from service.rpc.generated import alignment_pb2_grpc as pbg
from tests.service.conftest import ALICE, BOB, assert_problem, wait_job, wait_until

pytestmark = pytest.mark.slow  # starts servers and worker processes

EDGE_OPTIONS = {"stages": ["coarse"], "coarse_iterations": 30, "seed": 0}
AUTH = (("authorization", "Bearer key-alice"),)


@pytest.fixture(scope="module")
def captures(tmp_path_factory):
    """Three partial captures (2,500 Gaussians each) of one car, capture k = truth[k](car)."""
    from gsa.io.ply import write_ply
    from gsa.synth import make_object, random_sim3
    from gsa.synth.variants import cut_by_plane

    d = tmp_path_factory.mktemp("many")
    rng = np.random.default_rng([0, 30])
    paths, truth = [], []
    for k in range(3):
        m = make_object("car", seed=0, n_gaussians=2500, sample_seed=k)
        m = cut_by_plane(m, rng, keep=(0.8, 0.9))
        t = random_sim3(rng, scale_range=(0.5, 2.0))
        write_ply(m.transformed(t), d / f"capture{k}.ply")
        paths.append(d / f"capture{k}.ply")
        truth.append(t)
    return {"paths": paths, "truth": truth}


def upload(c: httpx.Client, path) -> str:
    with open(path, "rb") as fh:
        r = c.post("/v1/assets", files={"file": (path.name, fh)})
    assert r.status_code == 201, r.text
    return r.json()["id"]


@pytest.fixture(scope="module")
def assets(stack, captures):
    with httpx.Client(base_url=stack["url"], headers=ALICE, timeout=60) as c:
        return [upload(c, p) for p in captures["paths"]]


def rotation_error_deg(matrix, want) -> float:
    rot = np.asarray(matrix, np.float64)[:3, :3]
    rot = rot / np.cbrt(np.linalg.det(rot))
    cos = (np.trace(rot.T @ want.rotation) - 1) / 2
    return float(np.degrees(np.arccos(np.clip(cos, -1, 1))))


def check_against_truth(result: dict, assets: list[str], truth, reference: int = 0) -> None:
    assert result["reference"] == assets[reference]
    assert [m["asset_id"] for m in result["models"]] == assets
    for k, m in enumerate(result["models"]):
        want = truth[reference] @ truth[k].inverse()  # capture k -> the reference's frame
        assert rotation_error_deg(m["transform"], want) < 3.0, (k, m)
        assert abs(m["scale"] / want.scale - 1) < 0.03, (k, m["scale"], want.scale)
        assert m["file_transform"] == m["transform"]  # PLY files: the internal frame is the files'


def test_many_job_over_http(http, assets, captures):
    r = http.post("/v1/many-jobs", json={"assets": assets, "options": EDGE_OPTIONS, "merged": True})
    assert r.status_code == 202, r.text
    job = r.json()
    assert r.headers["Location"] == f"/v1/jobs/{job['id']}"
    assert job["sources"] == assets and job["target"] == assets[0]
    assert job["options"]["many"] == {"reference": assets[0], "edges": "auto", "merged": True, "merge": "concat"}
    stages = set()

    def done():
        j = http.get(f"/v1/jobs/{job['id']}").json()
        stages.add(j["stage"])
        return j if j["state"] in ("succeeded", "failed", "cancelled") else None

    final = wait_until(done, 180, 0.05, "the many job")
    assert final["state"] == "succeeded", final
    assert any(s and s.startswith("edge 1/3: ") for s in stages), stages  # which edge of how many
    assert any(s and s.startswith("edge 3/3: ") for s in stages), stages
    result = final["result"]
    check_against_truth(result, assets, captures["truth"])
    assert len(result["edges"]) == 3
    for e in result["edges"]:
        assert e["status"] in ("kept", "down-weighted", "pruned", "corrected")
        assert {"rotation_deg", "log_scale", "translation", "units"} <= set(e["residual"])
    assert result["pruned"] == [] and result["corrected"] == []
    names = {a["name"] for a in final["artifacts"]}
    assert names == {"many.json", "merged.ply", *(f"preview/model{k}.splat" for k in range(3))}
    many_json = http.get(f"/v1/jobs/{job['id']}/artifacts/many.json").json()
    assert many_json == result  # the result is many.json's content
    from service.api.results import JobResult

    typed = JobResult.model_validate(many_json)  # the typed result of the OpenAPI document, no fallback
    assert typed.models[1].asset_id == assets[1] and typed.edges[0].residual.units is not None
    assert typed.model_dump(mode="json") == many_json
    assert result["merge"]["gaussians"] == sum(int(http.get(f"/v1/assets/{a}").json()["n_gaussians"]) for a in assets)
    merged = http.get(f"/v1/jobs/{job['id']}/artifacts/merged.ply")
    assert merged.status_code == 200 and merged.content.startswith(b"ply")
    splat = http.get(f"/v1/jobs/{job['id']}/artifacts/merged.ply", params={"format": "splat"})
    assert splat.status_code == 200 and len(splat.content) == 32 * result["merge"]["gaussians"]
    # The results page shows the models and the graph (tests/service/test_view_many.py).
    page = http.get(f"/v1/jobs/{job['id']}/view")
    assert page.status_code == 200 and page.text.count("data-many-model=") == 3
    assert http.get("/v1/view/jobs").status_code == 200


def test_bad_many_requests(stack, http, assets, captures):
    def post(body):
        return http.post("/v1/many-jobs", json={"options": EDGE_OPTIONS, **body})

    p = assert_problem(post({"assets": assets[:1]}), 422, "invalid-input")
    assert p["option"] == "assets" and p["minimum"] == 2
    p = assert_problem(post({"assets": [assets[0]] + [f"ast_{k}" for k in range(70)]}), 422, "invalid-input")
    assert p["option"] == "assets" and p["maximum"] == 64
    # All pairs of 21 models is 210 alignments, past GSA_MAX_MANY_EDGES (200); 20 models' 190 pass that check.
    many = [assets[0]] + [f"ast_{k}" for k in range(20)]
    p = assert_problem(post({"assets": many, "edges": "all"}), 422, "invalid-input")
    assert p["option"] == "edges" and p["maximum"] == 200 and p["value"] == 210 and "'auto'" in p["detail"]
    assert_problem(post({"assets": many[:20], "edges": "all"}), 404, "not-found")
    assert_problem(post({"assets": [assets[0], assets[0]]}), 422, "invalid-input")
    p = assert_problem(post({"assets": assets[:2], "reference": assets[2]}), 422, "invalid-input")
    assert p["option"] == "reference"
    p = assert_problem(post({"assets": assets[:2], "edges": "some"}), 422, "invalid-input")
    assert p["option"] == "edges"
    p = assert_problem(post({"assets": assets[:2], "options": {"outputs": ["aligned"]}}), 422, "invalid-input")
    assert p["option"] == "outputs"
    p = assert_problem(post({"assets": assets[:2], "options": {"coarse_iterations": 0}}), 422, "invalid-input")
    assert p["option"] == "coarse_iterations"
    assert_problem(post({"assets": assets[:2], "colour": 1}), 422, "validation-error")  # unknown field
    assert_problem(post({"assets": [assets[0], "ast_0123456789abcdef"]}), 404, "not-found")
    with httpx.Client(base_url=stack["url"], headers=BOB, timeout=60) as bob:
        bobs = upload(bob, captures["paths"][0])
    assert_problem(post({"assets": [assets[0], bobs]}), 404, "not-found")  # another tenant's asset
    # Idempotency: the same key and body replay the job, another body with it is 422.
    first = http.post(
        "/v1/many-jobs", json={"assets": assets[:2], "options": EDGE_OPTIONS}, headers={"Idempotency-Key": "m1"}
    )
    again = http.post(
        "/v1/many-jobs", json={"assets": assets[:2], "options": EDGE_OPTIONS}, headers={"Idempotency-Key": "m1"}
    )
    assert first.status_code == again.status_code == 202
    assert again.json()["id"] == first.json()["id"] and again.headers["Idempotent-Replayed"] == "true"
    other = http.post(
        "/v1/many-jobs", json={"assets": assets[1:], "options": EDGE_OPTIONS}, headers={"Idempotency-Key": "m1"}
    )
    assert_problem(other, 422, "idempotency-key-reused")
    http.post(f"/v1/jobs/{first.json()['id']}:cancel")
    wait_job(http, first.json()["id"], timeout=60)


def test_cancel_a_running_many_job(http, assets):
    slow = {**EDGE_OPTIONS, "coarse_iterations": 300}
    job = http.post("/v1/many-jobs", json={"assets": assets, "options": slow}).json()
    wait_until(
        lambda: (http.get(f"/v1/jobs/{job['id']}").json()["stage"] or "").startswith("edge 1/3"),
        120,
        0.05,
        "the first edge to start",
    )
    r = http.post(f"/v1/jobs/{job['id']}:cancel")
    assert r.status_code == 202, r.text
    final = wait_job(http, job["id"], timeout=60)
    assert final["state"] == "cancelled", final
    assert final["artifacts"] == [] and final["result"] is None


def test_edges_spread_over_the_workers(stack, http, assets, captures):
    """One RQ job per edge: with a second worker registered, the job enqueues a task for each
    edge but the first, and its edges run on both workers (each edge names its worker); the
    result is the same job result (truth within 3°)."""
    import redis
    import rq

    from tests.service.conftest import start_worker

    queue = rq.Queue("gsa", connection=redis.Redis.from_url(stack["redis_url"]))
    second = start_worker(stack["tmp"], stack["env"], "edge-helper")
    try:
        wait_until(lambda: rq.Worker.count(queue=queue) >= 2, 60, 0.2, "a second worker")
        options = {**EDGE_OPTIONS, "coarse_iterations": 60}
        r = http.post("/v1/many-jobs", json={"assets": assets, "edges": "all", "options": options})
        assert r.status_code == 202, r.text
        final = wait_job(http, r.json()["id"], timeout=240)
    finally:
        second.stop()
    assert final["state"] == "succeeded", final
    result = final["result"]
    check_against_truth(result, assets, captures["truth"])
    assert result["timings"]["edge_tasks"] == 2  # edges - 1
    workers = [e["worker"] for e in result["edges"]]
    assert len(set(workers)) == 2 and all(w.startswith(("worker-", "edge-helper-")) for w in workers), (
        workers,
        result["timings"],
    )


def test_many_job_over_grpc(stack, assets, captures):
    ch = grpc.insecure_channel(stack["grpc"])
    stub = pbg.AlignmentServiceStub(ch)
    with pytest.raises(grpc.RpcError) as e:
        stub.SubmitManyAlignment(pb.ManyAlignmentRequest(asset_ids=assets[:1]), metadata=AUTH)
    assert e.value.code() == grpc.StatusCode.INVALID_ARGUMENT
    problem = json.loads(dict(e.value.trailing_metadata())["gsa-problem"])
    assert problem["option"] == "assets"
    job = stub.SubmitManyAlignment(
        pb.ManyAlignmentRequest(
            asset_ids=assets[:2], reference_asset_id=assets[1], options_json=json.dumps(EDGE_OPTIONS)
        ),
        metadata=AUTH,
    )
    assert list(job.source_asset_ids) == assets[:2] and job.target_asset_id == assets[1]

    def done():
        j = stub.GetJob(pb.JobRef(job_id=job.id), metadata=AUTH)
        return j if j.state in (pb.JOB_STATE_SUCCEEDED, pb.JOB_STATE_FAILED, pb.JOB_STATE_CANCELLED) else None

    final = wait_until(done, 120, 0.1, "the gRPC many job")
    assert final.state == pb.JOB_STATE_SUCCEEDED, final
    result = json.loads(final.result_json)
    check_against_truth(result, assets[:2], captures["truth"][:2], reference=1)
    # Job.transforms: one per model, each its file_transform with its confidence (the pair jobs' contract).
    assert len(final.transforms) == 2 and final.transform == final.transforms[0]
    for t, m in zip(final.transforms, result["models"]):
        assert np.allclose(np.reshape(t.matrix, (4, 4)), m["file_transform"], atol=1e-9)
        assert t.scale == pytest.approx(m["scale"]) and t.confidence == m["confidence"] and t.doubtful == m["doubtful"]
    assert np.allclose(np.reshape(final.transforms[1].matrix, (4, 4)), np.eye(4), atol=1e-9)  # the reference
    assert [a.name for a in final.artifacts] == ["many.json", "preview/model0.splat", "preview/model1.splat"]


def test_many_job_memory_prediction():
    """The largest pair's job plus every other model held, plus the merged model when asked:
    eight 5M SH-3 captures are refused under the default 8 GB budget, three small ones are not."""
    from types import SimpleNamespace

    from service.jobs.many import check_many_memory
    from service.models import Asset
    from service.problems import Problem

    def asset(n: int) -> Asset:
        return Asset(
            id=f"ast_{n}", owner="alice", kind="ply", key="k", size=n * 248, content_type="application/x-ply",
            n_gaussians=n, sha256="0", created_at=0.0,
        )  # fmt: skip

    b = SimpleNamespace(settings=SimpleNamespace(worker_memory_mb=8192))
    check_many_memory(b, [asset(3000)] * 3, {"stages": ["coarse"]}, merged=True)
    check_many_memory(b, [asset(2_000_000)] * 2, {"stages": ["coarse"]}, merged=False)
    with pytest.raises(Problem) as e:
        check_many_memory(b, [asset(5_000_000)] * 8, {"stages": ["coarse"]}, merged=True)
    p = e.value.to_dict()
    assert p["status"] == 422 and p["option"] == "memory" and p["maximum"] == 8192 and p["value"] > 8192
    # Holding more models, or the merged one, never predicts less.
    b.settings.worker_memory_mb = 6000
    check_many_memory(b, [asset(2_000_000)] * 2, {"stages": ["coarse"]}, merged=False)
    with pytest.raises(Problem):
        check_many_memory(b, [asset(2_000_000)] * 4, {"stages": ["coarse"]}, merged=True)


def test_many_job_operation_in_openapi(http):
    doc = http.get("/openapi.json").json()
    op = doc["paths"]["/v1/many-jobs"]["post"]
    assert op["operationId"] == "createManyJob"
    assert {"422", "404", "429", "507"} <= set(op["responses"])
    props = doc["components"]["schemas"]["JobResult"]["properties"]
    assert {"models", "edges", "pruned", "corrected", "reference"} <= set(props)


def test_a_model_align_many_cannot_use_fails_the_job_as_invalid_input(http, assets, captures, tmp_path):
    from gsa.io.ply import read_ply, write_ply

    tiny = read_ply(captures["paths"][0]).subset(np.arange(2))
    write_ply(tiny, tmp_path / "tiny.ply")
    job = http.post("/v1/many-jobs", json={"assets": [assets[0], upload(http, tmp_path / "tiny.ply")]}).json()
    final = wait_job(http, job["id"], timeout=60)
    assert final["state"] == "failed", final
    assert final["error"]["status"] == 422 and final["error"]["type"].endswith("/invalid-input"), final["error"]
    assert "at least 3 are needed" in final["error"]["detail"]


def test_many_job_in_embedded_mode(tmp_path, captures):
    """`gsa serve` alone (SQLite, in-process worker): the same job type, here over two captures."""
    from tests.service.conftest import service_env, start_api

    api, url, _ = start_api(tmp_path, service_env(tmp_path), name="embedded-many")
    try:
        with httpx.Client(base_url=url, headers=ALICE, timeout=60) as c:
            ids = [upload(c, p) for p in captures["paths"][:2]]
            r = c.post("/v1/many-jobs", json={"assets": ids, "options": EDGE_OPTIONS})
            assert r.status_code == 202, r.text
            final = wait_job(c, r.json()["id"], timeout=180)
        assert final["state"] == "succeeded", (final, api.tail())
        check_against_truth(final["result"], ids, captures["truth"][:2])
    finally:
        api.stop()


def test_many_job_from_the_python_client(stack, assets, captures):
    from gsa.client import GSAClient, ServiceError

    with GSAClient(stack["url"], "key-alice") as client:
        job = client.submit_many(assets[1:], options=EDGE_OPTIONS)
        final = client.wait(job["id"], timeout=120)
        check_against_truth(final["result"], assets[1:], captures["truth"][1:])
        with pytest.raises(ServiceError) as e:
            client.submit_many(assets[:1])
        assert e.value.status == 422
