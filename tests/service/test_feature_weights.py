"""`options.features: dinov2 | spheremap` on a deployment without those weights (the test
stack has none) is a 422 at submission over REST JSON, multipart and gRPC — it used to be
a 202 and then a job failing 500 with a message naming server settings."""

from __future__ import annotations

import json

import grpc
import pytest

from service.rpc.generated import alignment_pb2 as pb
from service.rpc.generated import alignment_pb2_grpc as pbg
from tests.service.conftest import assert_problem, submit_pair

pytestmark = pytest.mark.slow  # starts servers and worker processes


def _json_job(http, options: dict):
    # options are checked before the asset ids are looked up: a made-up id is the 404
    return http.post("/v1/jobs", json={"source": "ast_nope", "target": "ast_nope", "options": options})


@pytest.mark.parametrize("mode", ["dinov2", "spheremap"])
def test_learned_features_without_weights_are_refused_at_submission(stack, pair, mode):
    import httpx

    from tests.service.conftest import ALICE

    with httpx.Client(base_url=stack["url"], headers=ALICE, timeout=60) as http:
        body = assert_problem(_json_job(http, {"features": mode}), 422, "invalid-input")
        assert body["option"] == "features" and mode in body["detail"], body
        assert body["allowed"] == ["auto", "file", "canonical"], body
        assert "GSA_" not in body["detail"] and "/" not in body["detail"], body  # no server settings or paths
        r = submit_pair(http, pair, {"features": mode})
        assert assert_problem(r, 422, "invalid-input")["option"] == "features"
        assert_problem(_json_job(http, {"features": "canonical"}), 404, "not-found")  # the others pass
    ch = grpc.insecure_channel(stack["grpc"])
    try:
        header = pb.SubmitHeader(
            options_json=json.dumps({"features": mode}), source_asset_ids=["ast_nope"], target_asset_id="ast_nope"
        )
        with pytest.raises(grpc.RpcError) as e:
            pbg.AlignmentServiceStub(ch).SubmitAlignment(
                iter([pb.SubmitRequest(header=header)]), metadata=(("authorization", "Bearer key-alice"),)
            )
        assert e.value.code() == grpc.StatusCode.INVALID_ARGUMENT
        assert json.loads(dict(e.value.trailing_metadata())["gsa-problem"])["option"] == "features"
    finally:
        ch.close()


def test_configured_weights_make_them_available():
    from types import SimpleNamespace

    from service.jobs.options import check_feature_weights

    s = SimpleNamespace(features_backbone="/w/dinov2", features_head=None)
    check_feature_weights({"features": "dinov2"}, s)
    with pytest.raises(Exception) as e:
        check_feature_weights({"features": "spheremap"}, s)
    assert e.value.status == 422 and e.value.extra["allowed"] == ["auto", "file", "canonical", "dinov2"]
