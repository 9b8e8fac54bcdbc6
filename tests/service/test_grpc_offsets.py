"""gRPC GetArtifact: a negative offset or length is INVALID_ARGUMENT, not read as
0 / "to the end". Against the real stack (HTTP-created job, read over gRPC)."""

from __future__ import annotations

import json

import grpc
import httpx
import pytest

from service.rpc.generated import alignment_pb2 as pb
from service.rpc.generated import alignment_pb2_grpc as pbg
from tests.service.conftest import ALICE, submit_pair, wait_job

AUTH = (("authorization", "Bearer key-alice"),)


def test_negative_offsets_are_invalid_arguments(stack, pair):
    with httpx.Client(base_url=stack["url"], headers=ALICE, timeout=60) as c:
        job = submit_pair(c, pair, {"stages": ["coarse"], "outputs": ["result"]}).json()
        assert wait_job(c, job["id"])["state"] == "succeeded"
        whole = c.get(f"/v1/jobs/{job['id']}/artifacts/result.json").content
    ch = grpc.insecure_channel(stack["grpc"])
    try:
        s = pbg.AlignmentServiceStub(ch)
        for offset, length, option in ((-1, 0, "offset"), (-(10**12), 5, "offset"), (0, -3, "length")):
            req = pb.ArtifactRequest(job_id=job["id"], name="result.json", offset=offset, length=length)
            with pytest.raises(grpc.RpcError) as e:
                list(s.GetArtifact(req, metadata=AUTH))
            assert e.value.code() == grpc.StatusCode.INVALID_ARGUMENT, (offset, length)
            assert json.loads(dict(e.value.trailing_metadata())["gsa-problem"])["option"] == option
        ok = list(s.GetArtifact(pb.ArtifactRequest(job_id=job["id"], name="result.json", offset=3), metadata=AUTH))
        assert b"".join(x.data for x in ok) == whole[3:]
    finally:
        ch.close()
