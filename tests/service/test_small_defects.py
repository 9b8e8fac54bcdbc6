"""Smaller service defects, each against the real stack: NaN/Inf PLYs refused
at upload, artifacts honour If-None-Match."""

from __future__ import annotations

import io
import json

import numpy as np
import pytest

from gsa.io.ply import write_ply
from gsa.synth import make_object
from tests.service.conftest import assert_problem

pytestmark = pytest.mark.slow  # starts servers and worker processes


def _ply_bytes(tmp_path, field: str, value: float) -> bytes:
    model = make_object("car", seed=5, n_gaussians=400)
    arr = getattr(model, field)
    if arr.ndim == 1:
        arr[7] = value
    else:
        arr[7].flat[0] = value
    return write_ply(model, tmp_path / f"{field}.ply").read_bytes()


BAD = [
    ("means", np.nan, "means"),
    ("means", np.inf, "means"),
    ("quats", np.nan, "quats"),
    ("log_scales", np.nan, "log_scales"),
    ("sh", -np.inf, "sh"),
    ("opacity_logits", np.nan, "opacity_logits"),
]


@pytest.mark.parametrize(("field", "value", "named"), BAD)
def test_non_finite_ply_is_refused_at_upload(http, tmp_path, field, value, named):
    data = _ply_bytes(tmp_path, field, value)
    r = http.post("/v1/assets", files={"file": ("broken.ply", io.BytesIO(data))})
    body = assert_problem(r, 422)
    assert "broken.ply" in body["detail"] and named in body["detail"] and "NaN or Inf" in body["detail"], body


def test_non_finite_ply_is_refused_in_a_multipart_job(http, tmp_path, pair):
    data = _ply_bytes(tmp_path, "means", np.nan)
    before = {j["id"] for j in http.get("/v1/jobs").json()["items"]}
    with open(pair["target"], "rb") as t:
        r = http.post(
            "/v1/jobs",
            files=[("source", ("scan.ply", io.BytesIO(data))), ("target", ("target.ply", t))],
            data={"options": json.dumps({})},
        )
    body = assert_problem(r, 422)
    assert "scan.ply" in body["detail"] and "means" in body["detail"], body
    assert {j["id"] for j in http.get("/v1/jobs").json()["items"]} == before


@pytest.mark.parametrize("field", ["opacity_logits", "log_scales"])
def test_infinite_opacity_and_scale_are_still_accepted(http, tmp_path, field):
    """The readers clamp these (a warning, not an error): the upload check lets them through."""
    data = _ply_bytes(tmp_path, field, np.inf)
    r = http.post("/v1/assets", files={"file": ("clamped.ply", io.BytesIO(data))})
    assert r.status_code in (200, 201), r.text
    assert r.json()["n_gaussians"] == 400


def test_artifact_honours_if_none_match(http, pair):
    from tests.service.conftest import submit_pair, wait_job

    job = wait_job(http, submit_pair(http, pair, {"coarse_iterations": 50}).json()["id"], timeout=120)
    assert job["state"] == "succeeded", job
    url = f"/v1/jobs/{job['id']}/artifacts/aligned.ply"
    full = http.get(url)
    etag = full.headers["etag"]
    r = http.get(url, headers={"If-None-Match": etag})
    assert r.status_code == 304 and r.content == b"" and r.headers["etag"] == etag
    assert "content-length" not in r.headers or r.headers["content-length"] == "0"
    # a list, a weak tag and * match too (weak comparison); a range does not override it
    assert http.get(url, headers={"If-None-Match": f'"x", W/{etag}'}).status_code == 304
    assert http.get(url, headers={"If-None-Match": "*", "Range": "bytes=0-9"}).status_code == 304
    assert http.head(url, headers={"If-None-Match": etag}).status_code == 304
    other = http.get(url, headers={"If-None-Match": '"stale-1"'})
    assert other.status_code == 200 and other.content == full.content
