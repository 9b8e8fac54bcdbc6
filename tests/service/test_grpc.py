"""gRPC: generated code in sync, end to end against the same store as HTTP,
health and reflection."""

from __future__ import annotations

import json
from pathlib import Path

import grpc
import httpx
import numpy as np
import pytest

from service.rpc.generated import alignment_pb2 as pb
from service.rpc.generated import alignment_pb2_grpc as pbg
from tests.service.conftest import ALICE, ROOT, library_result

ALIGN = {"stages": ["coarse"], "coarse_iterations": 30, "seed": 0}
# Renders cost seconds per job on CPU: only the first end-to-end test asks for them.
OPTS = {**ALIGN, "outputs": ["result", "aligned", "merged"]}
AUTH = (("authorization", "Bearer key-alice"),)


def test_generated_code_in_sync(tmp_path):
    from service.rpc.generated.generate import FILES, generate

    generate(tmp_path)
    for name in FILES:
        assert (tmp_path / name).read_text() == (ROOT / "service" / "rpc" / "generated" / name).read_text(), (
            f"{name} is stale: run python -m service.rpc.generated.generate"
        )


@pytest.fixture
def stub(stack):
    ch = grpc.insecure_channel(stack["grpc"])
    yield pbg.AlignmentServiceStub(ch), ch
    ch.close()


def _chunks(path: Path, role, index, size=64 * 1024):
    data = path.read_bytes()
    for i in range(0, len(data), size):
        yield pb.SubmitRequest(chunk=pb.FileChunk(role=role, index=index, filename=path.name, data=data[i : i + size]))


def _submit(pair, idem=""):
    yield pb.SubmitRequest(header=pb.SubmitHeader(options_json=json.dumps(OPTS), idempotency_key=idem))
    yield from _chunks(pair["source"], pb.ROLE_SOURCE, 0)
    yield from _chunks(pair["target"], pb.ROLE_TARGET, 0)


def test_grpc_end_to_end_and_visible_over_http(stub, stack, pair):
    s, _ = stub
    job = s.SubmitAlignment(_submit(pair), metadata=AUTH)
    assert job.id.startswith("job_") and job.state in (
        pb.JOB_STATE_QUEUED,
        pb.JOB_STATE_RUNNING,
    )
    seen = list(s.WatchJob(pb.JobRef(job_id=job.id), metadata=AUTH, timeout=60))
    final = seen[-1]
    assert final.state == pb.JOB_STATE_SUCCEEDED, final
    assert all(a.progress <= b.progress for a, b in zip(seen, seen[1:]))
    ref = library_result(pair, ALIGN)
    np.testing.assert_allclose(
        np.array(final.transform.matrix).reshape(4, 4),
        ref.transform.matrix(),
        atol=1e-9,
    )
    np.testing.assert_allclose(final.transform.scale, ref.transform.scale, atol=1e-9)
    np.testing.assert_allclose(final.transform.quaternion, ref.transform.quaternion(), atol=1e-9)
    # the GT-free judgement travels with the transform
    assert final.transform.confidence == pytest.approx(ref.metrics["confidence"])
    assert final.transform.doubtful == ref.verdict.doubtful
    assert final.transform.ambiguous == ref.verdict.ambiguous

    # same store: HTTP sees the gRPC job, and the artifacts match byte for byte
    with httpx.Client(base_url=stack["url"], headers=ALICE) as http:
        hj = http.get(f"/v1/jobs/{job.id}").json()
        assert hj["state"] == "succeeded"
        np.testing.assert_allclose(hj["result"]["transform"], ref.transform.matrix(), atol=1e-9)
        over_http = http.get(f"/v1/jobs/{job.id}/artifacts/aligned.ply").content
    chunks = list(s.GetArtifact(pb.ArtifactRequest(job_id=job.id, name="aligned.ply"), metadata=AUTH))
    assert b"".join(c.data for c in chunks) == over_http
    assert chunks[0].total_size == len(over_http) and chunks[0].content_type == "application/x-ply"
    part = list(
        s.GetArtifact(
            pb.ArtifactRequest(job_id=job.id, name="aligned.ply", offset=5, length=20),
            metadata=AUTH,
        )
    )
    assert b"".join(c.data for c in part) == over_http[5:25]

    assert s.GetJob(pb.JobRef(job_id=job.id), metadata=AUTH).state == pb.JOB_STATE_SUCCEEDED
    with pytest.raises(grpc.RpcError) as e:
        s.CancelJob(pb.JobRef(job_id=job.id), metadata=AUTH)
    assert e.value.code() == grpc.StatusCode.FAILED_PRECONDITION


def test_grpc_http_job_visible_and_asset_ids(stub, stack, pair):
    s, _ = stub
    with httpx.Client(base_url=stack["url"], headers=ALICE) as http:
        ids = []
        for k in ("source", "target"):
            with open(pair[k], "rb") as fh:
                ids.append(http.post("/v1/assets", files={"file": (k + ".ply", fh)}).json()["id"])
        hjob = http.post("/v1/jobs", json={"source": ids[0], "target": ids[1], "options": OPTS}).json()
    final = list(s.WatchJob(pb.JobRef(job_id=hjob["id"]), metadata=AUTH, timeout=60))[-1]
    assert final.state == pb.JOB_STATE_SUCCEEDED and list(final.source_asset_ids) == [ids[0]]

    def by_ids(idem):
        yield pb.SubmitRequest(
            header=pb.SubmitHeader(
                source_asset_ids=[ids[0]],
                target_asset_id=ids[1],
                options_json=json.dumps(OPTS),
                idempotency_key=idem,
            )
        )

    a = s.SubmitAlignment(by_ids("g-1"), metadata=AUTH)
    b = s.SubmitAlignment(by_ids("g-1"), metadata=AUTH)
    assert a.id == b.id


def test_grpc_errors(stub, pair):
    s, _ = stub
    with pytest.raises(grpc.RpcError) as e:
        s.GetJob(pb.JobRef(job_id="job_x"), metadata=(("authorization", "Bearer wrong"),))
    assert e.value.code() == grpc.StatusCode.UNAUTHENTICATED
    with pytest.raises(grpc.RpcError) as e:
        s.GetJob(pb.JobRef(job_id="job_x"), metadata=AUTH)
    assert e.value.code() == grpc.StatusCode.NOT_FOUND
    problem = json.loads(dict(e.value.trailing_metadata())["gsa-problem"])
    assert problem["status"] == 404

    def not_ply():
        yield pb.SubmitRequest(header=pb.SubmitHeader())
        yield pb.SubmitRequest(chunk=pb.FileChunk(role=pb.ROLE_SOURCE, data=b"garbage" * 100))
        yield from _chunks(pair["target"], pb.ROLE_TARGET, 0)

    with pytest.raises(grpc.RpcError) as e:
        s.SubmitAlignment(not_ply(), metadata=AUTH)
    assert e.value.code() == grpc.StatusCode.INVALID_ARGUMENT


def test_a_huge_id_is_not_found_not_echoed(stub, http):
    """A 9 KB id (and option names as long) are answered with their own status and a short
    message: the problem no longer repeats what the client sent in full, which put the trailing
    metadata past gRPC's 8 KiB limit and the client saw RESOURCE_EXHAUSTED instead."""
    s, _ = stub
    huge = "job_" + "x" * 9000
    for call in (s.GetJob, s.CancelJob, s.DeleteJob):
        with pytest.raises(grpc.RpcError) as e:
            call(pb.JobRef(job_id=huge), metadata=AUTH, timeout=30)
        assert e.value.code() == grpc.StatusCode.NOT_FOUND, (call, e.value.code(), e.value.details()[:200])
        assert len(e.value.details()) < 200 and "x" * 100 not in e.value.details(), e.value.details()[:300]
        problem = json.loads(dict(e.value.trailing_metadata())["gsa-problem"])
        assert problem["status"] == 404 and "9004 characters" in problem["detail"], problem
    with pytest.raises(grpc.RpcError) as e:
        list(s.GetArtifact(pb.ArtifactRequest(job_id=huge, name="result.json"), metadata=AUTH, timeout=30))
    assert e.value.code() == grpc.StatusCode.NOT_FOUND
    # an unknown option whose name is 9 KB: the problem lists it, clipped
    header = pb.SubmitHeader(options_json=json.dumps({"o" * 9000: 1}), target_asset_id="ast_x")
    with pytest.raises(grpc.RpcError) as e:
        s.SubmitAlignment(iter([pb.SubmitRequest(header=header)]), metadata=AUTH, timeout=30)
    assert e.value.code() == grpc.StatusCode.INVALID_ARGUMENT, e.value.code()
    assert len(dict(e.value.trailing_metadata())["gsa-problem"]) <= 4096
    # over HTTP the id is in the problem's `instance` (the path); the detail says how long it was
    r = http.get("/v1/jobs/" + "job_" + "y" * 2000)
    assert r.status_code == 404 and "y" * 100 not in r.json()["detail"], r.text[:300]
    assert "job_x" in http.get("/v1/jobs/job_x").json()["detail"]  # an id of our shape is still named


def test_health_and_reflection(stub):
    from grpc_health.v1 import health_pb2, health_pb2_grpc
    from grpc_reflection.v1alpha import reflection_pb2, reflection_pb2_grpc

    _, ch = stub
    h = health_pb2_grpc.HealthStub(ch)
    assert (
        h.Check(health_pb2.HealthCheckRequest(service="gsa.v1.AlignmentService")).status
        == health_pb2.HealthCheckResponse.SERVING
    )
    r = reflection_pb2_grpc.ServerReflectionStub(ch)
    resp = next(r.ServerReflectionInfo(iter([reflection_pb2.ServerReflectionRequest(list_services="")])))
    names = {s.name for s in resp.list_services_response.service}
    assert {"gsa.v1.AlignmentService", "grpc.health.v1.Health"} <= names
