"""End to end over HTTP against a real uvicorn API + RQ worker + redis-server."""

from __future__ import annotations

import hashlib
import hmac
import io
import json
import re
import threading
import zipfile
from http.server import BaseHTTPRequestHandler, HTTPServer

import httpx
import numpy as np
import pytest

from tests.service.conftest import (
    BOB,
    MAX_UPLOAD,
    assert_problem,
    library_result,
    submit_pair,
    wait_job,
)

ALIGN = {"stages": ["coarse"], "coarse_iterations": 30, "seed": 0}
# Renders cost seconds per job on CPU: only the first end-to-end test asks for them.
OPTS = {**ALIGN, "outputs": ["result", "aligned", "merged"]}


def test_pair_job_end_to_end_matches_library(http, pair, tmp_path):
    r = submit_pair(http, pair, ALIGN)  # default outputs: result, aligned, merged, renders
    assert r.status_code == 202, r.text
    job = r.json()
    assert r.headers["location"] == f"/v1/jobs/{job['id']}"
    assert job["state"] in ("queued", "running", "succeeded")
    done = wait_job(http, job["id"], timeout=180)
    assert done["state"] == "succeeded", done
    assert done["progress"] == 1.0 and done["attempts"] == 1 and done["finished_at"]

    ref = library_result(pair, ALIGN)
    res = done["result"]
    np.testing.assert_allclose(np.array(res["transform"]), ref.transform.matrix(), atol=1e-9)
    np.testing.assert_allclose(res["scale"], ref.transform.scale, atol=1e-9)
    np.testing.assert_allclose(res["quaternion"], ref.transform.quaternion(), atol=1e-9)
    # and it is the right answer, not just the same one
    np.testing.assert_allclose(np.array(res["transform"]), pair["gt"].matrix(), atol=1e-3)

    names = {a["name"] for a in done["artifacts"]}
    assert {"aligned.ply", "merged.ply", "result.json"} <= names
    pngs = [a for a in done["artifacts"] if a["name"].startswith("renders/")]
    assert pngs and all(a["content_type"] == "image/png" for a in pngs), done["artifacts"]
    for a in done["artifacts"]:
        d = http.get(a["href"])
        assert d.status_code == 200 and d.headers["content-type"].startswith(a["content_type"])
        assert len(d.content) == a["size"]
        if a["content_type"] == "image/png":
            assert d.content.startswith(b"\x89PNG")
        (tmp_path / a["name"].replace("/", "_")).write_bytes(d.content)
    from gsa.io.ply import read_ply

    aligned = read_ply(tmp_path / "aligned.ply")
    expect = read_ply(pair["source"]).transformed(ref.transform)
    np.testing.assert_allclose(aligned.means, expect.means, atol=1e-5)
    rj = json.loads((tmp_path / "result.json").read_text())
    np.testing.assert_allclose(np.array(rj["transform"]), ref.transform.matrix(), atol=1e-9)


def test_assets_then_json_job_and_multi_model(http, pair):
    ids = {}
    for k in ("source", "source2", "target"):
        with open(pair[k], "rb") as fh:
            r = http.post("/v1/assets", files={"file": (f"{k}.ply", fh)})
        assert r.status_code == 201, r.text
        a = r.json()
        assert a["kind"] == "ply" and a["n_gaussians"] > 0
        assert a["sha256"] == hashlib.sha256(pair[k].read_bytes()).hexdigest()
        assert http.get(r.headers["location"]).json()["id"] == a["id"]
        ids[k] = a["id"]
    # another key cannot see it
    assert_problem(http.get(f"/v1/assets/{ids['source']}", headers=BOB), 404, "not-found")

    r = http.post(
        "/v1/jobs",
        json={
            "sources": [ids["source"], ids["source2"]],
            "target": ids["target"],
            "options": {**OPTS, "outputs": ["result", "aligned", "renders"]},
        },
    )
    assert r.status_code == 202, r.text
    done = wait_job(http, r.json()["id"], timeout=180)
    assert done["state"] == "succeeded", done
    assert len(done["result"]["results"]) == 2
    assert [x["source_asset_id"] for x in done["result"]["results"]] == [
        ids["source"],
        ids["source2"],
    ]
    names = {a["name"] for a in done["artifacts"]}
    renders = {n for n in names if "renders/" in n or n.startswith("synchronized/")}
    assert names - renders == {
        "s0/aligned.ply",
        "s0/result.json",
        "s1/aligned.ply",
        "s1/result.json",
    }
    # per-pair before/after views, plus all models from shared cameras
    assert "synchronized/synchronized.png" in renders
    assert any(n.startswith("s0/renders/") for n in renders)
    assert any(n.startswith("s1/renders/") for n in renders)
    png = http.get(f"/v1/jobs/{done['id']}/artifacts/synchronized/synchronized.png")
    assert png.headers["content-type"] == "image/png" and png.content.startswith(b"\x89PNG")
    assert http.get(f"/v1/jobs/{done['id']}/artifacts/s1/result.json").json()["source_asset_id"] == ids["source2"]


def test_idempotency_key(http, pair):
    r1 = submit_pair(http, pair, OPTS, headers={"Idempotency-Key": "k-123"})
    r2 = submit_pair(http, pair, OPTS, headers={"Idempotency-Key": "k-123"})
    assert r1.status_code == r2.status_code == 202
    assert r1.json()["id"] == r2.json()["id"]
    assert r2.headers.get("idempotent-replayed") == "true"
    r3 = submit_pair(http, pair, {**OPTS, "seed": 1}, headers={"Idempotency-Key": "k-123"})
    assert_problem(r3, 422, "idempotency-key-reused")
    # keys are per owner: bob's identical request makes his own job
    r4 = submit_pair(http, pair, OPTS, headers={**BOB, "Idempotency-Key": "k-123"})
    assert r4.status_code == 202 and r4.json()["id"] != r1.json()["id"]


def test_etag_304_range_206_and_list(http, pair):
    job = wait_job(http, submit_pair(http, pair, OPTS).json()["id"])
    r = http.get(f"/v1/jobs/{job['id']}")
    etag = r.headers["etag"]
    r304 = http.get(f"/v1/jobs/{job['id']}", headers={"If-None-Match": etag})
    assert r304.status_code == 304 and r304.content == b""
    assert http.get(f"/v1/jobs/{job['id']}", headers={"If-None-Match": '"other"'}).status_code == 200

    url = f"/v1/jobs/{job['id']}/artifacts/aligned.ply"
    full = http.get(url).content
    p = http.get(url, headers={"Range": "bytes=10-99"})
    assert p.status_code == 206 and p.content == full[10:100]
    assert p.headers["content-range"] == f"bytes 10-99/{len(full)}"
    tail = http.get(url, headers={"Range": "bytes=-16"})
    assert tail.status_code == 206 and tail.content == full[-16:]
    bad = http.get(url, headers={"Range": f"bytes={len(full)}-"})
    assert_problem(bad, 416)
    assert bad.headers["content-range"] == f"bytes */{len(full)}"
    assert_problem(http.get(f"/v1/jobs/{job['id']}/artifacts/nope.ply"), 404)

    for _ in range(2):
        submit_pair(http, pair, OPTS)
    page1 = http.get("/v1/jobs", params={"limit": 2}).json()
    assert len(page1["items"]) == 2 and page1["next_cursor"]
    page2 = http.get("/v1/jobs", params={"limit": 2, "cursor": page1["next_cursor"]}).json()
    seen = [j["id"] for j in page1["items"] + page2["items"]]
    assert len(seen) == len(set(seen))
    created = [j["created_at"] for j in page1["items"] + page2["items"]]
    assert created == sorted(created, reverse=True)
    ok = http.get("/v1/jobs", params={"state": "succeeded", "limit": 200}).json()["items"]
    assert ok and all(j["state"] == "succeeded" for j in ok)
    assert all(j["id"] not in {x["id"] for x in ok} for j in http.get("/v1/jobs", headers=BOB).json()["items"])
    assert_problem(http.get("/v1/jobs", params={"state": "bogus"}), 422, "validation-error")


def _blob_count(stack) -> int:
    # Uploads (content-addressed under cas/); artifacts of earlier jobs may still land in jobs/.
    roots = [stack["tmp"] / "data" / "blobs" / d for d in ("uploads", "cas")]
    return sum(1 for root in roots if root.exists() for p in root.rglob("*") if p.is_file())


def _asset_count(stack) -> int:
    import redis

    return len(redis.Redis.from_url(stack["redis_url"]).keys("gsa:asset:*"))


def _png(w=8, h=8) -> bytes:
    import struct
    import zlib

    raw = b"".join(b"\x00" + b"\x80" * (3 * w) for _ in range(h))

    def chunk(t, d):
        return struct.pack(">I", len(d)) + t + d + struct.pack(">I", zlib.crc32(t + d))

    return (
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0))
        + chunk(b"IDAT", zlib.compress(raw))
        + chunk(b"IEND", b"")
    )


def test_bad_inputs_get_problems_and_leave_nothing(http, stack, pair):
    wait_until_quiet = _blob_count(stack), _asset_count(stack)
    good = pair["source"].read_bytes()
    tgt = ("target.ply", pair["target"].read_bytes())

    def post(src_name, src_bytes):
        return http.post("/v1/jobs", files=[("source", (src_name, src_bytes)), ("target", tgt)])

    b = assert_problem(post("x.ply", b"hello, not a ply" * 10), 422, "invalid-input")
    assert "not" in b["detail"]
    b = assert_problem(post("trunc.ply", good[: len(good) // 2]), 422, "invalid-input")
    assert "truncated" in b["detail"]
    assert_problem(
        http.post(
            "/v1/assets",
            files={"file": ("x.ply", b"ply\nformat ascii 1.0\nend_header\n")},
        ),
        422,
    )

    # oversized: with Content-Length (rejected before reading) and chunked (while streaming)
    big = b"ply\n" + b"\0" * (MAX_UPLOAD + 10)
    assert_problem(
        http.post("/v1/assets", files={"file": ("big.ply", big)}),
        413,
        "payload-too-large",
    )

    def chunked():
        yield b'--bnd\r\nContent-Disposition: form-data; name="file"; filename="big.ply"\r\n\r\nply\n'
        for _ in range(MAX_UPLOAD // 65536 + 4):
            yield b"\0" * 65536
        yield b"\r\n--bnd--\r\n"

    r = http.post(
        "/v1/assets",
        content=chunked(),
        headers={"Content-Type": "multipart/form-data; boundary=bnd"},
    )
    assert_problem(r, 413, "payload-too-large")

    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        zf.writestr("ok/0.png", _png())
        zf.writestr("../evil.png", _png())
    b = assert_problem(
        http.post("/v1/assets", files={"file": ("imgs.zip", buf.getvalue())}),
        422,
        "invalid-input",
    )
    assert "unsafe path" in b["detail"]
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        zf.writestr("/abs.png", _png())
    assert_problem(http.post("/v1/assets", files={"file": ("imgs.zip", buf.getvalue())}), 422)
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as zf:  # a small bomb
        zf.writestr("a.png", _png()[:33] + b"\0" * 5_000_000)
    b = assert_problem(http.post("/v1/assets", files={"file": ("bomb.zip", buf.getvalue())}), 422)
    assert "ratio" in b["detail"]

    assert_problem(http.get("/v1/jobs/job_doesnotexist"), 404, "not-found")
    assert_problem(http.post("/v1/jobs/job_doesnotexist:cancel"), 404)
    r = httpx.get(stack["url"] + "/v1/jobs", headers={"Authorization": "Bearer wrong"})
    assert_problem(r, 401, "unauthorized")
    assert r.headers["www-authenticate"].startswith("Bearer")
    assert_problem(httpx.get(stack["url"] + "/v1/jobs"), 401)
    assert_problem(httpx.post(stack["url"] + "/v1/jobs", content=b"x"), 401)
    assert_problem(http.post("/v1/jobs", json={"target": "a", "bogus": 1}), 422, "validation-error")
    assert_problem(
        http.post(
            "/v1/jobs",
            content=b"{not json",
            headers={"Content-Type": "application/json"},
        ),
        422,
    )
    assert_problem(http.post("/v1/jobs", json={"source": "ast_x", "target": "ast_y"}), 404)
    b = assert_problem(submit_pair(http, pair, {"no_such_option": 1}), 422, "invalid-input")
    assert "no_such_option" in b["detail"]
    b = assert_problem(submit_pair(http, pair, {"dinov2_weights": "/etc/passwd"}), 422, "invalid-input")
    assert "set by the server" in b["detail"]
    assert_problem(http.get("/nowhere"), 404)

    assert (_blob_count(stack), _asset_count(stack)) == wait_until_quiet


def test_other_owner_cannot_see_or_cancel(http, pair):
    job = submit_pair(http, pair, OPTS).json()
    assert_problem(http.get(f"/v1/jobs/{job['id']}", headers=BOB), 404)
    assert_problem(http.post(f"/v1/jobs/{job['id']}:cancel", headers=BOB), 404)
    done = wait_job(http, job["id"])
    assert_problem(http.get(f"{done['artifacts'][0]['href']}", headers=BOB), 404)


def test_cancel_running_job_and_finished_job(http, pair):
    with open(pair["big_source"], "rb") as fh:
        src = http.post("/v1/assets", files={"file": ("big.ply", fh)}).json()["id"]
    with open(pair["big_target"], "rb") as fh:
        tgt = http.post("/v1/assets", files={"file": ("bigt.ply", fh)}).json()["id"]
    r = http.post(
        "/v1/jobs",
        json={
            "sources": [src] * 8,
            "target": tgt,
            "options": {"coarse_iterations": 100, "outputs": ["result"]},
        },
    )
    jid = r.json()["id"]
    wait_job(http, jid, states=("running",), timeout=60)
    c = http.post(f"/v1/jobs/{jid}:cancel")
    assert c.status_code == 202 and c.json()["cancel_requested"] is True
    done = wait_job(http, jid, timeout=30)
    assert done["state"] == "cancelled" and done["artifacts"] == [] and done["result"] is None
    assert http.post(f"/v1/jobs/{jid}:cancel").json()["state"] == "cancelled"  # idempotent

    ok = wait_job(http, submit_pair(http, pair, OPTS).json()["id"])
    assert_problem(http.post(f"/v1/jobs/{ok['id']}:cancel"), 409, "job-finished")


class _Hook(BaseHTTPRequestHandler):
    got: list = []
    fail_first = [True]

    def do_POST(self):
        body = self.rfile.read(int(self.headers["Content-Length"]))
        if self.fail_first[0]:  # the first delivery fails: the retry must come
            self.fail_first[0] = False
            self.send_response(500)
            self.end_headers()
            return
        _Hook.got.append((dict(self.headers), body))
        self.send_response(204)
        self.end_headers()

    def log_message(self, *a):
        pass


def test_webhook_signed_and_retried(http, pair):
    srv = HTTPServer(("127.0.0.1", 0), _Hook)
    threading.Thread(target=srv.serve_forever, daemon=True).start()
    try:
        url = f"http://127.0.0.1:{srv.server_port}/hook"
        job = submit_pair(http, pair, OPTS, webhook_url=url, webhook_secret="s3cret").json()
        wait_job(http, job["id"])
        from tests.service.conftest import wait_until

        wait_until(lambda: _Hook.got, 30, 0.1, "webhook delivery")
        headers, body = _Hook.got[0]
        payload = json.loads(body)
        assert payload["job_id"] == job["id"] and payload["state"] == "succeeded"
        # Times as the REST API writes them (ISO-8601), not a float.
        assert payload["finished_at"] == http.get(f"/v1/jobs/{job['id']}").json()["finished_at"]
        assert isinstance(payload["finished_at"], str) and payload["finished_at"].endswith("Z")
        mac = hmac.new(b"s3cret", headers["X-GSA-Timestamp"].encode() + b"." + body, hashlib.sha256).hexdigest()
        assert headers["X-GSA-Signature"] == "sha256=" + mac
    finally:
        srv.shutdown()


def test_image_set_job(http, pair):
    pytest.importorskip("pycolmap", reason="image-set jobs run pycolmap SfM, which is not installed")
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        for i in range(3):
            zf.writestr(f"views/{i:03d}.png", _png(16, 12))
    r = http.post("/v1/assets", files={"file": ("views.zip", buf.getvalue())})
    assert r.status_code == 201, r.text
    assert r.json()["kind"] == "images" and r.json()["n_images"] == 3
    # individual images in one upload become one image set
    r2 = http.post("/v1/assets", files=[("file", (f"{i}.png", _png())) for i in range(2)])
    assert r2.status_code == 201 and r2.json()["n_images"] == 2
    with open(pair["target"], "rb") as fh:
        tgt = http.post("/v1/assets", files={"file": ("t.ply", fh)}).json()["id"]
    job = wait_job(
        http,
        http.post("/v1/jobs", json={"source": r.json()["id"], "target": tgt}).json()["id"],
    )
    # Three flat grey 16x12 pictures: the real pipeline runs (images loaded,
    # pycolmap features and matching) and its mapper cannot register them; the
    # client gets the library's reason as a 422, and the job shows how far it got.
    assert job["state"] == "failed", job
    assert job["error"]["status"] == 422, job["error"]
    assert job["error"]["type"].endswith("/reconstruction-failed"), job["error"]
    assert re.match(r"source0 images: 0 of 3 images registered", job["error"]["detail"]), job["error"]
    assert job["stage"] == "recon:sfm:mapping", job
    assert 0.02 <= job["progress"] < 0.1, job  # inside the SfM span of the progress bar
    metrics = http.get("/metrics").text
    for stage in ("recon:images", "recon:sfm:features", "recon:sfm:matching"):
        assert f'gsa_stage_duration_seconds_count{{stage="{stage}"}}' in metrics, stage
    assert job["artifacts"] == []


def test_multipart_image_sets_replay_and_leave_nothing_on_failure(http, stack, pair):
    """source_images / target_images: each list of images becomes one image-set asset; the
    same request with its Idempotency-Key replays the job; when the target's images are bad,
    the source's image set already stored is discarded and the key can be used again."""
    images = [("source_images", (f"{i}.png", _png(16, 12))) for i in range(3)]
    files = [*images, ("target", ("t.ply", pair["target"].read_bytes()))]
    key = {"Idempotency-Key": f"image-sets-{id(files)}"}
    r = http.post("/v1/jobs", files=files, headers=key)
    assert r.status_code == 202, r.text
    job = r.json()
    src = http.get(f"/v1/assets/{job['sources'][0]}").json()
    assert (src["kind"], src["n_images"], src["filename"]) == ("images", 3, "source_images.zip")
    again = http.post("/v1/jobs", files=files, headers=key)
    assert again.status_code == 202 and again.json()["id"] == job["id"], again.text
    assert again.headers["Idempotent-Replayed"] == "true"
    http.post(f"/v1/jobs/{job['id']}:cancel")
    wait_job(http, job["id"])

    before = _blob_count(stack), _asset_count(stack)
    bad = [*images[:2], ("target_images", ("t.png", b"\x89PNG\r\n\x1a\n not a picture"))]
    other = {"Idempotency-Key": key["Idempotency-Key"] + "-bad"}
    assert_problem(http.post("/v1/jobs", files=bad, headers=other), 422, "invalid-input")
    assert (_blob_count(stack), _asset_count(stack)) == before
    fixed = [*images[:2], ("target_images", ("t.png", _png(16, 12)))]
    r = http.post("/v1/jobs", files=fixed, headers=other)  # the failed request left no claim
    assert r.status_code == 202, r.text
    http.post(f"/v1/jobs/{r.json()['id']}:cancel")


def test_ops_endpoints_and_openapi(stack, http):
    assert httpx.get(stack["url"] + "/healthz").json()["status"] == "ok"
    ready = httpx.get(stack["url"] + "/readyz").json()
    assert ready["status"] == "ready" and all(ready["checks"].values())
    assert_problem(httpx.get(stack["url"] + "/metrics"), 401)
    m = http.get("/metrics").text
    assert 'gsa_jobs{state="succeeded"}' in m and "gsa_queue_depth" in m and "gsa_http_requests_total" in m
    assert "gsa_stage_duration_seconds_count" in m
    spec = httpx.get(stack["url"] + "/openapi.json").json()
    paths = spec["paths"]
    for p in (
        "/v1/assets",
        "/v1/assets/{asset_id}",
        "/v1/jobs",
        "/v1/jobs/{job_id}",
        "/v1/jobs/{job_id}:cancel",
        "/v1/jobs/{job_id}/artifacts/{name}",
        "/healthz",
        "/readyz",
        "/metrics",
    ):
        assert p in paths, p
    body = paths["/v1/jobs"]["post"]["requestBody"]["content"]
    assert {"application/json", "multipart/form-data"} <= set(body)
    assert body["application/json"]["schema"]["$ref"].split("/")[-1] in spec["components"]["schemas"]
    assert "application/problem+json" in paths["/v1/jobs/{job_id}"]["get"]["responses"]["404"]["content"]
    assert "multipart/form-data" in paths["/v1/assets"]["post"]["requestBody"]["content"]
    assert httpx.get(stack["url"] + "/docs").status_code == 200


@pytest.mark.parametrize("bad", ["../etc/passwd", "a/../../b", "/abs", "C:\\x", "a\\b"])
def test_unsafe_zip_names(bad):
    from service.jobs.inputs import unsafe_member_name

    assert unsafe_member_name(bad)
    assert not unsafe_member_name("views/0001.png")


def test_python_client_resumes_downloads(stack, pair, tmp_path):
    from gsa.client import GSAClient, GSAError

    with GSAClient(stack["url"], api_key="key-alice") as c:
        job = c.submit(pair["source"], pair["target"], OPTS, idempotency_key="client-1")
        assert c.submit(pair["source"], pair["target"], OPTS, idempotency_key="client-1")["id"] == job["id"]
        job = c.wait(job["id"], timeout=60, poll=0.05)
        full = c.fetch(job["id"], "aligned.ply", tmp_path / "full.ply").read_bytes()
        # an interrupted earlier download: the client asks only for the rest (Range)
        (tmp_path / "resumed.ply.part").write_bytes(full[:1000])
        assert c.fetch(job["id"], "aligned.ply", tmp_path / "resumed.ply").read_bytes() == full
        assert [j["id"] for j in c.list(limit=200)["items"]].count(job["id"]) == 1
        with pytest.raises(GSAError) as e:
            c.status("job_missing")
        assert e.value.status == 404 and e.value.problem["type"].endswith("/not-found")
